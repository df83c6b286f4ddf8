"""The events and actions every device core without I/O shares: one name per concept (issue 22).

A core takes events (each with its time ``now``, monotonic seconds) and returns actions;
``core_runner.run_core`` carries each action out by the handler of its type, so two cores that
share a type here share its handler. What is a device's own (a deploy call, a trigger request,
a servo read cycle) stays in its core's module.

Actions:

- `Log` ``(level, text)``: a log line; `level` is a `logs.log_at` name, any case (``debug``,
  ``info``, ``warn``/``warning``, ``error``). Parachute deploy, trigger and settings cores,
  the handset rules, the parachute's MAVLink link core.
- `Record` ``(kind, fields, sync)``: a black-box record. Its `sync` says which of two different
  guarantees the core needs, and they stay apart: `SYNC_WAIT` (the record is on disk before the
  next action is carried out: the runtime waits, bounded, for the fsync; the deploy core's
  decision before its deploy frame leaves), `SYNC_ASK` (the runtime asks for an fsync and goes
  on at once: the trigger core's decisions, never held up behind the disk), `NO_SYNC` (written
  with the others). Parachute deploy, trigger and settings cores.
- `Request` ``(frame, expect, deadline, retries, silence_ok)``: send a frame that expects a reply
  of one of the types `expect` by `deadline`; the runtime feeds back its `Reply`, or `Timeout`,
  `Busy` or `LinkDown`. Parachute deploy and settings cores.
- `Answer` ``(result)``: the one answer to a call, a ``result.Result``. Parachute trigger and
  settings cores (the deploy core answers a ``DeployAnswer``: five outcomes and P11 counts).
- `SetTimer` ``(at)``: step `Tick` no later than `at` (a deadline the event set or moved); the
  runtime's ``DeadlineTimer.wake(by=at)``. Parachute trigger core, the handset rules.

Events:

- `LinkUp` ``(now)``: the port (re)opened; nothing is known of the device until it answers.
- `LinkDown` ``(now, reason, frame_left, shutting_down)``: the port closed (unplugged, a write
  failed); `frame_left`: the frame a `Request` waited on had left before (a core that waits on
  none ignores it); `shutting_down`: the driver closed it to stop.
- `Rebooted` ``(now, boot_count)``: the device rebooted, seen by another path (`boot_count` when
  read, None when only a heartbeat told).
- `Reply` ``(now, message)``: a decoded frame: the reply a `Request` waits for, or one unasked.
- `Timeout` ``(now, reason)``: the reply a `Request` expects did not come by its deadline.
- `Busy` ``(now, reason)``: the link could not send the `Request` now; nothing was sent.
- `Tick` ``(now)``: time passed (the runtime's timer, at a deadline a `SetTimer` gave, or
  sooner).

Kept apart on purpose: a `Request` waits for a reply with a deadline; the trigger core's
``Write`` (``dps_parachute_ros.trigger_core``) is a frame written at once, ahead of anything
queued, that expects no reply: its runtime feeds back ``Sent``/``NotSent`` with its token. The
servo bus's ``bus_schedule.Send`` owns bus time (when the frame goes and until when the
half-duplex bus is taken) and matches its reply by servo id: a bus transaction, not a `Request`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional, Tuple, Type

from uav_serial_common.result import Result

NO_SYNC = 'none'
"""`Record.sync`: written with the other records."""
SYNC_WAIT = 'wait'
"""`Record.sync`: on disk before the next action is carried out (a bounded wait)."""
SYNC_ASK = 'ask'
"""`Record.sync`: an fsync is asked for; the next action does not wait for it."""
SYNCS = (NO_SYNC, SYNC_WAIT, SYNC_ASK)


# -- actions -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Log:
    """A log line at `level` (a ``logs.log_at`` name, any case)."""

    level: str
    text: str


@dataclass(frozen=True)
class Record:
    """A black-box record of `kind` with `fields`; `sync`: `NO_SYNC`, `SYNC_WAIT`, `SYNC_ASK`."""

    kind: str
    fields: Tuple[Tuple[str, Any], ...]
    sync: str = NO_SYNC

    def __post_init__(self) -> None:
        """Refuse a sync that names neither guarantee (a bool here was the old meaning)."""
        if self.sync not in SYNCS:
            raise ValueError(f'Record.sync must be one of {SYNCS}, not {self.sync!r}')

    @classmethod
    def of(cls, kind: str, sync: str = NO_SYNC, **fields: Any) -> 'Record':
        """Build a record from keyword fields (in their order)."""
        return cls(kind, tuple(fields.items()), sync)


@dataclass(frozen=True)
class Request:
    """Send `frame` (with `retries`); feed back its reply (one of `expect`) or why none came.

    `silence_ok`: no reply does not make the device offline (its `Timeout` says only that no
    reply came).
    """

    frame: bytes
    expect: Tuple[Type, ...]
    deadline: float
    retries: int = 0
    silence_ok: bool = False


@dataclass(frozen=True)
class Answer:
    """The one answer to a call."""

    result: Result


@dataclass(frozen=True)
class SetTimer:
    """Step `Tick` no later than `at` (a deadline on the core's clock)."""

    at: float


# -- events ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class LinkUp:
    """The port (re)opened: nothing is known of the device until it answers."""

    now: float


@dataclass(frozen=True)
class LinkDown:
    """The port closed (unplugged, a write failed).

    `frame_left`: a frame of the `Request` waited on had left (any of its attempts);
    `shutting_down`: the driver stops.
    """

    now: float
    reason: str = 'port closed'
    frame_left: bool = True
    shutting_down: bool = False


@dataclass(frozen=True)
class Rebooted:
    """The device rebooted, seen by another path (`boot_count` when read; None: a heartbeat)."""

    now: float
    boot_count: Optional[int] = None


@dataclass(frozen=True)
class Reply:
    """A decoded frame from the device: the reply waited for, or one nobody asked for."""

    now: float
    message: Any


@dataclass(frozen=True)
class Timeout:
    """The reply the last `Request` expects did not come by its deadline (all its tries)."""

    now: float
    reason: str = ''


@dataclass(frozen=True)
class Busy:
    """The link could not send the last `Request` now (another of its kind): not sent."""

    now: float
    reason: str


@dataclass(frozen=True)
class Tick:
    """Time passed (the runtime's timer, at a deadline a `SetTimer` gave, or sooner)."""

    now: float
