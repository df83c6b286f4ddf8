"""The OriginMan driver's decisions (``originman_board_ros.plan``) in virtual time, no I/O.

A hypothesis state machine drives :class:`BoardPlan` the way the core's threads do (the timer
fires at the plan's deadlines, every frame the plan has ready is written at once, reads are
written by the worker and may never be answered) with random motor commands, servo floods,
stops, disconnects, reconnects and frames from the board, and checks its invariants after
every step (issue 22, OriginMan).
"""

from hypothesis import strategies as st
from hypothesis.stateful import initialize, invariant, precondition, rule, RuleBasedStateMachine
from originman_board_ros import protocol as p
from originman_board_ros.plan import (BoardPlan, board_time, Command, Deadline, Drop, DROPPED,
                                      FrameIn, FrameScheduler, MotorCommand, Move,
                                      OnlineChanged, PACE_AHEAD_S, PACE_MARGIN, Refuse, Send,
                                      SendDone,
                                      STOP_ALL_FRAME, StopMotors, Written)
from originman_board_ros.simulation import VirtualOriginManBoardModel
from model_runs import search
import pytest
from uav_serial_common.core_events import LinkDown, LinkUp, Log, SetTimer, Tick

MOTOR_TIMEOUT_S = 0.5
OFFLINE_TIMEOUT_S = 2.5
STOP_MARGIN_S = 0.05
SERVOS = list(range(30))
READ_FRAME = p.encode_bus_read(p.BusSub.READ_POSITION, 1)
LED_FRAME = p.encode_led(1, 100, 100, 1)


def decode(frame: bytes):
    return p.decode_host_command(p.BoardParser().feed(frame)[0])


# ----- single rules -----------------------------------------------------------------------------

def test_a_stop_leaves_before_queued_moves_and_commands():
    plan = BoardPlan(MOTOR_TIMEOUT_S, OFFLINE_TIMEOUT_S)
    plan.connection(True, 0.0)
    plan.frame(0.0)
    plan.scheduler.written(p.encode_bus_move(20, [(i, 500) for i in SERVOS]), 0.0)  # busy bus
    assert plan.move(20, [(1, 100), (2, 200)]) and plan.command(LED_FRAME)
    plan.stop_motors()
    kinds = []
    while True:
        item = plan.take(0.0)
        if item is None:
            break
        kinds.append(item[0])
    # The moves wait for room on the servo bus; the stop and the LED do not.
    assert kinds == ['stop', 'command'] and plan.scheduler.targets


def test_a_stop_drops_motor_commands_queued_before_it():
    # Found by the state machine: a motor command queued by one thread, a stop by another;
    # the stop left first and the command after it restarted the motors, unwatched.
    plan = BoardPlan(MOTOR_TIMEOUT_S, OFFLINE_TIMEOUT_S)
    plan.connection(True, 0.0)
    plan.frame(0.0)
    assert plan.motor_command(p.encode_motor_speeds([(0, 1.0)]), 0.0, ticket='run')
    assert plan.command(LED_FRAME, ticket='led')
    plan.stop_motors(ticket='stop')
    assert [plan.take(0.0)[2] for _ in range(2)] == ['stop', 'led'] and plan.take(0.0) is None


def test_the_newest_target_of_a_servo_replaces_the_queued_one_in_its_place():
    s = FrameScheduler()
    s.push_move(20, [(1, 100), (2, 200)])
    s.push_move(20, [(1, 111)])
    assert list(s.targets.items()) == [(1, (111, 20)), (2, (200, 20))] and s.coalesced == 1
    s.push_command(p.encode_bus_stop([2]), cancels=[2])
    assert list(s.targets) == [1]


def test_online_from_the_first_frame_after_a_reconnect():
    plan = BoardPlan(MOTOR_TIMEOUT_S, OFFLINE_TIMEOUT_S)
    assert plan.connection(True, 0.0) is None  # was offline already
    assert plan.frame(0.01) == (True, 'frames arriving')
    assert plan.connection(False, 1.0) == (False, 'port closed')
    assert plan.frame(1.1) is None  # no port: nothing counts
    plan.connection(True, 1.2)
    assert not plan.command(LED_FRAME)
    assert plan.frame(1.21) == (True, 'frames arriving') and plan.command(LED_FRAME)


