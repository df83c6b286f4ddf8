"""Plain-Python model of the handset as the drone's radio modem delivers it: frames out only.

No I/O, no threads, no wall clock: the caller passes the time (seconds, any origin; an earlier
time than the last is taken as the last). A pty wrapper
(``uav_serial_common.virtual_device.VirtualDeviceRunner``) turns this into a virtual serial
device; wire timing at ``baud`` belongs to that wrapper. Behaviour the handset document leaves
open follows the decisions in ``docs/protocols.md`` (H12 onwards).
"""

from __future__ import annotations

import math
import struct
from typing import Optional, Union

from handset_link_ros import protocol as p

STICK_TYPES = (p.CommandType.SET_YAW, p.CommandType.SET_PITCH, p.CommandType.SET_ROLL,
               p.CommandType.SET_ALTITUDE)
"""Sent every tick, in this order (H7)."""
AUX_TYPES = (p.CommandType.SET_LIGHTS, p.CommandType.SET_CAMERA_ANGLE,
             p.CommandType.SET_CAMERA_RECORD)
"""Sent on change and once every ``aux_period_s`` (H22)."""
FLOAT32_MAX = struct.unpack('<f', b'\xff\xff\x7f\x7f')[0]
_EPS = 1e-9
"""Tolerance of schedule comparisons, so a tick due at 1.0 s is sent by ``step(1.0)``."""

_ATTRIBUTE = {
    p.CommandType.SET_YAW: 'yaw_deg',
    p.CommandType.SET_PITCH: 'pitch_deg',
    p.CommandType.SET_ROLL: 'roll_deg',
    p.CommandType.SET_ALTITUDE: 'altitude_m',
    p.CommandType.SET_LIGHTS: 'lights_percent',
    p.CommandType.SET_CAMERA_ANGLE: 'camera_angle_deg',
    p.CommandType.SET_CAMERA_RECORD: 'camera_recording',
}


