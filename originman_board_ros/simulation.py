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

The model is assembled here from one module per responsibility (every name is re-exported):

- ``simulation_parts``: the parts of the board (LED and buzzer patterns, PWM servos, the LX bus
  servos, SBUS, the keys and their firmware driver);
- ``simulation_handlers``: the firmware's handler of each host command (motors, PWM servos,
  LEDs, buzzer, OLED, RGB, settings, the servo bus with its timing), a mixin;
- this module: the board's state, the wire (parser and inbox), the scenario, the views, power,
  the clock's events (reports, key scan, battery alarm) and the output.
"""

from __future__ import annotations

from collections import deque
import math
import struct
from typing import Callable, Deque, Dict, Iterable, List, Optional, Sequence, Tuple

from originman_board_ros import protocol as p
from originman_board_ros.simulation_handlers import (  # noqa: F401 (tests read them here)
    _servo_bus_time, FirmwareHandlers, SERVO_ANSWER_S, SERVO_BUS_BAUD, SERVO_TIMEOUT_S,
    servo_limits)
from originman_board_ros.simulation_parts import (  # noqa: F401 (the model's names)
    _Button, Beep, KEY_COMBO_MS, KEY_LONG_PRESS_MS, KEY_REPEAT_MS, KEY_SCAN_S, Pattern,
    PWM_POWER_UP_PULSE, PWM_STEP_S, PwmServo, SBUS_PERIOD_S, SbusState,
    SERVO_DEFAULT_TEMPERATURE_C, SERVO_DEFAULT_TEMPERATURE_LIMIT_C, SERVO_MAX_SPEED,
    SimBusServo)
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
KEY_CLICK_HOLD_S = 0.10
KEY_CLICK_GAP_S = 0.10
KEY_LONG_HOLD_S = 2.5
SBUS_CENTRE = 992
OLED_POWER_UP_TEXT = b'---.---.---.---'
COMMAND_LOG_SIZE = 2000


ImuSource = Callable[[float], Tuple[Sequence[float], Sequence[float]]]
"""A function of the model's time giving ``(accel_g, gyro_dps)`` for the next IMU report."""


# ---------------------------------------------------------------------------------------------
# The board
# ---------------------------------------------------------------------------------------------

class VirtualOriginManBoardModel(FirmwareHandlers, ClockedModel):
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


def _triple(values: Sequence[float], name: str) -> Tuple[float, float, float]:
    if len(values) != 3:
        raise ValueError(f'{name} needs three values, got {values!r}')
    out = tuple(float(v) for v in values)
    # The wire carries float32: what the model stores is what a decoder will see.
    packed = struct.unpack('<3f', struct.pack('<3f', *out))
    return (packed[0], packed[1], packed[2])
