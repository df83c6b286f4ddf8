"""The OriginMan driver's time-critical decisions, without I/O, thread or clock.

Events come in with their time, decisions go out; the caller (``core.OriginManCore``) owns the
port, the threads and the clocks, and carries the decisions out in the order given. Here:

* :class:`MotorWatchdog`: when the motors must be stopped (the board has none, §8, O38, O39);
* :class:`OnlineJudge`: online from the first frame after the port opened, offline after
  ``offline_timeout_s`` without one or when the port closes;
* :class:`FrameScheduler`: what goes to the board next. Motor stops first, then commands in
  the order given, then bus-servo moves, coalesced (the newest target of each servo wins) and
  paced by what the board's servo bus can carry, so that the board never holds more than
  ``ahead_s`` of servo-bus work in front of a stop (issue 21 item 7);
* :class:`BoardPlan`: the three together, with the rules that join them (no command but a stop
  to a board judged offline; queued commands are dropped when it goes offline).

:meth:`BoardPlan.step` is the one door every path of the core goes through (issue 22 item 2):
an event with its time in (the port opened or closed, a frame from the board, the worker's
``Tick``, the timer's ``Deadline``, a motor command or keep-alive, a stop, a command, a bus servo
move, a frame written, the end of a write, new timeouts), the actions out, in the order to carry
them out: ``Send`` (one at a time: the next is chosen when the one before is done, so a stop
queued meanwhile goes next, issue 22 item 3), ``OnlineChanged``, ``Refuse`` and ``Drop`` (a
caller's frame that will not leave), ``Log`` and ``SetTimer`` (the plan's next deadline). The
methods below it (``connection``, ``frame``, ``tick``, ``command``, ``take``...) are its parts,
kept for the tests that drive one rule alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple, Union

from originman_board_ros import protocol as p
from uav_serial_common.core_events import LinkDown, LinkUp, Log, SetTimer, Tick

__all__ = ['Action', 'BoardPlan', 'Command', 'Deadline', 'Drop', 'DROPPED', 'Event', 'FrameIn',
           'FrameScheduler', 'MotorCommand', 'MotorWatchdog', 'Move', 'OnlineChanged',
           'OnlineJudge', 'PACE_AHEAD_S', 'PACE_MARGIN', 'Reconfigure', 'Refuse', 'Send',
           'SendDone', 'STOP_ALL_FRAME', 'StopMotors', 'Written', 'board_time']

SERVO_BUS_BAUD = 115200
"""The board's servo bus (§6): 10 bits a byte."""
SERVO_TIMEOUT_S = 0.005
"""The firmware waits this long for a servo's answer (a read costs at most this)."""
BUS_MOVE_ITEM_BYTES = 10
"""One servo of a move is one 10-byte servo frame on the servo bus."""
PACE_AHEAD_S = 0.02
"""At most this much servo-bus work (plus one servo move) is left queued on the board; moves are
released once half of it is done."""
PACE_MARGIN = 1.25
"""Every frame is charged this many times its board time (§6's figures), so a flood feeds the
board 80 % of what it can do: a board slower than §6 says, or one that fell behind for a while,
works its backlog off meanwhile. Charged at 1.0, every late millisecond stayed queued in front
of the next stop for as long as the flood lasted (a board 10 % slow held a stop 0.55 s behind
moves after a 10 s flood)."""
STOP_ALL_FRAME = p.encode_motor_stop_mask((1 << p.MOTOR_COUNT) - 1)
PER_FRAME = (p.MAX_DATA - 4) // 3
"""Servos in one BUS_SERVO 0x01 frame."""

Change = Tuple[bool, str]
"""An online change: (online, reason)."""


# -- the events and actions of :meth:`BoardPlan.step` -------------------------------------------
# Besides the shared ``LinkUp(now)``, ``LinkDown(now, reason)`` and ``Tick(now)`` (the worker's
# round: the silence judgement, the watchdog, what is ready to send).

@dataclass(frozen=True)
class FrameIn:
    """A valid frame from the board arrived at ``now``."""

    now: float


@dataclass(frozen=True)
class Deadline:
    """The timer reached a deadline a ``SetTimer`` gave: the watchdog and the paced frames.

    Not the silence judgement: the worker judges it (``Tick``), and the online change it
    brings sets off the worker's duties (settings).
    """

    now: float


@dataclass(frozen=True)
class MotorCommand:
    """Set motor speeds with ``frame`` (None: a keep-alive that only restarts the timeout)."""

    now: float
    frame: Optional[bytes]
    ticket: object = None


