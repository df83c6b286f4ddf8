"""The handset's failsafe rules as a pure state machine: events with their time in, outputs out.

No clock, thread, lock or port here (issue 22 item 1): ``HandsetCore`` steps it
(``core_runner.run_core``) with the events ``Started``, ``StickFrame``, ``BatteryReading``,
``Reconfigured`` and ``Tick`` (time passed), each with its monotonic time, and carries out what
each step returns, in order: ``Log(level, text)``, ``FailsafeChanged(failsafe)``,
``LinkChanged()`` and, last, ``SetTimer(at)``: the next deadline of a rule (the runtime's timer
ticks by then). A test drives it (or the core around it) in virtual time.

The link is judged by the sticks (H8, issue 21 item 8). The aircraft flies by the four stick
setpoints together (SET_YAW, SET_PITCH, SET_ROLL, SET_ALTITUDE; each ``~/setpoint`` carries all
four), and the handset sends the four every tick (H7, H22), so each of them must be fresher
than ``link_timeout_s``: the oldest of the four judges the link. A stick value older than that
is a command nobody confirms, and the link is lost whatever else arrives (auxiliary frames,
other sticks, frames the driver refuses). A stick never received counts from start-up (a
handset never heard is a lost link, H8/H15). The link is up (``connected``) while all four are
fresher than the timeout, and regained when they are all fresh again.

The battery (H9): below ``low_battery_fraction`` is low, cleared at 5 points above. A reading
older than ``battery_timeout_s`` is stale: the battery is then unknown (``battery_fraction``
NaN, ``battery_stale``), which requests nothing by itself (the flight controller has its own
battery failsafe, and a bridge restarting must not send the aircraft home), and the node's
diagnostics warn that the low-battery failsafe cannot act. A low battery stays low while the
readings are missing: only a reading at or above the clearing level clears it, silence never
does.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Optional, Union

from uav_serial_common.core_events import Log, SetTimer, Tick  # (every core's: one handler)

ACTION_NONE = 'NONE'
ACTION_RETURN_TO_HOME = 'RETURN_TO_HOME'
BATTERY_CLEAR_MARGIN = 0.05
"""A low battery clears this far above ``low_battery_fraction`` (H9: 20 % → 25 %)."""
STICKS = ('yaw_deg', 'pitch_deg', 'roll_deg', 'altitude_m')
"""The stick setpoints the link is judged by, in wire order."""
NAN = math.nan


@dataclass(frozen=True)
class Failsafe:
    """The failsafe conditions (H8, H9) and the action requested while either holds (H10).

    ``battery_fraction``: the last reading, NaN when none came or it is stale
    (``battery_stale``: older than ``battery_timeout_s``).
    """

    link_lost: bool
    battery_low: bool
    action: str
    reason: str
    battery_fraction: float
    stamp: float
    battery_stale: bool = False


@dataclass(frozen=True)
class FailsafeChanged:
    """The failsafe changed (a condition, or what it says about the battery)."""

    failsafe: Failsafe


@dataclass(frozen=True)
class LinkChanged:
    """``connected`` changed."""


@dataclass(frozen=True)
class Started:
    """The link starts: a stick never received counts from ``now`` (H15)."""

    now: float


@dataclass(frozen=True)
class StickFrame:
    """An accepted stick frame (``name`` one of ``STICKS``) read at ``now``."""

    now: float
    name: str


@dataclass(frozen=True)
class BatteryReading:
    """The aircraft's battery charge, 0..1 (NaN or outside 0..1 says nothing, H9)."""

    now: float
    percentage: float


@dataclass(frozen=True)
class Reconfigured:
    """New settings (None: unchanged), checked by the caller; applied at once (H25)."""

    now: float
    link_timeout_s: Optional[float] = None
    low_battery_fraction: Optional[float] = None
    battery_timeout_s: Optional[float] = None


Event = Union[Started, StickFrame, BatteryReading, Reconfigured, Tick]
Output = Union[Log, FailsafeChanged, LinkChanged, SetTimer]


