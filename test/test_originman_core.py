"""OriginManCore against the board model on a real pty; time-based rules on a fake clock.

The core is started without its worker thread (``start(worker=False)``) and the test calls
``poll()`` at fake times, so watchdog, offline judgement, settings and polling are
deterministic while the bytes still cross a real pty.
"""

from dataclasses import replace
import gc
import math
import threading
import weakref

from originman_board_ros import protocol as p
from originman_board_ros.core import (ConfigError, IDLE_MAX_S, OriginManConfig, OriginManCore,
                                      Outcome, PwmServoStates, STANDARD_GRAVITY,
                                      WORKER_PERIOD_S)
from originman_board_ros.protocol import BusSub
from originman_rig import VirtualBoard
import pytest
from support import FakeClock
from uav_serial_common.process import wait_for, wait_scale


class Rig:
    def __init__(self, tmp_path, board_kwargs=None, **config):
        self.board = VirtualBoard(str(tmp_path / 'board'), **(board_kwargs or {}))
        # Off until the core holds the port: what the board sent before would be flushed at the
        # open, and silence() counts on every byte of the board reaching the core.
        self.model.power_off()
        self.board.start()
        self.clock = FakeClock()
        self.events = {k: [] for k in ('imu', 'battery', 'button', 'sbus', 'gamepad', 'asr',
                                       'states', 'online')}
        config.setdefault('read_timeout_s', 0.25)
        self.core = OriginManCore(
            OriginManConfig(port=self.board.path, **config), clock=self.clock,
            on_imu=self.events['imu'].append, on_battery=self.events['battery'].append,
            on_button=self.events['button'].append, on_sbus=self.events['sbus'].append,
            on_gamepad=self.events['gamepad'].append, on_asr=self.events['asr'].append,
            on_bus_servo_states=self.events['states'].append,
            on_online_change=lambda online, why: self.events['online'].append((online, why)))
        self.core.start(worker=False)
        assert self.core.link.wait_port_open(5 * wait_scale()), 'the core did not open the port'
        with self.board.locked():
            self.model.power_on()

    @property
    def model(self):
        return self.board.model

    @property
    def frames_out(self) -> int:
        return self.core.link.serial.stats.frames_out

    def frame_arrives(self):
        """Wait until a frame arrives after now (it is stamped with the fake clock's time)."""
        count = self.core.link.decoder.frames_decoded
        wait_for(lambda: self.core.link.decoder.frames_decoded > count, 5, what='a frame')

    def online(self):
        self.frame_arrives()
        # Counted when decoded, stepped into the core just after, on the reader thread (a
        # campaign run beside a busy loop looked in between).

        def polled_online():
            self.core.poll()  # (it returns nothing: the duties due, then look)
            return self.core.online
        wait_for(polled_online, 5, what='the board online')
        # The reader thread judges the board online with the frame, then calls
        # on_online_change: `online` may be seen before the callback has run (beside a busy
        # loop it was).
        wait_for(lambda: self.events['online'] and self.events['online'][-1][0], 5,
                 what='the online callback')

    def silence(self):
        """Switch the board off and wait until everything it sent has been read."""
        with self.board.locked():
            self.model.power_off()
        stats = self.core.link.serial.stats
        wait_for(lambda: stats.bytes_in == self.board.runner.bytes_out, 5,
                 what='the last bytes of the board')

    def _settle(self):
        sent = self.core.link.serial.stats.bytes_out
        wait_for(lambda: len(self.board.written(0)) >= sent, 5, what='the bytes on the wire')

    def mark(self):
        """A position in the wire log after everything the core has written so far."""
        self._settle()
        return self.board.mark()

    def wire(self, mark):
        """What the core wrote after ``mark``, once it has all reached the board."""
        self._settle()
        return self.board.commands(mark)

    def close(self):
        self.core.stop(stop_motors=False)
        self.board.stop()


@pytest.fixture
def make_rig(tmp_path):
    rigs = []

    def make(**kwargs):
        path = tmp_path / str(len(rigs))
        path.mkdir()
        rig = Rig(path, **kwargs)
        rigs.append(rig)
        return rig
    yield make
    for rig in rigs:
        rig.close()


@pytest.fixture
def rig(make_rig):
    r = make_rig()
    r.online()
    return r


# ----- online judgement -------------------------------------------------------------------------

def test_offline_after_offline_timeout_without_a_frame_and_online_again(make_rig):
    r = make_rig(offline_timeout_s=2.5)
    assert not r.core.online  # until a poll has seen a frame
    r.online()
    assert r.events['online'] == [(True, 'frames arriving')]
    r.silence()
    r.clock.advance(2.4)
    r.core.poll()
    assert r.core.online
    r.clock.advance(0.2)
    r.core.poll()
    assert not r.core.online
    assert r.events['online'][-1] == (False, 'no frame from the board for 2.6 s')
    with r.board.locked():
        r.model.power_on()
    r.online()
    assert [online for online, _ in r.events['online']] == [True, False, True]


