"""Commands to ``servo_bus_node`` from a process of its own, each with the time it was sent.

``python -m bench.servo_client MODE COUNT FIRST_TICKS IDS`` (MODE ``command`` or
``write_positions``) sends COUNT moves of the servos IDS (comma-separated) at random moments
(``command``: 15-35 ms apart; ``write_positions``: 10-30 ms after the previous answer), move k to
``FIRST_TICKS + k`` ticks, so each frame on the wire names its move. It prints one JSON line:
``{"sent": [[ticks, t_monotonic], ...], "round_trip_ms": [...], "failed": n}`` with the time
taken just before ``publish()`` / ``call_async()``. In a process of its own the publisher
shares no GIL with the virtual bus whose wire times the benchmark takes.
"""

from __future__ import annotations

import json
import math
import random
import sys
import threading
import time
from pathlib import Path
from typing import List

if __package__ in (None, ''):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _rad(ticks: int) -> float:
    return (ticks - 2048) * 2.0 * math.pi / 4096


def main(argv: List[str]) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from uav_serial_drivers.msg import ServoCommand
    from uav_serial_drivers.srv import WritePositions
    mode, count, first = argv[0], int(argv[1]), int(argv[2])
    ids = [int(i) for i in argv[3].split(',')]
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('bench_servo_client')
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    rng = random.Random(7 if mode == 'command' else 11)
    sent, round_trip, failed = [], [], 0
    if mode == 'command':
        pub = node.create_publisher(ServoCommand, '/servo_bus/command', 10)
        deadline = time.monotonic() + 20
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.5)
        for k in range(count):
            time.sleep(rng.uniform(0.015, 0.035))
            ticks = first + k
            msg = ServoCommand(ids=ids, positions=[_rad(ticks)] * len(ids), move_time_ms=0)
            t0 = time.monotonic()
            pub.publish(msg)
            sent.append((ticks, t0))
        time.sleep(0.5)  # delivered before the publisher goes
    else:
        client = node.create_client(WritePositions, '/servo_bus/write_positions')
        if not client.wait_for_service(timeout_sec=20.0):
            raise RuntimeError('~/write_positions not available')
        for k in range(count):
            time.sleep(rng.uniform(0.010, 0.030))
            ticks = first + k
            request = WritePositions.Request(ids=ids, positions=[_rad(ticks)] * len(ids),
                                             move_time_ms=0, staged=False)
            done = threading.Event()
            t0 = time.monotonic()
            future = client.call_async(request)
            future.add_done_callback(lambda _f: done.set())
            if not done.wait(10.0):
                failed += 1
                continue
            round_trip.append((time.monotonic() - t0) * 1000.0)
            if future.result().success:
                sent.append((ticks, t0))
            else:
                failed += 1
    print(json.dumps({'sent': sent, 'round_trip_ms': round_trip, 'failed': failed}), flush=True)
    executor.shutdown(timeout_sec=1.0)
    spinner.join(2.0)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def run_client(mode: str, count: int, first_ticks: int, ids: List[int],
               timeout: float = 120.0) -> dict:
    """Run the client process to the end; return what it printed."""
    import subprocess
    from bench.common import die_with_parent, ROOT, ros_env
    done = subprocess.run([sys.executable, '-m', 'bench.servo_client', mode, str(count),
                           str(first_ticks), ','.join(map(str, ids))],
                          cwd=str(ROOT), env=ros_env(), capture_output=True, text=True,
                          timeout=timeout, preexec_fn=die_with_parent)
    if done.returncode != 0:
        raise RuntimeError(f'servo_client {mode} failed:\n{done.stderr[-2000:]}')
    return json.loads(done.stdout.strip().splitlines()[-1])


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
