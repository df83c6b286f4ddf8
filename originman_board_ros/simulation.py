"""Plain-Python model of the OriginMan expansion board's firmware: host bytes in, board bytes out.

No I/O, no threads, no wall clock: the caller passes the time (seconds, any origin; an earlier
time than the last is taken as the last). ``receive(data, now)`` and ``step(now)`` return the
bytes the board has sent by ``now``; ``next_event_time()`` says when it will next send or change
something on its own. These fit ``VirtualDeviceRunner(on_input=sim.receive, on_tick=sim.step,
next_event=sim.next_event_time)``, which adds wire timing and the wire faults.

What is modelled, with the decisions of ``docs/protocols.md`` (O1..):

* the firmware's parser with its quirks (:class:`protocol.BoardParser`, O21, O22, O33): no
  resynchronisation on the byte after a failed 0xAA, FUNCTION >= 12 dropped, short frames read
  the CRC and then zeros, extra bytes ignored, nothing ever sent back for a bad frame;
* one handler at a time in arrival order; a bus-servo command takes the servo bus's time
  (115200 baud) and a read waits for the servo's answer (~1 ms) or the 5 ms timeout, so replies
  and later commands wait behind it (§6);
* reports: IMU at ``imu_rate_hz`` (g and deg/s, O7, O8), battery every 1.05 s (O9), key
  events from a 30 ms scan of scripted key presses exactly as the firmware's button driver
  (O17), SBUS frames while set, gamepad and ASR reports on demand;
* motors (set-points, type, stop mask; wire ids >= 4 ignored and counted, O3), PWM servos
  (linear motion in 20 ms steps, offsets, clamps, replies), a bus of LX servos (position and
  timed moves, loading on a move (O32), voltage, temperature, id, deviation, limits with the
  firmware's clamps (O24), stop; a read of an absent servo answers -1 after 5 ms, O14);
* the board's own behaviour (§8): a beep on every click, the low-battery alarm with the SYS
  0x01 threshold; ``buzzer_log`` records every beep pattern with its source;
* a fault: with ``answer_reads`` False the board handles every frame (commands act, reads
  take their servo-bus time) but sends no reply to a read, while its reports keep coming
  (issue 21 item 6). ``queue_log`` records how long each command waited for the receive task,
  behind the servo-bus work of the frames before it (item 7).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
import math
import struct
from typing import Callable, Deque, Dict, Iterable, List, Optional, Sequence, Tuple

from originman_board_ros import protocol as p
from uav_serial_common.device_model import ClockedModel

IMU_RATE_HZ = 50.0
"""O8: no rate is documented; 50 Hz is what the 2025 firmware's DRDY + 20 ms loop gives."""
BATTERY_PERIOD_S = 1.05
"""O9: 21 x 50 ms."""
BATTERY_MV = 7400
BATTERY_LIMIT_MV = 6300
"""The firmware's default low-battery threshold (SYS 0x01 changes it)."""
LOW_BATTERY_FLOOR_MV = 4900
LOW_BATTERY_DELAY_S = 10.0
LOW_BATTERY_BEEP = (2100, 800, 200, 5)
CLICK_BEEP = (2000, 50, 50, 1)
KEY_SCAN_S = 0.030
KEY_COMBO_MS = 300
KEY_LONG_PRESS_MS = 1500
KEY_REPEAT_MS = 400
KEY_CLICK_HOLD_S = 0.10
KEY_CLICK_GAP_S = 0.10
KEY_LONG_HOLD_S = 2.5
PWM_STEP_S = 0.020
PWM_POWER_UP_PULSE = 1500
SBUS_PERIOD_S = 0.014
SBUS_CENTRE = 992
OLED_POWER_UP_TEXT = b'---.---.---.---'
SERVO_BUS_BAUD = 115200
SERVO_ANSWER_S = 0.001
"""The servo's answer to a read, its frame included (§6)."""
SERVO_TIMEOUT_S = 0.005
"""The firmware's read timeout (``proc_timeout = 5`` ticks)."""
SERVO_MAX_SPEED = 1250.0
"""LX servos: 60 degrees (250 units) in 0.2 s at most."""
SERVO_DEFAULT_TEMPERATURE_C = 30
SERVO_DEFAULT_TEMPERATURE_LIMIT_C = 85
COMMAND_LOG_SIZE = 2000

