"""The rule "a settings write never fires the parachute" (D16), as a pure function. No I/O.

Every write of a module setting is a `settings_core.SettingsCore` transaction, which reads the
status afresh before each write and asks `would_deploy` here (an arm and the flag query too,
as a `JudgeCall`): at connect, after a reboot or a reconnect, for a parameter
set, for ``~/set_thresholds`` and ``~/set_auto_triggers``, when putting back a refused set, and
for the auto-trigger flag query (P14: a firmware may take it as "enable the attitude trigger").
The same function decides, on each status frame, whether a desired setting held back at connect
may now be written (the session then writes it, through the gate again).

A step is ``(name, value)``: a numeric setting by its parameter name and SI value
(``attitude_threshold_deg``, ``freefall_threshold_g``, ``freefall_time_s``,
``light_threshold_v``), or an auto-trigger flag as ``attitude`` / ``freefall`` with a bool.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Iterable, List, Optional, Sequence, Tuple

from dps_parachute_ros import protocol as p

Step = Tuple[str, Any]
ATTITUDE_STEPS = frozenset({'attitude_threshold_deg', 'attitude'})
FREEFALL_STEPS = frozenset({'freefall_threshold_g', 'freefall_time_s', 'freefall'})
TRIGGER_STEPS = ATTITUDE_STEPS | FREEFALL_STEPS
"""The light threshold only decides `bay_open` (D9): no trigger condition depends on it."""
JUDGED_STEPS = TRIGGER_STEPS | {'armed'}
"""``('armed', True)``: arming a module that meets a trigger condition fires it at once (P21)."""


@dataclass(frozen=True)
class Trigger:
    """The module's trigger settings as known (None = not known)."""

    attitude_threshold_deg: Optional[int]
    freefall_threshold_raw: Optional[int]
    attitude_enabled: Optional[bool]
    freefall_enabled: Optional[bool]

    def after(self, step: Step) -> 'Trigger':
        """Return the settings once `step` is written."""
        name, value = step
        if name == 'attitude_threshold_deg':
            return replace(self, attitude_threshold_deg=int(value))
        if name == 'freefall_threshold_g':
            return replace(self, freefall_threshold_raw=p.freefall_threshold_to_raw(value))
        if name == 'attitude':
            return replace(self, attitude_enabled=bool(value))
        if name == 'freefall':
            return replace(self, freefall_enabled=bool(value))
        return self


def order(steps: Iterable[Step]) -> List[Step]:
    """Return `steps` in the order that is safest to write.

    Disabling a trigger first, enabling one last: a set that raises a threshold and enables its
    trigger, or disables a trigger and lowers its threshold, never passes through a state that
    fires (the rule judges every step, so a bad order would only be refused, never fire).
    """
    def rank(step: Step) -> int:
        name, value = step
        if name in ('attitude', 'freefall'):
            return 2 if value else 0
        return 1
    return sorted(steps, key=rank)


def conditions(trigger: Trigger, tilt_deg: float, accel_g: float,
               which: Iterable[str] = ('attitude', 'freefall')) -> List[str]:
    """Return the trigger conditions that `trigger` meets at this tilt and acceleration.

    The module's rule (P21), judged conservatively: tilt at or above the threshold (it needs
    strictly above: a degree of margin), |a| at or below the free-fall threshold (it fires
    below it, after the free-fall time; the status rounds |a| to 0.1 g, so a reading at the
    threshold may be just below it), a flag not known counts as enabled.
    """
    met = []
    if 'attitude' in which and trigger.attitude_enabled is not False and \
            trigger.attitude_threshold_deg is not None and \
            tilt_deg >= trigger.attitude_threshold_deg:
        met.append(f'tilt {tilt_deg:g}° ≥ attitude threshold {trigger.attitude_threshold_deg}°')
    if 'freefall' in which and trigger.freefall_enabled is not False and \
            trigger.freefall_threshold_raw is not None and \
            round(accel_g * 10) <= trigger.freefall_threshold_raw:
        # The status gives |a| rounded to 0.1 g: at the threshold it may be just below it.
        relation = '<' if round(accel_g * 10) < trigger.freefall_threshold_raw else \
            '(rounded to 0.1 g) may be below'
        met.append(f'acceleration {accel_g:.1f} g {relation} free-fall threshold '
                   f'{trigger.freefall_threshold_raw / 10:.1f} g')
    return met


def would_deploy(trigger: Trigger, armed: Optional[bool], triggered: Optional[bool],
                 tilt_deg: float, accel_g: float, steps: Sequence[Step]) -> str:
    """Why writing `steps` in this order to this module would deploy it at once, or ''.

    Only an armed module that has not deployed can fire (P21); an armed state not known
    counts as armed. Each step is judged in the state it leaves: a setting on the trigger it
    touches, arming on both.
    """
    if triggered:
        return ''
    for step in steps:
        name, value = step
        if name == 'armed':
            armed = bool(value)
            which: Tuple[str, ...] = ('attitude', 'freefall')
            advice = 'level it, or raise the threshold or disable that trigger first'
        elif name in TRIGGER_STEPS:
            trigger = trigger.after(step)
            which = ('attitude',) if name in ATTITUDE_STEPS else ('freefall',)
            advice = 'lock first (~/arm false)'
        else:
            continue
        met = conditions(trigger, tilt_deg, accel_g, which) if armed is not False else []
        if met:
            return 'would deploy now: ' + '; '.join(met) + '; ' + advice
    return ''
