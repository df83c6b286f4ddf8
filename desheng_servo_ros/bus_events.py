"""The servo bus schedule's events and actions (``bus_schedule.BusSchedule.step``).

Events in: :class:`Command`, :class:`Call`, :class:`Shutdown`, :class:`Late`, and the shared
``core_events`` ``Reply``, ``LinkUp``/``LinkDown`` and ``Tick``. Actions out: :class:`Send`,
:class:`Answer`, :class:`ReadDone`, :class:`CycleDone`, and the shared ``Log`` and
``SetTimer``. A servo bus ``Send`` owns bus time (when the frame goes, until when the
half-duplex bus is taken) and matches its reply by servo id: a bus transaction, not a
``core_events.Request``.
"""

from __future__ import annotations

from typing import Any, Hashable, NamedTuple, Optional, Tuple, Union

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.schedule import Target
from uav_serial_common.core_events import LinkDown, LinkUp, Log, Reply, SetTimer, Tick


class Send(NamedTuple):
    """Put `frame` on the bus at `at`; the bus is taken until `deadline`.

    A reply of `reply_id` with `nparams` params is awaited until `deadline`; `reply_id` None:
    no reply, the bus is free again at `deadline` (the frame's wire time and a guard).
    """

    at: float
    frame: bytes
    kind: str
    reply_id: Optional[int]
    nparams: int
    deadline: float
    flush: bool = True
    """A request: stale input (and a partial frame) is discarded before it goes."""


class Answer(NamedTuple):
    """A service call's answer: the `token` of its :class:`Call`.

    `reply`: a ``transact``'s reply; `result`: the ``Result`` of a procedure of ``id_change``
    (``set_id``, ``factory_reset``), with its outcome.
    """

    token: Hashable
    ok: bool
    text: str
    reply: Optional[proto.Reply] = None
    result: Any = None


class ReadDone(NamedTuple):
    """A READ of the read loop is done: its `reply`, or None after its retries.

    `kind` (``state.READ_POSITION``, ``READ_WIDE``, ``READ_STATE``) says what it read;
    `started`: when its cycle started, on the read loop's clock (``step``'s ``pace_now``).
    The schedule judged the servo already (online, failures, torque); the driver takes the
    values (position, telemetry) and publishes.
    """

    now: float
    servo_id: int
    kind: int
    started: float
    reply: Optional[proto.Reply]


class CycleDone(NamedTuple):
    """A read cycle is complete (`reads` False: every servo offline, none due for a probe)."""

    now: float
    reads: bool


class Command(NamedTuple):
    """A ``~/command`` taken at `now`: its (id, ticks, ms) targets; the newest of a servo wins."""

    now: float
    targets: Tuple[Target, ...]


class Call(NamedTuple):
    """A service call at `now`: `name` with `args`; its :class:`Answer` carries `token`.

    Names: ``emergency_stop``, ``write_positions`` (targets), ``read_register`` (id, address,
    length[, retries]: answered with the reply's bytes of that block), ``set_torque`` (ids,
    enable), ``scan`` (first, last), ``set_id`` (old, new); and
    the parts a service procedure of the driver is made of: ``transact`` (frame, reply id,
    reply params, retries[, the wait of an attempt]: one request, answered with its reply),
    ``send`` (frames without a
    reply), ``hold`` (the read loop stops at the next READ boundary; answered when it has: the
    bus is the holder's and the other callers', with an emergency stop still first) and
    ``release`` (the token of the hold: the read loop goes on).
    """

    now: float
    token: Hashable
    name: str
    args: Tuple[Any, ...] = ()


QUIET_CALLS = frozenset({'scan', 'set_id', 'factory_reset', 'hold'})
"""Calls that need a quiet bus: the read loop stops at the next READ boundary meanwhile."""


class Late(NamedTuple):
    """`send` went late (a loaded host), seen at `now`.

    Its write began `lag` s after its time at the least, and had ended `lag_max` s after it
    (the host may hold the thread anywhere around the write). What the frame holds moves with
    it: the bus, until its reply's deadline or the end of its wire time, by `lag_max` (it may
    have left that late); the moment the request had left, after which a reply can be its
    answer, by `lag` (a reply that came after it is not refused).
    """

    now: float
    send: Send
    lag: float
    lag_max: float


class Shutdown(NamedTuple):
    """Stop at `now`: pending commands and calls dropped, torque off the last frame."""

    now: float


Event = Union[Command, Call, Late, Shutdown, Reply, LinkUp, LinkDown, Tick]
Action = Union[Send, Answer, ReadDone, CycleDone, Log, SetTimer]
