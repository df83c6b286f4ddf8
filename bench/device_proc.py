"""A virtual servo bus in its own process: background load that shares no GIL with a benchmark.

``python -m bench.device_proc LINK BAUD ID [ID ...]`` runs ``VirtualServoBus`` (``ServoBusSim``
behind a ``VirtualDeviceRunner``, with the benchmarks' response delay) at LINK until its stdin
closes or it gets SIGTERM/SIGINT; it prints ``ready`` once the port exists.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Iterator, List

if __package__ in (None, ''):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: List[str]) -> int:
    from bench.common import BENCH_SERVO_RESPONSE_DELAY_S
    from desheng_servo_ros.virtual_node import VirtualServoBus
    link, baud, ids = argv[0], int(argv[1]), [int(a) for a in argv[2:]]
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    bus = VirtualServoBus(link, ids, baud=baud, response_delay_s=BENCH_SERVO_RESPONSE_DELAY_S)
    bus.start()
    try:
        print('ready', flush=True)
        stop.wait()
    finally:
        bus.stop()
    return 0


@contextlib.contextmanager
def servo_bus_process(link: str, baud: int, ids: List[int],
                      timeout: float = 20.0) -> Iterator[subprocess.Popen]:
    """Run a virtual servo bus process for the duration of a ``with`` block."""
    from bench.common import die_with_parent, ROOT
    proc = subprocess.Popen([sys.executable, '-m', 'bench.device_proc', link, str(baud)]
                            + [str(i) for i in ids], cwd=str(ROOT), stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=die_with_parent)
    try:
        ready = threading.Event()
        threading.Thread(target=lambda: (proc.stdout.readline(), ready.set()),
                         daemon=True).start()
        if not ready.wait(timeout) or proc.poll() is not None:
            raise RuntimeError('virtual servo bus process did not start')
        yield proc
    finally:
        with contextlib.suppress(OSError):
            proc.stdin.close()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
