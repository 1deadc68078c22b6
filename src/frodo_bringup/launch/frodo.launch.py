"""Launch the FroDO node graph on a ROS 2 install: `ros2 launch frodo_bringup frodo.launch.py`.

Arguments: `params_file:=FILE` (default: the shipped config/frodo.yaml, generated from the nodes'
parameter specs by `frodo params --write`; a file of overrides is enough, nodes default the rest) and
`viewer:=true` (also start the Rerun viewer node). The node list mirrors `frodo_bringup/graph.py`
(a test checks that they agree); `frodo launch` is the same graph without ROS 2 launch installed.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
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


def generate_launch_description() -> LaunchDescription:
    """Declare the arguments and one Node action per graph node, all loading the same params file."""
    default_params = os.path.join(get_package_share_directory('frodo_bringup'), 'config', 'frodo.yaml')
    params_file = LaunchConfiguration('params_file')
    actions = [
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS 2 parameter YAML for the FroDO nodes'),
        DeclareLaunchArgument('viewer', default_value='false',
                              description='also start the Rerun viewer node (true/false)'),
    ]
    actions += [Node(package=package, executable=executable, name=executable, parameters=[params_file],
                     output='screen', emulate_tty=True)
                for package, executable in NODES]
    package, executable = VIEWER
    actions.append(Node(package=package, executable=executable, name=executable, parameters=[params_file],
                        output='screen', emulate_tty=True, condition=IfCondition(LaunchConfiguration('viewer'))))
    return LaunchDescription(actions)