def test_the_watchdog_stops_at_its_deadline_whatever_else_waits():
    plan = BoardPlan(MOTOR_TIMEOUT_S, OFFLINE_TIMEOUT_S)
    plan.connection(True, 0.0)
    plan.frame(0.0)
    assert plan.watchdog.deadline == 0.5  # O38: armed at connect
    assert plan.motor_command(p.encode_motor_speeds([(0, 1.0)]), 0.3)
    plan.scheduler.written(READ_FRAME, 0.3)  # a read that is never answered
    assert not plan.tick_watchdog(0.79)
    assert plan.tick_watchdog(0.8) and plan.take(0.8)[1] == STOP_ALL_FRAME
    assert plan.watchdog.deadline is None and not plan.tick_watchdog(5.0)


def test_board_time_counts_the_servo_bus():
    assert board_time(p.encode_bus_move(20, [(i, 500) for i in range(10)])) == pytest.approx(
        (4 + 3 * 10 + 6) * 10 / p.BAUD + 10 * 100 / 115200, rel=0.05)
    assert board_time(LED_FRAME) < 0.0003


class SlowBoard(VirtualOriginManBoardModel):
    """The board model, its receive task ``slower`` times slower than §6 says."""

    def __init__(self, slower, **kwargs):
        self.slower = slower
        super().__init__(**kwargs)

    def _handle(self, frame, t):
        return super()._handle(frame, t) * self.slower


@pytest.mark.parametrize('slower', [1.0, 1.1])
def test_a_stop_waits_little_on_a_slower_board_after_a_long_servo_flood(slower):
    # A flood of 20 servos at 100 Hz (more than the servo bus carries) for 10 s, then a stop,
    # in the board model's time. Paced at exactly §6's figures, a board 10 % slower kept every
    # late millisecond queued: the stop waited 0.55 s behind moves.
    ids = list(range(1, 21))
    board = SlowBoard(slower, bus_servo_ids=ids)
    plan = BoardPlan(0.0, OFFLINE_TIMEOUT_S)
    plan.connection(True, 0.0)
    plan.frame(0.0)
    now = 0.0

    def write_ready():
        while True:
            item = plan.take(now)
            if item is None:
                return
            board.receive(item[1], now)
            plan.scheduler.written(item[1], now)

    for k in range(1000):
        plan.move(20, [(i, (7 * k + i) % 1000) for i in ids])
        end = now + 0.01
        while True:
            write_ready()
            due = plan.scheduler.next_time(now)
            if due is None or due > end:
                break
            now = max(now, due)
        now = end
    plan.stop_motors()
    write_ready()
    board.step(now + 5.0)
    arrived, handled, _ = [e for e in board.queue_log if isinstance(e[2], p.StopMotors)][0]
    waited = handled - arrived
    # Behind at most the paced work and one servo of it, each a little slower.
    assert waited <= (PACE_AHEAD_S + 10 * 10 / 115200) * slower + 0.002, waited


# ----- step(): the path every thread of the core goes through ------------------------------------

def online_plan():
    plan = BoardPlan(MOTOR_TIMEOUT_S, OFFLINE_TIMEOUT_S)
    plan.step(LinkUp(0.0))
    plan.step(FrameIn(0.0))
    return plan


def sends(actions):
    return [a for a in actions if isinstance(a, Send)]


def test_round2_22_3_a_stop_queued_while_a_frame_is_written_is_the_next_write():
    plan = online_plan()
    plan.step(Written(0.0, p.encode_bus_move(20, [(i, 500) for i in SERVOS])))  # a busy bus
    first = sends(plan.step(Command(0.0, LED_FRAME, 'led')))
    assert [s.ticket for s in first] == ['led'] and plan.sending
    # While 'led' is being written, other threads queue commands, moves and then a stop: none
    # of them writes (one write at a time), and the stop is the next frame, after 'led' only.
    assert not sends(plan.step(Command(0.0, LED_FRAME, 'second')))
    assert not sends(plan.step(Move(0.0, 20, ((1, 100), (2, 200)), 'move')))
    assert not sends(plan.step(MotorCommand(0.0, p.encode_motor_speeds([(0, 1.0)]), 'run')))
    stop = plan.step(StopMotors(0.0, 'stop'))
    assert not sends(stop) and Drop('run', DROPPED) in stop  # a motor command before a stop
    plan.step(Written(0.0, LED_FRAME))
    assert [(s.kind, s.ticket) for s in sends(plan.step(SendDone(0.0)))] == [('stop', 'stop')]
    plan.step(Written(0.0, STOP_ALL_FRAME))
    assert [s.ticket for s in sends(plan.step(SendDone(0.0)))] == ['second']
    # The moves wait for room on the servo bus; the timer is told when.
    done = plan.step(SendDone(0.0))
    assert not sends(done) and isinstance(done[-1], SetTimer) and 0.0 < done[-1].at < 0.1