def test_o20_offline_while_the_port_is_missing(tmp_path):
    core = OriginManCore(OriginManConfig(port=str(tmp_path / 'nothing')), clock=FakeClock())
    core.start(worker=False)
    try:
        wait_for(lambda: 'no such device' in core.link.serial.last_error, 5,
                 what='the open error')
        core.poll()
        snap = core.snapshot()
        assert not snap.online and not snap.port_open and 'not open' in snap.status
        assert core.link.baud == 1_000_000
    finally:
        core.stop()


# ----- desired settings -------------------------------------------------------------------------

def test_settings_are_written_at_connect_and_after_the_board_comes_back(make_rig):
    r = make_rig(low_battery_mv=5000, motor_type='JGA27', pwm_servo_offsets_us=(10, -20))
    r.online()
    snap = r.core.snapshot()
    assert snap.settings_ok and 'PWM offsets 1: 10 us, 2: -20 us (read back)' in \
        snap.settings_message
    wait_for(lambda: r.model.battery_limit_mv == 5000 and r.model.motor_type == 2, 5,
             what='battery limit and motor type on the board')
    assert [r.model.pwm_servos[i].offset_us for i in (1, 2, 3)] == [10, -20, 0]
    r.silence()
    r.clock.advance(3.0)
    r.core.poll()
    assert not r.core.online
    with r.board.locked():
        r.model.power_on()
    assert (r.model.battery_limit_mv, r.model.motor_type) == (6300, 0)
    r.online()
    wait_for(lambda: r.model.battery_limit_mv == 5000 and r.model.motor_type == 2, 5,
             what='the settings written again')
    assert r.model.pwm_servos[2].offset_us == -20 and r.core.snapshot().settings_ok


def test_round2_22_a_setting_changed_while_the_settings_are_written_is_written_after_them(
        make_rig):
    """A parameter set while the worker writes the settings (at a connect, reading the PWM
    offsets back) is written next: that write ended by calling the settings done, and the new
    threshold never reached the board."""
    r = make_rig(low_battery_mv=7000, pwm_servo_offsets_us=(10,))
    real_read = r.core.link.read_pwm_offset
    changed = []

    def read_pwm_offset(servo_id, *args, **kwargs):
        if not changed:  # the parameter comes in while the connect's write reads back
            changed.append(True)
            r.core.reconfigure(replace(r.core.config, low_battery_mv=6800))
        return real_read(servo_id, *args, **kwargs)
    r.core.link.read_pwm_offset = read_pwm_offset
    r.online()  # the connect's settings, with the change in the middle
    assert changed and not r.core.snapshot().settings_ok  # not done: the change is due
    r.core.poll()
    wait_for(lambda: r.model.battery_limit_mv == 6800, 5, what='the new threshold on the board')
    assert r.core.snapshot().settings_ok and '6800 mV' in r.core.snapshot().settings_message


def test_keep_and_minus_1_write_nothing(rig):
    snap = rig.core.snapshot()
    assert snap.settings_ok and snap.settings_message == 'no desired settings'
    assert rig.frames_out == 0


def test_reconfigure_writes_changed_settings_at_once_and_changes_the_poll(make_rig):
    r = make_rig(bus_servo_ids=(1, 2))
    r.online()
    mark = r.mark()
    r.core.reconfigure(replace(r.core.config, low_battery_mv=6000, motor_type='JGB528',
                               pwm_servo_offsets_us=(0, 7), bus_servo_ids=(2, 3),
                               motor_timeout_s=0.0))
    r.core.poll()
    wait_for(lambda: r.model.battery_limit_mv == 6000 and r.model.motor_type == 3, 5,
             what='the changed settings on the board')
    assert r.model.pwm_servos[2].offset_us == 7 and r.core.snapshot().settings_ok
    assert p.SetBatteryLimit(6000) in r.wire(mark)
    assert r.core.bus_servo_ids == [2, 3]
    assert [s.id for s in r.core.snapshot().bus_servos] == [2, 3]
    with pytest.raises(ConfigError, match='port and baud'):
        r.core.reconfigure(replace(r.core.config, baud=115200))
    with pytest.raises(ConfigError, match='motor_type'):
        r.core.reconfigure(replace(r.core.config, motor_type='V8'))
    assert r.core.config.motor_type == 'JGB528'


def test_the_worker_sleeps_until_a_duty_is_due(make_rig):
    r = make_rig(bus_servo_ids=(1,), bus_servo_poll_hz=10.0, motor_timeout_s=0.05)
    assert r.core.next_wake() == WORKER_PERIOD_S  # offline: looking for the first frames
    r.online()
    # The motor timeout is the timer thread's, not the worker's (issue 21 item 6): the next
    # poll of the servo (10 Hz) is what is due next.
    r.clock.advance(0.06)
    r.core.poll()
    assert r.core.snapshot().watchdog_stops == 1
    assert 0.0 < r.core.next_wake() <= 0.1
    r.core.config = replace(r.core.config, bus_servo_poll_hz=0.0)
    assert r.core.next_wake() == IDLE_MAX_S


