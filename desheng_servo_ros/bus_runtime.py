"""The servo bus's runtime: one ``BusSchedule`` stepped through ``run_core`` on every path.

Issue 22 item 2, for the servo bus: the schedule the model test searches
(``bus_schedule.BusSchedule``) takes every decision of the bus (the READs and their pace, the
commands and their budget, an emergency stop first, a service's transactions and holds, the
shutdown's torque off), and this runs it on a serial port. Every path steps it with an event
through the shared runner (``core_runner.run_core``), one at a time under ``_lock``, and carries
out its actions, in its order, by one handler per action type:

- the link's **reader thread** steps each decoded reply (``Reply``, stamped when its bytes were
  read): a READ that follows goes out from that thread at once, as the read chain's did; and
  the port opening or closing (``LinkUp``/``LinkDown``);
- a **DeadlineTimer** steps ``Tick`` when the last ``SetTimer`` says (a reply's deadline, the
  next cycle, a command the budget holds back);
- **callers** step ``Command`` (``~/command``) and ``Call`` (a service: its ``Answer`` settles
  a :class:`~uav_serial_common.ticket.Ticket` the caller waits on, with a timeout).

Handlers: ``Send`` writes the frame (at its time: the frames of a batch follow each other's
wire time; or later, when the frame before it went late: ``bus_schedule.Line``), and a frame
that a loaded host wrote late is stepped back as ``Late`` (its reply's deadline, or the bus's
free time, moves with it); ``Answer`` settles the caller's ticket; ``ReadDone``/``CycleDone``
go to the owner's callbacks (quick ones: they run on the stepping thread, under the lock);
``Log`` logs; ``SetTimer`` wakes the timer by then. The actions are carried out under the
lock, so the frames leave in the order the schedule chose them, whichever thread stepped (a
write to the port takes microseconds; a frame of a batch waits at most the wire time of the
one before it).

The read loop's pace runs on ``clock`` (a test's clock), the bus's deadlines on the monotonic
clock (``BusSchedule.step``'s ``pace_now``).
"""

from __future__ import annotations

from contextlib import contextmanager
import math
import threading
import time
from typing import Any, Callable, Iterator, List, Optional, Sequence, Tuple

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.link import ServoBusLink
from desheng_servo_ros.bus_schedule import (Answer, BusSchedule, Call, Command, CycleDone,
                                            Line, ReadDone, Send, Shutdown)
from desheng_servo_ros.units import Joint
from uav_serial_common import core_events as ev
from uav_serial_common.core_runner import run_core
from uav_serial_common.deadline_timer import DeadlineTimer
from uav_serial_common.logs import log_at
from uav_serial_common.serial_link import LinkError
from uav_serial_common.ticket import Ticket

CALL_TIMEOUT_S = 2.0
"""How long a caller waits for its answer by default (the bus may be held meanwhile)."""
TIMER_IDLE_S = 0.1
# A reply's deadline waits this much longer at most while the reader holds unread bytes.
READER_GRACE_S = 0.05


class _Locked:
    """The schedule as ``run_core`` steps it: under the runtime's lock, with its pace clock."""

    def __init__(self, schedule: BusSchedule, clock: Callable[[], float]) -> None:
        self.schedule = schedule
        self.clock = clock

    def step(self, event: Any) -> List[Any]:
        return self.schedule.step(event, pace_now=self.clock())


