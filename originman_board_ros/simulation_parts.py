"""The parts of the OriginMan board in its firmware model: patterns, servos, SBUS, the keys.

Plain state with the time passed in, no I/O; the board
(:class:`~originman_board_ros.simulation.VirtualOriginManBoardModel`, which re-exports these
names) owns one of each and drives them from its handlers and events.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Deque, List, Optional, Tuple

from originman_board_ros import protocol as p

KEY_SCAN_S = 0.030
KEY_COMBO_MS = 300
KEY_LONG_PRESS_MS = 1500
KEY_REPEAT_MS = 400
PWM_STEP_S = 0.020
PWM_POWER_UP_PULSE = 1500
SBUS_PERIOD_S = 0.014
SERVO_MAX_SPEED = 1250.0
"""LX servos: 60 degrees (250 units) in 0.2 s at most."""
SERVO_DEFAULT_TEMPERATURE_C = 30
SERVO_DEFAULT_TEMPERATURE_LIMIT_C = 85


# ---------------------------------------------------------------------------------------------
# Parts of the board
# ---------------------------------------------------------------------------------------------

@dataclass
class Pattern:
    """An LED or buzzer pattern as the firmware runs it (O31: repeat 0 = forever)."""

    on_ms: int = 0
    off_ms: int = 0
    repeat: int = 0
    start: float = 0.0
    frequency_hz: int = 0

    def active_at(self, t: float) -> bool:
        """Whether the LED is lit (the buzzer sounds) at ``t``."""
        if self.on_ms == 0:
            return False
        if self.off_ms == 0:
            return True
        cycle = (self.on_ms + self.off_ms) / 1000.0
        elapsed = t - self.start
        if elapsed < 0:
            return False
        k = int(elapsed // cycle)
        if self.repeat and k >= self.repeat:
            return False
        return elapsed - k * cycle < self.on_ms / 1000.0


@dataclass
class Beep:
    """One buzzer pattern started on the board, and who started it."""

    time: float
    frequency_hz: int
    on_ms: int
    off_ms: int
    repeat: int
    source: str  # 'host', 'click' or 'low_battery'


class PwmServo:
    """One PWM output: linear motion in 20 ms steps, offset added to the output (§4.5)."""

    def __init__(self) -> None:
        self.offset_us = 0
        self._start = PWM_POWER_UP_PULSE
        self._target = PWM_POWER_UP_PULSE
        self._t0 = 0.0
        self._steps = 0

    def pulse_at(self, t: float) -> int:
        """Return the current pulse in us, without the offset (what a 0x05 read returns)."""
        if self._steps <= 0:
            return self._target
        done = int((t - self._t0) / PWM_STEP_S + 1e-9)
        remaining = self._steps - done
        if remaining <= 0:
            return self._target
        return self._target + int((self._start - self._target) / self._steps * remaining)

    def output_at(self, t: float) -> int:
        """Return the pulse on the pin, offset included."""
        return self.pulse_at(t) + self.offset_us

    @property
    def target_us(self) -> int:
        """Where the servo is going."""
        return self._target

    def move(self, pulse_us: int, duration_ms: int, t: float) -> None:
        """Start a move as the firmware does: pulse and duration clamped first."""
        pulse_us = min(p.PWM_PULSE_MAX_US, max(p.PWM_PULSE_MIN_US, pulse_us))
        duration_ms = min(p.PWM_DURATION_MAX_MS, max(p.PWM_DURATION_MIN_MS, duration_ms))
        self._start = self.pulse_at(t)
        self._target = pulse_us
        self._t0 = t
        self._steps = duration_ms // 20

    def set_offset(self, offset_us: int) -> None:
        """Set the deviation, clamped to -100..100 us."""
        self.offset_us = min(p.PWM_OFFSET_MAX_US, max(-p.PWM_OFFSET_MAX_US, offset_us))


class SimBusServo:
    """One LX serial-bus servo behind the board."""

    def __init__(self, servo_id: int, position: int = 500, now: float = 0.0) -> None:
        self.servo_id = servo_id
        self.present = True
        self.loaded = False
        self.temperature_c = SERVO_DEFAULT_TEMPERATURE_C
        self.voltage_mv: Optional[int] = None  # None: the board's battery voltage
        self.offset = 0
        self.saved_offset = 0
        self.angle_limits = (0, p.BUS_POSITION_MAX)
        self.voltage_limits = (p.BUS_VOLTAGE_MIN_MV, p.BUS_VOLTAGE_MAX_MV)
        self.temperature_limit_c = SERVO_DEFAULT_TEMPERATURE_LIMIT_C
        self._from = float(position)
        self._to = float(position)
        self._t0 = now
        self._t1 = now

    def position_at(self, t: float) -> float:
        """Where the horn is at ``t`` (logical units, 0..1000 unless moved by hand)."""
        if t >= self._t1 or self._t1 <= self._t0:
            return self._to
        if t <= self._t0:
            return self._from
        return self._from + (self._to - self._from) * (t - self._t0) / (self._t1 - self._t0)

    def read_position(self, t: float) -> int:
        """Return the int16 a 0x05 read returns."""
        return max(-32768, min(32767, int(round(self.position_at(t)))))

    def moving_at(self, t: float) -> bool:
        """Whether a move is under way."""
        return self._t0 <= t < self._t1 and self._from != self._to

    @property
    def target(self) -> float:
        """The end of the current (or last) move."""
        return self._to

    def move(self, position: int, duration_ms: int, t: float) -> None:
        """Move in ``duration_ms`` (or as fast as it can); a move loads the servo (O32)."""
        low, high = self.angle_limits
        target = float(min(high, max(low, position)))
        start = self.position_at(t)
        duration = max(duration_ms / 1000.0, abs(target - start) / SERVO_MAX_SPEED)
        self.loaded = True
        self._from, self._to, self._t0, self._t1 = start, target, t, t + duration

    def hold(self, t: float) -> None:
        """Stop where the horn is now."""
        here = self.position_at(t)
        self._from = self._to = here
        self._t0 = self._t1 = t

    def set_by_hand(self, position: float, t: float) -> None:
        """Turn the horn from outside (any int16, e.g. below 0 with an offset)."""
        self._from = self._to = float(position)
        self._t0 = self._t1 = t


@dataclass
class SbusState:
    """What the SBUS receiver currently reports."""

    channels: Tuple[int, ...]
    ch17: bool = False
    ch18: bool = False
    signal_loss: bool = False
    failsafe: bool = False
    period_s: float = SBUS_PERIOD_S


class _Button:
    """One key: the firmware's 30 ms scan, 2-scan debounce and event state machine (O17)."""

    NORMAL, PRESS, LONG_PRESS = range(3)

    def __init__(self, key_id: int) -> None:
        self.key_id = key_id
        self.script: Deque[Tuple[float, bool]] = deque()  # (time, pin level) to come
        self.pin = False
        self.last_raw = False
        self.last_filtered = False
        self.stage = self.NORMAL
        self.combo = 0
        self.ticks_ms = 0

    def busy(self) -> bool:
        """Whether scans can still change anything."""
        return bool(self.script) or self.stage != self.NORMAL or self.combo != 0 or \
            self.pin != self.last_raw or self.last_raw != self.last_filtered

    def scan(self, t: float) -> List[int]:
        """One scan at ``t``; returns the events it raises, in order."""
        while self.script and self.script[0][0] <= t:
            self.pin = self.script.popleft()[1]
        self.ticks_ms += int(KEY_SCAN_S * 1000)
        pin = self.pin
        if pin != self.last_raw:
            self.last_raw = pin
            return []
        if self.last_filtered == self.last_raw and self.stage == self.NORMAL:
            # Stable and idle: only the multi-click window can expire (O36).
            if self.ticks_ms > KEY_COMBO_MS and self.combo:
                self.combo = 0
                self.ticks_ms = 0
            return []
        self.last_filtered = self.last_raw
        events: List[int] = []
        if self.stage == self.NORMAL:
            if self.last_filtered:
                events.append(p.KeyEvent.PRESSED)
                if self.ticks_ms < KEY_COMBO_MS and self.combo > 0:
                    self.combo += 1
                    if self.combo == 2:
                        events.append(p.KeyEvent.DOUBLE_CLICK)
                    if self.combo == 3:
                        events.append(p.KeyEvent.TRIPLE_CLICK)
                self.ticks_ms = 0
                self.stage = self.PRESS
        elif self.stage == self.PRESS:
            if self.last_filtered:
                if self.ticks_ms > KEY_LONG_PRESS_MS:
                    events.append(p.KeyEvent.LONG_PRESS)
                    self.ticks_ms = 0
                    self.stage = self.LONG_PRESS
            else:
                events += [p.KeyEvent.RELEASE_FROM_SHORT_PRESS, p.KeyEvent.CLICK]
                self.combo = self.combo or 1
                self.stage = self.NORMAL
        else:
            if self.last_filtered:
                if self.ticks_ms > KEY_REPEAT_MS:
                    events.append(p.KeyEvent.LONG_PRESS_REPEAT)
                    self.ticks_ms = 0
            else:
                events.append(p.KeyEvent.RELEASE_FROM_LONG_PRESS)
                self.combo = 0
                self.ticks_ms = KEY_COMBO_MS + 1
                self.stage = self.NORMAL
        return events