def test_o37_a_quick_reset_is_noticed_through_the_offsets(make_rig):
    r = make_rig(pwm_servo_offsets_us=(0, 0, 15), settings_check_period_s=5.0)
    r.online()
    assert r.model.pwm_servos[3].offset_us == 15
    with r.board.locked():
        r.model.reboot()
    r.clock.advance(5.0)
    r.frame_arrives()
    r.core.poll()  # the check finds offset 0: due again
    assert r.core.online
    r.core.poll()
    assert r.model.pwm_servos[3].offset_us == 15
    # A service's value is what the check expects from then on: no fight with the user.
    assert r.core.set_pwm_servo_offset(3, -5).ok
    mark = r.mark()
    r.clock.advance(5.0)
    r.frame_arrives()
    r.core.poll()
    # The check reads the three offsets it knows and rewrites nothing.
    assert r.wire(mark) == [p.PwmRead(p.PwmSub.READ_OFFSET, i) for i in (1, 2, 3)]
    assert r.model.pwm_servos[3].offset_us == -5


# ----- the motor watchdog (O38, O39) -----------------------------------------------------------

def test_motors_stop_when_no_motor_command_came_for_the_timeout(make_rig):
    r = make_rig(motor_timeout_s=0.5)
    r.online()
    assert r.core.set_motor_speeds([1, 2], [1.0, -1.0]).ok
    wait_for(lambda: r.model.motor_set_points == [1.0, -1.0, 0.0, 0.0], 5, what='motors on')
    r.clock.advance(0.4)
    sent = r.frames_out
    r.core.poll()
    assert r.frames_out == sent
    assert r.core.set_motor_speeds([1], [0.0]).ok  # zeros restart the timeout too
    r.clock.advance(0.4)
    r.core.poll()
    assert r.frames_out == sent + 1
    assert r.core.set_motor_speeds([], []).ok  # an empty message is a keep-alive
    r.clock.advance(0.4)
    r.core.poll()
    assert r.frames_out == sent + 1
    r.clock.advance(0.11)
    r.core.poll()
    assert r.frames_out == sent + 2 and r.core.snapshot().watchdog_stops == 1
    wait_for(lambda: r.model.motor_set_points == [0.0] * 4, 5, what='every motor stopped')
    r.clock.advance(5.0)
    r.frame_arrives()
    r.core.poll()
    assert r.frames_out == sent + 2  # stopped once, not again and again


class FailingOnce:
    """A logger whose first warning raises (a log handler on a full disk), then logs."""

    def __init__(self):
        self.failed = False
        self.lines = []

    def warning(self, text):
        if not self.failed:
            self.failed = True
            raise OSError(28, 'No space left on device')
        self.lines.append(text)

    def __getattr__(self, name):  # info, error, exception: kept
        return lambda text, *args, **kwargs: self.lines.append(text)


def test_round2_22_2_a_failing_log_line_after_the_watchdog_stop_leaves_the_sending_going(
        tmp_path):
    """The watchdog's step gives its stop's Send, then its log line: a log line that raised
    lost the stop's SendDone, and the plan, left "sending", wrote nothing ever again (not the
    next command, not the next stop)."""
    board = VirtualBoard(str(tmp_path / 'board'))
    board.start()
    clock = FakeClock()
    log = FailingOnce()
    core = OriginManCore(OriginManConfig(port=board.path, motor_timeout_s=0.5,
                                         read_timeout_s=0.25), clock=clock, logger=log)
    try:
        core.start(worker=False)
        assert core.link.wait_port_open(5 * wait_scale())
        wait_for(lambda: core.link.decoder.frames_decoded > 0, 5, what='a frame')
        core.poll()
        assert core.online
        for speed in (1.0, 2.0):
            assert core.set_motor_speeds([1], [speed]).ok
            wait_for(lambda: board.model.motor_set_points[0] == speed, 5,
                     what=f'motor 1 at {speed}')
            clock.advance(0.5)
            core.poll()
            wait_for(lambda: board.model.motor_set_points[0] == 0.0, 5,
                     what='motor 1 stopped by the watchdog')
        assert log.failed and core.snapshot().watchdog_stops == 2
    finally:
        core.stop(stop_motors=False)
        board.stop()


def test_o39_a_refused_motor_command_does_not_restart_the_timeout(make_rig):
    r = make_rig(motor_timeout_s=0.5)
    r.online()
    r.core.set_motor_speeds([3], [2.0])
    r.clock.advance(0.3)
    mark = r.mark()
    assert r.core.set_motor_speeds([3], [math.nan]).cause == 'not_finite'
    r.clock.advance(0.25)
    r.core.poll()
    assert r.wire(mark) == [p.StopMotors(3, (0, 1, 2, 3))]


def test_o38_motors_left_running_are_stopped_a_timeout_after_connecting(make_rig):
    r = make_rig(motor_timeout_s=0.5, board_kwargs={'imu_rate_hz': 50})
    with r.board.locked():
        r.model.motor_set_points[0] = 1.5  # a previous driver left it running
    r.online()
    r.clock.advance(0.5)
    r.core.poll()
    wait_for(lambda: r.model.motor_set_points[0] == 0.0, 5, what='the motor stopped')