class BusRuntime:
    """A servo bus on a serial port, its decisions the schedule's (module doc).

    `bus`: the port and its counters (a ``ServoBusLink``; one is made for `port` and `baud`
    when None). Callbacks: `on_read` (each ``ReadDone``, on the stepping thread under the
    lock: quick), `on_cycle` (each ``CycleDone``, after the lock is let go), `on_log` (each
    ``Log``), `on_failure` (a step from the reader or the timer that raised: the bus goes on),
    `on_idle` (from the timer thread, about every ``TIMER_IDLE_S``: returns when it wants to be
    called again, or None).
    """

    def __init__(self, port: str, baud: int, joints: Sequence[Joint], *,
                 publish_rate_hz: float = 50.0, telemetry_period_s: float = 1.0,
                 max_retries: int = 1, margin_s: float = 0.005,
                 torque_off_on_shutdown: bool = True,
                 clock: Callable[[], float] = time.monotonic,
                 on_read: Optional[Callable[[ReadDone], None]] = None,
                 on_cycle: Optional[Callable[[CycleDone], None]] = None,
                 on_log: Optional[Callable[[str, str], None]] = None,
                 on_failure: Optional[Callable[[BaseException], None]] = None,
                 on_idle: Optional[Callable[[], Optional[float]]] = None,
                 bus: Optional[ServoBusLink] = None,
                 logger: Optional[Any] = None) -> None:
        self.clock = clock
        if bus is None:
            bus = ServoBusLink(port, baud, response_timeout_ms=margin_s * 1000.0,
                               max_retries=max_retries, logger=logger)
        self.bus = bus
        self.schedule = BusSchedule(joints, now=time.monotonic(), baud=baud,
                                    publish_rate_hz=publish_rate_hz,
                                    telemetry_period_s=telemetry_period_s,
                                    max_retries=max_retries, margin_s=bus.margin_s,
                                    torque_off_on_shutdown=torque_off_on_shutdown,
                                    pace_now=clock())
        self.schedule.slow_margin = bus.slow_margin
        self.schedule.silences = []
        self._stepper = _Locked(self.schedule, clock)
        self._lock = threading.RLock()  # a callback may command: the same thread steps again
        self._depth = 0  # steps in progress on the thread that holds the lock
        self._deferred: List[Callable[[], None]] = []  # run after the lock is let go
        self._log = logger
        self._on_read = on_read
        self._on_cycle = on_cycle
        self._on_log = on_log
        self._on_failure = on_failure
        self._on_idle = on_idle
        self._idle_due = 0.0
        self._reads_hold: Optional[Ticket] = None  # the hold of hold_reads (read_cycle)
        self._one_cycle: Optional[Ticket] = None  # settled by the cycle read_cycle waits for
        bus.on_reply = self._on_frame
        bus.on_bytes = self._on_bytes
        bus.on_link = self._on_connection
        bus.runtime = self
        self.link = bus.link
        self._timer = DeadlineTimer(self._duty, name='servo-bus-timer', idle_s=TIMER_IDLE_S,
                                    min_sleep_s=0.0002, on_error=self._timer_failed)
        self._handlers = {Send: self._send, Answer: self._answer, ReadDone: self._read,
                          CycleDone: self._cycle, ev.Log: self._log_line,
                          ev.SetTimer: self._set_timer}
        self._line = Line()  # when frames really went: a loaded host writes late
        self._due = math.inf  # the last step's SetTimer (inf: none)
        self._stepped_at = -math.inf  # when the schedule was last stepped (monotonic)
        self.frames_sent = 0
        self.last_frame: Optional[bytes] = None
        """The last frame written (the shutdown's torque off, once stopped)."""

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        """Open the port (its reader thread) and start the timer."""
        self.link.start()
        self._timer.start()

    def stop(self) -> List[bytes]:
        """Step the shutdown (torque off the last frame), let it leave, close the port.

        Returns the frames the shutdown wrote (none when the port was not open).
        """
        written = self.frames_sent
        sent = [a for a in self._step(Shutdown(time.monotonic())) if isinstance(a, Send)]
        written = self.frames_sent - written  # a write to a port that is not open fails
        self._timer.stop()
        if sent and written:  # the torque off leaves the line before the port closes
            time.sleep(max(0.0, self._line.free_at - time.monotonic()))
        self.link.stop()
        return [a.frame for a in sent][:written]

    @property
    def port_open(self) -> bool:
        """Whether the port is open."""
        return self.link.port_open

    @property
    def closed(self) -> bool:
        """Whether the shutdown was stepped (the bus takes nothing any more)."""
        return self.schedule.closed

    def locked(self) -> Any:
        """Return the step lock (to read or change the schedule's state between two steps)."""
        return self._lock

    def hold_reads(self) -> Ticket:
        """Hold the read loop from the next READ boundary (start-up, or tests: read_cycle)."""
        ticket = self._reads_hold = Ticket()
        self._step(Call(time.monotonic(), ticket, 'hold', ()))
        return ticket

    def release(self, ticket: Ticket) -> None:
        """Release a hold (hold_reads' or held's): the read loop goes on."""
        with self._lock:
            if ticket is self._reads_hold:
                self._reads_hold = None
            self._step(Call(time.monotonic(), Ticket(), 'release', (ticket,)))

    def read_cycle(self, timeout: float = 5.0) -> bool:
        """Let the held read loop run one cycle; return whether it completed in `timeout`."""
        with self._lock:
            hold = self._reads_hold
            if hold is None or self.schedule.closed:
                return False
            done = self._one_cycle = Ticket()
            self._reads_hold = Ticket()  # taken again by the cycle's CycleDone (_cycle)
            self._step(Call(time.monotonic(), Ticket(), 'release', (hold,)))
        ok = done.wait(timeout if self.port_open else min(timeout, 0.2))
        with self._lock:
            if self._one_cycle is done:  # none came: hold the reads again all the same
                self._one_cycle = None
                self._step(Call(time.monotonic(), self._reads_hold, 'hold', ()))
        return ok

    # -- callers --------------------------------------------------------------------------------

    def command(self, targets: Sequence[Tuple[int, int, int]]) -> None:
        """Queue (id, ticks, ms) targets: the newest of a servo goes at the next boundary."""
        self._step(Command(time.monotonic(), tuple(targets)))

    def call(self, name: str, *args: Any, timeout: float = CALL_TIMEOUT_S) -> Optional[Answer]:
        """Step a service call and wait for its answer; None when none came in `timeout`."""
        ticket = Ticket()
        self._step(Call(time.monotonic(), ticket, name, args))
        if not ticket.wait(timeout):
            if name == 'hold':  # never granted to nobody: a late grant would stop the reads
                self._step(Call(time.monotonic(), Ticket(), 'release', (ticket,)))
            return None
        return ticket.detail

    def emergency_stop(self, timeout: float = CALL_TIMEOUT_S) -> Optional[Answer]:
        """Torque off on every servo, ahead of everything queued."""
        return self.call('emergency_stop', timeout=timeout)

    def transact(self, frame: bytes, servo_id: int, nparams: int, retries: int = 0,
                 timeout: float = CALL_TIMEOUT_S,
                 wait: Optional[float] = None) -> Optional[proto.Reply]:
        """One request at the next boundary; its reply, or None (no reply, or no answer).

        `wait`: how long an attempt waits for its reply (default: wire time + margin).
        """
        answer = self.call('transact', frame, servo_id, nparams, retries, wait,
                           timeout=timeout)
        return None if answer is None else answer.reply

    @contextmanager
    def held(self, timeout: float = CALL_TIMEOUT_S) -> Iterator[bool]:
        """Hold the read loop (from the next READ boundary) for a service procedure.

        Yields whether the hold was granted; released on leaving.
        """
        ticket = Ticket()
        self._step(Call(time.monotonic(), ticket, 'hold', ()))
        granted = ticket.wait(timeout) and ticket.detail.ok
        try:
            yield granted
        finally:
            self._step(Call(time.monotonic(), Ticket(), 'release', (ticket,)))

    # -- stepping -------------------------------------------------------------------------------

    def _step(self, event: Any) -> List[Any]:
        """Step the schedule with `event`; carry out its actions here, in its order.

        Callbacks that publish (``on_cycle``) run after the lock is let go, on this thread.
        """
        with self._lock:
            self._depth += 1
            try:
                self._due = math.inf
                self._stepped_at = time.monotonic()
                self.schedule.margin_s = self.bus.margin_s  # derived again on each (re)open
                done = run_core(self._stepper, [event], self._handlers)
                if isinstance(event, ev.Reply):  # counted by whether it ended its request
                    self.bus.note_reply(event.message, self.schedule.last_taken)
                silences = self.schedule.silences
                if silences:
                    for servo_id, garbled in silences:
                        self.bus.note_silence(servo_id, garbled)
                    silences.clear()
            finally:
                self._depth -= 1
                deferred = self._deferred if self._depth == 0 else None
                if deferred:
                    self._deferred = []
        for call in deferred or ():
            call()
        return done

    def _guarded(self, event: Any) -> None:
        """Step from the reader or the timer thread: a failure is reported, the bus goes on."""
        try:
            self._step(event)
        except Exception as exc:  # noqa: BLE001 - the reader and the timer never die of it
            if self._on_failure is not None:
                self._on_failure(exc)
            else:
                self._emit('error', f'servo bus step failed: {exc!r}')

    def _on_bytes(self, data: bytes) -> None:
        # Reader thread, before the frames these bytes make: a request answered by bytes and
        # no frame was answered garbled (S24).
        with self._lock:
            self.schedule.received_bytes(len(data))

    def _on_frame(self, frame: proto.Reply) -> None:
        # Reader thread: stamped when its bytes were read, not when this thread got to it.
        now = self.link.last_rx_time or time.monotonic()
        self._guarded(ev.Reply(now, frame))

    def _on_connection(self, up: bool, reason: str) -> None:
        now = time.monotonic()
        self._guarded(ev.LinkUp(now) if up else ev.LinkDown(now, reason))

    def _duty(self) -> Optional[float]:
        # A deadline a later step moved (a reply came before it) costs no step; one every
        # TIMER_IDLE_S all the same, for the read loop's clock (a test's) that others move.
        now = time.monotonic()
        idle = self._idle(now)
        if now < self._due and now - self._stepped_at < TIMER_IDLE_S:
            return min(self._due, idle)
        schedule = self.schedule
        # Read once, without the lock: the reader may end the wait meanwhile (inf then).
        deadline = schedule.reply_deadline
        if schedule.awaiting(now) and deadline < math.inf and self.link.unread_input() and \
                now < deadline + READER_GRACE_S:
            # Bytes came in that the reader has not handed on yet: they may be the reply. On a
            # loaded host the reader can be late by more than a short deadline, and calling
            # that a timeout (and sending again on a half-duplex line) would report a silence
            # nobody saw. Woken when the reader has handed them on (its reply, if it was one,
            # stepped by then), the duty looks again at once.
            self.link.wait_handed_on(deadline + READER_GRACE_S - now)
            return time.monotonic()
        self._guarded(ev.Tick(now))
        due = min(self._due, idle)
        return None if due == math.inf else due

    def _idle(self, now: float) -> float:
        """Call on_idle when it is due; return when it is due next (inf: never)."""
        if self._on_idle is None:
            return math.inf
        if now >= self._idle_due:
            try:
                due = self._on_idle()
            except Exception as exc:  # noqa: BLE001 - the timer never dies of it
                self._emit('error', f'servo bus idle duty failed: {exc!r}')
                due = None
            self._idle_due = now + TIMER_IDLE_S if due is None else due
        return self._idle_due

    def _timer_failed(self, exc: BaseException) -> None:
        self._emit('error', f'servo bus timer failed: {exc!r}')

    # -- handlers -------------------------------------------------------------------------------

    def _send(self, action: Send) -> Optional[List[Any]]:
        delay = self._line.start(action) - time.monotonic()
        if delay > 0:  # a frame of a batch: after the one before it left the line
            time.sleep(delay)
        try:
            if action.reply_id is not None and action.flush:
                # As the read chain did: a request's reply is not an earlier one's. The
                # decoder's partial frame always (garbage must not swallow the reply); the
                # port's input too unless the reader thread steps this (it has just taken in
                # everything the port had, and flushing a pty is a slow ioctl).
                self.link.flush_input(port=not self.link.on_reader_thread())
            began = time.monotonic()
            self.link.write(action.frame)
        except LinkError as exc:
            return [ev.LinkDown(time.monotonic(), f'write failed: {exc}')]
        # The thread may be held up anywhere around the write: it began after `began` and
        # had ended by `ended` (the bus is held to the latter, a reply taken from the former).
        ended = time.monotonic()
        self.frames_sent += 1
        self.last_frame = action.frame
        late = self._line.wrote(action, began, ended, ended)
        return None if late is None else [late]

    @staticmethod
    def _answer(action: Answer) -> None:
        action.token.settle(action.ok, action)

    def _read(self, action: ReadDone) -> None:
        if self._on_read is not None:
            self._on_read(action)

    def _cycle(self, action: CycleDone) -> Optional[List[Any]]:
        if self._on_cycle is not None:
            self._deferred.append(lambda: self._on_cycle(action))
        done = self._one_cycle
        if done is not None:  # read_cycle's: the reads are held again before the next READ
            self._one_cycle = None
            self._deferred.append(lambda: done.settle(True))
            return [Call(action.now, self._reads_hold, 'hold', ())]
        return None

    def _log_line(self, action: ev.Log) -> None:
        if self._on_log is not None:
            self._on_log(action.level, action.text)
        else:
            self._emit(action.level, action.text)

    def _set_timer(self, action: ev.SetTimer) -> None:
        self._due = action.at
        self._timer.wake(by=action.at)

    def _emit(self, level: str, text: str) -> None:
        if self._log is not None:
            try:
                log_at(self._log, level, text)
            except Exception:  # noqa: BLE001 - logging never costs the bus
                pass
