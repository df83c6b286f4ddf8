"""How soon a motor stop reaches the OriginMan board while other threads flood it with frames.

The board is the firmware model on a real pty in a process of its own
(``test/originman_rig.BoardProcess``: no GIL shared with the driver); the driver is an
``OriginManCore`` in this process with its own threads. Two flood threads send, as callers of a
node would, 20 bus servo targets every 2 ms (``set_bus_servos``) and an LED or PWM servo command
every 2 ms, so that a caller is nearly always writing frames when a stop comes. Times are the
board's arrival times of the frames (``queue_log``, CLOCK_MONOTONIC, shared by both processes):

- ``originman_stop_*_ms``: from just before ``stop_all_motors()`` to the stop's arrival;
  ``originman_stop_return_*_ms``: to its return (the answer waits until the stop has left);
  ``originman_stop_frames_ahead_max``: the most frames that reached the board after the call
  and before its stop (1 = the one being written when the stop came);
- ``originman_watchdog_stop_*_ms``: from the watchdog's deadline (the last motor command plus
  ``motor_timeout_s``) to the stop's arrival, the same floods running;
- ``originman_stop_write_*_ms`` and ``originman_stop_writes_ahead_max`` (the driver's side,
  free of the board process's own scheduling on a loaded machine): from the call to the return
  of the stop's write to the pty, and the most frames the driver wrote between the call and
  its stop (1: the one being written when the stop came); ``originman_watchdog_stop_write_*``
  the same from the watchdog's deadline.
"""

from __future__ import annotations

import argparse
import random
import sys
import threading
import time
from typing import Any, Dict, List

from bench.common import percentile, ROOT, wait_for, workdir

if str(ROOT / 'test') not in sys.path:
    sys.path.insert(0, str(ROOT / 'test'))

IDS = list(range(1, 21))
MOTOR_TIMEOUT_S = 0.2
FLOOD_PERIOD_S = 0.002


class _Writes:
    """The driver's writes, timed when each returned (the link's ``write``, wrapped)."""

    def __init__(self, core: Any) -> None:
        self.log: List[tuple] = []
        serial = core.link.serial
        write = serial.write

        def timed(data: bytes) -> None:
            write(data)
            self.log.append((time.monotonic(), bytes(data)))
        serial.write = timed

    def stop_after(self, t0: float, stop_frame: bytes) -> Any:
        """Return when the first stop after ``t0`` was written, and the writes before it."""
        after = [(t, f) for t, f in list(self.log) if t >= t0]
        for k, (t, frame) in enumerate(after):
            if frame == stop_frame:
                return t, k
        return None


class _Floods:
    """Two caller threads: servo targets, and LED / PWM servo commands."""

    def __init__(self, core: Any) -> None:
        self.core = core
        self.done = threading.Event()
        self.counts = {'moves': 0, 'commands': 0}
        self.threads = [threading.Thread(target=self._moves, daemon=True),
                        threading.Thread(target=self._commands, daemon=True)]

    def _moves(self) -> None:
        k = 0
        while not self.done.is_set():
            k += 1
            self.core.set_bus_servos(IDS, [(100 + 7 * k + i) % 1000 for i in IDS], 0.02)
            self.counts['moves'] += 1
            time.sleep(FLOOD_PERIOD_S)

    def _commands(self) -> None:
        k = 0
        while not self.done.is_set():
            k += 1
            if k % 2:
                self.core.set_led(1, 0.1, 0.1, 1)
            else:
                self.core.set_pwm_servos([1, 2], [1000 + k % 1000, 2000 - k % 1000], 0.1)
            self.counts['commands'] += 1
            time.sleep(FLOOD_PERIOD_S)

    def __enter__(self) -> '_Floods':
        for thread in self.threads:
            thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.done.set()
        for thread in self.threads:
            thread.join(5)


def _ms(values: List[float], prefix: str) -> Dict[str, float]:
    return {f'{prefix}_p50_ms': percentile(values, 50) * 1e3,
            f'{prefix}_p99_ms': percentile(values, 99) * 1e3,
            f'{prefix}_max_ms': max(values, default=float('nan')) * 1e3,
            f'{prefix}_n': len(values)}