def test_motor_timeout_0_is_off(make_rig):
    r = make_rig(motor_timeout_s=0.0)
    r.online()
    r.core.set_motor_speeds([1], [1.0])
    sent = r.frames_out
    r.clock.advance(100.0)
    r.frame_arrives()
    r.core.poll()
    assert r.frames_out == sent


def test_stop_all_motors_and_shutdown_stop_every_motor(rig):
    rig.core.set_motor_speeds([1, 2, 3, 4], [1.0, 1.0, 1.0, 1.0])
    wait_for(lambda: rig.model.motor_set_points == [1.0] * 4, 5, what='motors on')
    rig.silence()  # offline or not, a stop goes out
    assert rig.core.stop_all_motors().ok
    with rig.board.locked():
        rig.model.power_on()
    rig.core.set_motor_speeds([2], [1.0])  # refused: offline in the core's view
    mark = rig.mark()
    rig.online()
    rig.core.set_motor_speeds([2], [1.0])
    wait_for(lambda: rig.model.motor_set_points[1] == 1.0, 5, what='motor 2 on')
    rig.core.stop()
    assert rig.wire(mark)[-1] == p.StopMotors(3, (0, 1, 2, 3))
    wait_for(lambda: rig.model.motor_set_points == [0.0] * 4, 5, what='every motor stopped')


def test_round2_22_3_a_stop_goes_next_behind_a_caller_writing_and_is_answered_at_once(rig):
    """A stop queued while another caller writes queued frames leaves after the frame being
    written, ahead of the others, and its caller is answered then, not after the rest."""
    core, real_send = rig.core, rig.core.link.send
    held = {p.SetLed: threading.Event(), p.SetBuzzer: threading.Event()}
    entered = []

    def send(frame):  # the real write, held at the LED and the buzzer until the test says
        kind = type(p.decode_host_command(p.BoardParser().feed(frame)[0]))
        entered.append(kind)
        if kind in held:
            held[kind].wait(60)  # (the test lets it go in any case)
        real_send(frame)
    core.link.send = send
    mark = rig.mark()
    answers = {}

    def call(name, *args):
        thread = threading.Thread(target=lambda: answers.update({name: getattr(core, name)(
            *args)}), daemon=True)
        thread.start()
        return thread
    threads = [call('set_led', 1, 0.1, 0.1, 1)]
    try:
        wait_for(lambda: p.SetLed in entered, 5, what='the LED being written')
        threads.append(call('set_buzzer', 2000, 0.05, 0.05, 1))
        threads.append(call('set_bus_servos', [1, 2], [100, 200], 0.02))
        plan = core._plan
        wait_for(lambda: plan.scheduler.commands and plan.scheduler.targets, 5,
                 what='a command and moves queued behind the LED')
        threads.append(call('stop_all_motors'))
        wait_for(lambda: plan.scheduler.stops, 5, what='the stop queued')
        held[p.SetLed].set()
        # Before: the stop left next, but its caller waited for the whole drain of the
        # caller that wrote it (here: held at the buzzer).
        wait_for(lambda: 'stop_all_motors' in answers, 5, what='the answer to the stop')
        assert answers['stop_all_motors'].ok
        assert entered[:3] == [p.SetLed, p.StopMotors, p.SetBuzzer]
    finally:
        for event in held.values():
            event.set()
        for thread in threads:
            thread.join(10)
    assert all(result.ok for result in answers.values()), answers
    assert [type(c) for c in rig.wire(mark)] == [p.SetLed, p.StopMotors, p.SetBuzzer, p.BusMove]


def test_round2_22_2_a_frame_still_queued_when_its_caller_stops_waiting_is_unknown_not_failed(
        rig, monkeypatch):
    """A caller whose frame is still queued when it stops waiting gets UNKNOWN (it may leave
    later, and does), not a failure; its outcome, when it comes, is not kept for nobody."""
    import originman_board_ros.core as core_module
    import originman_board_ros.core_commands as commands_module
    monkeypatch.setattr(core_module, 'SEND_WAIT_S', 0.3)
    core, real_send = rig.core, rig.core.link.send
    release = threading.Event()
    tickets = []  # (weak: what the test holds must not keep them)

    class Ticket(core_module.Ticket):
        __slots__ = ()

        def __init__(self):
            super().__init__()
            tickets.append(weakref.ref(self))
    monkeypatch.setattr(core_module, 'Ticket', Ticket)
    monkeypatch.setattr(commands_module, 'Ticket', Ticket)

    def send(frame):  # the LED's write held: the port takes nothing meanwhile
        if isinstance(p.decode_host_command(p.BoardParser().feed(frame)[0]), p.SetLed):
            release.wait(30)
        real_send(frame)
    core.link.send = send
    mark = rig.mark()
    answers = {}
    writer = threading.Thread(target=lambda: answers.update(led=core.set_led(1, 0.1, 0.1, 1)),
                              daemon=True)
    writer.start()
    try:
        wait_for(lambda: core._plan.sending, 5, what='the LED being written')
        result = core.set_buzzer(2000, 0.05, 0.05, 1)
        assert result.outcome == Outcome.UNKNOWN and 'may leave later' in result.message, result
    finally:
        release.set()
        writer.join(10)
    assert answers['led'].ok
    assert [type(c) for c in rig.wire(mark)] == [p.SetLed, p.SetBuzzer]  # it did leave
    # Both tickets were settled ('sent') and nothing keeps them, the one whose caller gave up
    # included: no outcome kept for nobody.
    assert len(tickets) == 2
    gc.collect()
    assert [ref() for ref in tickets] == [None, None]