class VirtualHandset:
    """Deterministic model of a handset sending at ``rate_hz`` through a radio modem (H22).

    ``step(now)`` returns the bytes sent by ``now``; ``next_event_time()`` says when the next
    ones are due. Every tick carries SET_YAW, SET_PITCH, SET_ROLL and SET_ALTITUDE; the three
    auxiliary commands follow in the tick after they change and all three once every
    ``aux_period_s`` (the first tick included). Values are public attributes (``yaw_deg``,
    ``pitch_deg``, ``roll_deg``, ``altitude_m``, ``lights_percent``, ``camera_angle_deg``,
    ``camera_recording``), set directly or through the ``set_*`` methods, and read at each tick.

    What an encoding cannot carry (H23): int8 and int16 carry whole units, so values are rounded
    to the nearest whole unit (halves away from zero) and saturate at the type's limits (int8
    −128..127: a yaw of 150° goes out as 127); float32 carries the nearest float32, saturating at
    ±3.4e38; JSON carries the value as given. Values outside the H4 ranges are sent as they are,
    so the driver's refusal (H6) can be exercised; ``send_raw`` covers everything else.

    The host never writes to the handset (H11): ``receive`` ignores its input and counts it.
    """

    def __init__(self, now: float = 0.0, *, rate_hz: float = 50.0,
                 encoding: p.Encoding = 'json', aux_period_s: float = 1.0,
                 radio_link: bool = True) -> None:
        self._now = float(now)
        self.rate_hz = 50.0
        self.set_rate(rate_hz)
        if not aux_period_s > 0:
            raise ValueError(f'aux_period_s must be positive, got {aux_period_s!r}')
        self.aux_period_s = float(aux_period_s)
        self.encoding: p.Encoding = 'json'
        self.set_encoding(encoding)

        self.yaw_deg = 0.0
        self.pitch_deg = 0.0
        self.roll_deg = 0.0
        self.altitude_m = 0.0
        self.lights_percent = 0
        self.camera_angle_deg = 0.0
        self.camera_recording = False

        self.radio_link = bool(radio_link)
        # Ticks are counted from an origin (origin + k / rate), so they do not drift by summing
        # rounded periods; the origin moves when the rate changes or the radio link resumes.
        self._tick_origin = self._now
        self._tick_index = 0
        self._next_aux = self._now
        self._sent_aux: dict[int, object] = {}
        self._raw: list[bytes] = []

        # Counters for tests and the wrapper's diagnostics.
        self.ticks = 0
        self.frames_sent = 0
        self.frames_by_type: dict[int, int] = {t: 0 for t in p.SPECS}
        self.raw_bytes_sent = 0
        self.bytes_ignored = 0

    # -- clock -----------------------------------------------------------------------------

    @property
    def now(self) -> float:
        """The model's current time in seconds."""
        return self._now

    def step(self, now: float) -> bytes:
        """Advance the model to ``now`` and return the bytes it has sent by then."""
        return b''.join(self.step_frames(now))

    def step_frames(self, now: float) -> list[bytes]:
        """Like ``step``, one item per frame (or ``send_raw`` chunk), in wire order."""
        now = max(float(now), self._now)
        out, self._raw = self._raw, []
        while True:
            due = self._next_tick()
            if due is None or due > now + _EPS:
                break
            self._now = max(self._now, due)
            out += self._tick()
            self._tick_index += 1
        self._now = now
        return out

    def advance(self, dt: float) -> bytes:
        """Advance the model by ``dt`` seconds and return the bytes it has sent by then."""
        return self.step(self._now + dt)

    def receive(self, data: bytes, now: Optional[float] = None) -> bytes:
        """Take bytes from the host: ignored and counted (H11); return the bytes due by ``now``."""
        self.bytes_ignored += len(data)
        return self.step(self._now if now is None else now)

    def next_event_time(self) -> Optional[float]:
        """Earliest time at which the model will send something, None if never on its own."""
        if self._raw:
            return self._now
        return self._next_tick()

    # -- scenario --------------------------------------------------------------------------

    def set_sticks(self, yaw_deg: Optional[float] = None, pitch_deg: Optional[float] = None,
                   roll_deg: Optional[float] = None, altitude_m: Optional[float] = None) -> None:
        """Set any of the four stick values (degrees, metres); the next tick sends them."""
        for name, value in (('yaw_deg', yaw_deg), ('pitch_deg', pitch_deg),
                            ('roll_deg', roll_deg), ('altitude_m', altitude_m)):
            if value is not None:
                setattr(self, name, _finite(name, value))

    def set_lights(self, percent: Union[int, float]) -> None:
        """Set the lights level in percent; sent in the next tick."""
        self.lights_percent = _finite('lights_percent', percent)

    def set_camera_angle(self, angle_deg: float) -> None:
        """Set the camera angle in degrees; sent in the next tick."""
        self.camera_angle_deg = _finite('camera_angle_deg', angle_deg)

    def set_camera_recording(self, recording: bool) -> None:
        """Start (True) or stop (False) recording; sent in the next tick."""
        self.camera_recording = bool(recording)

    def set_encoding(self, encoding: p.Encoding) -> None:
        """Switch the payload encoding of every following frame (H5)."""
        if encoding not in p.ENCODINGS:
            raise ValueError(f'encoding must be one of {", ".join(p.ENCODINGS)}, '
                             f'got {encoding!r}')
        self.encoding = encoding

    def set_rate(self, rate_hz: float) -> None:
        """Change the tick rate; the next tick keeps its time, the following use the new rate."""
        if isinstance(rate_hz, bool) or not isinstance(rate_hz, (int, float)) or \
                not 0 < rate_hz <= 1000:
            raise ValueError(f'rate_hz must be in (0, 1000], got {rate_hz!r}')
        if hasattr(self, '_tick_index'):
            self._tick_origin = self._tick_origin + self._tick_index / self.rate_hz
            self._tick_index = 0
        self.rate_hz = float(rate_hz)

    def set_radio_link(self, up: bool) -> None:
        """Stop (False) or resume (True) transmitting, as when the handset goes out of range.

        Ticks missed meanwhile are not made up; the first tick after resuming is at once and
        carries all three auxiliary commands.
        """
        up = bool(up)
        if up and not self.radio_link:
            self._tick_origin = self._now
            self._tick_index = 0
            self._next_aux = self._now
        self.radio_link = up

    def send_raw(self, data: bytes) -> None:
        """Queue arbitrary bytes, sent at once (also while the radio link is down)."""
        data = bytes(data)
        if data:
            self._raw.append(data)
            self.raw_bytes_sent += len(data)

    # -- internals -------------------------------------------------------------------------

    def _next_tick(self) -> Optional[float]:
        if not self.radio_link:
            return None
        return self._tick_origin + self._tick_index / self.rate_hz

    def _tick(self) -> list[bytes]:
        self.ticks += 1
        types = list(STICK_TYPES)
        periodic = self._now >= self._next_aux - _EPS
        if periodic:
            self._next_aux += self.aux_period_s
            if self._next_aux <= self._now:
                self._next_aux = self._now + self.aux_period_s
        for type_ in AUX_TYPES:
            value = getattr(self, _ATTRIBUTE[type_])
            if periodic or self._sent_aux.get(type_) != value:
                self._sent_aux[type_] = value
                types.append(type_)
        frames = [self._frame(t) for t in types]
        self.frames_sent += len(frames)
        for type_ in types:
            self.frames_by_type[type_] += 1
        return frames

    def _frame(self, type_: p.CommandType) -> bytes:
        value = getattr(self, _ATTRIBUTE[type_])
        if type_ == p.CommandType.SET_CAMERA_RECORD:
            value = int(bool(value))
        encoding = self.encoding
        if encoding in ('int8', 'int16'):
            lo, hi = p.INT_LIMITS[encoding]
            value = max(lo, min(hi, _round_half_away(value)))
        elif encoding == 'float32':
            value = max(-FLOAT32_MAX, min(FLOAT32_MAX, float(value)))
        return p.encode_command(type_, value, encoding, check=False)


def _finite(name: str, value: Union[int, float]) -> Union[int, float]:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or \
            not math.isfinite(value):
        raise ValueError(f'{name} must be a finite number, got {value!r}')
    return value


def _round_half_away(value: Union[int, float]) -> int:
    """Round to the nearest whole number, halves away from zero (2.5 → 3, −2.5 → −3)."""
    if isinstance(value, int):
        return value
    return int(math.copysign(math.floor(abs(value) + 0.5), value))
