"""Launch the FroDO node graph on a ROS 2 install: `ros2 launch frodo_bringup frodo.launch.py`.

Arguments: `params_file:=FILE` (default: the shipped config/frodo.yaml, generated from the nodes'
parameter specs by `frodo params --write`; a file of overrides is enough, nodes default the rest),
`viewer:=true` (also start the Rerun viewer node) and `optim_workers:=N` (N optimiser processes
`optim_node`, `optim_node_1..N-1` splitting the objects by id, each with the file's `optim_node` parameters, as
`frodo launch --optim-workers N`; default `auto`: 2 where there are 2 CPUs or more, else 1). The node list mirrors `frodo_bringup/graph.py`
(a test checks that they agree); `frodo launch` is the same graph without ROS 2 launch installed.
"""
import os

import yaml
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

# (package, executable = node name), in data-flow order: frodo_bringup.graph.NODES.
NODES = (
    ('frodo_detection', 'detection_node'),
    ('frodo_association', 'association_node'),
    ('frodo_shape', 'shape_node'),
    ('frodo_optim', 'optim_node'),
)
VIEWER = ('frodo_bringup', 'viewer_node')
OPTIMISER = ('frodo_optim', 'optim_node')
AUTO_OPTIM_WORKERS = 2    # frodo_bringup.graph.AUTO_OPTIM_WORKERS


def optimiser_nodes(context) -> list:
    """One optim_node, or `optim_workers` workers: optim_node (worker 0: merges the shares, reports for all)
    and optim_node_<k> (a node named otherwise does not read the file's `optim_node` section, so each gets that
    section's values, then its worker index and count), as frodo_bringup.graph.optimiser_workers."""
    package, executable = OPTIMISER
    params_file = LaunchConfiguration('params_file').perform(context)
    value = LaunchConfiguration('optim_workers').perform(context)
    cpus = len(os.sched_getaffinity(0))
    count = min(AUTO_OPTIM_WORKERS, cpus) if value == 'auto' else int(value)
    if count < 1:
        raise ValueError(f"optim_workers must be at least 1 or 'auto', got {value}")
    if count == 1:
        return [Node(package=package, executable=executable, name=executable, parameters=[params_file],
                     output='screen', emulate_tty=True)]
    with open(params_file) as f:
        document = yaml.safe_load(f) or {}
    section = {}
    for key in (executable, f'/{executable}'):
        section.update((document.get(key) or {}).get('ros__parameters') or {})
    # 1/count of the CPUs as torch threads each, as graph.optimiser_workers: OpenMP teams spinning against each other
    threads = str(max(1, cpus // count))
    return [Node(package=package, executable=executable, name=executable if k == 0 else f'{executable}_{k}',
                 output='screen', emulate_tty=True,
                 parameters=[params_file, {**section, 'worker_index': k, 'worker_count': count}],
                 additional_env={'OMP_NUM_THREADS': threads})
            for k in range(count)]


def generate_launch_description() -> LaunchDescription:
    """Declare the arguments and one Node action per graph node, all loading the same params file."""
    default_params = os.path.join(get_package_share_directory('frodo_bringup'), 'config', 'frodo.yaml')
    params_file = LaunchConfiguration('params_file')
    actions = [
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS 2 parameter YAML for the FroDO nodes'),
        DeclareLaunchArgument('viewer', default_value='false',
                              description='also start the Rerun viewer node (true/false)'),
        DeclareLaunchArgument('optim_workers', default_value='auto',
                              description='optimiser processes splitting the objects by id (auto: 2 on 2 CPUs or '
                                          'more, else 1)'),
    ]
    actions += [Node(package=package, executable=executable, name=executable, parameters=[params_file],
                     output='screen', emulate_tty=True)
                for package, executable in NODES if (package, executable) != OPTIMISER]
    actions.append(OpaqueFunction(function=optimiser_nodes))
    package, executable = VIEWER
    actions.append(Node(package=package, executable=executable, name=executable, parameters=[params_file],
                        output='screen', emulate_tty=True, condition=IfCondition(LaunchConfiguration('viewer'))))
    return LaunchDescription(actions)