# ----- validation: refused before anything reaches the wire ------------------------------------

REFUSALS = [
    ('set_motor_speeds', ([5], [1.0]), 'out_of_range'),
    ('set_motor_speeds', ([1], [6.01]), 'out_of_range'),
    ('set_motor_speeds', ([1], [math.inf]), 'not_finite'),
    ('set_motor_speeds', ([1, 2], [1.0]), 'length_mismatch'),
    ('set_motor_speeds', ([1, 1], [1.0, 2.0]), 'duplicate'),
    ('set_pwm_servos', ([0], [1500], 1.0), 'out_of_range'),
    ('set_pwm_servos', ([1], [2501], 1.0), 'out_of_range'),
    ('set_pwm_servos', ([1], [1500], 0.019), 'out_of_range'),
    ('set_pwm_servos', ([1], [1500], 30.5), 'out_of_range'),
    ('set_pwm_servos', ([], [], 1.0), 'empty'),
    ('set_bus_servos', ([254], [500], 1.0), 'out_of_range'),
    ('set_bus_servos', ([1], [1001], 1.0), 'out_of_range'),
    ('set_bus_servos', ([1], [500], 65.536), 'out_of_range'),
    ('set_bus_servos', ([1], [500], math.nan), 'not_finite'),
    ('set_led', (3, 0.1, 0.1, 1), 'out_of_range'),
    ('set_led', (1, 65.536, 0.1, 1), 'out_of_range'),
    ('set_led', (1, -0.1, 0.1, 1), 'out_of_range'),
    ('set_buzzer', (70000, 0.1, 0.1, 1), 'out_of_range'),
    ('set_buzzer', (2000, 0.1, math.nan, 1), 'not_finite'),
    ('set_oled', (1, 'x' * 24), 'too_long'),
    ('set_oled', (1, 'é' * 12), 'too_long'),
    ('set_oled', (0, 'x'), 'out_of_range'),
    ('set_rgb', ([0], [1], [1], [1]), 'out_of_range'),
    ('set_rgb', ([1, 2], [1], [1, 2], [1, 2]), 'length_mismatch'),
    ('set_rgb', ([1], [256], [1], [1]), 'out_of_range'),
    ('set_bus_servo_torque', ([], True), 'empty'),
    ('stop_bus_servos', ([300],), 'out_of_range'),
    ('set_bus_servo_id', (1, 254), 'out_of_range'),
    ('set_bus_servo_id', (2, 2), 'out_of_range'),
    ('set_bus_servo_offset', (1, 126, False), 'out_of_range'),
    ('set_bus_servo_limits', (1, 600, 500, 0, 0, 0), 'out_of_range'),
    ('set_bus_servo_limits', (1, 0, 1001, 0, 0, 0), 'out_of_range'),
    ('set_bus_servo_limits', (1, 0, 0, 4499, 9000, 0), 'out_of_range'),
    ('set_bus_servo_limits', (1, 0, 0, 9000, 8000, 0), 'out_of_range'),
    ('set_bus_servo_limits', (1, 0, 0, 0, 14001, 0), 'out_of_range'),
    ('set_bus_servo_limits', (1, 0, 0, 0, 0, 101), 'out_of_range'),
    ('set_pwm_servo_offset', (1, 101), 'out_of_range'),
    ('set_pwm_servo_offset', (5, 0), 'out_of_range'),
    ('get_pwm_servo_state', ([1, 1],), 'duplicate'),
    ('get_bus_servo_state', ([1, 300],), 'out_of_range'),
]


def test_bad_commands_are_refused_with_a_reason_and_nothing_is_sent(rig):
    sent = rig.frames_out
    for method, args, cause in REFUSALS:
        result = getattr(rig.core, method)(*args)
        assert (result.outcome, result.cause) == (Outcome.REFUSED, cause), (method, args, result)
        assert result.message
    assert rig.frames_out == sent
    refusals = rig.core.snapshot().refusals
    assert sum(refusals.values()) == len(REFUSALS)
    assert refusals['out_of_range'] == sum(1 for *_, c in REFUSALS if c == 'out_of_range')


def test_o40_commands_are_refused_while_the_board_is_offline(make_rig):
    r = make_rig()
    r.online()
    r.silence()
    r.clock.advance(3.0)
    r.core.poll()
    sent = r.frames_out
    result = r.core.set_led(1, 0.1, 0.1, 1)
    assert (result.outcome, result.cause) == (Outcome.REFUSED, 'offline')
    assert r.core.get_bus_servo_state([1]).cause == 'offline'
    assert r.frames_out == sent
    assert r.core.stop_all_motors().outcome is Outcome.SENT and r.frames_out == sent + 1