@dataclass(frozen=True)
class StopMotors:
    """Stop every motor, ahead of every queued frame, online or not."""

    now: float
    ticket: object = None


@dataclass(frozen=True)
class Command:
    """A command after those queued; ``cancels`` drops queued bus servo targets of those ids."""

    now: float
    frame: bytes
    ticket: object = None
    cancels: Tuple[int, ...] = ()


@dataclass(frozen=True)
class Move:
    """Bus servo targets ``items`` ((id, position), ...) in ``duration_ms``."""

    now: float
    duration_ms: int
    items: Tuple[Tuple[int, int], ...]
    ticket: object = None


@dataclass(frozen=True)
class Written:
    """``frame`` left at ``now`` (every frame, reads included): the board's work to come.

    It sends nothing (the link reports it from inside its write).
    """

    now: float
    frame: bytes


@dataclass(frozen=True)
class SendDone:
    """The ``Send`` being carried out is over (``error``: why it did not leave, else None)."""

    now: float
    error: Optional[str] = None


@dataclass(frozen=True)
class Reconfigure:
    """New timeouts."""

    now: float
    motor_timeout_s: float
    offline_timeout_s: float


@dataclass(frozen=True)
class Send:
    """Write ``frame`` now (``kind``: stop, motor, command or move), then step ``SendDone``.

    One at a time: no other ``Send`` comes before that ``SendDone``.
    """

    kind: str
    frame: bytes
    ticket: object = None


@dataclass(frozen=True)
class OnlineChanged:
    """The board is judged ``online`` (or not) at ``now``, for ``reason``."""

    online: bool
    reason: str
    now: float


@dataclass(frozen=True)
class Refuse:
    """The frame of ``ticket`` was not queued: the board is offline; nothing was sent."""

    ticket: object
    reason: str


@dataclass(frozen=True)
class Drop:
    """The frame of ``ticket`` was queued and dropped unsent (a stop after it, or offline)."""

    ticket: object
    reason: str


QUIET_EVENTS = (Written, FrameIn, LinkUp, LinkDown)
"""Events whose step never gives a ``Send``: the link reports them from inside its locks (a
write, the decoder), and none of them makes a frame ready (the port opening or closing leaves
the board offline, a frame only makes it online: nothing is queued then; every event that
queues a frame sends it or finds a ``Send`` out). Their thread never writes."""
Event = Union[LinkUp, LinkDown, FrameIn, Tick, Deadline, MotorCommand, StopMotors, Command,
              Move, Written, SendDone, Reconfigure]
Action = Union[Send, OnlineChanged, Refuse, Drop, Log, SetTimer]
DROPPED = 'dropped before it left (a motor stop came after it, or the board went offline)'


def _bus_bytes_time(nbytes: int) -> float:
    return nbytes * 10 / SERVO_BUS_BAUD


def board_time(frame: bytes, baud: int = p.BAUD) -> float:
    """How long the board is busy with ``frame``: its bytes on the wire and its servo bus."""
    wire = len(frame) * 10 / baud
    frames = p.BoardParser().feed(frame)
    if not frames:
        return wire
    cmd = p.decode_host_command(frames[0])
    if isinstance(cmd, p.BusMove):
        return wire + len(cmd.items) * _bus_bytes_time(BUS_MOVE_ITEM_BYTES)
    if isinstance(cmd, p.BusStop):
        return wire + len(cmd.ids) * _bus_bytes_time(6)
    if isinstance(cmd, p.BusRead):
        return wire + _bus_bytes_time(6) + SERVO_TIMEOUT_S
    if type(cmd).__name__.startswith('Bus'):
        return wire + _bus_bytes_time(10)
    return wire


class MotorWatchdog:
    """When every motor must be stopped: ``timeout_s`` after the last motor command (0: never)."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self.last_command_at: Optional[float] = None
        self.stopped = True
        self.fired = 0

    def command(self, now: float) -> None:
        """Note a motor command accepted at ``now``; zeros and keep-alives count too."""
        self.last_command_at = now
        self.stopped = False

    def port_opened(self, now: float) -> None:
        """Arm at a connect: the motors' state is unknown, as if commanded now (O38)."""
        self.command(now)

    def stop(self) -> None:
        """Note that every motor was told to stop; its frame is on its way."""
        self.stopped = True

    @property
    def deadline(self) -> Optional[float]:
        """When the motors must be stopped, None when nothing is running."""
        if self.timeout_s <= 0 or self.stopped or self.last_command_at is None:
            return None
        return self.last_command_at + self.timeout_s

    def due(self, now: float) -> bool:
        """Whether the stop is due at ``now``."""
        deadline = self.deadline
        return deadline is not None and now >= deadline