def test_round2_22_3_the_watchdog_stop_goes_next_behind_a_frame_being_written():
    plan = online_plan()
    plan.step(MotorCommand(0.0, p.encode_motor_speeds([(0, 1.0)]), 'run'))
    plan.step(SendDone(0.0))
    for k in range(5):  # a caller is writing its frame when the deadline comes
        plan.step(Command(0.4, LED_FRAME, k))
    fired = plan.step(Deadline(0.5))
    assert not sends(fired) and [type(a) for a in fired] == [Log]
    assert sends(plan.step(SendDone(0.5)))[0].frame == STOP_ALL_FRAME


def test_round2_22_2_nothing_but_a_stop_is_written_while_offline():
    plan = BoardPlan(MOTOR_TIMEOUT_S, OFFLINE_TIMEOUT_S)
    plan.step(LinkUp(0.0))  # the port is open, no frame from the board yet
    led = plan.step(Command(0.0, LED_FRAME, 'led'))
    assert Refuse('led', 'the board is offline') in led and not sends(led)
    assert Refuse('move', 'the board is offline') in plan.step(Move(0.0, 20, ((1, 1),), 'move'))
    assert Refuse('run', 'the board is offline') in plan.step(
        MotorCommand(0.0, p.encode_motor_speeds([(0, 1.0)]), 'run'))
    assert [(s.kind, s.ticket) for s in sends(plan.step(StopMotors(0.0, 'stop')))] == \
        [('stop', 'stop')]
    # Online, then the port closes with commands queued behind a write: they are dropped.
    plan.step(SendDone(0.0))
    plan.step(FrameIn(0.1))
    plan.step(Command(0.1, LED_FRAME, 'a'))
    plan.step(Command(0.1, LED_FRAME, 'b'))
    down = plan.step(LinkDown(0.2))
    assert OnlineChanged(False, 'port closed', 0.2) in down and Drop('b', DROPPED) in down
    assert not sends(plan.step(SendDone(0.2)))


def test_round2_22_2_set_timer_is_the_watchdog_deadline():
    plan = online_plan()
    assert plan.step(Tick(0.1))[-1] == SetTimer(MOTOR_TIMEOUT_S)  # armed at the connect (O38)
    plan.step(MotorCommand(0.3, None, 'keep-alive'))
    assert plan.step(Tick(0.31))[-1] == SetTimer(0.3 + MOTOR_TIMEOUT_S)
    assert not sends(plan.step(Deadline(0.79)))
    fired = plan.step(Deadline(0.8))
    assert [type(a) for a in fired] == [Send, Log] and fired[0].frame == STOP_ALL_FRAME
    assert not [a for a in plan.step(SendDone(0.8)) if isinstance(a, SetTimer)]
    plan.step(LinkDown(1.0))
    plan.step(LinkUp(2.0))  # re-armed at the connect, whatever it was before
    assert plan.step(Tick(2.0))[-1] == SetTimer(2.0 + MOTOR_TIMEOUT_S)


def test_round2_22_2_found_the_paced_moves_timer_is_their_time_not_a_rounding_after_it():
    # Found by the 20,000-sequence search: the timer for a paced move was set at
    # now + (ready - now), which rounds: 0.001 + (0.009776736111111113 - 0.001) is
    # 0.009776736111111115, 2e-18 s after the move is ready ("nothing ready waits without a
    # writer or a timer" failed).
    plan = online_plan()
    plan.step(SendDone(0.001))
    ready = 0.009776736111111113
    plan.scheduler.board_free_at = ready + plan.scheduler.ahead_s / 2
    actions = plan.step(Move(0.001, 100, ((1, 500),)))
    assert not sends(actions)
    assert actions[-1] == SetTimer(plan.scheduler.next_time(0.001)) == SetTimer(ready)