def test_o47_led_and_buzzer_times_round_to_ms_and_never_become_0(rig):
    mark = rig.mark()
    assert rig.core.set_led(2, 0.0004, 0.0, 0).ok
    assert rig.core.set_led(1, 65.535, 0.0015, 3).ok
    assert rig.core.set_buzzer(2400, 0.1, 0.9, 1).ok
    assert rig.wire(mark) == [p.SetLed(2, 1, 0, 0), p.SetLed(1, 65535, 2, 3),
                              p.SetBuzzer(2400, 100, 900, 1)]


def test_o18_o19_rgb_pixels_are_1_based_and_oled_text_fits(rig):
    mark = rig.mark()
    assert rig.core.set_rgb([2, 1], [255, 0], [0, 0], [0, 9]).ok
    assert rig.core.set_oled(2, 'é' * 11 + 'x').ok
    assert rig.wire(mark) == [p.SetRgb(((1, 255, 0, 0), (0, 0, 0, 9))),
                              p.SetOledText(2, ('é' * 11 + 'x').encode())]
    wait_for(lambda: rig.model.rgb == [(0, 0, 9), (255, 0, 0)], 5, what='the pixels')


def test_o45_write_only_commands_report_sent_not_done(rig):
    result = rig.core.stop_bus_servos([1, 2])
    assert result.ok and result.message == 'stop bus servos [1, 2]: sent'
    assert rig.core.set_oled(1, 'hello').message == "OLED line 1: 'hello': sent"


def test_o46_offsets_that_do_not_read_back_are_written_again_a_second_later(make_rig):
    r = make_rig(pwm_servo_offsets_us=(25,), motor_timeout_s=0.0)
    # Later than both attempts of the read-back (2 x 0.25 s): a late reply to the first attempt
    # would still be a valid answer to the second.
    r.board.runner.faults.reply_delay_s = 0.6
    r.online()
    snap = r.core.snapshot()
    assert not snap.settings_ok and 'could not write the settings' in snap.settings_message
    r.board.runner.faults.reply_delay_s = 0.0
    wait_for(lambda: r.core.link.unexpected_replies == 2, 5, what='both late replies')
    mark = r.mark()
    r.clock.advance(0.9)
    r.core.poll()
    assert r.wire(mark) == []
    r.clock.advance(0.1)
    r.core.poll()
    assert r.core.snapshot().settings_ok
    assert r.wire(mark) == [p.PwmSetOffset(1, 25), p.PwmRead(p.PwmSub.READ_OFFSET, 1)]


def test_o3_motor_ids_1_to_4_are_wire_ids_0_to_3(rig):
    mark = rig.mark()
    assert rig.core.set_motor_speeds([1, 4], [0.5, -6.0]).ok
    assert rig.wire(mark) == [p.SetMotorSpeeds(1, ((0, 0.5), (3, -6.0)))]


def test_o10_pwm_servos_move_in_one_multi_frame(rig):
    mark = rig.mark()
    assert rig.core.set_pwm_servos([3], [900], 0.02).ok
    assert rig.core.set_pwm_servos([1, 2], [500, 2500], 1.5).ok
    assert rig.wire(mark) == [p.PwmMove(1, 20, ((3, 900),)),
                              p.PwmMove(1, 1500, ((1, 500), (2, 2500)))]


def test_o49_bus_servo_moves_are_split_into_frames_that_fit(rig):
    mark = rig.mark()
    ids = list(range(100))
    assert rig.core.set_bus_servos(ids, [500] * 100, 1.0).ok

    def moves():
        return [m for m in rig.wire(mark) if isinstance(m, p.BusMove)]
    # Paced by the servo bus (issue 21 item 7): in several frames, each within 83 servos.
    wait_for(lambda: sum(len(m.items) for m in moves()) >= 100, 5, what='every target')
    assert all(1 <= len(m.items) <= 83 for m in moves())
    assert [i for m in moves() for i, _ in m.items] == ids


# ----- bus servo services (O6, O14, O24) --------------------------------------------------------

def test_o14_get_state_reads_everything_and_a_failed_servo_is_never_a_value(rig):
    with rig.board.locked():
        rig.model.bus_servo(1).temperature_c = 40
        rig.model.bus_servo(1).offset = -3
    result = rig.core.get_bus_servo_state([1, 9])
    assert result.outcome is Outcome.FAILED
    assert 'servo 9' in result.message and 'servo 1' not in result.message  # names the failed
    one, nine = result.value
    assert (one.id, one.online, one.position, one.temperature_c, one.offset, one.max_position,
            one.min_voltage_v, one.max_temperature_c) == (1, True, 500, 40.0, -3, 1000, 4.5,
                                                          85.0)
    assert one.position_rad == 0.0 and one.voltage_v == pytest.approx(7.4)
    assert (nine.id, nine.online) == (9, False) and math.isnan(nine.voltage_v)
    assert rig.core.get_bus_servo_state([2, 3]).ok


