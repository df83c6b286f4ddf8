"""A ``~/imu`` subscriber in its own process: receive times that share no GIL with a benchmark.

``python -m bench.imu_receiver TOPIC OUT`` subscribes to TOPIC (``sensor_msgs/Imu``,
reliable, depth 200) on the environment's ROS domain, records ``(angular_velocity.x,
time.monotonic(), header stamp)`` of every message (the monotonic clock is the machine's, the
same in every process) and writes them as JSON to OUT when its stdin closes or it gets
SIGTERM/SIGINT. Once the first message came it prints ``ready`` and the offset of the wall
clock from the monotonic one. The latency benchmark marks each IMU report with its own gyro x.
"""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Iterator, List, Tuple

if __package__ in (None, ''):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: List[str]) -> int:
    import time

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import Imu
    topic, out = argv[0], argv[1]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('bench_imu_receiver')
    raw: List[Tuple[bytes, float]] = []
    monotonic = time.monotonic
    first = threading.Event()

    def on_imu(data: bytes) -> None:
        # The serialized message: it is deserialized after the run, not on the clock.
        raw.append((data, monotonic()))
        first.set()
    node.create_subscription(Imu, topic, on_imu,
                             QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE),
                             raw=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    while not first.wait(0.1) and not stop.is_set():
        pass
    print(f'ready {time.time() - monotonic()!r}', flush=True)
    stop.wait()
    executor.shutdown(timeout_sec=1.0)
    received = []
    for data, t in raw:
        msg = deserialize_message(data, Imu)
        stamp = msg.header.stamp
        received.append((msg.angular_velocity.x, t, stamp.sec + stamp.nanosec * 1e-9))
    Path(out).write_text(json.dumps(received))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


@contextlib.contextmanager
def imu_receiver(topic: str, out: Path, timeout: float = 30.0) -> Iterator[float]:
    """Run a receiver for a ``with`` block, yield its wall-clock offset; records in `out` after."""
    from bench.common import die_with_parent, ROOT, ros_env
    proc = subprocess.Popen([sys.executable, '-m', 'bench.imu_receiver', topic, str(out)],
                            cwd=str(ROOT), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            env=ros_env(), text=True, start_new_session=True,
                            preexec_fn=die_with_parent)
    try:
        ready = threading.Event()
        line: List[str] = []
        threading.Thread(target=lambda: (line.append(proc.stdout.readline()), ready.set()),
                         daemon=True).start()
        if not ready.wait(timeout) or proc.poll() is not None or not line[0].strip():
            raise RuntimeError('the IMU receiver process received nothing')
        yield float(line[0].split()[1])
    finally:
        with contextlib.suppress(OSError):
            proc.stdin.close()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
