"""What the servo driver knows and is told: config, readings, the servo record.

No I/O, no threads. The registers the driver reads (the read loop's three READs), the node's
configuration, a diagnostic :class:`Health`, what a reply tells (:class:`Reading`,
:class:`Telemetry`), the snapshots the node publishes, and
:class:`ServoRecord`, what the driver knows of one servo (written by the read loop's thread
and the schedule's judgement, see ``core.py`` for who writes what when).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
import math
from typing import Any, Dict, List, NamedTuple, Optional, Sequence, Tuple

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.registers import by_name
from desheng_servo_ros.units import Joint
# The drivers' one result type; a service's `value` is a dict of its response fields.
from uav_serial_common.result import Outcome, Result  # noqa: F401

# Registers, by name from the table (registers.py).
TORQUE = by_name('torque_enable')
ID = by_name('id')
FIRMWARE = by_name('firmware_version')
POSITION = by_name('present_position')
SPEED = by_name('present_speed')
CURRENT = by_name('current')
TEMPERATURE = by_name('temperature')
RUN_PRESETS = tuple(by_name(f'run_preset_{k}') for k in (1, 2, 3))
FACTORY_ID = ID.default  # S23: RESET gives every servo the table's default id
LOCK_FLAG = by_name('lock_flag')
# The read loop's READs. Each cycle reads position + speed of every servo; where a servo's
# telemetry is due, that READ runs on to the temperature (0x38..0x3F) and a second one takes
# 0x28..0x30 (torque switch, current, and the lock flag). Two short blocks rather than one of
# 24 (0x28..0x3F): no READ holds the bus longer than 2 ms at 115200 baud (the block of 24 held
# it 3.3 ms), and a command waits for the READ in flight.
# The three are of different lengths because a READ's reply names no address: a late reply of
# one block, arriving while the next READ of that servo waits, would be taken for the other's
# (when both were 8 bytes, the current's low byte was once read as the temperature: a fresh
# clone's run of 2026-11-28). One block's late reply taken for its own next READ is that
# block, one attempt older.
assert SPEED.address == POSITION.end and LOCK_FLAG.address == CURRENT.end
POSITION_READ = (POSITION.address, POSITION.size + SPEED.size)
WIDE_READ = (POSITION.address, TEMPERATURE.end - POSITION.address)
STATE_READ = (TORQUE.address, LOCK_FLAG.end - TORQUE.address)
W_TEMPERATURE = TEMPERATURE.address - POSITION.address
S_CURRENT = CURRENT.address - TORQUE.address
# What a READ of the loop is for (the plan's entries, the tags of its replies), and its block
# (address, length) by that tag.
READ_POSITION, READ_WIDE, READ_STATE = 0, 1, 2
LOOP_READS = (POSITION_READ, WIDE_READ, STATE_READ)
assert len({length for _, length in LOOP_READS}) == len(LOOP_READS)


ALL_IDS = range(proto.MIN_ID, proto.MAX_ID + 1)

OK, WARN, ERROR, STALE = 0, 1, 2, 3
"""Diagnostic levels (diagnostic_msgs' values)."""


@dataclass
class ServoBusConfig:
    """What the driver is told at start (the node's parameters)."""

    port: str = '/dev/ttyUSB1'
    baud: int = 115200
    servo_ids: Sequence[int] = ()
    joint_names: Sequence[str] = ()
    ticks_per_revolution: int = 4096
    zero_tick: int = 2048
    publish_rate_hz: float = 50.0
    telemetry_period_s: float = 1.0
    default_move_time_ms: int = 0
    response_timeout_ms: float = 0.0
    max_retries: int = 1
    torque_on_start: bool = False
    torque_off_on_shutdown: bool = True
    adjust_latency_timer: bool = True

    RUNTIME = ('publish_rate_hz', 'telemetry_period_s', 'default_move_time_ms',
               'response_timeout_ms', 'max_retries', 'torque_off_on_shutdown')
    """What may change while running; everything else shapes the driver and is read once."""

    @classmethod
    def from_values(cls, values: Dict[str, Any]) -> 'ServoBusConfig':
        """Build a config from a dict with (at least) the field names; others are ignored."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})


class Health(NamedTuple):
    """A diagnostic status: level (OK..STALE), message, key/value pairs."""

    level: int
    message: str
    values: List[Tuple[str, Any]]


class Reading(NamedTuple):
    """What one reply tells of a servo's position (replaced whole on every reply)."""

    ticks: int
    rad: float
    speed_raw: int
    velocity: float
    status: int
    at: float
    """When the reply arrived (the reader thread took it off the port), monotonic [s]."""


class Telemetry(NamedTuple):
    """What the slow READ tells (replaced whole)."""

    current_ma: float
    temperature_c: float
    torque_enabled: bool


class ServoSnapshot(NamedTuple):
    """One servo as of the last cycle."""

    id: int
    name: str
    online: bool
    seen: bool
    position_ticks: int
    position_rad: float
    speed_raw: int
    velocity: float
    current_ma: float
    temperature_c: float
    status: int
    torque_enabled: bool
    error_count: int
    duplicate: bool
    read_at: float = math.nan
    """When the position arrived off the wire (monotonic clock) [s]; NaN before the first."""

    @property
    def faults(self) -> List[str]:
        """Names of the documented fault bits set in the last status byte (S4)."""
        return fault_names(self.status)


def fault_names(status: int) -> List[str]:
    """Return the names of the documented fault bits set in a status byte (S4)."""
    return [name for bit, name in _FAULT_BITS if status & bit]


_FAULT_BITS = ((proto.STATUS_OVERLOAD, 'overload'),
               (proto.STATUS_OVER_TEMPERATURE, 'over-temperature'),
               (proto.STATUS_VOLTAGE_FAULT, 'voltage fault'))
# Immutable tuples on the hot path are built without NamedTuple's keyword handling.
new_tuple = tuple.__new__


@dataclass(frozen=True)
class BusSnapshot:
    """Every configured servo, and whether the port is open."""

    port_open: bool
    servos: Tuple[ServoSnapshot, ...] = field(default_factory=tuple)
    read_at: Optional[float] = None
    """When the oldest position of an online servo arrived off the wire (monotonic) [s]: the
    time the messages are stamped with; None when no servo is online."""


class ServoRecord:
    """What the driver knows of one servo (``core.py`` says who writes it when)."""

    __slots__ = ('id', 'name', 'index', 'frames', 'online', 'seen',
                 'failures', 'error_count', 'reading', 'telemetry', 'next_telemetry',
                 'next_probe', 'direction', 'telemetry_started', 'surplus_mark',
                 'duplicate_until')

    def __init__(self, joint: Joint, index: int) -> None:
        self.id = joint.id
        self.name = joint.name
        self.index = index
        # By READ_POSITION, READ_WIDE, READ_STATE: (frame, reply params).
        self.frames = tuple((proto.encode_read(joint.id, *block), block[1])
                            for block in LOOP_READS)
        self.online = False
        self.seen = False
        self.failures = 0
        self.error_count = 0
        self.reading = Reading(0, math.nan, 0, 0.0, 0, math.nan)
        self.telemetry = Telemetry(math.nan, math.nan, False)
        self.next_telemetry = 0.0
        self.next_probe = 0.0
        self.direction = 1.0
        self.telemetry_started = False
        self.surplus_mark: Optional[int] = None
        self.duplicate_until = -math.inf

    @property
    def joint(self) -> Joint:
        """Return the servo's id and joint name."""
        return Joint(self.id, self.name)

    def set_torque(self, enabled: bool) -> None:
        """Record the torque switch as read or written."""
        self.telemetry = self.telemetry._replace(torque_enabled=enabled)
