"""The OriginMan core's commands (the topics): validation, then the frame, then the wire.

Part of :class:`~originman_board_ros.core.OriginManCore` (``originman_board_ros.core``
assembles it; the shared state, ``_lock`` and the other threads are described there).
Threads:

* **caller threads** (a node's executor) call the command methods. They validate (the helpers
  below raise :class:`Refused`; nothing is sent before they all pass), then step the plan with
  their frame (``_step``). The plan refuses it while the board is offline; else the caller
  writes what the plan has ready if no other thread is writing, and waits until its own frame
  has left (``_wait``, on its :class:`~uav_serial_common.ticket.Ticket`), whichever thread
  wrote it.

Owns, under ``_lock``: the refusal counters (``_refusals``).
"""

from __future__ import annotations

import math
from typing import Any, Callable, Iterable, List, Sequence, Tuple

from originman_board_ros import protocol as p
from originman_board_ros.core_types import _is_int, Refused
from originman_board_ros.link import LinkError, LinkTimeout
from originman_board_ros.plan import MotorCommand, Move, StopMotors
from uav_serial_common.result import Result
from uav_serial_common.ticket import Ticket

STOP_ALL_MASK = (1 << p.MOTOR_COUNT) - 1
LED_TIME_MAX_S = 65.535
BUS_DURATION_MAX_S = 65.535
PWM_DURATION_MIN_S = 0.02
PWM_DURATION_MAX_S = 30.0


# ---------------------------------------------------------------------------------------------
# Validation helpers (they raise Refused; nothing is sent before they all pass)
# ---------------------------------------------------------------------------------------------

def _ints(name: str, values: Iterable[Any], lo: int, hi: int) -> List[int]:
    out = []
    for value in values:
        if not _is_int(value):
            if isinstance(value, float) and math.isfinite(value) and value.is_integer():
                value = int(value)
            else:
                raise Refused('out_of_range', f'{name} must be integers in {lo}..{hi}, '
                                              f'got {value!r}')
        if not lo <= value <= hi:
            raise Refused('out_of_range', f'{name} {value} is out of range {lo}..{hi}')
        out.append(int(value))
    return out


def _int(name: str, value: Any, lo: int, hi: int) -> int:
    return _ints(name, [value], lo, hi)[0]


