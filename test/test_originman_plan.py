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
from originman_board_ros.plan import (BoardPlan, board_time, FrameScheduler, PACE_AHEAD_S,
                                      STOP_ALL_FRAME)
from originman_board_ros.simulation import VirtualOriginManBoardModel
from model_runs import search
import pytest

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


# ----- the state machine ------------------------------------------------------------------------

class BoardPlanMachine(RuleBasedStateMachine):
    """The plan as the core runs it, against a record of the wire."""

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
        if online:  # most interleavings worth trying start from a board that talks
            self.connect()
            self.frame_from_the_board()

    # -- the runtime, emulated -------------------------------------------------------------------

    def drain(self):
        while True:
            stops_waiting = bool(self.plan.scheduler.stops)
            online = self.plan.online
            item = self.plan.take(self.now)
            if item is None:
                return
            kind, frame, _ = item
            if stops_waiting:
                assert kind == 'stop', 'a frame left before a waiting stop'
            if kind != 'stop':
                assert online, f'{kind} sent to a board judged offline'
            if not self.connected:
                continue  # the write fails: the port is closed
            if kind == 'stop' and self.armed_at is not None:
                late = self.now - self.armed_at
                assert late <= MOTOR_TIMEOUT_S + STOP_MARGIN_S, f'stop {late:.3f} s late'
            if kind == 'stop':
                # The stop waits on the board behind at most the paced work (and two reads).
                backlog = self.plan.scheduler.backlog(self.now)
                assert backlog <= PACE_AHEAD_S + 2 * board_time(READ_FRAME) + 0.002, backlog
                self.armed_at = None
            self.plan.scheduler.written(frame, self.now)
            self.wire.append((self.now, kind, frame))
            cmd = decode(frame)
            if isinstance(cmd, (p.SetMotorSpeeds, p.StopMotors)):
                self.motor_frames.append(cmd)
            if isinstance(cmd, p.BusMove):
                for servo_id, position in cmd.items:
                    self.on_board[servo_id] = position

    def timer_until(self, end):
        """The timer thread: fire every deadline up to ``end``, writing what is due."""
        while True:
            deadline = self.plan.watchdog.deadline if self.plan.judge.port_open else None
            paced = self.plan.scheduler.next_time(self.now)
            due = min([t for t in (deadline, paced) if t is not None], default=None)
            if due is None or due > end:
                break
            self.now = max(self.now, due)
            self.plan.tick_watchdog(self.now)
            self.drain()
        self.now = max(self.now, end)

    def dropped(self):
        # Targets dropped because the board went offline are no one's newest any more.
        for servo_id in list(self.wanted):
            if servo_id not in self.plan.scheduler.targets and \
                    self.on_board.get(servo_id) != self.wanted[servo_id]:
                del self.wanted[servo_id]

    # -- events ----------------------------------------------------------------------------------

    @rule()
    def connect(self):
        if not self.connected:
            self.connected = True
            self.motor_frames = []
            self.plan.connection(True, self.now)
            self.armed_at = self.now
            self.drain()

    @rule()
    def disconnect(self):
        if self.connected:
            self.connected = False
            self.plan.connection(False, self.now)
            self.armed_at = None  # no port: nothing to stop; O38 re-arms at the connect
            self.dropped()

    @rule()
    def frame_from_the_board(self):
        self.plan.frame(self.now)
        if self.connected:
            assert self.plan.online, 'a frame on an open port and the board not online'

    @rule()
    def worker_poll(self):
        change, _ = self.plan.tick(self.now)
        if change is not None and not change[0]:
            self.dropped()
        self.drain()

    # A caller queues its frame, then drains; another thread's frames may be queued between
    # (``drain`` False: the caller has not reached its drain yet).

    @rule(speed=st.one_of(st.none(), st.floats(-6, 6)), drain=st.booleans())
    def motor_command(self, speed, drain):
        frame = None if speed is None else p.encode_motor_speeds([(0, speed)])
        accepted = self.plan.motor_command(frame, self.now)
        assert accepted == self.plan.online
        if accepted and self.connected:
            self.armed_at = self.now
        if drain:
            self.drain()

    @rule()
    def a_caller_drains(self):
        self.drain()

    @rule(calls=st.lists(st.sampled_from(['motor', 'led', 'move', 'stop']), min_size=2,
                         max_size=6))
    def callers_at_once(self, calls):
        """Several threads queue their frames before any of them drains."""
        for k, call in enumerate(calls):
            if call == 'motor':
                if self.plan.motor_command(p.encode_motor_speeds([(1, 2.0)]), self.now) and \
                        self.connected:
                    self.armed_at = self.now
            elif call == 'led':
                self.plan.command(LED_FRAME)
            elif call == 'move':
                items = [(i, (k * 101 + i) % 1001) for i in SERVOS[:10]]
                if self.plan.move(20, items):
                    self.wanted.update(items)
            else:
                self.plan.stop_motors()
        self.drain()

    @rule()
    def stop_motors(self):
        self.plan.stop_motors()
        self.drain()

    @rule(ids=st.lists(st.sampled_from(SERVOS), min_size=1, max_size=8, unique=True),
          position=st.integers(0, 1000), duration=st.sampled_from([0, 20, 100]),
          drain=st.booleans())
    def bus_servo_command(self, ids, position, duration, drain):
        items = [(i, (position + 13 * i) % 1001) for i in ids]
        if self.plan.move(duration, items):
            self.wanted.update(items)
        else:
            assert not self.plan.online
        if drain:
            self.drain()

    @rule(rounds=st.integers(5, 40), duration=st.sampled_from([0, 20]))
    def servo_command_flood(self, rounds, duration):
        """Issue 21 item 7: 20 servos every 10 ms, more than the servo bus carries."""
        for k in range(rounds):
            items = [(i, (k * 37 + i) % 1001) for i in SERVOS[:20]]
            if self.plan.move(duration, items):
                self.wanted.update(items)
            self.drain()
            self.timer_until(self.now + 0.01)

    @rule(drain=st.booleans())
    def led_command(self, drain):
        assert self.plan.command(LED_FRAME) == self.plan.online
        if drain:
            self.drain()

    @rule(count=st.integers(1, 40))
    def reads_left_unanswered(self, count):
        """Issue 21 item 6: the worker writes reads and waits 2 x 50 ms for each, in vain."""
        for _ in range(count):
            if not (self.connected and self.plan.online):
                break
            self.plan.scheduler.written(READ_FRAME, self.now)
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

    @precondition(lambda self: self.plan.online and self.plan.scheduler.targets)
    @rule()
    def queued_targets_leave_as_the_bus_frees(self):
        self.timer_until(self.now + 0.5)
        assert not self.plan.scheduler.targets, 'targets stuck with the servo bus idle'


def test_round2_6_7_11a_board_plan_invariants_hold_over_random_sequences():
    search(BoardPlanMachine, 'originman', steps=50)
