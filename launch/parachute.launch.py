"""Start parachute_node for a DPS-S parachute module.

ros2 launch uav_serial_drivers parachute.launch.py port:=/dev/ttyUSB0 namespace:=uav1
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    """Declare namespace, port and params_file; run the driver with them."""
    default_params = PathJoinSubstitution(
        [FindPackageShare('uav_serial_drivers'), 'config', 'parachute.yaml'])
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the node and its topics'),
        DeclareLaunchArgument('port', default_value='/dev/ttyUSB0',
                              description='serial device of the parachute module'),
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='parameter file (see config/parachute.yaml)'),
        Node(
            package='uav_serial_drivers',
            executable='parachute_node',
            name='parachute',
            namespace=LaunchConfiguration('namespace'),
            parameters=[LaunchConfiguration('params_file'),
                        {'port': LaunchConfiguration('port')}],
            output='screen',
            emulate_tty=True,
        ),
    ])
