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
wire time); ``Answer`` settles the caller's ticket; ``ReadDone``/``CycleDone`` go to the
owner's callbacks (quick ones: they run on the stepping thread, under the lock); ``Log`` logs;
``SetTimer`` wakes the timer by then. The actions are carried out under the lock, so the frames
leave in the order the schedule chose them, whichever thread stepped (a write to the port takes
microseconds; a frame of a batch waits at most the wire time of the one before it).

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
from desheng_servo_ros.bus_schedule import (Answer, BusSchedule, Call, Command, CycleDone,
                                            ReadDone, Send, Shutdown)
from desheng_servo_ros.units import Joint
from uav_serial_common import core_events as ev
from uav_serial_common.core_runner import run_core
from uav_serial_common.deadline_timer import DeadlineTimer
from uav_serial_common.logs import log_at
from uav_serial_common.serial_link import LinkError, SerialLink
from uav_serial_common.ticket import Ticket

CALL_TIMEOUT_S = 2.0
"""How long a caller waits for its answer by default (the bus may be held meanwhile)."""
TIMER_IDLE_S = 0.1


class _Locked:
    """The schedule as ``run_core`` steps it: under the runtime's lock, with its pace clock."""

    def __init__(self, schedule: BusSchedule, clock: Callable[[], float]) -> None:
        self.schedule = schedule
        self.clock = clock

    def step(self, event: Any) -> List[Any]:
        return self.schedule.step(event, pace_now=self.clock())


class BusRuntime:
    """A servo bus on a serial port, its decisions the schedule's (module doc)."""

    def __init__(self, port: str, baud: int, joints: Sequence[Joint], *,
                 publish_rate_hz: float = 50.0, telemetry_period_s: float = 1.0,
                 max_retries: int = 1, margin_s: float = 0.005,
                 torque_off_on_shutdown: bool = True,
                 clock: Callable[[], float] = time.monotonic,
                 on_read: Optional[Callable[[ReadDone], None]] = None,
                 on_cycle: Optional[Callable[[CycleDone], None]] = None,
                 logger: Optional[Any] = None) -> None:
        self.clock = clock
        self.schedule = BusSchedule(joints, now=time.monotonic(), baud=baud,
                                    publish_rate_hz=publish_rate_hz,
                                    telemetry_period_s=telemetry_period_s,
                                    max_retries=max_retries, margin_s=margin_s,
                                    torque_off_on_shutdown=torque_off_on_shutdown,
                                    pace_now=clock())
        self._stepper = _Locked(self.schedule, clock)
        self._lock = threading.RLock()  # a callback may command: the same thread steps again
        self._log = logger
        self._on_read = on_read
        self._on_cycle = on_cycle
        self.link = SerialLink(port, baud, proto.StreamDecoder('reply'),
                               on_frame=self._on_frame, on_connection=self._on_connection,
                               logger=logger)
        self._timer = DeadlineTimer(self._duty, name='servo-bus-timer', idle_s=TIMER_IDLE_S,
                                    min_sleep_s=0.0002, on_error=self._timer_failed)
        self._handlers = {Send: self._send, Answer: self._answer, ReadDone: self._read,
                          CycleDone: self._cycle, ev.Log: self._log_line,
                          ev.SetTimer: self._set_timer}
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

    def stop(self) -> None:
        """Step the shutdown (torque off the last frame), let it leave, close the port."""
        sent = [a for a in self._step(Shutdown(time.monotonic())) if isinstance(a, Send)]
        self._timer.stop()
        if sent:  # the torque off leaves the line before the port closes
            time.sleep(max(0.0, sent[-1].deadline - time.monotonic()))
        self.link.stop()

    @property
    def port_open(self) -> bool:
        """Whether the port is open."""
        return self.link.port_open

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
                 timeout: float = CALL_TIMEOUT_S) -> Optional[proto.Reply]:
        """One request at the next boundary; its reply, or None (no reply, or no answer)."""
        answer = self.call('transact', frame, servo_id, nparams, retries, timeout=timeout)
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
        """Step the schedule with `event`; carry out its actions here, in its order."""
        with self._lock:
            self._due = math.inf
            self._stepped_at = time.monotonic()
            return run_core(self._stepper, [event], self._handlers)

    def _on_frame(self, frame: proto.Reply) -> None:
        # Reader thread: stamped when its bytes were read, not when this thread got to it.
        now = self.link.last_rx_time or time.monotonic()
        self._step(ev.Reply(now, frame))

    def _on_connection(self, up: bool, reason: str) -> None:
        now = time.monotonic()
        self._step(ev.LinkUp(now) if up else ev.LinkDown(now, reason))

    def _duty(self) -> Optional[float]:
        # A deadline a later step moved (a reply came before it) costs no step; one every
        # TIMER_IDLE_S all the same, for the read loop's clock (a test's) that others move.
        now = time.monotonic()
        if now < self._due and now - self._stepped_at < TIMER_IDLE_S:
            return self._due
        self._step(ev.Tick(now))
        due = self._due
        return None if due == math.inf else due

    def _timer_failed(self, exc: BaseException) -> None:
        self._emit('error', f'servo bus timer failed: {exc!r}')

    # -- handlers -------------------------------------------------------------------------------

    def _send(self, action: Send) -> Optional[List[Any]]:
        delay = action.at - time.monotonic()
        if delay > 0:  # a frame of a batch: after the one before it left the line
            time.sleep(delay)
        try:
            self.link.write(action.frame)
        except LinkError as exc:
            return [ev.LinkDown(time.monotonic(), f'write failed: {exc}')]
        self.frames_sent += 1
        self.last_frame = action.frame
        return None

    @staticmethod
    def _answer(action: Answer) -> None:
        action.token.settle(action.ok, action)

    def _read(self, action: ReadDone) -> None:
        if self._on_read is not None:
            self._on_read(action)

    def _cycle(self, action: CycleDone) -> None:
        if self._on_cycle is not None:
            self._on_cycle(action)

    def _log_line(self, action: ev.Log) -> None:
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
