"""Start parachute_node and parachute_mavlink: the DPS-S parachute as a MAVLink component.

ros2 launch uav_serial_drivers parachute_mavlink.launch.py port:=/dev/ttyUSB0 \
    mavlink_url:=udpout:127.0.0.1:14550 system_id:=1
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    """Run the parachute driver with its release gate and the autopilot link."""
    share = FindPackageShare('uav_serial_drivers')
    namespace = LaunchConfiguration('namespace')
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of both nodes and their topics'),
        DeclareLaunchArgument('port', default_value='/dev/ttyUSB0',
                              description='serial device of the parachute module'),
        DeclareLaunchArgument('mavlink_url', default_value='udpout:127.0.0.1:14550',
                              description='pymavlink connection string to the autopilot'),
        DeclareLaunchArgument('system_id', default_value='1',
                              description="the vehicle's MAVLink system id (0 = learn it)"),
        DeclareLaunchArgument('parachute_params', default_value=PathJoinSubstitution(
            [share, 'config', 'parachute.yaml']), description='parachute_node parameters'),
        DeclareLaunchArgument('params_file', default_value=PathJoinSubstitution(
            [share, 'config', 'parachute_mavlink.yaml']),
            description='parachute_mavlink parameters'),
        Node(package='uav_serial_drivers', executable='parachute_node', name='parachute',
             namespace=namespace,
             parameters=[LaunchConfiguration('parachute_params'),
                         {'port': LaunchConfiguration('port'),
                          'release_gate': 'parachute_mavlink/release_gate'}],
             output='screen', emulate_tty=True),
        Node(package='uav_serial_drivers', executable='parachute_mavlink',
             name='parachute_mavlink', namespace=namespace,
             parameters=[LaunchConfiguration('params_file'),
                         {'mavlink_url': LaunchConfiguration('mavlink_url'),
                          'system_id': ParameterValue(LaunchConfiguration('system_id'),
                                                      value_type=int)}],
             output='screen', emulate_tty=True),
    ])
