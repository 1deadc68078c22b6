"""FroDO parameters are read once, at start-up: in a real rclpy graph a set at run time (what `ros2 param set`
sends, through the node's parameter services) is refused with rclpy's read-only reason, while start-up
overrides still apply."""
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

from frodo_common.node import READ_ONLY_NOTE, FrodoNode, parameter_descriptor
from frodo_common.params import COMMON_PARAMS, ParamSpec

SPECS = (ParamSpec('threshold', 0.5, 'A test threshold.'),)


class _Params(FrodoNode):
    def __init__(self):
        super().__init__('params_node', SPECS, parameter_overrides=[Parameter('threshold', value=0.75)])


def test_descriptor_is_read_only_and_says_so():
    descriptor = parameter_descriptor(SPECS[0])
    assert descriptor.read_only
    assert descriptor.description == f'A test threshold. {READ_ONLY_NOTE}' and 'read-only' in READ_ONLY_NOTE


def test_a_set_at_run_time_is_refused_with_the_read_only_reason():
    rclpy.init()
    try:
        node = _Params()
        caller = rclpy.create_node('params_caller')
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.add_node(caller)

        # Start-up overrides are applied when the parameter is declared, read-only or not.
        assert node.params['threshold'] == 0.75 and node.get_parameter('threshold').value == 0.75
        names = [spec.name for spec in COMMON_PARAMS + SPECS]
        for name in names:
            descriptor = node.describe_parameter(name)
            assert descriptor.read_only and READ_ONLY_NOTE in descriptor.description, name

        # In-process set: refused, nothing changes.
        (local,) = node.set_parameters([Parameter('threshold', value=0.9)])
        assert not local.successful and 'read-only' in local.reason and 'threshold' in local.reason

        # Remote set through the parameter services, as `ros2 param set /params_node diagnostics_period 5.0` does.
        client = AsyncParameterClient(caller, node.get_fully_qualified_name())
        assert client.wait_for_services(timeout_sec=20.0), 'parameter services of params_node not discovered'
        future = client.set_parameters([Parameter('threshold', value=0.9),
                                        Parameter('diagnostics_period', value=5.0)])
        executor.spin_until_future_complete(future, timeout_sec=20.0)
        assert future.done(), 'no reply from params_node to set_parameters'
        results = future.result().results
        assert len(results) == 2
        for result, name in zip(results, ('threshold', 'diagnostics_period')):
            assert not result.successful, f'{name}: set was accepted but the node never re-reads it'
            assert result.reason == f'Trying to set a read-only parameter: {name}.'

        # The node's values are unchanged, as seen remotely and in the node.
        future = client.get_parameters(['threshold', 'diagnostics_period'])
        executor.spin_until_future_complete(future, timeout_sec=20.0)
        assert future.done()
        assert [v.double_value for v in future.result().values] == [0.75, 0.5]
        assert node.params['threshold'] == 0.75 and node.params['diagnostics_period'] == 0.5
        executor.shutdown()
        caller.destroy_node()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
