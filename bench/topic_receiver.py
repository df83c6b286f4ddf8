"""A subscriber in its own process that records when each message left its publisher.

``python -m bench.topic_receiver TYPE TOPIC OUT`` subscribes to TOPIC (TYPE such as
``sensor_msgs/msg/JointState``; reliable, depth 200) on the environment's ROS domain and records,
for every message, the serialized bytes, ``time.monotonic()`` at receipt and the middleware's
*source timestamp* (``MessageInfo``: the publisher's system clock when it wrote the sample).
When its stdin closes or it gets SIGTERM/SIGINT it deserializes them and writes
``[[message as a dict of the fields asked for], t_received, source_timestamp_s], ...]`` as JSON
to OUT. Once the first message came it prints ``ready`` and the offset of the wall clock from
the monotonic one, so a benchmark turns the source timestamps into its own monotonic time. The
fields recorded are given by ``--fields a,b.c`` (default: ``header.stamp`` and ``position``).
"""

from __future__ import annotations

import contextlib
import importlib
import json
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any, Iterator, List, Sequence, Tuple

if __package__ in (None, ''):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DEFAULT_FIELDS = ('header.stamp', 'position')


def _message_type(name: str) -> Any:
    package, kind, cls = name.split('/')
    return getattr(importlib.import_module(f'{package}.{kind}'), cls)


def _field(msg: Any, path: str) -> Any:
    for part in path.split('.'):
        msg = getattr(msg, part)
    if hasattr(msg, 'sec') and hasattr(msg, 'nanosec'):
        return msg.sec + msg.nanosec * 1e-9
    if isinstance(msg, (str, int, float, bool)):
        return msg
    return list(msg)


def main(argv: List[str]) -> int:
    import time

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message
    from rclpy.signals import SignalHandlerOptions
    fields: Sequence[str] = DEFAULT_FIELDS
    if '--fields' in argv:
        at = argv.index('--fields')
        fields = argv[at + 1].split(',')
        argv = argv[:at] + argv[at + 2:]
    msg_type, topic, out = _message_type(argv[0]), argv[1], argv[2]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('bench_topic_receiver')
    raw: List[Tuple[bytes, float, int]] = []
    monotonic = time.monotonic
    first = threading.Event()

    def on_message(data: bytes, info: Any) -> None:
        # Serialized: deserialized after the run, not on the clock.
        raw.append((data, monotonic(), info['source_timestamp']))
        first.set()
    node.create_subscription(msg_type, topic, on_message,
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
    for data, t, source_ns in raw:
        msg = deserialize_message(data, msg_type)
        received.append(({name: _field(msg, name) for name in fields}, t, source_ns * 1e-9))
    Path(out).write_text(json.dumps(received))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


@contextlib.contextmanager
def topic_receiver(msg_type: str, topic: str, out: Path, fields: Sequence[str] = DEFAULT_FIELDS,
                   timeout: float = 30.0) -> Iterator[float]:
    """Run a receiver for a ``with`` block, yield its wall-clock offset; records in `out` after."""
    from bench.common import die_with_parent, ROOT, ros_env
    proc = subprocess.Popen([sys.executable, '-m', 'bench.topic_receiver', msg_type, topic,
                             str(out), '--fields', ','.join(fields)],
                            cwd=str(ROOT), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            env=ros_env(), text=True, start_new_session=True,
                            preexec_fn=die_with_parent)
    try:
        ready = threading.Event()
        line: List[str] = []
        threading.Thread(target=lambda: (line.append(proc.stdout.readline()), ready.set()),
                         daemon=True).start()
        if not ready.wait(timeout) or proc.poll() is not None or not line[0].strip():
            raise RuntimeError(f'the receiver of {topic} received nothing')
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