def _stop_after(board: Any, t0: float, p: Any) -> Any:
    """Return the first stop that arrived after ``t0`` and how many frames arrived before it."""
    log = board.call('queue_log')
    after = [e for e in log if e[0] >= t0]
    for k, (arrived, _, cmd) in enumerate(after):
        if isinstance(cmd, p.StopMotors):
            return arrived, k
    return None


def run(stops: int = 40, watchdog_stops: int = 20) -> Dict[str, Any]:
    """Measure both latencies (``stops`` calls, ``watchdog_stops`` watchdog firings)."""
    from originman_board_ros import protocol as p
    from originman_board_ros.core import OriginManConfig, OriginManCore
    from originman_board_ros.plan import STOP_ALL_FRAME
    from originman_rig import BoardProcess

    out: Dict[str, Any] = {}
    rng = random.Random(7)
    with workdir('originman-stop-') as tmp:
        board = BoardProcess(str(tmp / 'board'), bus_servo_ids=IDS)
        try:
            # The calls: no watchdog, so that every stop on the wire is a call's.
            core = OriginManCore(OriginManConfig(port=board.path, motor_timeout_s=0.0,
                                                 bus_servo_ids=()))
            writes = _Writes(core)
            core.start()
            calls, returns, ahead, written, writes_ahead = [], [], [], [], []
            try:
                wait_for(lambda: core.online, 10, what='the board online')
                with _Floods(core):
                    time.sleep(0.5)
                    for _ in range(stops):
                        time.sleep(rng.uniform(0.03, 0.08))
                        t0 = time.monotonic()
                        result = core.stop_all_motors()
                        returns.append(time.monotonic() - t0)
                        if not result.ok:
                            continue
                        found = wait_for(lambda: _stop_after(board, t0, p), 10,
                                         what='the stop on the wire')
                        calls.append(found[0] - t0)
                        ahead.append(found[1])
                        wrote = wait_for(lambda: writes.stop_after(t0, STOP_ALL_FRAME), 10,
                                         what='the stop written')
                        written.append(wrote[0] - t0)
                        writes_ahead.append(wrote[1])
            finally:
                core.stop(stop_motors=False)
            # The watchdog: a motor command, then nothing but the floods.
            core = OriginManCore(OriginManConfig(port=board.path,
                                                 motor_timeout_s=MOTOR_TIMEOUT_S,
                                                 bus_servo_ids=()))
            writes = _Writes(core)
            core.start()
            fired, fired_written = [], []
            try:
                wait_for(lambda: core.online, 10, what='the board online')
                with _Floods(core):
                    time.sleep(MOTOR_TIMEOUT_S + 0.3)  # the stop armed at connect (O38)
                    for _ in range(watchdog_stops):
                        if not core.set_motor_speeds([1], [1.0]).ok:
                            continue
                        with core._lock:
                            last = core._plan.watchdog.last_command_at
                        deadline = last + MOTOR_TIMEOUT_S
                        found = wait_for(lambda: _stop_after(board, deadline, p), 10,
                                         what='the watchdog stop on the wire')
                        fired.append(found[0] - deadline)
                        wrote = wait_for(lambda: writes.stop_after(deadline, STOP_ALL_FRAME),
                                         10, what='the watchdog stop written')
                        fired_written.append(wrote[0] - deadline)
                        time.sleep(rng.uniform(0.02, 0.06))
            finally:
                core.stop(stop_motors=False)
        finally:
            board.stop()
    out.update(_ms(calls, 'originman_stop'))
    out.update(_ms(returns, 'originman_stop_return'))
    out['originman_stop_frames_ahead_max'] = max(ahead, default=-1)
    out.update(_ms(written, 'originman_stop_write'))
    out['originman_stop_writes_ahead_max'] = max(writes_ahead, default=-1)
    out.update(_ms(fired, 'originman_watchdog_stop'))
    out.update(_ms(fired_written, 'originman_watchdog_stop_write'))
    return out


def main() -> None:
    """Print the figures on a ``bench:`` line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--quick', action='store_true', help='15 stops and 8 watchdog stops')
    parser.add_argument('--stops', type=int, default=40)
    parser.add_argument('--watchdog-stops', type=int, default=20)
    a = parser.parse_args()
    r = run(stops=15 if a.quick else a.stops, watchdog_stops=8 if a.quick else a.watchdog_stops)
    print('bench: ' + ' '.join(
        f'{k}={v:.2f}' if isinstance(v, float) else f'{k}={v}' for k, v in r.items()))


if __name__ == '__main__':
    main()