class HandsetRules:
    """Link loss by the sticks, battery hysteresis and staleness; every method is pure."""

    def __init__(self, link_timeout_s: float, low_battery_fraction: float,
                 battery_timeout_s: float, now: float) -> None:
        self.link_timeout_s = link_timeout_s
        self.low_battery_fraction = low_battery_fraction
        self.battery_timeout_s = battery_timeout_s
        self.started_at = now
        self.stick_at: dict[str, float] = {}
        """When each stick was last accepted."""
        self.link_lost = False
        self.connected = False
        self.battery = NAN
        """The last usable reading (kept when it goes stale, for the log)."""
        self.battery_at: Optional[float] = None
        self.battery_stale = False
        self.battery_low = False
        self.battery_out_of_range = 0
        """Battery percentages outside 0..1 received (ignored, H9)."""

    # -- events ---------------------------------------------------------------------------------

    def step(self, event: Event) -> list[Output]:
        """Take one event; return its outputs in order, then ``SetTimer`` when a rule is due."""
        if isinstance(event, StickFrame):
            out = self.stick(event.name, event.now)
        elif isinstance(event, Tick):
            out = self.tick(event.now)
        elif isinstance(event, BatteryReading):
            out = self.battery_reading(event.percentage, event.now)
        elif isinstance(event, Reconfigured):
            out = self.reconfigure(event.now, event.link_timeout_s, event.low_battery_fraction,
                                   event.battery_timeout_s)
        elif isinstance(event, Started):
            out = self.start(event.now)
        else:
            raise TypeError(f'the handset rules take no {type(event).__name__}')
        due = self.next_deadline()
        if due is not None:
            out.append(SetTimer(due))
        return out

    def start(self, now: float) -> list[Output]:
        """Start counting from ``now`` (H15: not lost before the timeout)."""
        self.started_at = now
        return []

    def stick(self, name: str, now: float) -> list[Output]:
        """Take an accepted stick frame (``name`` one of ``STICKS``) read at ``now``."""
        if name not in STICKS:
            raise ValueError(f'{name!r} is not a stick setpoint')
        out = self.tick(now)  # time passes first: what expired before this frame did
        self.stick_at[name] = max(now, self.stick_at.get(name, now))
        self._judge_link(now, out)
        return out

    def tick(self, now: float) -> list[Output]:
        """Let time pass to ``now``: a stale stick loses the link, a stale battery is unknown."""
        out: list[Output] = []
        self._judge_link(now, out)
        self._judge_battery_age(now, out)
        return out

    def battery_reading(self, percentage: float, now: float) -> list[Output]:
        """Take the aircraft's battery charge, 0..1; NaN or outside 0..1 says nothing (H9)."""
        out = self.tick(now)
        if isinstance(percentage, bool) or not isinstance(percentage, (int, float)) \
                or math.isnan(percentage):
            return out
        if not 0.0 <= percentage <= 1.0:
            self.battery_out_of_range += 1
            if self.battery_out_of_range == 1:
                out.append(Log('WARN', f'battery percentage {percentage!r} is outside 0..1 and '
                                       f'says nothing about the battery; ignored (logged once)'))
            return out
        self.battery = float(percentage)
        self.battery_at = now
        back = self.battery_stale
        self.battery_stale = False
        if back:
            out.append(Log('WARN', f'battery reported again: {self.battery * 100:.1f} %'))
        if not self._judge_battery_level(now, out) and back:
            out.append(FailsafeChanged(self.failsafe(now)))
        return out

    def reconfigure(self, now: float, link_timeout_s: Optional[float] = None,
                    low_battery_fraction: Optional[float] = None,
                    battery_timeout_s: Optional[float] = None) -> list[Output]:
        """Apply new settings at once (H25); the caller has checked them."""
        if link_timeout_s is not None:
            self.link_timeout_s = link_timeout_s
        if low_battery_fraction is not None:
            self.low_battery_fraction = low_battery_fraction
        if battery_timeout_s is not None:
            self.battery_timeout_s = battery_timeout_s
        out = self.tick(now)
        if self.battery_at is not None and not self.battery_stale:
            self._judge_battery_level(now, out)  # a stale level is not judged again
        return out

    # -- state ----------------------------------------------------------------------------------

    def oldest_stick(self) -> float:
        """Return the time of the oldest stick value (start-up for a stick never received)."""
        return min(self.stick_at.get(name, self.started_at) for name in STICKS)

    def stick_age(self, now: float) -> float:
        """Age of the oldest stick value, NaN until all four were received."""
        if len(self.stick_at) < len(STICKS):
            return NAN
        return max(0.0, now - self.oldest_stick())

    def next_deadline(self) -> Optional[float]:
        """Return when ``tick()`` may next change something by itself (None: nothing due)."""
        deadlines = []
        if not self.link_lost:
            deadlines.append(self.oldest_stick() + self.link_timeout_s)
        if self.battery_at is not None and not self.battery_stale:
            deadlines.append(self.battery_at + self.battery_timeout_s)
        return min(deadlines, default=None)

    def failsafe(self, now: float) -> Failsafe:
        """Return the failsafe conditions and the requested action at ``now``."""
        reasons = []
        if self.link_lost:
            reasons.append(self._lost_reason())
        if self.battery_low:
            stale = f' (no reading for {self.battery_timeout_s:g} s)' if self.battery_stale \
                else ''
            reasons.append(f'battery low: {self.battery * 100:.1f} % < '
                           f'{self.low_battery_fraction * 100:.0f} %{stale}')
        action = ACTION_RETURN_TO_HOME if reasons else ACTION_NONE
        if not reasons:
            reasons.append('handset link up' if self.connected else self._waiting())
            reasons.append(self._battery_text())
        elif self.battery_stale and not self.battery_low:
            reasons.append(self._battery_text())
        fraction = NAN if self.battery_stale else self.battery
        return Failsafe(self.link_lost, self.battery_low, action, '; '.join(reasons), fraction,
                        now, self.battery_stale)

    # -- rules ----------------------------------------------------------------------------------

    def _judge_link(self, now: float, out: list) -> None:
        # The same sum as next_deadline(): a poll at the deadline always finds it expired.
        expired = now >= self.oldest_stick() + self.link_timeout_s
        fresh = len(self.stick_at) == len(STICKS) and not expired
        if expired and not self.link_lost:
            self.link_lost = True
            self.connected = False
            out.append(Log('ERROR', f'handset link lost: {self._stale_sticks(now)}; requesting '
                                    f'return to home (H8)'))
            out.append(FailsafeChanged(self.failsafe(now)))
            out.append(LinkChanged())
        elif fresh and self.link_lost:
            self.link_lost = False
            self.connected = True
            failsafe = self.failsafe(now)
            # H24: a failsafe change is a WARN at least, the clearing included.
            out.append(Log('WARN', f'handset link regained (H8): every stick setpoint fresher '
                                   f'than {self.link_timeout_s:g} s; failsafe now '
                                   f'{failsafe.action}: {failsafe.reason}'))
            out.append(FailsafeChanged(failsafe))
            out.append(LinkChanged())
        elif fresh and not self.connected:
            self.connected = True
            out.append(Log('INFO', 'handset heard: link up (every stick setpoint received)'))
            out.append(LinkChanged())

    def _judge_battery_age(self, now: float, out: list) -> None:
        if self.battery_at is None or self.battery_stale \
                or now < self.battery_at + self.battery_timeout_s:
            return
        self.battery_stale = True
        low = ' (the low-battery condition holds until a reading clears it)' \
            if self.battery_low else ''
        out.append(Log('WARN', f'battery unknown: no reading for {self.battery_timeout_s:g} s '
                               f'(last {self.battery * 100:.1f} %); the low-battery failsafe '
                               f'cannot act on it{low}'))
        out.append(FailsafeChanged(self.failsafe(now)))

    def _judge_battery_level(self, now: float, out: list) -> bool:
        """Apply the hysteresis to the last reading; return whether the condition changed."""
        low = self.low_battery_fraction
        clear = low + BATTERY_CLEAR_MARGIN
        level = self.battery
        if not self.battery_low and level < low:
            self.battery_low = True
            out.append(Log('WARN', f'battery low: {level * 100:.1f} % < {low * 100:.0f} %; '
                                   f'requesting return to home (H9)'))
            out.append(FailsafeChanged(self.failsafe(now)))
            return True
        if self.battery_low and level >= clear - 1e-9:
            # H20: 0.20 + 0.05 is 0.25000000000000006 in binary, and 25 % must clear.
            self.battery_low = False
            failsafe = self.failsafe(now)
            out.append(Log('WARN', f'battery back at {level * 100:.1f} % (>= {clear * 100:.0f} '
                                   f'%): low-battery condition cleared (H9); failsafe now '
                                   f'{failsafe.action}: {failsafe.reason}'))
            out.append(FailsafeChanged(failsafe))
            return True
        return False

    # -- wording --------------------------------------------------------------------------------

    def _stale_sticks(self, now: float) -> str:
        limit = self.link_timeout_s
        never = [n for n in STICKS if n not in self.stick_at]
        old = [n for n in STICKS if n in self.stick_at and now >= self.stick_at[n] + limit]
        parts = []
        if never:
            parts.append(f'no valid {"/".join(never)} frame for {limit:g} s since start-up')
        if old:
            parts.append(f'no valid {"/".join(old)} frame for {limit:g} s since the last one')
        return ', '.join(parts) or f'no valid stick frame for {limit:g} s'

    def _lost_reason(self) -> str:
        heard = ' since start-up' if not self.stick_at else ''
        return f'link lost: a stick setpoint not refreshed by a valid handset frame for ' \
            f'{self.link_timeout_s:g} s{heard}'

    def _waiting(self) -> str:
        missing = [n for n in STICKS if n not in self.stick_at]
        what = f' ({"/".join(missing)} not received yet)' if self.stick_at and missing else ''
        return f'waiting for the handset{what} (lost after {self.link_timeout_s:g} s without ' \
            f'a valid stick frame)'

    def _battery_text(self) -> str:
        if self.battery_stale:
            return f'battery unknown: no reading for {self.battery_timeout_s:g} s (last ' \
                f'{self.battery * 100:.1f} %)'
        if math.isnan(self.battery):
            return 'battery not reported'
        return f'battery {self.battery * 100:.1f} %'