def test_o6_torque_on_sends_0x0c_and_is_read_back(rig):
    mark = rig.mark()
    assert rig.core.set_bus_servo_torque([1, 2], True).ok
    assert rig.model.bus_servo(1).loaded and rig.model.bus_servo(2).loaded
    result = rig.core.set_bus_servo_torque([2, 9], False)
    assert result.outcome is Outcome.FAILED  # servo 9 answers its read with a failure (O14)
    assert 'servo 9' in result.message and '[2]' in result.message  # who did and who did not
    torque = [c for c in rig.wire(mark) if isinstance(c, p.BusTorque)]
    assert torque == [p.BusTorque(1, True), p.BusTorque(2, True), p.BusTorque(2, False),
                      p.BusTorque(9, False)]


def test_o44_set_id_is_refused_when_the_new_id_answers_and_renames_the_polled_servo(make_rig):
    r = make_rig(bus_servo_ids=(1, 2))
    r.online()
    mark = r.mark()
    result = r.core.set_bus_servo_id(1, 2)
    assert (result.outcome, result.cause) == (Outcome.REFUSED, 'id_taken')
    assert not any(isinstance(c, p.BusWriteId) for c in r.wire(mark))
    # Nobody at 7: nothing written.
    assert r.core.set_bus_servo_id(7, 8).outcome is Outcome.REFUSED
    assert not any(isinstance(c, p.BusWriteId) for c in r.wire(mark))
    assert r.core.set_bus_servo_id(1, 12).ok
    assert [s.servo_id for s in r.model.bus_servos] == [12, 2, 3]
    assert r.core.bus_servo_ids == [12, 2]


def test_o48_offset_and_limits_are_written_and_read_back(rig):
    result = rig.core.set_bus_servo_offset(3, -60, True)
    assert result.ok and 'saved' in result.message
    assert rig.model.bus_servo(3).saved_offset == -60
    mark = rig.mark()
    assert rig.core.set_bus_servo_limits(3, 100, 900, 0, 0, 70).ok
    servo = rig.model.bus_servo(3)
    assert (servo.angle_limits, servo.voltage_limits, servo.temperature_limit_c) == \
        ((100, 900), (4500, 14000), 70)
    assert not any(isinstance(c, p.BusSetLimits) and c.sub == BusSub.SET_VOLTAGE_LIMITS
                   for c in rig.wire(mark))
    result = rig.core.set_bus_servo_limits(3, 0, 0, 0, 0, 0)
    assert result.outcome is Outcome.DONE and 'nothing to change' in result.message
    assert rig.core.set_bus_servo_limits(9, 0, 0, 5000, 9000, 0).outcome is Outcome.FAILED


def test_o43_pwm_state_of_every_servo_and_offset(rig):
    assert rig.core.set_pwm_servo_offset(2, 40).ok
    rig.core.set_pwm_servos([2], [2000], 0.02)
    wait_for(lambda: rig.core.get_pwm_servo_state([2]).value.pulses_us == (2000,), 5,
             what='PWM servo 2 at 2000 us')
    result = rig.core.get_pwm_servo_state([])
    assert result.outcome is Outcome.DONE
    assert result.value == PwmServoStates((1500, 2000, 1500, 1500), (0, 40, 0, 0))


# ----- bus servo polling ------------------------------------------------------------------------

def bus_reads(r, mark, servo_id, sub=BusSub.READ_POSITION):
    return sum(1 for c in r.wire(mark) if c == p.BusRead(sub, servo_id))


def test_polling_reads_positions_at_the_rate_and_telemetry_every_period(make_rig):
    r = make_rig(bus_servo_ids=(1, 2), bus_servo_poll_hz=10.0,
                 bus_servo_telemetry_period_s=2.0)
    mark = r.mark()
    r.online()  # the first poll: positions and telemetry
    with r.board.locked():
        r.model.bus_servo(2).set_by_hand(750, r.model.now)
    for _ in range(10):
        r.clock.advance(0.1)
        r.core.poll()
        r.core.poll()  # nothing more is due at the same time
    assert bus_reads(r, mark, 1) == bus_reads(r, mark, 2) == 11
    assert bus_reads(r, mark, 1, BusSub.READ_VOLTAGE) == 1
    r.clock.advance(1.0)
    r.core.poll()
    assert bus_reads(r, mark, 2, BusSub.READ_TEMPERATURE) == 2
    states = r.events['states'][-1]
    assert [(s.id, s.online, s.position) for s in states] == [(1, True, 500), (2, True, 750)]
    assert states[1].position_rad == pytest.approx(math.radians(250 * 0.24))
    assert states[0].voltage_v == pytest.approx(7.4) and states[0].temperature_c == 30.0
    assert r.core.snapshot().bus_servos == tuple(states)


def test_o43_get_state_without_ids_reads_every_polled_servo(make_rig):
    r = make_rig(bus_servo_ids=(3, 1), bus_servo_poll_hz=0.0)
    r.online()
    result = r.core.get_bus_servo_state([])
    assert result.ok and [s.id for s in result.value] == [3, 1]
    assert all(s.online and s.max_temperature_c == 85.0 for s in result.value)


