"""Plain-Python model of the DPS-S parachute module: host bytes in, module bytes out.

No I/O, no threads, no wall clock: the caller passes the time (seconds, any origin; an earlier
time than the last is taken as the last). A pty wrapper turns this into a virtual serial device;
wire timing at ``baud`` belongs to that wrapper. Behaviour the vendor document leaves open follows
the decisions in ``docs/protocols.md`` (P13 onwards).
"""

from __future__ import annotations

from collections import deque
import math

from dps_parachute_ros import protocol as p
from uav_serial_common.device_model import ClockedModel

POWER_UP_HEARTBEAT_GAP_S = 0.05
"""The module sends its second power-up heartbeat 50 ms after the first (P5)."""
TRIGGER_REQUEST_WINDOW_S = 1.0
"""A trigger request must be confirmed within this time (P10)."""
ATTITUDE_RESET_MARGIN_DEG = 10
"""The attitude trigger re-arms this far below the threshold (P9)."""
PROTECTION_AFTER_FAILURES = 3
"""Unsuccessful trigger attempts in a row that put the module into protection (P11)."""
RECORD_SLOTS = p.RECORD_SLOTS
"""Trigger records kept, oldest overwritten first."""


class VirtualParachute(ClockedModel):
    """Deterministic device model of a DPS-S parachute module.

    Drive it with ``receive(data, now)`` for host bytes and ``step(now)`` for the passage of
    time; both return the bytes the module sends by ``now``. Scenario methods (``set_tilt``,
    ``start_free_fall``, ``power_cycle`` ...) act at the model's current time (``now``).

    Public state (read it, or set the settings directly in tests): ``powered``, ``armed``,
    ``triggered``, ``streaming``, ``protection``, ``external_power``, ``boot_count``,
    ``attitude_threshold_deg``, ``freefall_threshold_raw`` (0.1 g), ``freefall_time_raw``
    (0.01 s), ``light_threshold_raw`` (0.1 V), ``attitude_trigger_enabled``,
    ``freefall_trigger_enabled``, ``baud_code``, ``tilt_deg``, ``accel_g``,
    ``cell_voltage_v``, ``charge_voltage_v``.

    Faults of the module itself: ``igniter_fault`` (trigger attempts do not deploy),
    ``lost_commands`` (command codes of host frames that never reach it) and ``stream_dead``
    (its status stream stops and stream on/off, 0x13, is ignored; every other query answered).
    Faults of the wire (lost, corrupted, late replies, noise) are the runner's
    (:class:`uav_serial_common.virtual_device.WireFaults`), the same for every device.
    """

    def __init__(self, now: float = 0.0, *, flag_layout: p.FlagLayout = 'table',
                 trigger_request_header: bytes = p.MODULE_HEADER,
                 voltage_reply_code: int = p.CMD_TRIGGER_RECORDS,
                 stream_period_s: float = 0.1, boot_count: int = 0,
                 external_power: bool = True, powered: bool = True,
                 cell_voltage_v: float = 3.9, charge_voltage_v: float = 4.2,
                 dark_light_v: float = 0.2, open_light_v: float = 3.0,
                 serial_link_timeout_s: float = 30.0) -> None:
        if flag_layout not in ('table', 'prose'):
            raise ValueError(f"flag_layout must be 'table' or 'prose', got {flag_layout!r}")
        if trigger_request_header not in (p.MODULE_HEADER, p.HOST_HEADER):
            raise ValueError('trigger_request_header must be the module or the host header')
        if voltage_reply_code not in (p.CMD_CELL_VOLTAGE, p.CMD_TRIGGER_RECORDS):
            raise ValueError('voltage_reply_code must be 0x34 or 0x35')
        if not stream_period_s > 0:
            raise ValueError(f'stream_period_s must be positive, got {stream_period_s!r}')
        super().__init__(now)
        self.flag_layout = flag_layout
        self.trigger_request_header = bytes(trigger_request_header)
        self.voltage_reply_code = voltage_reply_code
        self.stream_period_s = float(stream_period_s)
        self.cell_voltage_v = cell_voltage_v
        self.charge_voltage_v = charge_voltage_v
        self.dark_light_v = dark_light_v
        self.open_light_v = open_light_v
        self.serial_link_timeout_s = serial_link_timeout_s

        # Settings kept in the module's non-volatile memory across power cycles (P17).
        self.attitude_threshold_deg = 60
        self.freefall_threshold_raw = 5
        self.freefall_time_raw = 160
        self.light_threshold_raw = 12
        self.attitude_trigger_enabled = True
        self.freefall_trigger_enabled = True
        self.baud_code = 6
        self.boot_count = boot_count & 0xFF
        self.tilt_offset_deg = 0.0
        self._records: deque[bytes] = deque(maxlen=RECORD_SLOTS)

        # Physics and supply.
        self.external_power = external_power
        self.tilt_deg = 0.0
        self.accel_g = 1.0
        self.light_override_v: float | None = None
        self._freefall_end: float | None = None

        # Fault injection.
        self.igniter_fault = False
        # Command codes of host frames lost on the way in (a bad RX line, a glitching
        # connector): the module never sees them, and keeps streaming.
        self.lost_commands: set[int] = set()
        self._stream_dead = False

        # Counters for tests and the wrapper's diagnostics.
        self.requests_sent = 0
        self.requests_confirmed = 0
        self.requests_expired = 0
        self.deployments = 0
        self.failed_attempts_total = 0

        self.decoder = p.StreamDecoder('from_host')
        self._last_host_frame: float | None = None
        self.powered = False
        self._reset_volatile()
        if powered:
            self._boot()

    # -- wire (step, advance, now and next_event_time are ClockedModel's) -------------------

    @property
    def baud(self) -> int:
        """The module's serial rate in bit/s; changes right after the 0x24 reply is queued."""
        return p.BAUD_CODES[self.baud_code]

    def receive(self, data: bytes, now: float | None = None) -> bytes:
        """Take bytes from the host at ``now`` (default: current time); return bytes sent."""
        if now is not None:
            self._advance_to(now)
        if self.powered:
            for frame in self.decoder.feed(data):
                if not self.powered:
                    break  # shut down by an earlier frame of the same chunk
                if frame.code in self.lost_commands:
                    continue
                self._handle(frame)
                self._evaluate()
        return self._collect()

    # -- scenario --------------------------------------------------------------------------

    def set_tilt(self, degrees: float) -> None:
        """Set the true tilt (angle to the horizontal plane) in degrees."""
        self.tilt_deg = float(degrees)
        self._evaluate()

    def set_accel(self, g: float) -> None:
        """Set the magnitude of the measured acceleration in g; cancels a scripted free fall."""
        self.accel_g = abs(float(g))
        self._freefall_end = None
        self._evaluate()

    def start_free_fall(self, duration_s: float) -> None:
        """Fall freely (0 g) for ``duration_s`` seconds from now, then read 1 g again."""
        self.accel_g = 0.0
        self._freefall_end = self._now + duration_s
        self._evaluate()

    def set_light(self, volts: float | None) -> None:
        """Force the light-sensor voltage; ``None`` returns to the modelled bay light."""
        self.light_override_v = volts

    def set_external_power(self, on: bool) -> None:
        """Connect or remove external power; connecting it wakes a module that is off."""
        was_on = self.external_power
        self.external_power = bool(on)
        if not self.powered:
            if on and not was_on:
                self._boot()
            return
        if not on and self._pending is not None:
            # On battery the module does not ask (P10); a crash still pending deploys now (P20).
            sources = self._pending[1]
            self._pending = None
            self._fire(sources)
        self._evaluate()

    def power_off(self) -> None:
        """Switch the module off (as the mechanical switch would)."""
        self.powered = False
        self._reset_volatile()

    def power_on(self) -> None:
        """Switch the module on: boot count +1, two heartbeats 50 ms apart (P5)."""
        if not self.powered:
            self._boot()

    def power_cycle(self) -> None:
        """Switch off and on again at the current time."""
        self.power_off()
        self._boot()

    def trigger_pwm(self) -> bool:
        """Deploy through the PWM input (source 0x04); returns whether it deployed."""
        if not self.powered or not self._can_fire():
            if self.powered and not self.protection:
                self._failed_attempt()
            return False
        return self._fire(p.SOURCE_PWM)

    @property
    def stream_dead(self) -> bool:
        """Fault: the stream task hangs; no status frame, 0x13 ignored (no reply, no effect).

        Setting it stops the stream; clearing it lets 0x13 work again (the stream stays off
        until the host turns it on). Every other command is answered throughout.
        """
        return self._stream_dead

    @stream_dead.setter
    def stream_dead(self, dead: bool) -> None:
        self._stream_dead = bool(dead)
        if dead:
            self.streaming = False
            self._stream_at = None

    # -- read-only views -------------------------------------------------------------------

    @property
    def reported_tilt_deg(self) -> int:
        """Tilt the module reports: whole degrees relative to the zeroed mounting, 0..255."""
        return min(255, int(abs(self.tilt_deg - self.tilt_offset_deg) + 0.5))

    @property
    def light_level_v(self) -> float:
        """Light-sensor voltage: dark while the bay is closed, bright once it opened."""
        if self.light_override_v is not None:
            return self.light_override_v
        return self.open_light_v if self._bay_open else self.dark_light_v

    @property
    def measured_voltage_v(self) -> float:
        """What the 0x34 query reports: charging voltage on external power, else the cell's."""
        return self.charge_voltage_v if self.external_power else self.cell_voltage_v

    @property
    def records(self) -> list[bytes]:
        """Stored 16-byte trigger records, oldest first."""
        return list(self._records)

    @property
    def pending_request(self) -> bool:
        """Whether a trigger request awaits the host's confirmation."""
        return self._pending is not None

    @property
    def pending_since(self) -> float | None:
        """When the pending trigger request was made (the module's clock), or None."""
        return None if self._pending is None else self._pending[0]

    @property
    def failed_attempts(self) -> int:
        """Unsuccessful trigger attempts in a row since the last success or boot (P11)."""
        return self._failed

    # -- internals: power ------------------------------------------------------------------

    def _reset_volatile(self) -> None:
        self.armed = False
        self.triggered = False
        self.streaming = False
        self.protection = False
        self._failed = 0
        self._pending: tuple[float, int] | None = None
        self._stream_at: float | None = None
        self._second_heartbeat_at: float | None = None
        self._attitude_latched = False
        self._freefall_latched = False
        self._below_since: float | None = None
        self._bay_open = False
        self.decoder.reset()

    def _boot(self) -> None:
        self._reset_volatile()
        self.powered = True
        self.boot_count = (self.boot_count + 1) & 0xFF
        self._boot_time = self._now
        self._queue(self._now, p.encode_module_heartbeat())
        self._second_heartbeat_at = self._now + POWER_UP_HEARTBEAT_GAP_S
        self._evaluate()

    # -- internals: time -------------------------------------------------------------------

    def _advance_to(self, now: float) -> None:
        super()._advance_to(now)
        self._evaluate()  # the auto triggers judged at the new time

    def _freefall_fire_time(self) -> float | None:
        if (self._below_since is None or self._freefall_latched
                or not self.freefall_trigger_enabled or not self._eligible()):
            return None
        return self._below_since + self.freefall_time_raw / 100

    def _next_internal_event(self) -> float | None:
        if not self.powered:
            return None
        times = [self._second_heartbeat_at, self._freefall_end, self._freefall_fire_time(),
                 self._stream_at if self.streaming else None,
                 self._pending[0] + TRIGGER_REQUEST_WINDOW_S if self._pending else None]
        present = [t for t in times if t is not None]
        return min(present) if present else None

    def _process_events(self) -> None:
        now = self._now
        if self._second_heartbeat_at is not None and self._second_heartbeat_at <= now:
            self._second_heartbeat_at = None
            self._queue(now, p.encode_module_heartbeat())
        # Conditions are judged before a scripted free fall ends at the same instant.
        self._evaluate()
        if self._freefall_end is not None and self._freefall_end <= now:
            self._freefall_end = None
            self.accel_g = 1.0
            self._evaluate()
        if self._pending is not None and self._pending[0] + TRIGGER_REQUEST_WINDOW_S <= now:
            # P10: no confirmation in time is a refusal; the module does not deploy.
            self._pending = None
            self.requests_expired += 1
            self._evaluate()
        if self.streaming and self._stream_at is not None and self._stream_at <= now:
            self._stream_at += self.stream_period_s
            self._queue(now, self._status_frame())

    # -- internals: crash detection --------------------------------------------------------

    def _eligible(self) -> bool:
        return (self.powered and self.armed and not self.triggered and not self.protection
                and self._pending is None)

    def _can_fire(self) -> bool:
        return self.armed and not self.triggered and not self.protection

    def _evaluate(self) -> None:
        if not self.powered:
            return
        tilt = self.reported_tilt_deg
        threshold = self.attitude_threshold_deg
        if self._attitude_latched and tilt <= threshold - ATTITUDE_RESET_MARGIN_DEG:
            self._attitude_latched = False
        if self.accel_g < self.freefall_threshold_raw / 10:
            if self._below_since is None:
                self._below_since = self._now
        else:
            self._below_since = None
            self._freefall_latched = False
        if not self._eligible():
            return
        sources = 0
        if self.attitude_trigger_enabled and not self._attitude_latched and tilt > threshold:
            self._attitude_latched = True
            sources |= p.SOURCE_ATTITUDE
        fire_at = self._freefall_fire_time()
        if fire_at is not None and self._now >= fire_at:
            self._freefall_latched = True
            sources |= p.SOURCE_FREEFALL
        if not sources:
            return
        if self.external_power:
            self._pending = (self._now, sources)
            self.requests_sent += 1
            self._queue(self._now, p.encode_trigger_request(self.trigger_request_header))
        else:
            self._fire(sources)

    def _fire(self, sources: int) -> bool:
        """Try to deploy; success locks the module, failure counts towards protection."""
        if not self._can_fire():
            return False
        if self.igniter_fault:
            self._failed_attempt()
            return False
        self._pending = None
        self.triggered = True
        self.armed = False
        self._failed = 0
        self._bay_open = True
        self.deployments += 1
        self._records.append(self._record(sources))
        return True

    def _failed_attempt(self) -> None:
        self._failed += 1
        self.failed_attempts_total += 1
        if self._failed >= PROTECTION_AFTER_FAILURES:
            self.protection = True

    def _record(self, sources: int) -> bytes:
        serial_link = (self._last_host_frame is not None
                       and self._now - self._last_host_frame <= self.serial_link_timeout_s)
        return p.encode_trigger_record(
            boot_count=self.boot_count,
            uptime_s=min(0xFFFF, int(self._now - self._boot_time)),
            source=sources,
            attitude_threshold_raw=self.attitude_threshold_deg,
            freefall_threshold_raw=self.freefall_threshold_raw,
            freefall_time_raw=self.freefall_time_raw,
            serial_link=serial_link,
            charging=self.external_power,
            light_threshold_raw=self.light_threshold_raw,
            cell_voltage_raw=_raw(self.measured_voltage_v, 0.02))

    # -- internals: output -----------------------------------------------------------------

    def _reply(self, *frames: bytes) -> None:
        self._queue(self._now, b''.join(frames))

    def _status_frame(self) -> bytes:
        accel_raw = min(255, int(self.accel_g * 10 + 0.5))
        return p.encode_status_frame(self.reported_tilt_deg, accel_raw, self.triggered,
                                     self.armed)

    def _flags_reply(self) -> bytes:
        value = p.encode_auto_trigger_flags(self.attitude_trigger_enabled,
                                            self.freefall_trigger_enabled, self.flag_layout)
        return p.module_frame(p.CMD_ATTITUDE_TRIGGER, value)

    # -- internals: commands ---------------------------------------------------------------

    def _handle(self, frame: p.Frame) -> None:
        """Answer one host frame; anything undocumented or malformed gets no reply (P18)."""
        self._last_host_frame = self._now
        code = frame.code
        control, value = frame.data[0], frame.data[1]
        reply = self._reply
        if code == p.CMD_HEARTBEAT:
            if frame.data == p.HEARTBEAT_PAYLOAD:
                reply(p.encode_module_heartbeat())
        elif code == p.CMD_TRIGGER_REQUEST:
            if frame.data == p.CONFIRM_PAYLOAD:
                self._confirm()
        elif code == p.CMD_ARM:
            if value in (0, 1):
                self.armed = value == 1
                reply(p.module_frame(code, value))
        elif code == p.CMD_DEPLOY:
            self._serial_deploy(value)
        elif code == p.CMD_SHUTDOWN:
            if value == 1:
                reply(p.module_frame(code, 1))
                self.power_off()
        elif code == p.CMD_STREAMING:
            if value in (0, 1) and not self.stream_dead:
                self.streaming = value == 1
                self._stream_at = self._now + self.stream_period_s if self.streaming else None
                reply(p.module_frame(code, value))
        elif code == p.CMD_LIGHT_LEVEL:
            reply(p.module_frame(code, _raw(self.light_level_v, 0.1)))
        elif code in (p.CMD_ATTITUDE_TRIGGER, p.CMD_FREEFALL_TRIGGER):
            self._auto_trigger_command(code, control, value)
        elif code in _SETTINGS:
            attribute = _SETTINGS[code]
            if control == p.CTRL_SET:
                setattr(self, attribute, value)
                reply(p.module_frame(code, value))
            elif control == p.CTRL_QUERY:
                reply(p.module_frame(code, getattr(self, attribute)))
        elif code == p.CMD_BOOT_COUNT:
            reply(p.module_frame(code, self.boot_count))
        elif code == p.CMD_BAUD_RATE:
            if control == p.CTRL_SET and value in p.BAUD_CODES:
                reply(p.module_frame(code, value))
                self.baud_code = value
        elif code == p.CMD_SENSOR_ZERO:
            self.tilt_offset_deg = self.tilt_deg
            reply(p.module_frame(code, 1))
        elif code == p.CMD_ARMED:
            reply(p.module_frame(code, int(self.armed)))
        elif code == p.CMD_TRIGGERED:
            reply(p.module_frame(code, int(self.triggered)))
        elif code == p.CMD_STATUS:
            reply(self._status_frame())
        elif code == p.CMD_CHARGING:
            reply(p.module_frame(code, int(self.external_power)))
        elif code == p.CMD_CELL_VOLTAGE:
            reply(p.module_frame(self.voltage_reply_code, _raw(self.measured_voltage_v, 0.02)))
        elif code == p.CMD_TRIGGER_RECORDS:
            empty = p.encode_trigger_record(0, 0, 0, 0, 0, 0, False, False, 0, 0)
            slots = list(self._records) + [empty] * (RECORD_SLOTS - len(self._records))
            reply(*slots)

    def _auto_trigger_command(self, code: int, control: int, value: int) -> None:
        if control == p.CTRL_SET and value in (0, 1):
            if code == p.CMD_ATTITUDE_TRIGGER:
                self.attitude_trigger_enabled = value == 0
            else:
                self.freefall_trigger_enabled = value == 0
            self._reply(self._flags_reply())
        elif control == p.CTRL_QUERY:
            self._reply(self._flags_reply())

    def _serial_deploy(self, value: int) -> None:
        if value == 0:
            # "Forbid trigger": acknowledged with 0x00, changes nothing (P19).
            self._reply(p.module_frame(p.CMD_DEPLOY, 0))
            return
        if value != 1:
            return
        if self.protection:
            ok = False
        elif not self._can_fire():
            self._failed_attempt()
            ok = False
        else:
            ok = self._fire(p.SOURCE_SERIAL)
        self._reply(p.module_frame(p.CMD_DEPLOY, 1 if ok else 0))

    def _confirm(self) -> None:
        if self._pending is None:
            return  # nothing to confirm: ignored, no reply (P10)
        sources = self._pending[1]
        self._pending = None
        self.requests_confirmed += 1
        self._fire(sources)


_SETTINGS = {
    p.CMD_LIGHT_THRESHOLD: 'light_threshold_raw',
    p.CMD_ATTITUDE_THRESHOLD: 'attitude_threshold_deg',
    p.CMD_FREEFALL_THRESHOLD: 'freefall_threshold_raw',
    p.CMD_FREEFALL_TIME: 'freefall_time_raw',
}


def _raw(value: float, step: float) -> int:
    """Quantise a measurement to a byte of ``step`` units, clamped to 0..255."""
    if not math.isfinite(value):
        return 0
    return max(0, min(255, int(value / step + 0.5)))
