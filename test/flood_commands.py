"""Publish ServoCommand on /servo_bus/command at a rate for a while, from a process of its own.

Run by test_servo_safety.py (so the flood does not take the GIL from the virtual bus in the test
process). Usage: ``python flood_commands.py RATE_HZ SECONDS [IDS]`` (IDS: comma-separated servo
ids, default 1,2; an unknown id makes every command a refusal); prints one JSON line: commands
sent, the last positions, the times (monotonic and wall) of the first and last publication, and
whether (and by when: ``t_acked``) the driver acknowledged every sample before the publisher
left.
"""

import json
import sys
import time

import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from uav_serial_common.process import wait_scale
from uav_serial_drivers.msg import ServoCommand

# How long the publisher waits for the driver to acknowledge its last samples.
ACK_TIMEOUT_S = 30.0


def main() -> None:
    rate, seconds = float(sys.argv[1]), float(sys.argv[2])
    ids = [int(i) for i in (sys.argv[3] if len(sys.argv) > 3 else '1,2').split(',')]
    rclpy.init()
    node = Node('command_flood')
    pub = node.create_publisher(ServoCommand, '/servo_bus/command', 10)
    # Wait for the driver's subscription, so no command is lost to discovery.
    deadline = time.monotonic() + 10 * wait_scale()
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    count = int(rate * seconds)
    start = time.monotonic()
    start_wall = time.time()
    last = None
    for k in range(count):
        due = start + k / rate
        while time.monotonic() < due:
            time.sleep(max(0.0, min(0.0005, due - time.monotonic())))
        x = round(-1.0 + 2.0 * (k % 1000) / 1000, 4)
        last = [x, -x]
        pub.publish(ServoCommand(ids=ids, positions=last, move_time_ms=0))
        t_last, t_last_wall = time.monotonic(), time.time()
    # The publisher is reliable: wait until the driver has acknowledged every sample it still
    # holds (the newest above all) before it goes away. A fixed pause was not enough: beside a
    # busy loop the driver's process did not run for a while, the last samples had not reached
    # it, and a publisher gone 0.5 s after them never sent them again (the newest command was
    # then never on the wire). `acked` says whether that came within the wait.
    acked = pub.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT_S))
    # By then the driver's middleware held every sample: when the newest one reached the driver
    # is between t_last and t_acked (a sample lost in a full socket buffer is repaired only at
    # the writer's next heartbeat, seconds later beside a busy loop).
    t_acked = time.monotonic()
    print(json.dumps({'sent': count, 'last': last, 't_start': start, 't_last': t_last,
                      't_acked': t_acked, 't_start_wall': start_wall,
                      't_last_wall': t_last_wall, 'acked': acked}), flush=True)
    node.destroy_node()
    rclpy.shutdown()


if __name__ == '__main__':
    main()
