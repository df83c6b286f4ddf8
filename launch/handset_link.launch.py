"""Start handset_link_node for the radio modem of the handset link.

ros2 launch uav_serial_drivers handset_link.launch.py port:=/dev/ttyUSB2 namespace:=uav1
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    """Declare namespace, port and params_file; run the driver with them."""
    default_params = PathJoinSubstitution(
        [FindPackageShare('uav_serial_drivers'), 'config', 'handset_link.yaml'])
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the node and its topics'),
        DeclareLaunchArgument('port', default_value='/dev/ttyUSB2',
                              description='serial device of the radio modem'),
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='parameter file (see config/handset_link.yaml)'),
        Node(
            package='uav_serial_drivers',
            executable='handset_link_node',
            name='handset_link',
            namespace=LaunchConfiguration('namespace'),
            parameters=[LaunchConfiguration('params_file'),
                        {'port': LaunchConfiguration('port')}],
            output='screen',
            emulate_tty=True,
        ),
    ])