class OnlineJudge:
    """Online from the first frame on an open port; offline without one for ``timeout_s``."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self.port_open = False
        self.last_frame_at: Optional[float] = None
        self.online = False

    def connection(self, up: bool, now: float) -> Optional[Change]:
        """Judge a port that opened (``up``) or closed; frames before now no longer count."""
        self.port_open = up
        self.last_frame_at = None
        return self._set(False, 'port open, no frame from the board yet' if up
                         else 'port closed')

    def frame(self, now: float) -> Optional[Change]:
        """Judge a valid frame from the board that arrived at ``now``."""
        if not self.port_open:
            return None
        self.last_frame_at = now
        return self._set(True, 'frames arriving')

    def tick(self, now: float) -> Optional[Change]:
        """Judge the silence at ``now``."""
        last = self.last_frame_at
        if self.online and last is not None and now - last >= self.timeout_s:
            return self._set(False, f'no frame from the board for {now - last:.1f} s')
        return None

    @property
    def deadline(self) -> Optional[float]:
        """When silence makes the board offline, None while it is offline."""
        if not self.online or self.last_frame_at is None:
            return None
        return self.last_frame_at + self.timeout_s

    def _set(self, online: bool, reason: str) -> Optional[Change]:
        if online == self.online:
            return None
        self.online = online
        return online, reason


class FrameScheduler:
    """The outgoing frames, in the order they must leave, paced by the board's servo bus.

    Three lines: motor stops, commands (first come, first out), and the newest target of each
    bus servo (a servo keeps its place in the line when its target changes). :meth:`take`
    gives the next frame to write; :meth:`written` is told about every frame that left (reads
    included), to estimate when the board will be through with them.
    """

    def __init__(self, ahead_s: float = PACE_AHEAD_S, baud: int = p.BAUD) -> None:
        self.ahead_s = ahead_s
        self.baud = baud
        self.stops: List[Tuple[bytes, object]] = []
        self.commands: List[Tuple[bytes, object, bool]] = []  # (frame, ticket, motor)
        self.targets: Dict[int, Tuple[int, int]] = {}  # id -> (position, duration ms)
        self.board_free_at = 0.0
        self.coalesced = 0
        self.dropped: List[object] = []
        """Tickets of queued frames dropped unsent (by a stop, or :meth:`clear`), oldest first;
        whoever reads them empties it."""

    def push_stop(self, frame: bytes, ticket: object = None) -> None:
        """Queue a motor stop ahead of everything; it drops queued motor commands.

        A motor command queued before the stop was given before it: sent after the stop, it
        would start the motors again with nothing left to stop them.
        """
        self._drop([c for c in self.commands if c[2]])
        self.commands = [c for c in self.commands if not c[2]]
        self.stops.append((frame, ticket))

    def push_command(self, frame: bytes, ticket: object = None,
                     cancels: Sequence[int] = (), motor: bool = False) -> None:
        """Queue a command after those queued; ``cancels`` drops queued targets of those servos.

        ``motor``: the command sets motor speeds (a stop drops it while it waits).
        """
        if p.BUS_BROADCAST_ID in cancels:
            self.targets.clear()
        for servo_id in cancels:
            self.targets.pop(servo_id, None)
        self.commands.append((frame, ticket, motor))

    def push_move(self, duration_ms: int, items: Sequence[Tuple[int, int]]) -> None:
        """Queue bus servo targets: each replaces the queued target of its servo."""
        for servo_id, position in items:
            if servo_id in self.targets:
                self.coalesced += 1
            self.targets[servo_id] = (position, duration_ms)

    def clear(self) -> int:
        """Drop every queued command and target (not the stops); return how many."""
        n = len(self.commands) + len(self.targets)
        self._drop(self.commands)
        self.commands = []
        self.targets.clear()
        return n

    def _drop(self, commands: Sequence[Tuple[bytes, object, bool]]) -> None:
        self.dropped.extend(ticket for _, ticket, _ in commands if ticket is not None)

    def backlog(self, now: float) -> float:
        """Seconds of work the board still has from frames written before ``now``.

        Charged with ``PACE_MARGIN``: an upper bound while the board keeps §6's pace.
        """
        return max(0.0, self.board_free_at - now)

    def written(self, frame: bytes, now: float) -> None:
        """``frame`` left at ``now``."""
        self.board_free_at = max(self.board_free_at, now) + \
            board_time(frame, self.baud) * PACE_MARGIN

    def take(self, now: float) -> Optional[Tuple[str, bytes, object]]:
        """Return the next frame to write at ``now``: ``(kind, frame, ticket)``, or None."""
        if self.stops:
            frame, ticket = self.stops.pop(0)
            return 'stop', frame, ticket
        if self.commands:
            frame, ticket, motor = self.commands.pop(0)
            return 'motor' if motor else 'command', frame, ticket
        if not self.targets:
            return None
        if now < self.board_free_at - self.ahead_s / 2:
            return None  # released in batches of at least half the room, not one by one
        room = self.ahead_s - self.backlog(now)
        item_s = _bus_bytes_time(BUS_MOVE_ITEM_BYTES) * PACE_MARGIN
        budget = max(1, min(PER_FRAME, int(room / item_s)))
        duration = next(iter(self.targets.values()))[1]
        items = []
        for servo_id, (position, ms) in self.targets.items():
            if ms == duration:
                items.append((servo_id, position))
                if len(items) == budget:
                    break
        for servo_id, _ in items:
            del self.targets[servo_id]
        return 'move', p.encode_bus_move(duration, items), None

    def next_time(self, now: float) -> Optional[float]:
        """When :meth:`take` will next give a frame (now if one is ready), None if never."""
        if self.stops or self.commands:
            return now
        if self.targets:
            return max(now, self.board_free_at - self.ahead_s / 2)
        return None


class BoardPlan:
    """The watchdog, the online judgement and the scheduler, with the rules between them."""

    def __init__(self, motor_timeout_s: float, offline_timeout_s: float,
                 ahead_s: float = PACE_AHEAD_S, baud: int = p.BAUD) -> None:
        self.watchdog = MotorWatchdog(motor_timeout_s)
        self.judge = OnlineJudge(offline_timeout_s)
        self.scheduler = FrameScheduler(ahead_s, baud)
        self.sending = False
        """A ``Send`` of :meth:`step` is being carried out (until its ``SendDone``)."""

    def step(self, event: Event, pace_now: Optional[float] = None) -> List[Action]:
        """Take one event; return what to carry out, in order.

        ``pace_now``: the board's clock, for pacing the servo moves, when it is not the
        events' (a test's fake clock for the rules, the wall for the board); default
        ``event.now``. At most one ``Send`` is out at a time: the next is chosen when the one
        before is done (``SendDone``), so a stop that comes meanwhile goes next, ahead of
        every queued frame. A ``Send`` comes first (a stop leaves before its log line);
        ``SetTimer`` last: when the timer must step ``Deadline`` (the watchdog's deadline, or
        when the next paced frame may leave), on the events' clock.
        """
        now = event.now
        pace = now if pace_now is None else pace_now
        out: List[Action] = []
        change: Optional[Change] = None
        if isinstance(event, (LinkUp, LinkDown)):
            change = self.connection(isinstance(event, LinkUp), now)
        elif isinstance(event, FrameIn):
            change = self.frame(now)
        elif isinstance(event, Tick):
            change = self.judge.tick(now)
            self._went_offline(change)
            self._watchdog(now, out)
        elif isinstance(event, Deadline):
            self._watchdog(now, out)
        elif isinstance(event, MotorCommand):
            if not self.motor_command(event.frame, now, event.ticket):
                out.append(Refuse(event.ticket, 'the board is offline'))
        elif isinstance(event, StopMotors):
            self.stop_motors(event.ticket)
        elif isinstance(event, Command):
            if not self.command(event.frame, event.ticket, event.cancels):
                out.append(Refuse(event.ticket, 'the board is offline'))
        elif isinstance(event, Move):
            if not self.move(event.duration_ms, event.items):
                out.append(Refuse(event.ticket, 'the board is offline'))
        elif isinstance(event, Written):
            self.scheduler.written(event.frame, pace)
        elif isinstance(event, SendDone):
            self.sending = False
        elif isinstance(event, Reconfigure):
            self.configure(event.motor_timeout_s, event.offline_timeout_s)
        else:
            raise TypeError(f'not an event of the board plan: {event!r}')
        if change is not None:
            out.append(OnlineChanged(change[0], change[1], now))
        if not self.sending and not isinstance(event, QUIET_EVENTS):
            item = self.take(pace)
            if item is not None:
                self.sending = True
                out.insert(0, Send(*item))
        out.extend(Drop(ticket, DROPPED) for ticket in self.scheduler.dropped)
        self.scheduler.dropped.clear()
        due = self.timer_due(now, pace)
        if due is not None:
            out.append(SetTimer(due))
        return out

    def timer_due(self, now: float, pace_now: Optional[float] = None) -> Optional[float]:
        """When the timer must step ``Deadline`` (on ``now``'s clock), None: no deadline.

        The watchdog's deadline while the port is open; when the next paced frame may leave
        while no ``Send`` is out (the one out is followed by the next when it is done).
        """
        pace = now if pace_now is None else pace_now
        dues = []
        deadline = self.watchdog.deadline
        if deadline is not None and self.judge.port_open:
            dues.append(deadline)
        if not self.sending:
            paced = self.scheduler.next_time(pace)
            if paced is not None:
                # On one clock, the time itself: now + (paced - now) rounds, and a timer set
                # 2e-18 s after the frame is ready was found late (the 20,000-sequence search).
                dues.append(paced if pace == now else now + (paced - pace))
        return min(dues, default=None)

    def _watchdog(self, now: float, out: List[Action]) -> None:
        last = self.watchdog.last_command_at
        if self.tick_watchdog(now):
            out.append(Log('warn', f'no motor command for {now - (last or now):.2f} s '
                                   f'(motor_timeout_s {self.watchdog.timeout_s:g}): '
                                   'stopping every motor'))

    @property
    def online(self) -> bool:
        """Whether the board is judged online."""
        return self.judge.online

    def configure(self, motor_timeout_s: float, offline_timeout_s: float) -> None:
        """Take changed timeouts."""
        self.watchdog.timeout_s = motor_timeout_s
        self.judge.timeout_s = offline_timeout_s

    def connection(self, up: bool, now: float) -> Optional[Change]:
        """Take a port that opened or closed at ``now``."""
        if up:
            self.watchdog.port_opened(now)
        change = self.judge.connection(up, now)
        self._went_offline(change)
        return change

    def frame(self, now: float) -> Optional[Change]:
        """Take a frame from the board that arrived at ``now``."""
        return self.judge.frame(now)

    def tick(self, now: float) -> Tuple[Optional[Change], bool]:
        """Run the timers at ``now``; return (an online change, whether a stop was queued)."""
        change = self.judge.tick(now)
        self._went_offline(change)
        return change, self.tick_watchdog(now)

    def tick_watchdog(self, now: float) -> bool:
        """Run the watchdog alone at ``now``; return whether it queued a stop (ahead of all)."""
        if self.judge.port_open and self.watchdog.due(now):
            self.stop_motors()
            self.watchdog.fired += 1
            return True
        return False

    def motor_command(self, frame: Optional[bytes], now: float, ticket: object = None) -> bool:
        """Queue a motor command (None: a keep-alive); refused (False) while offline."""
        if not self.judge.online:
            return False
        self.watchdog.command(now)
        if frame is not None:
            self.scheduler.push_command(frame, ticket, motor=True)
        return True

    def stop_motors(self, ticket: object = None) -> None:
        """Queue a stop of every motor ahead of everything, online or not."""
        self.watchdog.stop()
        self.scheduler.push_stop(STOP_ALL_FRAME, ticket)

    def command(self, frame: bytes, ticket: object = None, cancels: Sequence[int] = ()) -> bool:
        """Queue a command; refused (False) while offline."""
        if not self.judge.online:
            return False
        self.scheduler.push_command(frame, ticket, cancels)
        return True

    def move(self, duration_ms: int, items: Sequence[Tuple[int, int]]) -> bool:
        """Queue bus servo targets (the newest of each servo wins); False while offline."""
        if not self.judge.online:
            return False
        self.scheduler.push_move(duration_ms, items)
        return True

    def take(self, now: float) -> Optional[Tuple[str, bytes, object]]:
        """Return the next frame to write at ``now``; only stops while offline."""
        if not self.judge.online and not self.scheduler.stops:
            self.scheduler.clear()
        return self.scheduler.take(now)

    def next_time(self, now: float) -> Optional[float]:
        """When :meth:`tick` or :meth:`take` next has something to do."""
        times = [t for t in (self.watchdog.deadline, self.judge.deadline,
                             self.scheduler.next_time(now)) if t is not None]
        return min(times) if times else None

    def _went_offline(self, change: Optional[Change]) -> None:
        if change is not None and not change[0]:
            self.scheduler.clear()
