"""The handset link device: setpoints, auxiliary state, link health and the failsafe (H3-H11).

No ROS here: a node turns the callbacks into messages and the battery topic into
``on_battery()``. The core reads the radio modem through ``link.ModemLink`` and never writes to it
(H11). Decision numbers refer to ``docs/protocols.md``.

Threads, and what each one owns:

- The link's reader thread (SerialLink) reads the port, decodes, and calls ``_on_received``.
  Accepted frames update the state and reach ``on_setpoint`` / ``on_auxiliary`` from that thread
  before the next read, never batched on a timer: a stick frame is delivered within the read that
  completed it (H7). Frames of one read may share one setpoint update (``updated`` names them).
- The core's timer thread (``start()``) sleeps until the next deadline (link loss when a stick
  setpoint is ``link_timeout_s`` old, H8; a stale battery reading; a partial frame's 0.1 s, H3)
  and calls ``poll()``. An event that sets a deadline (bytes of a partial frame read, a frame,
  a battery reading, a new setting) wakes it by then (``DeadlineTimer.wake(by=...)``), so no
  deadline waits for the timer's longest sleep.
- The owner's threads (a node's executor) call ``on_battery()`` and the snapshot getters.

State lives under ``_lock``, held briefly and never during a callback. Every change runs, with
its callbacks, under ``_emit_lock``, so two threads never deliver failsafe changes out of order.
Callbacks must not block; they may call the getters. A callback that raises is logged, never
propagated. With ``start(run_threads=False)`` nothing runs on its own: the caller drives
``feed()`` and ``poll()`` with its own (fake) clock.

The failsafe decisions (link loss by the sticks, battery hysteresis and staleness) are
``rules.HandsetRules``: pure, stepped here (``core_runner.run_core``) with each event and its
time; this class decodes, keeps the setpoints and counters, and carries the rules' actions out:
log lines and changes as callbacks, ``SetTimer`` as a wake of the timer by its deadline.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace
import logging
import math
import threading
import time
import traceback
from typing import Any, Callable, Deque, Optional

from handset_link_ros import protocol as p
from handset_link_ros.link import ModemLink, Received
from handset_link_ros.rules import (ACTION_NONE, ACTION_RETURN_TO_HOME,  # noqa: F401 (API)
                                    BATTERY_CLEAR_MARGIN, BatteryReading, Event, Failsafe,
                                    FailsafeChanged, HandsetRules, LinkChanged, Log,
                                    Reconfigured, Started, StickFrame)
from uav_serial_common.core_events import SetTimer, Tick
from uav_serial_common.core_runner import run_core
from uav_serial_common.deadline_timer import DeadlineTimer
from uav_serial_common.logs import Throttle
from uav_serial_common.records import evolve

REJECTION_LOG_PERIOD_S = 1.0
"""Rejected frames are logged at most once per type per second (H6)."""
BITS_PER_BYTE = 10
MAX_TIMER_SLEEP_S = 0.5
"""The timer thread sleeps until its next deadline, at most this long (a wake-up costs CPU).
Every deadline an event sets wakes it by then: this bound is a backstop, never a deadline's
lateness."""

STICK_FIELDS: dict[int, str] = {
    p.CommandType.SET_YAW: 'yaw_deg',
    p.CommandType.SET_PITCH: 'pitch_deg',
    p.CommandType.SET_ROLL: 'roll_deg',
    p.CommandType.SET_ALTITUDE: 'altitude_m',
}
"""Stick command type to its ``Setpoint`` field."""
AUX_FIELDS: dict[int, str] = {
    p.CommandType.SET_LIGHTS: 'lights_percent',
    p.CommandType.SET_CAMERA_ANGLE: 'camera_angle_deg',
    p.CommandType.SET_CAMERA_RECORD: 'camera_recording',
}
"""Auxiliary command type to its ``Auxiliary`` field."""

NAN = math.nan
RUNTIME_FIELDS = frozenset({'link_timeout_s', 'expected_rate_hz', 'low_battery_fraction',
                            'battery_timeout_s'})
"""``HandsetConfig`` fields ``reconfigure()`` may change while the link runs."""


@dataclass(frozen=True)
class HandsetConfig:
    """Settings of one handset link; raises ValueError naming a bad value."""

    port: str = '/dev/ttyUSB2'
    baud: int = 115200
    link_timeout_s: float = 5.0
    expected_rate_hz: float = 50.0
    low_battery_fraction: float = 0.20
    rate_window_s: float = 1.0
    battery_timeout_s: float = 10.0
    """A battery reading older than this is stale: the battery is unknown (issue 21 item 8)."""

    def __post_init__(self) -> None:
        if not isinstance(self.port, str) or not self.port:
            raise ValueError(f'port must be a device path or pyserial URL, got {self.port!r}')
        if isinstance(self.baud, bool) or not isinstance(self.baud, int) or self.baud <= 0:
            raise ValueError(f'baud must be a positive integer, got {self.baud!r}')
        for name in ('link_timeout_s', 'expected_rate_hz', 'rate_window_s',
                     'battery_timeout_s'):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f'{name} must be a positive number, got {value!r}')
        low = self.low_battery_fraction
        if not isinstance(low, (int, float)) or not 0.0 <= low <= 1.0 - BATTERY_CLEAR_MARGIN:
            raise ValueError(f'low_battery_fraction must be in 0..{1 - BATTERY_CLEAR_MARGIN:.2f} '
                             f'(it clears {BATTERY_CLEAR_MARGIN:.2f} above), got {low!r}')


@dataclass(frozen=True)
class Setpoint:
    """The stick setpoints; NaN until received. ``updated``: the fields this update set."""

    yaw_deg: float = NAN
    pitch_deg: float = NAN
    roll_deg: float = NAN
    altitude_m: float = NAN
    updated: tuple[str, ...] = ()
    stamp: float = NAN
    """Clock time of the last byte of the newest frame in this update (H7)."""


@dataclass(frozen=True)
class Auxiliary:
    """Lights (−1 until received), camera angle (NaN until received) and recording."""

    lights_percent: int = -1
    camera_angle_deg: float = NAN
    camera_recording: bool = False
    camera_recording_known: bool = False
    updated: tuple[str, ...] = ()
    stamp: float = NAN


@dataclass(frozen=True)
class LinkState:
    """Health of the handset link at ``stamp``.

    ``connected``: every stick setpoint was refreshed by a valid frame within ``link_timeout_s``
    (false before all four came; ``rules.py``).
    ``frame_rate_hz``: valid frames per second; ``command_rate_hz``: those of the most frequent
    type (the handset's tick rate), both over the last ``rate_window_s``.
    ``last_frame_age_s``: NaN before the first valid frame.
    """

    connected: bool
    port_open: bool
    frame_rate_hz: float
    command_rate_hz: float
    frames_accepted: int
    frames_malformed: int
    frames_out_of_range: int
    frames_unknown_type: int
    frames_rejected_recently: int
    last_frame_age_s: float
    stamp: float
    stick_age_s: float = NAN
    """Age of the oldest stick setpoint, the one the link is judged by; NaN until all four."""


@dataclass
class _Pending:
    """A setpoint or auxiliary update being gathered from one read."""

    names: list = field(default_factory=list)
    stamp: float = NAN
    values: dict = field(default_factory=dict)


class HandsetCore:
    """One handset link: the modem's port, the decoded state and the failsafe rules."""

    def __init__(
        self,
        config: HandsetConfig,
        clock: Callable[[], float] = time.monotonic,
        on_setpoint: Optional[Callable[[Setpoint], None]] = None,
        on_auxiliary: Optional[Callable[[Auxiliary], None]] = None,
        on_link: Optional[Callable[[LinkState], None]] = None,
        on_failsafe: Optional[Callable[[Failsafe], None]] = None,
        on_log: Optional[Callable[[str, str], None]] = None,
    ) -> None:
        self.config = config
        self._clock = clock
        self._on_setpoint = on_setpoint
        self._on_auxiliary = on_auxiliary
        self._on_link = on_link
        self._on_failsafe = on_failsafe
        self._on_log = on_log or _python_log
        self._lock = threading.Lock()
        self._emit_lock = threading.RLock()
        self._timer = DeadlineTimer(self._timer_duty, name='handset-link-timer', clock=clock,
                                    idle_s=MAX_TIMER_SLEEP_S, on_error=self._timer_failed)

        self._setpoint = Setpoint()
        self._aux = Auxiliary()
        self._sp_pending = _Pending()
        self._aux_pending = _Pending()
        self._rules = HandsetRules(config.link_timeout_s, config.low_battery_fraction,
                                   config.battery_timeout_s, clock())
        self._last_valid: Optional[float] = None
        self._port_open = False
        self.frames_accepted = 0
        self.frames_malformed = 0
        self.frames_out_of_range = 0
        self.frames_unknown_type = 0
        self._window: Deque[float] = deque()
        self._window_by_type: dict[int, Deque[float]] = {t: deque() for t in p.SPECS}
        self._rejections: Deque[float] = deque()
        self._throttle = Throttle()
        self._unknown_logged: set[int] = set()

        self.link = ModemLink(config.port, config.baud, self._on_received,
                              on_connection=self._on_connection, clock=clock,
                              logger=_LogAdapter(self._log), on_held=self._due_by)

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self, run_threads: bool = True) -> None:
        """Start counting the link timeout (H8), report the initial state, open the port.

        ``run_threads=False`` opens nothing and starts no thread: the caller feeds bytes with
        ``feed()`` and lets time pass with ``poll()``.
        """
        with self._emit_lock:
            with self._lock:
                now = self._clock()
                self._step(Started(now), now, [])
                # H15: not connected before the first valid frame, not lost before the timeout.
                emits = [(self._on_link, self._link_state(now)),
                         (self._on_failsafe, self._rules.failsafe(now))]
            self._emit(emits)
        if run_threads and not self._timer.is_alive():
            self.link.start()
            self._timer.start()

    def stop(self) -> None:
        """Stop the timer thread and close the port."""
        self._timer.stop(2.0)
        self.link.stop()

    # -- inputs ---------------------------------------------------------------------------------

    def feed(self, data: bytes) -> None:
        """Take bytes as read from the modem (what the reader thread does; tests call it)."""
        self.link.feed(data)

    def poll(self) -> None:
        """Let time pass: settle a quiet partial frame (H3), a lost link (H8), a stale battery."""
        self.link.poll()
        with self._emit_lock:
            with self._lock:
                emits: list = []
                now = self._clock()
                self._step(Tick(now), now, emits)
            self._emit(emits)

    def on_battery(self, percentage: float) -> None:
        """Take the aircraft's battery charge, 0..1 (``sensor_msgs/BatteryState.percentage``).

        Below ``low_battery_fraction`` is low, cleared at 5 points above (H9). NaN says nothing;
        a value outside 0..1 says nothing either and is logged once. A reading older than
        ``battery_timeout_s`` is stale: the battery is unknown (``rules.py``).
        """
        with self._emit_lock:
            emits: list = []
            with self._lock:
                now = self._clock()
                self._step(BatteryReading(now, percentage), now, emits)
            self._emit(emits)

    @property
    def battery_out_of_range(self) -> int:
        """Battery percentages outside 0..1 received (ignored, H9)."""
        return self._rules.battery_out_of_range

    def reconfigure(self, **changes: Any) -> None:
        """Change the ``RUNTIME_FIELDS`` (timeouts, rate, battery threshold) at runtime.

        Raises ValueError naming a bad value (nothing changes then). The rules are applied to the
        new values at once: a shorter timeout can declare the link lost, a higher threshold the
        battery low (H25).
        """
        fixed = set(changes) - RUNTIME_FIELDS
        if fixed:
            raise ValueError(f'{", ".join(sorted(fixed))} cannot change while the link runs')
        with self._emit_lock:
            emits: list = []
            with self._lock:
                self.config = replace(self.config, **changes)
                now = self._clock()
                self._step(Reconfigured(
                    now, **{k: v for k, v in changes.items() if k != 'expected_rate_hz'}),
                    now, emits)  # (a shorter timeout is due sooner: SetTimer)
            self._emit(emits)

    # -- snapshots ------------------------------------------------------------------------------

    def setpoint(self) -> Setpoint:
        """Return the latest stick setpoints (``updated`` empty)."""
        with self._lock:
            return replace(self._setpoint, updated=())

    def auxiliary(self) -> Auxiliary:
        """Return the latest auxiliary state (``updated`` empty)."""
        with self._lock:
            return replace(self._aux, updated=())

    def battery_last(self) -> tuple[float, float]:
        """Return the last usable battery reading and its age (NaN, NaN before the first)."""
        with self._lock:
            at = self._rules.battery_at
            if at is None:
                return NAN, NAN
            return self._rules.battery, max(0.0, self._clock() - at)

    def link_state(self) -> LinkState:
        """Return the link's health now (rates over the last ``rate_window_s``)."""
        with self._lock:
            return self._link_state(self._clock())

    def failsafe(self) -> Failsafe:
        """Return the failsafe conditions and the requested action now."""
        with self._lock:
            return self._rules.failsafe(self._clock())

    # -- reader thread --------------------------------------------------------------------------

    def _on_received(self, batch: Received) -> None:
        with self._emit_lock:
            emits: list = []
            with self._lock:
                for result in batch.results:
                    self._apply(result, batch.time, emits)
                self._flush_setpoint(emits)
                self._flush_aux(emits)
                self._prune(batch.time)
            self._emit(emits)

    def _on_connection(self, up: bool, reason: str) -> None:
        # Reported, but no failsafe of its own: the H8 timer decides (H21), so a modem that
        # comes back within link_timeout_s requests nothing.
        with self._emit_lock:
            with self._lock:
                self._port_open = up
                emits = [(self._on_link, self._link_state(self._clock()))]
            self._emit(emits)

    def _apply(self, result: p.Decoded, now: float, emits: list) -> None:
        if isinstance(result, p.Command):
            self._accept(result, now, emits)
            return
        self._rejections.append(now)
        if isinstance(result, p.OutOfRange):
            self.frames_out_of_range += 1
            self._throttled(('out_of_range', result.type), now, emits,
                            f'refused {result.type.name} frame ({result.encoding}): '
                            f'{result.reason.split(": ", 1)[-1]}; not applied (H6)')
        elif isinstance(result, p.UnknownType):
            self.frames_unknown_type += 1
            if result.type not in self._unknown_logged:
                self._unknown_logged.add(result.type)
                emits.append(('WARN', f'ignoring frames of unknown type 0x{result.type:02X} '
                                      f'(H4; counted, logged once per type)'))
        else:
            self.frames_malformed += 1
            what = result.type.name if result.type is not None else 'frame'
            self._throttled(('malformed', result.type), now, emits,
                            f'malformed {what}: {result.reason}; dropped (H3, H5)')

    def _accept(self, cmd: p.Command, now: float, emits: list) -> None:
        # Only an accepted frame is a valid frame (H14): a handset that sends nothing usable
        # controls nothing, however busy the line.
        self.frames_accepted += 1
        self._window.append(now)
        self._window_by_type[cmd.type].append(now)
        self._last_valid = now
        # The last byte of this frame arrived before the bytes read after it (H16).
        stamp = now - cmd.bytes_after * BITS_PER_BYTE / self.config.baud
        name = STICK_FIELDS.get(cmd.type)
        if name is not None:
            # Only a stick frame keeps the link (issue 21 item 8): auxiliary ones never do.
            self._step(StickFrame(now, name), now, emits)
            pending = self._sp_pending
            if name in pending.values:
                self._flush_setpoint(emits)  # the same field twice: one update per frame
                pending = self._sp_pending
            pending.values[name] = float(cmd.value)
            pending.names.append(name)
            pending.stamp = stamp
            return
        name = AUX_FIELDS[cmd.type]
        changes = {name: cmd.value}
        if cmd.type == p.CommandType.SET_CAMERA_RECORD:
            if self._aux.camera_recording_known and self._aux.camera_recording == cmd.value:
                return
            changes['camera_recording_known'] = True
        elif getattr(self._aux, name) == cmd.value:
            return  # H17: on change; NaN and -1 (never received) equal no value
        if name in self._aux_pending.names:
            self._flush_aux(emits)
        self._aux = evolve(self._aux, **changes)
        self._aux_pending.names.append(name)
        self._aux_pending.stamp = stamp

    def _flush_setpoint(self, emits: list) -> None:
        pending = self._sp_pending
        if pending.names:
            self._setpoint = evolve(self._setpoint, updated=tuple(pending.names),
                                    stamp=pending.stamp, **pending.values)
            emits.append((self._on_setpoint, self._setpoint))
            self._sp_pending = _Pending()

    def _flush_aux(self, emits: list) -> None:
        pending = self._aux_pending
        if pending.names:
            self._aux = evolve(self._aux, updated=tuple(pending.names), stamp=pending.stamp)
            emits.append((self._on_auxiliary, self._aux))
            self._aux_pending = _Pending()

    def _throttled(self, key: Any, now: float, emits: list, text: str) -> None:
        """Log at most once per key per second, saying how many were held back (H6, H19)."""
        note = self._throttle.admit(key, now, REJECTION_LOG_PERIOD_S)
        if note is not None:
            emits.append(('WARN', text + note))

    # -- rules ----------------------------------------------------------------------------------

    def _step(self, event: Event, now: float, emits: list) -> None:
        """Step the rules with `event` (``_lock`` held); carry out their actions in order.

        Log lines and changes become callbacks run after the lock is let go (``emits``); a
        deadline wakes the timer by then (its condition only, never a driver's lock).
        """
        run_core(self._rules, [event], {
            Log: lambda action: emits.append((action.level, action.text)),
            FailsafeChanged: lambda action: emits.append((self._on_failsafe, action.failsafe)),
            LinkChanged: lambda action: emits.append((self._on_link, self._link_state(now))),
            SetTimer: lambda action: self._due_by(action.at)})

    def _prune(self, now: float) -> None:
        """Forget frame times older than the rate window (bounded memory under any input)."""
        horizon = now - self.config.rate_window_s
        for times in (self._window, self._rejections, *self._window_by_type.values()):
            while times and times[0] <= horizon:
                times.popleft()

    def _link_state(self, now: float) -> LinkState:
        # H18: frames counted over the last rate_window_s, divided by it.
        self._prune(now)
        window = self.config.rate_window_s
        busiest = max(len(t) for t in self._window_by_type.values())
        age = NAN if self._last_valid is None else max(0.0, now - self._last_valid)
        return LinkState(
            connected=self._rules.connected, port_open=self._port_open,
            frame_rate_hz=len(self._window) / window, command_rate_hz=busiest / window,
            frames_accepted=self.frames_accepted, frames_malformed=self.frames_malformed,
            frames_out_of_range=self.frames_out_of_range,
            frames_unknown_type=self.frames_unknown_type,
            frames_rejected_recently=len(self._rejections), last_frame_age_s=age, stamp=now,
            stick_age_s=self._rules.stick_age(now))

    # -- timer thread ---------------------------------------------------------------------------

    def _timer_duty(self) -> Optional[float]:
        """Poll now, return when ``poll()`` is next due (the timer thread's duty)."""
        self.poll()
        return self.next_deadline()

    def _due_by(self, due: Optional[float]) -> None:
        """Have the timer poll by `due`, a deadline an event set (None: nothing due)."""
        if due is not None:
            self._timer.wake(by=due)

    def _timer_failed(self, exc: BaseException) -> None:
        self._log('ERROR', f'handset timer failed:\n{traceback.format_exc()}')

    def next_deadline(self) -> Optional[float]:
        """When ``poll()`` next has something to do (clock time), None if nothing is due.

        The timer thread sleeps until then; a caller on a fake clock polls then.
        """
        deadlines = []
        idle = self.link.idle_deadline()
        if idle is not None:
            deadlines.append(idle)
        with self._lock:
            due = self._rules.next_deadline()
        if due is not None:
            deadlines.append(due)
        return min(deadlines, default=None)

    # -- callbacks ------------------------------------------------------------------------------

    def _emit(self, emits: list) -> None:
        """Run gathered callbacks in order; a log entry is ``(level, text)``."""
        for target, arg in emits:
            if isinstance(target, str):
                self._log(target, arg)
                continue
            if target is None:
                continue
            try:
                target(arg)
            except Exception:  # noqa: BLE001 - a consumer's bug must not stop the link
                self._log('ERROR', f'{getattr(target, "__name__", target)} failed:\n'
                                   f'{traceback.format_exc()}')

    def _log(self, level: str, text: str) -> None:
        try:
            self._on_log(level, text)
        except Exception:  # noqa: BLE001 - logging must never break the reader
            pass


class _LogAdapter:
    """The logger interface SerialLink uses, onto ``on_log``."""

    def __init__(self, log: Callable[[str, str], None]) -> None:
        self._log = log

    def debug(self, text: str) -> None:
        self._log('DEBUG', text)

    def info(self, text: str) -> None:
        self._log('INFO', text)

    def warning(self, text: str) -> None:
        self._log('WARN', text)

    warn = warning

    def error(self, text: str) -> None:
        self._log('ERROR', text)


_LEVELS = {'DEBUG': logging.DEBUG, 'INFO': logging.INFO, 'WARN': logging.WARNING,
           'ERROR': logging.ERROR}


def _python_log(level: str, text: str) -> None:
    logging.getLogger('handset_link').log(_LEVELS.get(level, logging.INFO), text)
