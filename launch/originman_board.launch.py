"""Start originman_board_node for the OriginMan expansion board.

ros2 launch uav_serial_drivers originman_board.launch.py port:=/dev/ttyS1 namespace:=uav1
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    """Declare namespace, port and params_file; run the driver with them."""
    default_params = PathJoinSubstitution(
        [FindPackageShare('uav_serial_drivers'), 'config', 'originman_board.yaml'])
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the node and its topics'),
        DeclareLaunchArgument('port', default_value='/dev/ttyS1',
                              description='serial device of the board (the OriginMan: '
                                          '/dev/ttyS1; a USB adapter: /dev/ttyUSB0)'),
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='parameter file (see config/originman_board.yaml)'),
        Node(
            package='uav_serial_drivers',
            executable='originman_board_node',
            name='originman_board',
            namespace=LaunchConfiguration('namespace'),
            parameters=[LaunchConfiguration('params_file'),
                        {'port': LaunchConfiguration('port')}],
            output='screen',
            emulate_tty=True,
        ),
    ])