def _seconds(name: str, value: Any, lo: float, hi: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise Refused('out_of_range', f'{name} must be a number of seconds, got {value!r}')
    if not math.isfinite(value):
        raise Refused('not_finite', f'{name} {value} is not finite')
    if not lo <= value <= hi:
        raise Refused('out_of_range', f'{name} {value:g} s is out of range {lo:g}..{hi:g} s')
    return float(value)


def _to_ms(seconds: float) -> int:
    ms = int(round(seconds * 1000.0))
    # A time > 0 shorter than 1 ms is 1 ms: 0 would mean "off" to the board (§4.2).
    return 1 if seconds > 0 and ms == 0 else ms


def _pattern(on_s: Any, off_s: Any, repeat: Any) -> Tuple[int, int, int]:
    """On and off times [ms] and repeat count of an LED or buzzer pattern, checked (O31)."""
    return (_to_ms(_seconds('on_s', on_s, 0.0, LED_TIME_MAX_S)),
            _to_ms(_seconds('off_s', off_s, 0.0, LED_TIME_MAX_S)),
            _int('repeat', repeat, 0, p.U16_MAX))


def _same_length(**lists: Sequence) -> None:
    lengths = {name: len(values) for name, values in lists.items()}
    if len(set(lengths.values())) > 1:
        detail = ', '.join(f'{name} has {n}' for name, n in lengths.items())
        raise Refused('length_mismatch', f'the lists must have the same length: {detail}')


def _distinct(name: str, ids: Sequence[int]) -> None:
    seen = set()
    for i in ids:
        if i in seen:
            raise Refused('duplicate', f'{name} lists {i} twice')
        seen.add(i)


class Commands:
    """The command methods of :class:`~originman_board_ros.core.OriginManCore`."""

    # -- command plumbing -----------------------------------------------------------------------

    def _refuse(self, exc: Refused) -> Result:
        with self._lock:
            self._refusals[exc.cause] = self._refusals.get(exc.cause, 0) + 1
        return Result.refused(exc.cause, str(exc))

    def _require_online(self) -> None:
        if not self.link.port_open:
            raise Refused('offline', f'port {self.config.port} is not open: '
                                     f'{self.link.serial.last_error or "connecting"}')
        if not self._plan.online:
            raise Refused('offline', f'the board is offline ({self._status})')

    def _send_all(self, frames: Sequence[bytes], what: str,
                  cancels: Sequence[int] = ()) -> Result:
        try:
            for frame in frames:
                self._write(frame, cancels)
        except LinkTimeout as exc:
            return Result.unknown(f'{what}: {exc}', cause='timeout')
        except LinkError as exc:
            return Result.failed(f'{what}: not sent: {exc}', cause='link_down')
        # The board never acknowledges these: "sent" is all anyone can know.
        return Result.sent(f'{what}: sent')

    def _command(self, build: Callable[[], Tuple[List[bytes], str]]) -> Result:
        try:
            frames, what = build()
            self._require_online()
        except Refused as exc:
            return self._refuse(exc)
        return self._send_all(frames, what)

    # -- topics ---------------------------------------------------------------------------------

    def set_led(self, led_id: int, on_s: float, off_s: float, repeat: int) -> Result:
        """Blink LED 1 or 2 (on 0 = off, off 0 = steady, repeat 0 = forever, O31)."""
        def build() -> Tuple[List[bytes], str]:
            led = _int('led_id', led_id, p.LED_IDS[0], p.LED_IDS[-1])
            on, off, count = _pattern(on_s, off_s, repeat)
            return [p.encode_led(led, on, off, count)], \
                f'LED {led}: on {on} ms, off {off} ms, repeat {count}'
        return self._command(build)

    def set_buzzer(self, frequency_hz: int, on_s: float, off_s: float,
                   repeat: int) -> Result:
        """Beep (frequency 0 or on 0 = silent, off 0 = continuous, repeat 0 = forever)."""
        def build() -> Tuple[List[bytes], str]:
            freq = _int('frequency_hz', frequency_hz, 0, p.U16_MAX)
            on, off, count = _pattern(on_s, off_s, repeat)
            return [p.encode_buzzer(freq, on, off, count)], \
                f'buzzer: {freq} Hz, on {on} ms, off {off} ms, repeat {count}'
        return self._command(build)

    def set_rgb(self, indices: Sequence[int], red: Sequence[int], green: Sequence[int],
                blue: Sequence[int]) -> Result:
        """Colour RGB pixels 1..2 (1-based here, 0-based on the wire, O18)."""
        def build() -> Tuple[List[bytes], str]:
            idx = _ints('indices', list(indices), 1, p.RGB_PIXEL_COUNT)
            _same_length(indices=idx, red=list(red), green=list(green), blue=list(blue))
            if not idx:
                raise Refused('empty', 'no pixel given')
            _distinct('indices', idx)
            r, g, b = (_ints(n, list(v), 0, 255) for n, v in
                       (('red', red), ('green', green), ('blue', blue)))
            pixels = [(i - 1, r[k], g[k], b[k]) for k, i in enumerate(idx)]
            return [p.encode_rgb(pixels)], 'RGB ' + ', '.join(
                f'{i}: ({r[k]}, {g[k]}, {b[k]})' for k, i in enumerate(idx))
        return self._command(build)

    def set_oled(self, line: int, text: str) -> Result:
        """Show ``text`` (at most 23 bytes of UTF-8, O19) on OLED line 1 or 2."""
        def build() -> Tuple[List[bytes], str]:
            n = _int('line', line, p.OLED_LINES[0], p.OLED_LINES[-1])
            if not isinstance(text, str):
                raise Refused('out_of_range', f'text must be a string, got {text!r}')
            size = len(text.encode('utf-8'))
            if size > p.OLED_TEXT_MAX_BYTES:
                raise Refused('too_long', f'OLED text is {size} bytes of UTF-8, at most '
                                          f'{p.OLED_TEXT_MAX_BYTES} fit: {text!r}')
            return [p.encode_oled(n, text)], f'OLED line {n}: {text!r}'
        return self._command(build)

    def set_motor_speeds(self, motor_ids: Sequence[int], rps: Sequence[float]) -> Result:
        """Set motor speeds (ids 1..4, O3; finite, |rps| <= 6). Any call restarts the timeout.

        An empty call sends nothing and only restarts the motor timeout (a keep-alive).
        """
        def build() -> Tuple[List[bytes], str]:
            ids = _ints('motor_ids', list(motor_ids), 1, p.MOTOR_COUNT)
            speeds = list(rps)
            _same_length(motor_ids=ids, rps=speeds)
            _distinct('motor_ids', ids)
            for value in speeds:
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise Refused('out_of_range', f'rps must be numbers, got {value!r}')
                if not math.isfinite(value):
                    raise Refused('not_finite', f'rps {value} is not finite')
                if abs(value) > p.MAX_RPS:
                    raise Refused('out_of_range', f'rps {value:g} is beyond +-{p.MAX_RPS:g} '
                                                  '(the fastest motor type)')
            if not ids:
                return [], 'motor timeout restarted'
            frame = p.encode_motor_speeds([(i - 1, float(v)) for i, v in zip(ids, speeds)])
            return [frame], 'motors ' + ', '.join(
                f'{i}: {v:g} r/s' for i, v in zip(ids, speeds))
        try:
            frames, what = build()
            self._require_online()
        except Refused as exc:
            return self._refuse(exc)
        ticket = Ticket()
        # Zeros and empty calls restart the timeout too; a refused one does not: its sender
        # is not in control of the motors (O39). The new deadline reaches the timer as the
        # plan's SetTimer.
        self._step(MotorCommand(self._clock(), frames[0] if frames else None, ticket))
        if self._refused(ticket):
            return self._refuse(Refused('offline', f'the board is offline ({self._status})'))
        if not frames:
            return Result.sent(f'{what}: sent')
        try:
            error = self._wait(ticket)
        except LinkTimeout as exc:
            return Result.unknown(f'{what}: {exc}', cause='timeout')
        if error is not None:
            return Result.failed(f'{what}: not sent: {error}', cause='link_down')
        return Result.sent(f'{what}: sent')

    def stop_all_motors(self) -> Result:
        """Set every motor's speed to 0 (MOTOR 0x03, mask 0x0F), offline or not; for shutdown.

        The stop goes out ahead of every queued frame, after at most the one frame another
        thread is writing; the answer comes once it has left.
        """
        ticket = Ticket()
        self._step(StopMotors(self._clock(), ticket))
        try:
            error = self._wait(ticket)
        except LinkTimeout as exc:
            return Result.unknown(f'stop all motors: {exc}', cause='timeout')
        if error is not None:
            return Result.failed(f'stop all motors: not sent: {error}', cause='link_down')
        return Result.sent('stop all motors: sent')

    def set_pwm_servos(self, ids: Sequence[int], pulses_us: Sequence[int],
                       duration_s: float) -> Result:
        """Move PWM servos 1..4 to 500..2500 us in 0.02..30 s, one frame (O10)."""
        def build() -> Tuple[List[bytes], str]:
            servo_ids = _ints('ids', list(ids), 1, p.PWM_SERVO_COUNT)
            pulses = _ints('pulses_us', list(pulses_us), p.PWM_PULSE_MIN_US,
                           p.PWM_PULSE_MAX_US)
            _same_length(ids=servo_ids, pulses_us=pulses)
            if not servo_ids:
                raise Refused('empty', 'no PWM servo given')
            _distinct('ids', servo_ids)
            duration = _seconds('duration_s', duration_s, PWM_DURATION_MIN_S,
                                PWM_DURATION_MAX_S)
            ms = max(p.PWM_DURATION_MIN_MS, _to_ms(duration))
            return [p.encode_pwm_move(ms, list(zip(servo_ids, pulses)))], \
                f'PWM servos {servo_ids} to {pulses} us in {ms} ms'
        return self._command(build)

    def set_bus_servos(self, ids: Sequence[int], positions: Sequence[int],
                       duration_s: float) -> Result:
        """Move bus servos (ids 0..253) to positions 0..1000 in 0..65.535 s (O23)."""
        def build() -> Tuple[List[bytes], str]:
            servo_ids = _ints('ids', list(ids), 0, p.BUS_ID_MAX)
            targets = _ints('positions', list(positions), 0, p.BUS_POSITION_MAX)
            _same_length(ids=servo_ids, positions=targets)
            if not servo_ids:
                raise Refused('empty', 'no bus servo given')
            _distinct('ids', servo_ids)
            ms = _to_ms(_seconds('duration_s', duration_s, 0.0, BUS_DURATION_MAX_S))
            return (ms, list(zip(servo_ids, targets))), \
                f'bus servos {servo_ids} to {targets} in {ms} ms'
        try:
            (ms, items), what = build()
            self._require_online()
        except Refused as exc:
            return self._refuse(exc)
        ticket = Ticket()
        # Issue 21 item 7: the newest target of each servo waits for room on the board's
        # servo bus; a later command for the same servo replaces it.
        self._step(Move(self._clock(), ms, tuple(items), ticket))
        if self._refused(ticket):
            return self._refuse(Refused('offline', f'the board is offline ({self._status})'))
        with self._lock:
            waiting = [i for i, _ in items if i in self._plan.scheduler.targets]
        if waiting:
            return Result.sent(f'{what}: queued (the servo bus is busy; a newer target of the '
                               'same servo replaces it)')
        return Result.sent(f'{what}: sent')