def test_round2_22_2_every_thread_that_steps_may_write_but_never_two_at_once():
    plan = online_plan()
    assert sends(plan.step(Command(0.0, LED_FRAME, 1)))
    # Not from Written: the link reports it from inside its write.
    assert not sends(plan.step(Written(0.0, LED_FRAME)))
    plan.step(SendDone(0.0))
    for event in (Written(0.0, LED_FRAME), FrameIn(0.0), LinkUp(0.0), LinkDown(0.0)):
        assert not sends(plan.step(event))  # the reader's and the link's never write
    plan.step(LinkUp(0.0))
    plan.step(FrameIn(0.0))
    assert sends(plan.step(Command(0.0, LED_FRAME, 1)))
    for event in (Tick(0.0), Deadline(0.0), FrameIn(0.0), Command(0.0, LED_FRAME, 2)):
        assert not sends(plan.step(event))
    assert [s.ticket for s in sends(plan.step(SendDone(0.0)))] == [2]


# ----- the state machine ------------------------------------------------------------------------

class BoardPlanMachine(RuleBasedStateMachine):
    """The plan as the core runs it (every path through ``step``), against a record of the wire.

    Actions are carried out as the core's handlers do: a ``Send`` is written (``Written`` and
    ``SendDone`` stepped), unless a write is held: then several threads step the plan while one
    writes (``callers_while_one_writes``). The timer steps ``Deadline`` at the earliest
    ``SetTimer`` it was given, and at no other time: the deadlines the plan gives are all it has.
    """

    @initialize(online=st.booleans())
    def start(self, online):
        self.plan = BoardPlan(MOTOR_TIMEOUT_S, OFFLINE_TIMEOUT_S)
        self.now = 0.0
        self.connected = False
        self.armed_at = None      # motors may run since then (a command, or the connect: O38)
        self.wanted = {}          # servo -> newest target accepted
        self.on_board = {}        # servo -> last target written
        self.wire = []            # (time, kind, frame)
        self.motor_frames = []    # motor speeds and stops written since the port opened
        self.timer_at = None      # the earliest SetTimer since the timer last ran
        self.in_flight = None     # the Send being written
        self.hold = False         # the write in flight is not over yet
        self.read_at = -1.0
        self.unpaced_until = 0.0  # when the board is through with the commands written
        self.tickets = 0
        self.waiting = set()      # tickets of frames queued, not yet answered
        self.answered = set()
        if online:  # most interleavings worth trying start from a board that talks
            self.connect()
            self.frame_from_the_board()

    # -- the runtime, emulated -------------------------------------------------------------------

    def ticket(self):
        self.tickets += 1
        self.waiting.add(self.tickets)
        return self.tickets

    def answer(self, ticket):
        if ticket is None:
            return
        assert ticket not in self.answered, f'ticket {ticket} answered twice'
        self.waiting.discard(ticket)
        self.answered.add(ticket)

    def run(self, event):
        """Step ``event`` and the events its actions bring about, as ``run_core`` does."""
        events = [event]
        while events:
            event = events.pop(0)
            stops_waiting = bool(self.plan.scheduler.stops)
            for action in self.plan.step(event):
                if isinstance(action, Send):
                    assert self.in_flight is None, 'two frames written at once'
                    if stops_waiting:
                        assert action.kind == 'stop', 'a frame left before a waiting stop'
                    if action.kind != 'stop':
                        assert self.plan.online, f'{action.kind} sent to a board judged offline'
                    self.in_flight = action
                    if not self.hold:
                        events += self.write()
                elif isinstance(action, SetTimer):
                    self.timer_at = action.at if self.timer_at is None else \
                        min(self.timer_at, action.at)
                elif isinstance(action, (Refuse, Drop)):
                    self.answer(action.ticket)
        if not self.plan.online:
            self.dropped()

    def write(self):
        """Write the frame in flight; return the events that follow."""
        action, self.in_flight = self.in_flight, None
        kind, frame = action.kind, action.frame
        self.answer(action.ticket)
        if not self.connected:
            return [SendDone(self.now, 'port closed')]
        if kind == 'stop' and self.armed_at is not None:
            late = self.now - self.armed_at
            assert late <= MOTOR_TIMEOUT_S + STOP_MARGIN_S, f'stop {late:.3f} s late'
        if kind == 'stop':
            # The stop waits on the board behind at most the paced work, two reads and what
            # is left of the commands given before it (they go first, unpaced, O55: found by
            # the search, a burst of a hundred callers' motor and LED frames at one instant).
            backlog = self.plan.scheduler.backlog(self.now)
            unpaced = max(0.0, self.unpaced_until - self.now)
            assert backlog <= PACE_AHEAD_S + 2 * board_time(READ_FRAME) + unpaced + 0.002, \
                backlog
            self.armed_at = None
        elif kind in ('command', 'motor'):
            self.unpaced_until = max(self.unpaced_until, self.now) + \
                board_time(frame) * PACE_MARGIN
        self.wire.append((self.now, kind, frame))
        cmd = decode(frame)
        if isinstance(cmd, (p.SetMotorSpeeds, p.StopMotors)):
            self.motor_frames.append(cmd)
        if isinstance(cmd, p.BusMove):
            for servo_id, position in cmd.items:
                self.on_board[servo_id] = position
        return [Written(self.now, frame), SendDone(self.now)]

    def timer_until(self, end):
        """The timer thread: step ``Deadline`` at each deadline it was given, up to ``end``."""
        while self.timer_at is not None and self.timer_at <= end:
            self.now = max(self.now, self.timer_at)
            self.timer_at = None
            self.run(Deadline(self.now))
        self.now = max(self.now, end)

    def dropped(self):
        # Targets dropped because the board went offline are no one's newest any more.
        for servo_id in list(self.wanted):
            if servo_id not in self.plan.scheduler.targets and \
                    self.on_board.get(servo_id) != self.wanted[servo_id]:
                del self.wanted[servo_id]

    def read(self):
        # The worker waits for the reply to each read: the board answers it after the work
        # before it and its own, so a read follows the one before by at least that.
        if self.now >= self.read_at + board_time(READ_FRAME):
            self.read_at = self.now
            self.run(Written(self.now, READ_FRAME))

    def motor(self, speed=2.0):
        frame = None if speed is None else p.encode_motor_speeds([(1, speed)])
        online = self.plan.online
        self.run(MotorCommand(self.now, frame, self.ticket() if frame else None))
        if online and self.connected:
            self.armed_at = self.now
        return online

    def move(self, items, duration=20):
        ticket = self.ticket()
        self.run(Move(self.now, duration, tuple(items), ticket))
        if ticket in self.answered:
            assert not self.plan.online
        else:
            self.waiting.discard(ticket)  # a move is never answered: its targets are queued
            self.wanted.update(items)

    # -- events ----------------------------------------------------------------------------------

    @rule()
    def connect(self):
        if not self.connected:
            self.connected = True
            self.motor_frames = []
            self.run(LinkUp(self.now))
            self.armed_at = self.now

    @rule()
    def disconnect(self):
        if self.connected:
            self.connected = False
            self.run(LinkDown(self.now))
            self.armed_at = None  # no port: nothing to stop; O38 re-arms at the connect

    @rule()
    def frame_from_the_board(self):
        self.run(FrameIn(self.now))
        if self.connected:
            assert self.plan.online, 'a frame on an open port and the board not online'

    @rule()
    def worker_poll(self):
        self.run(Tick(self.now))

    @rule(speed=st.one_of(st.none(), st.floats(-6, 6)))
    def motor_command(self, speed):
        assert self.motor(speed) == self.plan.online or not self.connected

    @rule(calls=st.lists(st.sampled_from(['motor', 'led', 'move', 'stop', 'read']), min_size=2,
                         max_size=8))
    def callers_while_one_writes(self, calls):
        """Issue 22 item 3: threads step the plan while another writes the frame in flight.

        The first call's frame is being written; the others queue theirs. When that write is
        over, the next frame is a stop if one was queued (``run`` checks it).
        """
        self.hold = True
        self.run(Command(self.now, LED_FRAME, self.ticket()))
        for k, call in enumerate(calls):
            if call == 'motor':
                self.motor()
            elif call == 'led':
                self.run(Command(self.now, LED_FRAME, self.ticket()))
            elif call == 'move':
                self.move([(i, (k * 101 + i) % 1001) for i in SERVOS[:10]])
            elif call == 'read':
                self.read()  # the worker's read leaves beside the plan's frames
            else:
                self.run(StopMotors(self.now, self.ticket()))
        self.hold = False
        if self.in_flight is not None:
            self.run_after(self.write())

    def run_after(self, events):
        for event in events:
            self.run(event)

    @rule()
    def stop_motors(self):
        self.run(StopMotors(self.now, self.ticket()))

    @rule(ids=st.lists(st.sampled_from(SERVOS), min_size=1, max_size=8, unique=True),
          position=st.integers(0, 1000), duration=st.sampled_from([0, 20, 100]))
    def bus_servo_command(self, ids, position, duration):
        self.move([(i, (position + 13 * i) % 1001) for i in ids], duration)

    @rule(rounds=st.integers(5, 40), duration=st.sampled_from([0, 20]))
    def servo_command_flood(self, rounds, duration):
        """Issue 21 item 7: 20 servos every 10 ms, more than the servo bus carries."""
        for k in range(rounds):
            self.move([(i, (k * 37 + i) % 1001) for i in SERVOS[:20]], duration)
            self.timer_until(self.now + 0.01)

    @rule()
    def led_command(self):
        online = self.plan.online
        ticket = self.ticket()
        self.run(Command(self.now, LED_FRAME, ticket))
        assert (ticket in self.answered) == (not online or not self.connected or
                                             ticket in self.answered)

    @rule(count=st.integers(1, 40))
    def reads_left_unanswered(self, count):
        """Issue 21 item 6: the worker writes reads and waits 2 x 50 ms for each, in vain."""
        for _ in range(count):
            if not (self.connected and self.plan.online):
                break
            self.read()
            self.timer_until(self.now + 0.1)

    @rule(dt=st.floats(0.001, 1.5))
    def time_passes(self, dt):
        self.timer_until(self.now + dt)

    # -- invariants ------------------------------------------------------------------------------

    @invariant()
    def motors_stop_within_the_timeout(self):
        if self.armed_at is not None:
            late = self.now - self.armed_at
            assert late <= MOTOR_TIMEOUT_S + STOP_MARGIN_S, f'motors ran {late:.3f} s'

    @invariant()
    def motors_the_watchdog_lets_go_of_are_stopped(self):
        if self.connected and self.plan.watchdog.deadline is None and self.motor_frames:
            assert isinstance(self.motor_frames[-1], p.StopMotors), self.motor_frames[-1]
            assert not any(motor for _, _, motor in self.plan.scheduler.commands)

    @invariant()
    def the_newest_target_of_each_servo_wins(self):
        for servo_id, target in self.wanted.items():
            if servo_id not in self.plan.scheduler.targets:
                assert self.on_board.get(servo_id) == target, servo_id
            else:
                assert self.plan.scheduler.targets[servo_id][0] == target

    @invariant()
    def nothing_but_stops_waits_while_offline(self):
        if not self.plan.online:
            assert not self.plan.scheduler.commands and not self.plan.scheduler.targets

    @invariant()
    def every_call_is_answered_once_its_frame_left_or_was_dropped(self):
        # Between rules no write is in flight: every ticket still waiting is queued.
        assert self.in_flight is None and not self.plan.sending
        queued = {t for _, t in self.plan.scheduler.stops} | \
            {t for _, t, _ in self.plan.scheduler.commands}
        assert self.waiting <= queued, self.waiting - queued

    @invariant()
    def nothing_ready_waits_without_a_writer_or_a_timer(self):
        assert not self.plan.scheduler.stops and not self.plan.scheduler.commands
        if self.plan.scheduler.targets:
            paced = self.plan.scheduler.next_time(self.now)
            assert self.timer_at is not None and self.timer_at <= paced, (self.timer_at, paced)

    @precondition(lambda self: self.plan.online and self.plan.scheduler.targets)
    @rule()
    def queued_targets_leave_as_the_bus_frees(self):
        self.timer_until(self.now + 0.5)
        assert not self.plan.scheduler.targets, 'targets stuck with the servo bus idle'


def test_round2_6_7_11a_board_plan_invariants_hold_over_random_sequences():
    search(BoardPlanMachine, 'originman', steps=50)