def test_o42_a_missing_servo_goes_offline_and_is_reprobed_once_a_second(make_rig):
    r = make_rig(bus_servo_ids=(1, 9), bus_servo_poll_hz=10.0)
    r.online()
    for _ in range(2):
        r.clock.advance(0.1)
        r.core.poll()
    states = r.events['states'][-1]
    assert [(s.id, s.online, s.failed_reads) for s in states] == [(1, True, 0), (9, False, 3)]
    assert 'no valid answer' in states[1].last_error
    mark = r.mark()
    for _ in range(10):
        r.clock.advance(0.1)
        r.core.poll()
    assert bus_reads(r, mark, 9) == 1 and bus_reads(r, mark, 1) == 10
    with r.board.locked():
        r.model.add_bus_servo(9)
    for _ in range(10):
        r.clock.advance(0.1)
        r.core.poll()
    assert r.events['states'][-1][1].online


def test_servos_are_offline_while_the_board_is(make_rig):
    r = make_rig(bus_servo_ids=(1,))
    r.online()
    assert r.events['states'][-1][0].online
    r.silence()
    r.clock.advance(3.0)
    r.core.poll()
    assert not r.events['states'][-1][0].online


# ----- reports in SI units (O7, O9, O15, O16, O17) ---------------------------------------------

def test_o7_imu_in_si_units(rig):
    with rig.board.locked():
        rig.model.set_imu(accel_g=(0.0, -0.5, 1.0), gyro_dps=(180.0, 0.0, -90.0))
    wait_for(lambda: rig.events['imu'] and rig.events['imu'][-1].report.gyro_dps[0] == 180.0,
             5, what='the new IMU sample')
    sample = rig.events['imu'][-1]
    assert sample.linear_acceleration == pytest.approx((0.0, -0.5 * STANDARD_GRAVITY,
                                                        STANDARD_GRAVITY))
    assert sample.angular_velocity == pytest.approx((math.pi, 0.0, -math.pi / 2))
    assert sample.received_at == rig.clock()


def test_o9_battery_in_volts_with_the_warning_threshold(make_rig):
    r = make_rig(low_battery_mv=7000, board_kwargs={'battery_period_s': 0.05,
                                                    'battery_mv': 6900})
    wait_for(lambda: r.events['battery'], 5, what='a battery report')
    sample = r.events['battery'][-1]
    assert (sample.voltage_v, sample.millivolts, sample.low) == (6.9, 6900, True)
    snap = r.core.snapshot()
    assert snap.battery_mv == 6900 and snap.battery_low and snap.battery_warn_mv == 7000


def test_o17_buttons_o16_sbus_o15_gamepad_and_asr(rig):
    with rig.board.locked():
        rig.model.press_key(1, 'click')
        rig.model.set_sbus([172, 992, 1812] + [992] * 13, ch18=True)
        rig.model.send_gamepad(buttons=0x8001, hat=13, lx=127, ly=-128, ry=64)
        rig.model.send_asr(b'\xbb\xcc\x07\x08\x09')
    wait_for(lambda: len(rig.events['button']) == 3 and rig.events['sbus'] and
             rig.events['gamepad'] and rig.events['asr'], 5, what='every kind of report')
    assert [b.event_name for b in rig.events['button']] == [
        'pressed', 'release_from_short_press', 'click']
    sbus = rig.events['sbus'][0]
    assert sbus.normalized[:3] == pytest.approx(((172 - 992) / 820, 0.0, 1.0))
    assert sbus.ch18 and not sbus.signal_loss
    pad = rig.events['gamepad'][0]
    assert pad.axes == pytest.approx((1.0, -1.0, 0.0, 64 / 127, -1.0, 0.0))
    assert pad.buttons == (1,) + (0,) * 14 + (1,)
    assert rig.events['asr'][0].data == b'\xbb\xcc\x07\x08\x09'
    assert rig.core.snapshot().reports['button'] == 3


# ----- configuration ----------------------------------------------------------------------------

@pytest.mark.parametrize('field, value, words', [
    ('motor_type', 'JGB999', 'motor_type'),
    ('low_battery_mv', -2, 'low_battery_mv'),
    ('pwm_servo_offsets_us', (0, 0, 0, 0, 0), 'pwm_servo_offsets_us'),
    ('pwm_servo_offsets_us', (101,), 'pwm_servo_offsets_us'),
    ('bus_servo_ids', (1, 1), 'twice'),
    ('bus_servo_ids', (254,), 'bus_servo_ids'),
    ('offline_timeout_s', 0.0, 'offline_timeout_s'),
    ('motor_timeout_s', math.nan, 'motor_timeout_s'),
    ('bus_servo_poll_hz', -1.0, 'bus_servo_poll_hz'),
])
def test_a_bad_configuration_is_refused_by_name(field, value, words):
    with pytest.raises(ConfigError, match=words):
        OriginManCore(OriginManConfig(**{field: value}))


def test_o20_the_defaults_are_the_contracts():
    config = OriginManConfig().validated()
    assert (config.port, config.baud, config.offline_timeout_s, config.low_battery_mv,
            config.motor_type, config.motor_timeout_s, config.bus_servo_poll_hz,
            config.bus_servo_telemetry_period_s) == ('/dev/ttyS1', 1_000_000, 2.5, -1, 'keep',
                                                     0.5, 10.0, 2.0)
