"""Start servo_bus_node for a bus of Desheng servos.

ros2 launch uav_serial_drivers servo_bus.launch.py port:=/dev/ttyUSB1 namespace:=uav1
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    """Declare namespace, port and params_file; run the driver with them."""
    default_params = PathJoinSubstitution(
        [FindPackageShare('uav_serial_drivers'), 'config', 'servo_bus.yaml'])
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the node and its topics'),
        DeclareLaunchArgument('port', default_value='/dev/ttyUSB1',
                              description='serial device of the servo bus'),
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='parameter file (see config/servo_bus.yaml)'),
        Node(
            package='uav_serial_drivers',
            executable='servo_bus_node',
            name='servo_bus',
            namespace=LaunchConfiguration('namespace'),
            parameters=[LaunchConfiguration('params_file'),
                        {'port': LaunchConfiguration('port')}],
            output='screen',
            emulate_tty=True,
        ),
    ])