ImuSource = Callable[[float], Tuple[Sequence[float], Sequence[float]]]
"""A function of the model's time giving ``(accel_g, gyro_dps)`` for the next IMU report."""


def _servo_bus_time(nbytes: int) -> float:
    return nbytes * 10 / SERVO_BUS_BAUD


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


# ---------------------------------------------------------------------------------------------
# The board
# ---------------------------------------------------------------------------------------------

class VirtualOriginManBoardModel(ClockedModel):
    """Deterministic model of the board firmware, clocked by its caller.

    Public state (read it in tests; the scenario methods change it): ``powered``,
    ``battery_mv``, ``battery_limit_mv``, ``imu_rate_hz``, ``accel_g``, ``gyro_dps``,
    ``motor_type``, ``motor_set_points`` (wire ids 0..3), ``motors_initialized``,
    ``pwm_servos`` (ids 1..4), ``bus_servos`` (list of :class:`SimBusServo`), ``leds``
    (ids 1..2), ``buzzer``, ``buzzer_log``, ``oled_lines`` (1..2), ``rgb`` (pixels 0..1),
    ``sbus``, ``low_battery_alarms``, ``command_log`` ((time, command) handled, newest last).
    ``answer_reads`` (False: reads get no reply, reports go on), ``queue_log`` ((arrival, handled,
    command), newest last). Counters: ``frames_handled``, ``commands_ignored``,
    ``bad_motor_ids``, ``bad_pwm_ids``, ``bus_reads``, ``bus_read_failures``, ``reports_sent``
    and the parser's ``parser.*``.
    """

    def __init__(self, now: float = 0.0, *, bus_servo_ids: Iterable[int] = (1, 2, 3),
                 battery_mv: int = BATTERY_MV, imu_rate_hz: float = IMU_RATE_HZ,
                 battery_period_s: float = BATTERY_PERIOD_S) -> None:
        if not battery_period_s > 0:
            raise ValueError(f'battery_period_s must be positive, got {battery_period_s!r}')
        super().__init__(now)
        self.battery_period_s = float(battery_period_s)
        self.battery_mv = int(battery_mv)
        self.imu_rate_hz = 0.0
        self.accel_g: Tuple[float, float, float] = (0.0, 0.0, 1.0)
        self.gyro_dps: Tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.imu_source: Optional[ImuSource] = None
        self.bus_servos: List[SimBusServo] = []
        for servo_id in bus_servo_ids:
            self.add_bus_servo(servo_id)
        self.parser = p.BoardParser()
        self.command_log: Deque[Tuple[float, p.HostCommand]] = deque(maxlen=COMMAND_LOG_SIZE)
        self.buzzer_log: List[Beep] = []
        self.frames_handled = 0
        self.commands_ignored = 0
        self.bad_motor_ids = 0
        self.bad_pwm_ids = 0
        self.bus_reads = 0
        self.bus_read_failures = 0
        self.reports_sent = 0
        self.answer_reads = True
        self.queue_log: Deque[Tuple[float, float, p.HostCommand]] = deque(
            maxlen=COMMAND_LOG_SIZE)
        self.low_battery_alarms = 0
        self.boots = 0
        self.powered = False
        self._boot()
        self.set_imu(rate_hz=imu_rate_hz)

    # -- wire (step, advance, now and next_event_time are ClockedModel's) ----------------------

    def receive(self, data: bytes, now: Optional[float] = None) -> bytes:
        """Take host bytes that finished arriving at ``now``; return the bytes sent by then."""
        if now is not None:
            self._advance_to(now)
        if self.powered:
            for frame in self.parser.feed(data):
                self._inbox.append((self._now, frame))
            self._advance_to(self._now)
        return self._collect()

    @property
    def handler_free_at(self) -> float:
        """When the firmware's receive task can start the next command (§6)."""
        return self._handler_free_at

    # -- scenario -------------------------------------------------------------------------------

    def set_imu(self, accel_g: Optional[Sequence[float]] = None,
                gyro_dps: Optional[Sequence[float]] = None,
                rate_hz: Optional[float] = None) -> None:
        """Set what the IMU reports (g, deg/s, O7) and/or its rate (0 = silent, O8)."""
        if accel_g is not None:
            self.accel_g = _triple(accel_g, 'accel_g')
        if gyro_dps is not None:
            self.gyro_dps = _triple(gyro_dps, 'gyro_dps')
        if rate_hz is not None:
            if not (math.isfinite(rate_hz) and rate_hz >= 0):
                raise ValueError(f'rate_hz must be >= 0, got {rate_hz!r}')
            self.imu_rate_hz = float(rate_hz)
            self._imu_at = self._now + 1.0 / rate_hz if rate_hz > 0 else None

    def set_imu_source(self, source: Optional[ImuSource]) -> None:
        """Let ``source(t)`` give ``(accel_g, gyro_dps)`` for each report at ``t``; None: fixed.

        A scenario that moves the board (a sway, a turn), or one that marks every report with
        a value of its own to follow it through a driver (the latency benchmark).
        """
        self.imu_source = source

    def set_battery_period(self, period_s: float) -> None:
        """Change the battery report period (1.05 s on the real board); the next is due then."""
        if not period_s > 0:
            raise ValueError(f'period_s must be positive, got {period_s!r}')
        self.battery_period_s = float(period_s)
        self._battery_at = self._now + self.battery_period_s

    def set_battery_mv(self, millivolts: int) -> None:
        """Set the battery voltage the board measures."""
        self.battery_mv = int(millivolts)
        self._check_battery()

    def press_key(self, key_id: int, kind: str = 'click', hold_s: Optional[float] = None) -> None:
        """Press key 1 or 2 from now, the way ``kind`` says.

        ``click``, ``double``, ``triple``, ``long`` (held ``hold_s``, default 2.5 s), or
        ``down`` / ``up`` to hold and release by hand.
        """
        if key_id not in self._buttons:
            raise ValueError(f'key_id must be one of {p.KEY_IDS}, got {key_id!r}')
        button = self._buttons[key_id]
        t = max(self._now, button.script[-1][0] if button.script else self._now)
        if kind in ('click', 'double', 'triple'):
            clicks = {'click': 1, 'double': 2, 'triple': 3}[kind]
            hold = KEY_CLICK_HOLD_S if hold_s is None else hold_s
            for k in range(clicks):
                button.script.append((t, True))
                button.script.append((t + hold, False))
                t += hold + KEY_CLICK_GAP_S
        elif kind == 'long':
            button.script.append((t, True))
            button.script.append((t + (KEY_LONG_HOLD_S if hold_s is None else hold_s), False))
        elif kind in ('down', 'up'):
            button.script.append((t, kind == 'down'))
        else:
            raise ValueError(f"kind must be click, double, triple, long, down or up, "
                             f"got {kind!r}")
        self._schedule_scan()

    def set_sbus(self, channels: Optional[Sequence[int]] = None, ch17: bool = False,
                 ch18: bool = False, signal_loss: bool = False, failsafe: bool = False,
                 period_s: float = SBUS_PERIOD_S) -> None:
        """Start SBUS frames (16 raw channels, O16) every ``period_s``; ``None`` stops them."""
        if channels is None:
            self.sbus = None
            self._sbus_at = None
            return
        if len(channels) != p.SBUS_CHANNELS:
            raise ValueError(f'SBUS needs {p.SBUS_CHANNELS} channels, got {len(channels)}')
        self.sbus = SbusState(tuple(int(c) for c in channels), ch17, ch18, signal_loss,
                              failsafe, period_s)
        self._sbus_at = self._now

    def send_gamepad(self, buttons: int = 0, hat: int = 0, lx: int = 0, ly: int = 0,
                     rx: int = 0, ry: int = 0) -> None:
        """Send one gamepad report now (O15; the OriginMan board itself never does)."""
        self._report(self._now, p.encode_gamepad_report(buttons, hat, lx, ly, rx, ry))

    def send_asr(self, data: bytes = b'\xbb\xcc\x00\x01\x00') -> None:
        """Send one speech-recognition result now (FUNCTION 12, O2)."""
        self._report(self._now, p.encode_asr_report(data))

    def add_bus_servo(self, servo_id: int, position: int = 500) -> SimBusServo:
        """Connect a servo to the bus (same id twice: their answers collide)."""
        if not 0 <= servo_id <= p.BUS_ID_MAX:
            raise ValueError(f'bus servo id must be 0..{p.BUS_ID_MAX}, got {servo_id!r}')
        servo = SimBusServo(servo_id, position, self._now)
        self.bus_servos.append(servo)
        return servo

    def remove_bus_servo(self, servo_id: int) -> None:
        """Disconnect every servo with ``servo_id``: its reads fail after the timeout."""
        self.bus_servos = [s for s in self.bus_servos if s.servo_id != servo_id]

    def bus_servo(self, servo_id: int) -> SimBusServo:
        """Return the (first) servo with ``servo_id``."""
        for s in self.bus_servos:
            if s.servo_id == servo_id:
                return s
        present = [s.servo_id for s in self.bus_servos]
        raise KeyError(f'no bus servo {servo_id} (present: {present})')

    def power_off(self) -> None:
        """Switch the board off: silent, deaf, every setting lost."""
        self.powered = False
        self._drop_output()

    def power_on(self) -> None:
        """Switch the board on again (a reboot): power-up state, reports restart."""
        if not self.powered:
            self._boot()

    def reboot(self) -> None:
        """Power-cycle at the current time."""
        self.power_off()
        self._boot()

    # -- views ----------------------------------------------------------------------------------

    def motor_speed(self, wire_id: int) -> float:
        """Return the speed wire id ``wire_id`` is driven at: its set-point clamped to the type."""
        limit = p.MOTOR_TYPE_MAX_RPS[p.MotorType(self.motor_type)]
        return max(-limit, min(limit, self.motor_set_points[wire_id]))

    def pwm_pulse(self, servo_id: int) -> int:
        """PWM servo ``servo_id``'s current pulse without offset (what a read returns)."""
        return self.pwm_servos[servo_id].pulse_at(self._now)

    def oled_text(self, line: int) -> str:
        """Return the text shown on OLED line 1 or 2."""
        return self.oled_lines[line].decode('utf-8', errors='replace')

    # -- power ----------------------------------------------------------------------------------

    def _boot(self) -> None:
        self.powered = True
        self.boots += 1
        now = self._now
        self.parser.reset()
        self._inbox: Deque[Tuple[float, p.HostFrame]] = deque()
        self._handler_free_at = now
        self.battery_limit_mv = BATTERY_LIMIT_MV
        self.motor_type = int(p.MotorType.JGB520)
        self.motor_set_points = [0.0] * p.MOTOR_COUNT
        self.motors_initialized = False
        self.pwm_servos: Dict[int, PwmServo] = {i: PwmServo()
                                                for i in range(1, p.PWM_SERVO_COUNT + 1)}
        self.leds: Dict[int, Pattern] = {i: Pattern(start=now) for i in p.LED_IDS}
        self.buzzer = Pattern(start=now)
        self.oled_lines: Dict[int, bytes] = {i: OLED_POWER_UP_TEXT for i in p.OLED_LINES}
        self.rgb: List[Tuple[int, int, int]] = [(0, 0, 0)] * p.RGB_PIXEL_COUNT
        self._buttons = {i: _Button(i) for i in p.KEY_IDS}
        self._scan_at: Optional[float] = None
        self._boot_time = now
        self._battery_at = now + self.battery_period_s
        self._imu_at = now + 1.0 / self.imu_rate_hz if self.imu_rate_hz > 0 else None
        self.sbus: Optional[SbusState] = None
        self._sbus_at: Optional[float] = None
        self._low_since: Optional[float] = None
        self._check_battery()

    # -- time -----------------------------------------------------------------------------------

    def _next_internal_event(self) -> Optional[float]:
        if not self.powered:
            return None
        times = [self._battery_at, self._imu_at, self._scan_at, self._sbus_at,
                 self._low_since + LOW_BATTERY_DELAY_S if self._low_since is not None else None]
        if self._inbox:
            times.append(max(self._inbox[0][0], self._handler_free_at))
        present = [t for t in times if t is not None]
        return min(present) if present else None

    def _process_events(self) -> None:
        now = self._now
        if self._inbox and max(self._inbox[0][0], self._handler_free_at) <= now:
            arrived, frame = self._inbox.popleft()
            self._handler_free_at = now + self._handle(frame, now)
            self.queue_log.append((arrived, now, self.command_log[-1][1]))
        if self._imu_at is not None and self._imu_at <= now:
            self._imu_at += 1.0 / self.imu_rate_hz
            if self.imu_source is not None:
                self.accel_g, self.gyro_dps = (_triple(v, n) for v, n in zip(
                    self.imu_source(now), ('accel_g', 'gyro_dps')))
            self._report(now, p.encode_imu_report(self.accel_g, self.gyro_dps))
        if self._battery_at <= now:
            self._battery_at += self.battery_period_s
            self._report(now, p.encode_battery_report(max(0, min(p.U16_MAX, self.battery_mv))))
        if self._sbus_at is not None and self._sbus_at <= now and self.sbus is not None:
            s = self.sbus
            self._sbus_at += s.period_s
            self._report(now, p.encode_sbus_report(s.channels, s.ch17, s.ch18, s.signal_loss,
                                                   s.failsafe))
        if self._low_since is not None and self._low_since + LOW_BATTERY_DELAY_S <= now:
            self._low_since += LOW_BATTERY_DELAY_S
            self.low_battery_alarms += 1
            self._beep(now, *LOW_BATTERY_BEEP, source='low_battery')
        if self._scan_at is not None and self._scan_at <= now:
            self._scan(now)

    def _schedule_scan(self) -> None:
        if self._scan_at is not None or not self.powered:
            return
        # Scans run on the board's 30 ms grid from boot, whether or not a key is busy.
        k = math.floor((self._now - self._boot_time) / KEY_SCAN_S + 1e-9) + 1
        self._scan_at = self._boot_time + k * KEY_SCAN_S

    def _scan(self, now: float) -> None:
        for button in self._buttons.values():
            for event in button.scan(now):
                self._report(now, p.encode_key_report(button.key_id, event))
                if event == p.KeyEvent.CLICK:
                    self._beep(now, *CLICK_BEEP, source='click')
        if any(b.busy() for b in self._buttons.values()):
            self._scan_at = now + KEY_SCAN_S
        else:
            self._scan_at = None

    def _check_battery(self) -> None:
        low = LOW_BATTERY_FLOOR_MV < self.battery_mv < self.battery_limit_mv
        if not low:
            self._low_since = None
        elif self._low_since is None:
            self._low_since = self._now

    # -- output ---------------------------------------------------------------------------------

    def _report(self, due: float, frame: bytes) -> None:
        if not self.powered:
            return
        self.reports_sent += 1
        self._queue(due, frame)

    def _reply(self, due: float, frame: bytes) -> None:
        if self.answer_reads:
            self._report(due, frame)

    def _beep(self, t: float, frequency_hz: int, on_ms: int, off_ms: int, repeat: int,
              source: str) -> None:
        self.buzzer = Pattern(on_ms if frequency_hz else 0, off_ms, repeat, t, frequency_hz)
        self.buzzer_log.append(Beep(t, frequency_hz, on_ms, off_ms, repeat, source))

    # -- handlers -------------------------------------------------------------------------------

    def _handle(self, frame: p.HostFrame, t: float) -> float:
        """Run one command at ``t``; return how long the receive task is busy with it."""
        cmd = p.decode_host_command(frame)
        self.frames_handled += 1
        self.command_log.append((t, cmd))
        if isinstance(cmd, p.IgnoredCommand):
            self.commands_ignored += 1
            return 0.0
        if isinstance(cmd, p.SetBatteryLimit):
            self.battery_limit_mv = cmd.limit_mv
            self._check_battery()
        elif isinstance(cmd, p.SetLed):
            if cmd.led_id in self.leds:  # O25
                self.leds[cmd.led_id] = Pattern(cmd.on_ms, cmd.off_ms, cmd.repeat, t)
            else:
                self.commands_ignored += 1
        elif isinstance(cmd, p.SetBuzzer):
            self._beep(t, cmd.frequency_hz, cmd.on_ms, cmd.off_ms, cmd.repeat, 'host')
        elif isinstance(cmd, (p.SetMotorSpeeds, p.StopMotors, p.SetMotorType)):
            self._motor(cmd)
        elif isinstance(cmd, (p.PwmMove, p.PwmRead, p.PwmSetOffset)):
            self._pwm(cmd, t)
        elif isinstance(cmd, p.SetOledText):
            if cmd.line in self.oled_lines:
                # O19: the real board overflows its 24-byte buffer; the model keeps 23 bytes.
                self.oled_lines[cmd.line] = cmd.text[:p.OLED_TEXT_MAX_BYTES]
            else:
                self.commands_ignored += 1
        elif isinstance(cmd, p.SetRgb):
            for index, r, g, b in cmd.pixels:
                if index < p.RGB_PIXEL_COUNT:  # O18
                    self.rgb[index] = (r, g, b)
                else:
                    self.commands_ignored += 1
        else:
            return self._bus(cmd, t)
        return 0.0

    def _motor(self, cmd: p.HostCommand) -> None:
        self.motors_initialized = True
        if isinstance(cmd, p.SetMotorSpeeds):
            for wire_id, speed in cmd.items:
                if wire_id < p.MOTOR_COUNT:
                    self.motor_set_points[wire_id] = speed
                else:
                    # O3: an out-of-bounds write in the firmware; the model ignores it.
                    self.bad_motor_ids += 1
        elif isinstance(cmd, p.StopMotors):
            for wire_id in cmd.wire_ids:
                if wire_id < p.MOTOR_COUNT:
                    self.motor_set_points[wire_id] = 0.0
                else:
                    self.bad_motor_ids += 1
        else:
            # O5: anything but 0..3 selects JGB520.
            self.motor_type = cmd.type_code if cmd.type_code < len(p.MotorType) else 0

    def _pwm(self, cmd: p.HostCommand, t: float) -> None:
        if isinstance(cmd, p.PwmMove):
            for servo_id, pulse in cmd.items:
                servo = self._pwm_servo(servo_id)
                if servo is not None:
                    servo.move(pulse, cmd.duration_ms, t)
            return
        servo = self._pwm_servo(cmd.servo_id)
        if servo is None:
            return  # no reply for id 0 or > 4
        if isinstance(cmd, p.PwmSetOffset):
            servo.set_offset(cmd.offset_us)
        elif cmd.sub == p.PwmSub.READ_PULSE:
            self._reply(t, p.encode_pwm_pulse_reply(cmd.servo_id, servo.pulse_at(t)))
        else:
            self._reply(t, p.encode_pwm_offset_reply(cmd.servo_id, servo.offset_us))

    def _pwm_servo(self, servo_id: int) -> Optional[PwmServo]:
        servo = self.pwm_servos.get(servo_id)
        if servo is None:
            # O30: id 0 indexes out of bounds in the firmware, > 4 is skipped; both ignored.
            self.bad_pwm_ids += 1
        return servo

    def _targets(self, servo_id: int) -> List[SimBusServo]:
        if servo_id == p.BUS_BROADCAST_ID:
            return list(self.bus_servos)
        return [s for s in self.bus_servos if s.servo_id == servo_id]

    def _bus(self, cmd: p.HostCommand, t: float) -> float:
        if isinstance(cmd, p.BusMove):
            position_items = [(sid, min(pos, p.BUS_POSITION_MAX)) for sid, pos in cmd.items]
            for servo_id, position in position_items:  # O23: > 1000 clamped to 1000
                for servo in self._targets(servo_id):
                    servo.move(position, cmd.duration_ms, t)
            return len(cmd.items) * _servo_bus_time(10)
        if isinstance(cmd, p.BusStop):
            for servo_id in cmd.ids:
                for servo in self._targets(servo_id):
                    servo.hold(t)
            return len(cmd.ids) * _servo_bus_time(6)
        if isinstance(cmd, p.BusRead):
            return self._bus_read(cmd, t)
        servos = self._targets(cmd.servo_id)
        for servo in servos:
            if isinstance(cmd, p.BusTorque):
                servo.loaded = cmd.enable
                servo.hold(t)
            elif isinstance(cmd, p.BusWriteId):
                servo.servo_id = cmd.new_id
            elif isinstance(cmd, p.BusSetOffset):
                if -p.BUS_OFFSET_MAX <= cmd.offset <= p.BUS_OFFSET_MAX:  # O35
                    servo.offset = cmd.offset
            elif isinstance(cmd, p.BusSaveOffset):
                servo.saved_offset = servo.offset
            elif isinstance(cmd, p.BusSetLimits):
                servo_limits(servo, cmd.sub, cmd.low, cmd.high)
            elif isinstance(cmd, p.BusSetTemperatureLimit):
                servo.temperature_limit_c = min(cmd.max_c, p.BUS_TEMPERATURE_LIMIT_MAX_C)
        params = 4 if isinstance(cmd, p.BusSetLimits) else 1
        return _servo_bus_time(6 + params)

    def _bus_read(self, cmd: p.BusRead, t: float) -> float:
        self.bus_reads += 1
        servos = self._targets(cmd.servo_id)
        # Two answers at once collide on the half-duplex bus: the board sees a bad frame.
        servo = servos[0] if len(servos) == 1 else None
        duration = _servo_bus_time(6) + (SERVO_ANSWER_S if servo else SERVO_TIMEOUT_S)
        done = t + duration
        if servo is None:
            self.bus_read_failures += 1
            # O14: the model sends zeros with a failure (the firmware sometimes garbage).
            reply = p.encode_bus_reply(cmd.servo_id, cmd.sub, None, p.BUS_FAILURE)
        else:
            reply = p.encode_bus_reply(cmd.servo_id, cmd.sub, self._bus_value(servo, cmd.sub,
                                                                              done))
        self._reply(done, reply)
        return duration

    def _bus_value(self, servo: SimBusServo, sub: int, t: float) -> p.BusValue:
        if sub == p.BusSub.READ_POSITION:
            return servo.read_position(t)
        if sub == p.BusSub.READ_VOLTAGE:
            mv = servo.voltage_mv if servo.voltage_mv is not None else self.battery_mv
            return max(0, min(p.U16_MAX, mv))
        if sub == p.BusSub.READ_TEMPERATURE:
            return max(0, min(255, int(servo.temperature_c)))
        if sub == p.BusSub.READ_LOAD:
            return int(servo.loaded)
        if sub == p.BusSub.READ_ID:
            return servo.servo_id
        if sub == p.BusSub.READ_OFFSET:
            return servo.offset
        if sub == p.BusSub.READ_ANGLE_LIMITS:
            return servo.angle_limits
        if sub == p.BusSub.READ_VOLTAGE_LIMITS:
            return servo.voltage_limits
        return servo.temperature_limit_c


def servo_limits(servo: SimBusServo, sub: int, low: int, high: int) -> None:
    """Apply a limit command with the firmware's clamps, then its swap (O24)."""
    if sub == p.BusSub.SET_ANGLE_LIMITS:
        low, high = min(low, p.BUS_POSITION_MAX), min(high, p.BUS_POSITION_MAX)
        servo.angle_limits = (min(low, high), max(low, high))
    else:
        low, high = max(low, p.BUS_VOLTAGE_MIN_MV), min(high, p.BUS_VOLTAGE_MAX_MV)
        servo.voltage_limits = (min(low, high), max(low, high))


def _triple(values: Sequence[float], name: str) -> Tuple[float, float, float]:
    if len(values) != 3:
        raise ValueError(f'{name} needs three values, got {values!r}')
    out = tuple(float(v) for v in values)
    # The wire carries float32: what the model stores is what a decoder will see.
    packed = struct.unpack('<3f', struct.pack('<3f', *out))
    return (packed[0], packed[1], packed[2])
