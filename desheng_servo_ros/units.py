"""Positions in rad and ticks, and commands turned into (id, ticks, run time) targets. No ROS.

Ticks are 0..4095 (S5); rad = (ticks - ``zero_tick``) * 2 pi / ``ticks_per_revolution``
(REP-103). Every value a message can carry is either converted or refused with a ValueError
that says what is wrong, in a bounded message (``uav_serial_common.text``): no input raises
anything else (``docs/protocols.md``, driver decisions "Units" and "Commands").
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

from desheng_servo_ros import protocol as proto
from uav_serial_common.text import few, short

Target = Tuple[int, int, int]
"""(servo id, position ticks, run time ms): one entry of a SYNC WRITE."""


@dataclass(frozen=True)
class Units:
    """The conversion between a servo's ticks and rad."""

    ticks_per_revolution: int = 4096
    zero_tick: int = 2048

    @property
    def rad_per_tick(self) -> float:
        """Return the angle of one tick [rad]."""
        return 2.0 * math.pi / self.ticks_per_revolution

    def ticks_to_rad(self, ticks: int) -> float:
        """Convert a position in ticks to rad (zero at ``zero_tick``)."""
        return (ticks - self.zero_tick) * self.rad_per_tick

    def rad_range(self) -> Tuple[float, float]:
        """Return the positions in rad that map into 0..4095 ticks."""
        return self.ticks_to_rad(proto.POSITION_MIN), self.ticks_to_rad(proto.POSITION_MAX)

    def rad_to_ticks(self, rad: float, who: str = 'position') -> int:
        """Convert rad to the nearest tick; ValueError naming `who` outside 0..4095 ticks."""
        try:
            rad = float(rad)
        except OverflowError:
            raise ValueError(f'{who}: position {short(rad)} is outside the valid range') from None
        except (TypeError, ValueError):
            raise ValueError(f'{who}: position {short(rad)} is not a number') from None
        if not math.isfinite(rad):
            raise ValueError(f'{who}: position {rad} is not a finite number')
        # Checked as a float before any int(): 1e308 rad would overflow the conversion.
        exact = self.zero_tick + rad / self.rad_per_tick
        if not (proto.POSITION_MIN - 0.5 <= exact < proto.POSITION_MAX + 0.5):
            lo, hi = self.rad_range()
            raise ValueError(f'{who}: position {rad:.6g} rad is outside the valid range '
                             f'{lo:.4f}..{hi:.4f} rad (ticks 0..4095)')
        return min(proto.POSITION_MAX, max(proto.POSITION_MIN, int(round(exact))))


@dataclass(frozen=True)
class Joint:
    """A configured servo as commands address it: bus id and joint name."""

    id: int
    name: str


def check_move_time(move_time_ms: int, default_ms: int) -> int:
    """Return the run time to send: -1 means `default_ms`; ValueError outside 0..65535."""
    if isinstance(move_time_ms, bool) or not isinstance(move_time_ms, int):
        raise ValueError(f'move_time_ms must be an integer, got {short(move_time_ms)}')
    if move_time_ms == -1:
        move_time_ms = default_ms
    if not 0 <= move_time_ms <= proto.RUN_TIME_MAX_MS:
        raise ValueError(f'move_time_ms must be -1 (default) or 0..{proto.RUN_TIME_MAX_MS}, '
                         f'got {move_time_ms}')
    return move_time_ms


def _twice(keys: Sequence) -> List:
    seen, twice = set(), []
    for key in keys:
        if key in seen and key not in twice:
            twice.append(key)
        seen.add(key)
    return twice


def select(joints: Sequence[Joint], ids: Sequence[int]) -> List[Joint]:
    """Return the joints of `ids` (empty = all configured); ValueError on unknown or repeated."""
    ids = list(ids)
    if not ids:
        if not joints:
            raise ValueError('no servos configured (yet)')
        return list(joints)
    by_id: Dict[int, Joint] = {j.id: j for j in joints}
    return _pick(by_id, ids, lambda unknown: f'unknown servo id(s) {few(unknown)}; configured: '
                 f'{few(by_id, 12)} (~/scan lists the bus)',
                 lambda twice: f'servo id(s) listed twice: {few(twice)}')


def _pick(table: Dict[Any, Joint], keys: Sequence, unknown: Callable[[List], str],
          twice: Callable[[List], str]) -> List[Joint]:
    """Return the joints of `keys`; ValueError (`unknown`, then `twice`) for bad keys."""
    missing = [k for k in keys if k not in table]
    if missing:
        raise ValueError(unknown(missing))
    repeated = _twice(keys)
    if repeated:
        raise ValueError(twice(repeated))
    return [table[k] for k in keys]


def resolve_targets(joints: Sequence[Joint], units: Units, names: Sequence[str],
                    ids: Sequence[int], positions: Sequence[float], move_time_ms: int,
                    default_move_time_ms: int = 0) -> List[Target]:
    """Turn a command (names or ids, positions in rad) into targets; ValueError says why not."""
    names, ids, positions = list(names), list(ids), list(positions)
    if names and ids:
        raise ValueError('give names or ids, not both')
    if not names and not ids:
        raise ValueError('give the servos by names or by ids')
    keys = names or ids
    if len(keys) != len(positions):
        raise ValueError(f'{len(keys)} {"names" if names else "ids"} but '
                         f'{len(positions)} positions')
    ms = check_move_time(move_time_ms, default_move_time_ms)
    if names:
        by_name: Dict[str, Joint] = {j.name: j for j in joints}
        selected = _pick(by_name, names, lambda unknown: f'unknown joint name(s) '
                         f'{few(unknown)}; known: {few(by_name, 12)}',
                         lambda twice: f'joint(s) listed twice: {few(twice)}')
    else:
        selected = select(joints, ids)
    return [(j.id, units.rad_to_ticks(rad, f'{j.name} (id {j.id})'), ms)
            for j, rad in zip(selected, positions)]


def servo_list(ids: Sequence[int], names: Optional[Sequence[str]] = None) -> List[Joint]:
    """Return the joints of `servo_ids` and `joint_names`; ValueError for a list that cannot be."""
    ids, names = list(ids), list(names or [])
    bad = [i for i in ids if not proto.is_servo_id(i)]
    if bad:
        raise ValueError(f'servo_ids must be 1..250, got {few(bad)}')
    twice = _twice(ids)
    if twice:
        raise ValueError(f'servo_ids lists an id twice: {few(twice)}')
    if names and len(names) != len(ids):
        raise ValueError(
            f'joint_names has {len(names)} names but servo_ids has {len(ids)} ids: give one '
            'name per id, or no names (servo_<id>)')
    if not names:
        names = [f'servo_{i}' for i in ids]
    twice = _twice(names)
    if twice:
        raise ValueError(f'joint_names lists a name twice: {few(twice)}')
    return [Joint(i, n) for i, n in zip(ids, names)]
