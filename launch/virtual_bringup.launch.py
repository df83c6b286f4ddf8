"""Every virtual device and every driver wired to it: the whole stack without hardware.

ros2 launch uav_serial_drivers virtual_bringup.launch.py
ros2 launch uav_serial_drivers virtual_bringup.launch.py mavlink:=true   # + the autopilot link
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    """Run each virtual device with its driver (parachute, servo bus, handset, OriginMan board)."""
    share = FindPackageShare('uav_serial_drivers')
    parachute_link = LaunchConfiguration('parachute_link')
    servo_link = LaunchConfiguration('servo_link')
    handset_link = LaunchConfiguration('handset_link')
    originman_link = LaunchConfiguration('originman_link')
    namespace = LaunchConfiguration('namespace')
    mavlink = LaunchConfiguration('mavlink')
    return LaunchDescription([
        DeclareLaunchArgument('mavlink', default_value='false',
                              description='also run parachute_mavlink against a virtual '
                                          'autopilot (udp 127.0.0.1:14550)'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of every node'),
        DeclareLaunchArgument('parachute_link', default_value='/tmp/vparachute',
                              description='path of the virtual parachute port'),
        DeclareLaunchArgument('servo_link', default_value='/tmp/vservobus',
                              description='path of the virtual servo bus port'),
        DeclareLaunchArgument('handset_link', default_value='/tmp/vhandset',
                              description='path of the virtual handset modem port'),
        DeclareLaunchArgument('originman_link', default_value='/tmp/voriginman',
                              description='path of the virtual OriginMan board port'),
        Node(package='uav_serial_drivers', executable='virtual_parachute',
             name='virtual_parachute', namespace=namespace,
             parameters=[{'link': parachute_link}], output='screen'),
        Node(package='uav_serial_drivers', executable='virtual_servo_bus',
             name='virtual_servo_bus', namespace=namespace,
             parameters=[{'link': servo_link, 'servo_ids': [1, 2, 3]}], output='screen'),
        Node(package='uav_serial_drivers', executable='virtual_originman_board',
             name='virtual_originman_board', namespace=namespace,
             parameters=[{'link': originman_link, 'bus_servo_ids': [1, 2, 3]}],
             output='screen'),
        Node(package='uav_serial_drivers', executable='parachute_node', name='parachute',
             namespace=namespace,
             parameters=[PathJoinSubstitution([share, 'config', 'parachute.yaml']),
                         {'port': parachute_link}],
             output='screen'),
        Node(package='uav_serial_drivers', executable='servo_bus_node', name='servo_bus',
             namespace=namespace,
             parameters=[PathJoinSubstitution([share, 'config', 'servo_bus.yaml']),
                         {'port': servo_link, 'servo_ids': [1, 2, 3]}],
             output='screen'),
        Node(package='uav_serial_drivers', executable='originman_board_node',
             name='originman_board', namespace=namespace,
             parameters=[PathJoinSubstitution([share, 'config', 'originman_board.yaml']),
                         {'port': originman_link, 'bus_servo_ids': [1, 2, 3]}],
             output='screen'),
        Node(package='uav_serial_drivers', executable='virtual_handset',
             name='virtual_handset', namespace=namespace,
             parameters=[{'link': handset_link}], output='screen'),
        Node(package='uav_serial_drivers', executable='virtual_autopilot',
             name='virtual_autopilot', namespace=namespace, condition=IfCondition(mavlink),
             parameters=[{'mavlink_url': 'udpin:127.0.0.1:14550'}], output='screen'),
        Node(package='uav_serial_drivers', executable='parachute_mavlink',
             name='parachute_mavlink', namespace=namespace, condition=IfCondition(mavlink),
             parameters=[PathJoinSubstitution([share, 'config', 'parachute_mavlink.yaml']),
                         {'mavlink_url': 'udpout:127.0.0.1:14550',
                          'handset_failsafe_to_autopilot': True}],
             output='screen'),
        Node(package='uav_serial_drivers', executable='handset_link_node', name='handset_link',
             namespace=namespace,
             parameters=[PathJoinSubstitution([share, 'config', 'handset_link.yaml']),
                         {'port': handset_link}],
             output='screen'),
    ])
