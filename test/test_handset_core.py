"""The handset link core: with a fake clock against the model, then on a real pty."""

import math
import subprocess
import sys
import threading
import time

import pytest

from handset_link_ros import protocol as p
from handset_link_ros.core import (ACTION_NONE, ACTION_RETURN_TO_HOME, HandsetConfig,
                                   HandsetCore)
from handset_link_ros.simulation import VirtualHandset
from support import FakeClock
from uav_serial_common.process import wait_for
from uav_serial_common.virtual_device import VirtualDeviceRunner

T = p.CommandType
START = 1000.0


class Recorder:
    """Everything the core reported, in order, from whichever thread."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.setpoints, self.auxiliary, self.links, self.failsafes, self.logs = [], [], [], [], []

    def callbacks(self) -> dict:
        return dict(on_setpoint=self._add(self.setpoints), on_auxiliary=self._add(self.auxiliary),
                    on_link=self._add(self.links), on_failsafe=self._add(self.failsafes),
                    on_log=lambda level, text: self._add(self.logs)((level, text)))

    def _add(self, target: list):
        def add(item) -> None:
            with self.lock:
                target.append(item)
        return add

    def logs_at(self, level: str) -> list:
        with self.lock:
            return [text for lvl, text in self.logs if lvl == level]


class Rig:
    """A core without threads, fed by the handset model on one fake clock."""

    def __init__(self, **config) -> None:
        self.clock = FakeClock(START)
        self.seen = Recorder()
        config.setdefault('port', 'loop://')
        self.core = HandsetCore(HandsetConfig(**config), clock=self.clock,
                                **self.seen.callbacks())
        self.core.start(run_threads=False)
        self.sim = VirtualHandset(now=self.clock.t)

    def run(self, seconds: float, step: float = 0.01) -> None:
        """Let time pass: the model's bytes are read every `step`, timers polled each time."""
        base = self.clock.t
        for i in range(1, round(seconds / step) + 1):
            self.clock.t = base + i * step  # no drift from summing steps
            data = self.sim.step(self.clock.t)
            if data:
                self.core.feed(data)
            self.core.poll()

    def feed(self, data: bytes) -> None:
        self.core.feed(data)

    def wait(self, seconds: float) -> None:
        """Let time pass with a silent line."""
        self.clock.t += seconds
        self.core.poll()


@pytest.fixture
def rig():
    return Rig()


# ---------------------------------------------------------------------------------------------
# Start-up, H8 link loss
# ---------------------------------------------------------------------------------------------

def test_h15_start_up_reports_the_failsafe_and_the_link_once(rig):
    assert len(rig.seen.failsafes) == 1 and len(rig.seen.links) == 1
    failsafe = rig.seen.failsafes[0]
    assert (failsafe.link_lost, failsafe.battery_low, failsafe.action) == \
        (False, False, ACTION_NONE)
    assert 'waiting for the handset' in failsafe.reason
    link = rig.seen.links[0]
    assert not link.connected and math.isnan(link.last_frame_age_s)
    setpoint = rig.core.setpoint()
    assert all(math.isnan(v) for v in (setpoint.yaw_deg, setpoint.pitch_deg, setpoint.roll_deg,
                                       setpoint.altitude_m))
    aux = rig.core.auxiliary()
    assert aux.lights_percent == -1 and math.isnan(aux.camera_angle_deg)
    assert not aux.camera_recording_known


def test_h8_a_handset_never_heard_is_a_lost_link_after_the_timeout_from_start_up(rig):
    rig.wait(4.99)
    assert not rig.core.failsafe().link_lost and len(rig.seen.failsafes) == 1
    rig.wait(0.01)
    failsafe = rig.seen.failsafes[-1]
    assert failsafe.link_lost and failsafe.action == ACTION_RETURN_TO_HOME
    assert 'since start-up' in failsafe.reason
    assert any('handset link lost' in t for t in rig.seen.logs_at('ERROR'))
    rig.wait(10.0)
    assert len(rig.seen.failsafes) == 2  # reported on change only


def test_h8_link_lost_after_the_timeout_since_the_last_valid_frame_and_regained(rig):
    rig.run(1.0)
    assert rig.core.link_state().connected
    rig.sim.set_radio_link(False)
    last = rig.core.link_state().stamp
    rig.run(4.9)
    assert not rig.core.failsafe().link_lost
    rig.run(0.2)
    lost = rig.seen.failsafes[-1]
    assert lost.link_lost and lost.action == ACTION_RETURN_TO_HOME
    assert lost.stamp - last == pytest.approx(5.0, abs=0.011)
    assert not rig.seen.links[-1].connected
    rig.sim.set_radio_link(True)
    rig.run(0.01)
    regained = rig.seen.failsafes[-1]
    assert not regained.link_lost and regained.action == ACTION_NONE
    assert rig.seen.links[-1].connected
    regained_log = [t for t in rig.seen.logs_at('WARN') if 'regained' in t]
    assert len(regained_log) == 1 and 'failsafe now NONE' in regained_log[0]


def test_h14_h8_frames_the_driver_refuses_do_not_keep_the_link(rig):
    rig.run(0.5)
    rig.sim.set_radio_link(False)
    refused = p.encode_command(T.SET_YAW, 500, check=False) + p.build_frame(0x0B, b'\x00')
    for _ in range(60):
        rig.feed(refused + b'\xaa\x03\x01\x00\x00\x00')
        rig.wait(0.1)
    assert rig.core.failsafe().link_lost
    assert rig.core.link_state().frames_out_of_range == 60


def test_h8_the_timeout_is_the_configured_one():
    rig = Rig(link_timeout_s=0.5)
    rig.wait(0.49)
    assert not rig.core.failsafe().link_lost
    rig.wait(0.01)
    assert rig.core.failsafe().link_lost


# ---------------------------------------------------------------------------------------------
# H9 battery
# ---------------------------------------------------------------------------------------------

def test_h20_h9_low_below_20_percent_clears_at_25(rig):
    core = rig.core
    for level, low in [(0.5, False), (0.20, False), (0.199, True), (0.15, True), (0.249, True),
                       (0.25, False), (0.21, False), (0.19, True)]:
        core.on_battery(level)
        assert core.failsafe().battery_low is low, level
        assert core.failsafe().battery_fraction == level
    assert [f.battery_low for f in rig.seen.failsafes[1:]] == [True, False, True]
    assert rig.seen.failsafes[-1].action == ACTION_RETURN_TO_HOME
    assert 'battery low: 19.0 % < 20 %' in rig.seen.failsafes[-1].reason
    # H19, H24: every change is logged at WARN with its reason, the clearing included.
    warnings = rig.seen.logs_at('WARN')
    assert len(warnings) == 3 and 'cleared' in warnings[1] and 'failsafe now NONE' in warnings[1]


def test_h9_nan_says_nothing_about_the_battery(rig):
    rig.core.on_battery(0.1)
    rig.core.on_battery(math.nan)
    state = rig.core.failsafe()
    assert state.battery_low and state.battery_fraction == 0.1
    assert len(rig.seen.failsafes) == 2


def test_h9_outside_0_to_1_says_nothing_and_is_logged_once(rig):
    rig.core.on_battery(0.5)
    for level in (1.5, -0.1, 42.0):
        rig.core.on_battery(level)
    state = rig.core.failsafe()
    assert not state.battery_low and state.battery_fraction == 0.5
    warnings = [t for t in rig.seen.logs_at('WARN') if 'outside 0..1' in t]
    assert len(warnings) == 1 and '1.5' in warnings[0]
    assert rig.core.battery_out_of_range == 3


def test_h9_the_threshold_is_configurable():
    rig = Rig(low_battery_fraction=0.3)
    rig.core.on_battery(0.29)
    assert rig.core.failsafe().battery_low
    rig.core.on_battery(0.34)
    assert rig.core.failsafe().battery_low
    rig.core.on_battery(0.35)
    assert not rig.core.failsafe().battery_low


def test_h25_reconfigure_applies_the_rules_to_the_new_values_at_once(rig):
    rig.run(0.5)
    rig.sim.set_radio_link(False)
    rig.wait(1.0)
    assert not rig.core.failsafe().link_lost
    rig.core.reconfigure(link_timeout_s=0.5)
    assert rig.seen.failsafes[-1].link_lost
    rig.core.on_battery(0.22)
    assert not rig.core.failsafe().battery_low
    rig.core.reconfigure(low_battery_fraction=0.25)
    assert rig.seen.failsafes[-1].battery_low
    with pytest.raises(ValueError, match='low_battery_fraction'):
        rig.core.reconfigure(low_battery_fraction=2.0)
    with pytest.raises(ValueError, match='port'):
        rig.core.reconfigure(port='/dev/ttyUSB9')
    assert (rig.core.config.low_battery_fraction, rig.core.config.port) == (0.25, 'loop://')


def test_h10_return_to_home_is_requested_while_either_condition_holds(rig):
    rig.core.on_battery(0.1)
    rig.wait(5.0)
    state = rig.core.failsafe()
    assert state.link_lost and state.battery_low and state.action == ACTION_RETURN_TO_HOME
    assert 'link lost' in state.reason and 'battery low' in state.reason
    rig.core.on_battery(0.9)
    assert rig.core.failsafe().action == ACTION_RETURN_TO_HOME
    rig.run(0.02)
    assert rig.core.failsafe().action == ACTION_NONE
    assert [f.action for f in rig.seen.failsafes] == [
        ACTION_NONE, ACTION_RETURN_TO_HOME, ACTION_RETURN_TO_HOME, ACTION_RETURN_TO_HOME,
        ACTION_NONE]


# ---------------------------------------------------------------------------------------------
# Setpoints and auxiliary state
# ---------------------------------------------------------------------------------------------

def test_h7_setpoints_are_delivered_by_the_read_that_completes_them(rig):
    frame = p.encode_set_yaw(-170.5)
    rig.feed(frame[:-1])
    assert rig.seen.setpoints == []  # one byte short...
    rig.feed(frame[-1:])
    # ...and the last byte delivers it, within that read: no timer, no following frame.
    assert [(s.updated, s.yaw_deg) for s in rig.seen.setpoints] == [(('yaw_deg',), -170.5)]
    rig.feed(p.encode_set_pitch(10, 'int8') + p.encode_set_roll(-20, 'int16')
             + p.encode_set_altitude(42, 'float32'))
    setpoint = rig.seen.setpoints[-1]
    assert (setpoint.yaw_deg, setpoint.pitch_deg, setpoint.roll_deg, setpoint.altitude_m) == \
        (-170.5, 10.0, -20.0, 42.0)


def test_h16_frames_read_together_share_one_setpoint_naming_what_they_set(rig):
    rig.feed(p.encode_set_yaw(10) + p.encode_set_altitude(5))
    assert len(rig.seen.setpoints) == 1
    setpoint = rig.seen.setpoints[0]
    assert setpoint.updated == ('yaw_deg', 'altitude_m')
    assert setpoint.yaw_deg == 10.0 and math.isnan(setpoint.pitch_deg)


def test_h16_every_accepted_stick_frame_gets_a_setpoint_of_its_own_value(rig):
    # Two ticks in one read: the same field twice, so two updates (no value is lost), and a
    # repeated unchanged value is delivered too.
    rig.feed(p.encode_set_yaw(10) + p.encode_set_pitch(1) + p.encode_set_yaw(11)
             + p.encode_set_yaw(11, 'int8'))
    assert [(s.updated, s.yaw_deg) for s in rig.seen.setpoints] == [
        (('yaw_deg', 'pitch_deg'), 10.0), (('yaw_deg',), 11.0), (('yaw_deg',), 11.0)]


def test_a_ticking_handset_gives_one_setpoint_per_tick(rig):
    rig.feed(rig.sim.step(rig.clock.t))
    rig.run(1.0, step=0.02)
    assert rig.sim.ticks == 51 and len(rig.seen.setpoints) == 51
    assert all(s.updated == ('yaw_deg', 'pitch_deg', 'roll_deg', 'altitude_m')
               for s in rig.seen.setpoints)


def test_h16_h7_the_stamp_is_the_arrival_of_the_frame_last_byte(rig):
    rig.feed(p.encode_set_yaw(1) + b'\x00' * 115)  # 115 bytes after it: 10 ms at 115200 baud
    assert rig.seen.setpoints[0].stamp == pytest.approx(START - 0.00998, abs=1e-4)


def test_h17_auxiliary_is_reported_on_change_only(rig):
    rig.run(0.1)
    assert len(rig.seen.auxiliary) == 1
    first = rig.seen.auxiliary[0]
    assert (first.lights_percent, first.camera_angle_deg, first.camera_recording,
            first.camera_recording_known) == (0, 0.0, False, True)
    assert set(first.updated) == {'lights_percent', 'camera_angle_deg', 'camera_recording'}
    rig.run(2.0)  # the periodic repeats change nothing
    assert len(rig.seen.auxiliary) == 1
    rig.sim.set_lights(75)
    rig.run(0.05)
    assert len(rig.seen.auxiliary) == 2
    assert rig.seen.auxiliary[-1].updated == ('lights_percent',)
    assert rig.core.auxiliary().lights_percent == 75
    rig.sim.set_camera_recording(True)
    rig.run(0.05)
    assert rig.seen.auxiliary[-1].camera_recording is True


def test_every_encoding_reaches_the_setpoint():
    for encoding in p.ENCODINGS:
        rig = Rig()
        rig.sim.set_encoding(encoding)
        rig.sim.set_sticks(yaw_deg=-100.0, altitude_m=120.0)
        rig.run(0.02)
        assert (rig.core.setpoint().yaw_deg, rig.core.setpoint().altitude_m) == (-100.0, 120.0)


# ---------------------------------------------------------------------------------------------
# Rejections (H3, H4, H6), rates, age
# ---------------------------------------------------------------------------------------------

def test_h19_h6_refused_frames_are_counted_and_logged_once_per_type_per_second(rig):
    for _ in range(10):
        rig.feed(p.encode_command(T.SET_YAW, 200, check=False))
        rig.feed(p.encode_command(T.SET_LIGHTS, 5.5, 'float32', check=False))
        rig.wait(0.05)
    warnings = rig.seen.logs_at('WARN')
    assert len(warnings) == 2
    assert 'SET_YAW' in warnings[0] and 'yaw 200 is out of range' in warnings[0]
    assert 'SET_LIGHTS' in warnings[1] and 'not a whole number' in warnings[1]
    rig.wait(0.6)
    rig.feed(p.encode_command(T.SET_YAW, -181, check=False))
    assert '(9 more like it since the last report)' in rig.seen.logs_at('WARN')[-1]
    state = rig.core.link_state()
    assert state.frames_out_of_range == 21 and state.frames_accepted == 0
    assert rig.seen.setpoints == [] and math.isnan(rig.core.setpoint().yaw_deg)


def test_h3_malformed_and_unknown_frames_are_counted_and_ignored(rig):
    rig.feed(b'\x00\xff' + p.build_frame(0x42, b'xyz') + b'\xaa\x03\x01\x5a\x00\x55')
    rig.feed(p.build_frame(T.SET_YAW, b'{"yaw": NaN}'))
    rig.feed(p.build_frame(0x42, b''))
    state = rig.core.link_state()
    assert (state.frames_malformed, state.frames_unknown_type, state.frames_accepted) == (2, 2, 0)
    assert state.frames_rejected_recently == 4
    assert len([t for t in rig.seen.logs_at('WARN') if 'unknown type 0x42' in t]) == 1
    rig.wait(1.0)
    assert rig.core.link_state().frames_rejected_recently == 0


def test_h3_a_partial_frame_is_settled_after_0_1_s_of_silence(rig):
    rig.feed(p.encode_set_yaw(5)[:6])
    rig.wait(0.09)
    assert rig.core.link_state().frames_malformed == 0
    rig.wait(0.01)
    assert rig.core.link_state().frames_malformed == 1
    assert 'silence' in rig.seen.logs_at('WARN')[-1]


def test_h18_rates_are_measured_over_the_last_second(rig):
    rig.run(3.0)
    state = rig.core.link_state()
    assert state.command_rate_hz == pytest.approx(50.0, abs=1.0)
    # Four stick frames per tick, the three auxiliary ones once a second.
    assert state.frame_rate_hz == pytest.approx(203.0, abs=4.0)
    rig.sim.set_rate(20.0)
    rig.run(2.0)
    assert rig.core.link_state().command_rate_hz == pytest.approx(20.0, abs=1.0)
    rig.sim.set_radio_link(False)
    rig.run(1.1)
    state = rig.core.link_state()
    assert (state.command_rate_hz, state.frame_rate_hz) == (0.0, 0.0)
    assert state.connected  # 1.1 s of silence is no lost link yet
    assert state.last_frame_age_s == pytest.approx(1.1, abs=0.06)


def test_a_callback_that_raises_is_logged_and_the_link_goes_on():
    def broken(setpoint):
        raise RuntimeError('consumer bug')

    logs = []
    core = HandsetCore(HandsetConfig(port='loop://'), clock=FakeClock(START), on_setpoint=broken,
                       on_log=lambda level, text: logs.append((level, text)))
    core.start(run_threads=False)
    core.feed(p.encode_set_yaw(1) + p.encode_set_yaw(2))
    assert sum('consumer bug' in text for level, text in logs if level == 'ERROR') == 2
    assert core.link_state().frames_accepted == 2 and core.setpoint().yaw_deg == 2.0


@pytest.mark.parametrize('bad', [dict(link_timeout_s=0), dict(expected_rate_hz=-1),
                                 dict(low_battery_fraction=0.99), dict(baud=0), dict(port=''),
                                 dict(link_timeout_s=math.nan)])
def test_config_refuses_bad_values(bad):
    with pytest.raises(ValueError):
        HandsetConfig(**bad)


def test_the_core_does_not_import_rclpy():
    code = ('import sys, handset_link_ros.core, handset_link_ros.simulation; '
            'sys.exit("rclpy" in sys.modules)')
    assert subprocess.run([sys.executable, '-c', code]).returncode == 0


# ---------------------------------------------------------------------------------------------
# On a real pty, through the virtual-device runner
# ---------------------------------------------------------------------------------------------

def create_runner(sim: VirtualHandset, path: str) -> VirtualDeviceRunner:
    return VirtualDeviceRunner(path, on_input=sim.receive, on_tick=sim.step,
                               next_event=sim.next_event_time, baud=115200)


@pytest.fixture
def pty_rig(tmp_path):
    sim = VirtualHandset(now=time.monotonic())
    runner = create_runner(sim, str(tmp_path / 'vhandset')).start()
    seen = Recorder()
    made = []

    def make(**config) -> HandsetCore:
        core = HandsetCore(HandsetConfig(port=runner.path, **config), **seen.callbacks())
        made.append(core)
        core.start()
        return core

    yield sim, runner, seen, make
    for core in made:
        core.stop()
    runner.stop()


def test_h21_h11_pty_setpoints_follow_the_handset_and_survive_an_unplug(pty_rig):
    sim, runner, seen, make = pty_rig
    core = make()
    with runner.locked():
        sim.set_sticks(yaw_deg=33.0)
    wait_for(lambda: core.setpoint().yaw_deg == 33.0, 3, what='the first setpoint')
    wait_for(lambda: core.link_state().command_rate_hz >= 45, 3, what='50 Hz ticks')
    before = len(seen.links)
    runner.unplug(duration_s=0.3)
    wait_for(lambda: any(not s.port_open for s in seen.links[before:]), 3,
             what='the port closing')
    wait_for(lambda: seen.links[-1].port_open, 5, what='the port reopening')
    with runner.locked():
        sim.set_sticks(yaw_deg=-44.0)
        sim.set_encoding('float32')
    wait_for(lambda: core.setpoint().yaw_deg == -44.0, 3, what='setpoints after the replug')
    assert not any(f.link_lost for f in seen.failsafes)
    # H11: the driver never wrote a byte to the handset's modem.
    assert runner.bytes_in == 0 and sim.bytes_ignored == 0


def test_pty_link_lost_with_the_radio_and_regained(pty_rig):
    sim, runner, seen, make = pty_rig
    core = make(link_timeout_s=0.5)
    wait_for(lambda: core.link_state().connected, 3, what='the handset heard')
    with runner.locked():
        sim.set_radio_link(False)
    wait_for(lambda: core.failsafe().link_lost, 3, what='the link lost')
    assert seen.failsafes[-1].action == ACTION_RETURN_TO_HOME
    with runner.locked():
        sim.set_radio_link(True)
    wait_for(lambda: not core.failsafe().link_lost, 3, what='the link regained')
    # Published on each change: not lost, lost, regained (a loaded host that stalls the
    # virtual handset past the timeout adds a loss and a regain of its own).
    lost = [f.link_lost for f in seen.failsafes]
    assert lost[0] is False and lost[-1] is False and True in lost, lost
    assert all(a != b for a, b in zip(lost, lost[1:])), lost


def test_pty_a_truncated_frame_and_silence_are_one_malformed_frame(pty_rig):
    sim, runner, seen, make = pty_rig
    with runner.locked():
        sim.set_radio_link(False)
    core = make()
    wait_for(lambda: core.link.port_open, 3, what='the port open')
    with runner.locked():
        sim.send_raw(p.encode_set_yaw(90)[:9])
    wait_for(lambda: core.link_state().frames_malformed == 1, 3, what='the partial settled')
    assert 'silence' in seen.logs_at('WARN')[-1]
    with runner.locked():
        sim.send_raw(p.encode_set_yaw(90))
    wait_for(lambda: core.setpoint().yaw_deg == 90.0, 3, what='the next frame whole')


# ---------------------------------------------------------------------------------------------
# Issue 21 item 8: the sticks judge the link; a battery reading that stops is unknown
# ---------------------------------------------------------------------------------------------

def _advance(rig: Rig, seconds: float) -> None:
    """Let time pass as the core's timer thread would: a poll at each of its deadlines."""
    end = rig.clock.t + seconds
    while (due := rig.core.next_deadline()) is not None and due <= end:
        rig.clock.t = max(rig.clock.t, due)
        rig.core.poll()
    rig.clock.t = end
    rig.core.poll()


def _quiet_for(rig: Rig, seconds: float, every: float, frames: bytes) -> None:
    """Let `seconds` pass with only `frames` arriving every `every` s (the model silent)."""
    end = rig.clock.t + seconds
    while rig.clock.t + every <= end + 1e-9:
        _advance(rig, every)
        rig.feed(frames)
    _advance(rig, end - rig.clock.t)


def test_round2_8_auxiliary_frames_do_not_keep_a_dead_stick_link(rig):
    rig.run(1.0)
    last_stick = rig.clock.t
    assert rig.core.link_state().connected
    rig.sim.set_radio_link(False)
    lights = p.encode_set_lights(40) + p.encode_set_camera_angle(10.0)
    _quiet_for(rig, 12.0, 1.0, lights)  # lights and camera at 1 Hz, no stick
    lost = [f for f in rig.seen.failsafes if f.link_lost]
    assert lost and lost[0].action == ACTION_RETURN_TO_HOME
    assert lost[0].stamp - last_stick == pytest.approx(5.0, abs=1e-6)
    assert rig.core.failsafe().link_lost and not rig.core.link_state().connected
    assert rig.core.auxiliary().lights_percent == 40  # the auxiliary frames were taken
    assert any('handset link lost' in t for t in rig.seen.logs_at('ERROR'))


def test_round2_8_a_valid_auxiliary_frame_every_4_s_is_a_lost_link():
    rig = Rig()
    _quiet_for(rig, 12.0, 4.0, p.encode_set_lights(10))
    assert rig.core.failsafe().link_lost
    assert rig.seen.failsafes[1].stamp == pytest.approx(START + 5.0)


def test_round2_8_each_stick_must_be_fresh_one_stale_stick_is_a_lost_link(rig):
    # Yaw, pitch and roll every 10 ms, the altitude not since the radio went: the aircraft would
    # fly an altitude nobody confirms.
    rig.run(1.0)
    last_altitude = rig.clock.t
    rig.sim.set_radio_link(False)
    three = p.encode_set_yaw(5.0) + p.encode_set_pitch(1.0) + p.encode_set_roll(2.0)
    _quiet_for(rig, 6.0, 0.01, three)
    lost = next(f for f in rig.seen.failsafes if f.link_lost)
    assert lost.stamp - last_altitude == pytest.approx(5.0, abs=1e-6)
    assert any('altitude_m' in t for t in rig.seen.logs_at('ERROR'))
    # The link comes back with the altitude, the four fresh again.
    rig.feed(p.encode_set_altitude(12.0))
    assert not rig.core.failsafe().link_lost and rig.core.link_state().connected


def test_round2_8_all_four_sticks_every_4_s_keep_the_link_of_a_5_s_timeout():
    rig = Rig()
    sticks = p.encode_set_yaw(1.0) + p.encode_set_pitch(1.0) + p.encode_set_roll(1.0) + \
        p.encode_set_altitude(3.0)
    _quiet_for(rig, 20.0, 4.0, sticks)
    assert [f.link_lost for f in rig.seen.failsafes] == [False]
    assert rig.core.link_state().stick_age_s == pytest.approx(0.0)


def test_round2_8_a_battery_reading_that_stops_is_unknown_after_battery_timeout_s():
    rig = Rig(battery_timeout_s=3.0)
    rig.run(0.5)
    rig.core.on_battery(0.5)
    rig.run(2.9)
    assert rig.core.failsafe().battery_fraction == 0.5
    rig.run(0.2)
    state = rig.core.failsafe()
    assert state.battery_stale and math.isnan(state.battery_fraction)
    assert state.action == ACTION_NONE  # unknown is no return to home by itself
    published = rig.seen.failsafes[-1]
    assert 'battery unknown' in published.reason and published.battery_stale
    assert any('battery unknown' in t for t in rig.seen.logs_at('WARN'))
    rig.core.on_battery(0.45)
    state = rig.core.failsafe()
    assert not state.battery_stale and state.battery_fraction == 0.45
    assert rig.seen.failsafes[-1].battery_fraction == 0.45
    # A low battery that goes silent stays low: only a reading clears it.
    rig.core.on_battery(0.1)
    rig.run(3.1)
    state = rig.core.failsafe()
    assert state.battery_low and state.battery_stale and state.action == ACTION_RETURN_TO_HOME
    assert math.isnan(state.battery_fraction)
    rig.core.on_battery(0.3)
    assert not rig.core.failsafe().battery_low


# ---------------------------------------------------------------------------------------------
# Issue 22 item 2: the H3 gap is a deadline of the core, and the reader wakes the timer by it
# ---------------------------------------------------------------------------------------------

STICKS = p.encode_set_yaw(1.0) + p.encode_set_pitch(1.0) + p.encode_set_roll(1.0) + \
    p.encode_set_altitude(3.0)


def test_round2_2_the_core_is_due_at_a_partial_frames_gap_counted_from_its_last_byte():
    rig = Rig(link_timeout_s=60.0)
    rig.feed(STICKS)
    link_due = rig.core.next_deadline()
    assert link_due == pytest.approx(START + 60.0)
    frame = p.encode_set_yaw(90)
    rig.wait(0.5)
    rig.feed(frame[:3])
    first = rig.clock.t
    assert rig.core.next_deadline() == pytest.approx(first + p.IDLE_TIMEOUT_S)
    rig.clock.t = first + 0.05
    rig.feed(frame[3:6])  # more of the same frame: the gap is counted from the last byte
    due = rig.core.next_deadline()
    assert due == pytest.approx(first + 0.05 + p.IDLE_TIMEOUT_S)
    rig.clock.t = first + p.IDLE_TIMEOUT_S  # the first bytes' gap: not quiet that long
    rig.core.poll()
    assert rig.core.link_state().frames_malformed == 0
    rig.clock.t = due  # the core's own deadline: a poll then settles it (H3)
    rig.core.poll()
    assert rig.core.link_state().frames_malformed == 1
    assert 'silence' in rig.seen.logs_at('WARN')[-1]
    assert rig.core.next_deadline() == pytest.approx(link_due)
    assert rig.core.link_state().frames_accepted == 4


def test_round2_2_each_read_that_holds_a_partial_frame_tells_when_it_is_due():
    """The reader's side of the wake, in virtual time: ``on_held`` gets the gap's deadline."""
    from handset_link_ros.link import ModemLink
    clock = FakeClock(START)
    held: list = []
    link = ModemLink('loop://', 115200, lambda batch: None, clock=clock, on_held=held.append)
    frame = p.encode_set_yaw(90)
    link.feed(frame[:3])
    assert held == [pytest.approx(START + p.IDLE_TIMEOUT_S)]
    clock.t += 0.05
    link.feed(frame[3:6])
    assert held[-1] == pytest.approx(START + 0.05 + p.IDLE_TIMEOUT_S)
    link.feed(frame[6:] + STICKS)  # whole frames hold nothing: no deadline to keep
    assert len(held) == 2


def test_round2_2_pty_a_partial_frame_is_settled_by_the_timer_the_reader_woke(
        pty_rig, monkeypatch):
    """The timer settles a partial frame at its gap because the read woke it, not by chance.

    The port is a pyserial URL (``spy://``, as a modem behind ``socket://`` or ``rfc2217://``
    would be): SerialLink reads it with pyserial's blocking read, which cannot wake at the
    gap, so only the core's timer settles the partial frame on time. The two backstops that
    would settle it eventually (the timer's longest sleep and the reader's read timeout, 0.5 s
    each) are made far longer than the wait: before the reader woke the timer, the partial was
    settled by whichever backstop came first, and here by none within the wait.
    """
    from handset_link_ros import core as core_module
    from handset_link_ros import link as link_module
    monkeypatch.setattr(core_module, 'MAX_TIMER_SLEEP_S', 600.0)
    monkeypatch.setattr(link_module, 'READ_TIMEOUT_S', 600.0)
    sim, runner, seen, _ = pty_rig
    with runner.locked():
        sim.set_radio_link(False)
    core = HandsetCore(HandsetConfig(port=f'spy://{runner.path}?file=/dev/null',
                                     link_timeout_s=600.0), **seen.callbacks())
    try:
        core.start()
        wait_for(lambda: core.link.port_open, 5, what='the port open')
        with runner.locked():
            sim.send_raw(p.encode_set_yaw(90)[:9])
        wait_for(lambda: core.link_state().frames_malformed == 1, 20,
                 what='the partial frame settled by the timer at its gap')
        assert 'silence' in seen.logs_at('WARN')[-1]
        with runner.locked():
            sim.send_raw(p.encode_set_yaw(90))
        wait_for(lambda: core.setpoint().yaw_deg == 90.0, 5, what='the next frame whole')
        assert core.link_state().frames_malformed == 1
    finally:
        core.stop()


def _core_with_a_long_timer_sleep(monkeypatch, seen: Recorder, **config) -> HandsetCore:
    """A started core whose timer's longest sleep is far longer than any wait of the test.

    Only a wake by the deadline an event set can then have the timer act within the wait
    (before, the timer acted at its next wake-up, up to MAX_TIMER_SLEEP_S = 0.5 s late).
    """
    from handset_link_ros import core as core_module
    monkeypatch.setattr(core_module, 'MAX_TIMER_SLEEP_S', 600.0)
    core = HandsetCore(HandsetConfig(port='loop://', **config), **seen.callbacks())
    core.start()
    core.feed(STICKS)  # as the reader would: the link is up
    wait_for(lambda: core.link_state().connected, 5, what='the link up')
    return core


def test_round2_2_a_battery_reading_wakes_the_timer_by_its_staleness_deadline(monkeypatch):
    seen = Recorder()
    core = _core_with_a_long_timer_sleep(monkeypatch, seen, link_timeout_s=600.0,
                                         battery_timeout_s=0.3)
    try:
        core.on_battery(0.5)
        wait_for(lambda: core.failsafe().battery_stale, 20, what='the battery reading stale')
        assert seen.failsafes[-1].battery_stale
        assert not core.failsafe().link_lost
    finally:
        core.stop()


def test_round2_2_a_shorter_link_timeout_wakes_the_timer_by_the_new_deadline(monkeypatch):
    seen = Recorder()
    core = _core_with_a_long_timer_sleep(monkeypatch, seen, link_timeout_s=600.0)
    try:
        core.reconfigure(link_timeout_s=0.3)  # H25: due 0.3 s after the sticks, not in 600 s
        wait_for(lambda: core.failsafe().link_lost, 20, what='the link lost at the new timeout')
        assert seen.failsafes[-1].link_lost
        assert seen.failsafes[-1].action == ACTION_RETURN_TO_HOME
    finally:
        core.stop()


def test_round2_2_the_rules_are_a_core_run_core_steps_each_step_ending_with_its_deadline():
    from handset_link_ros.rules import (BatteryReading, FailsafeChanged, HandsetRules,
                                        LinkChanged, Log, Reconfigured, Started, StickFrame)
    from uav_serial_common.core_events import SetTimer, Tick
    from uav_serial_common.core_runner import run_core
    rules = HandsetRules(link_timeout_s=5.0, low_battery_fraction=0.2, battery_timeout_s=10.0,
                         now=0.0)
    handlers = {kind: (lambda action: None)
                for kind in (Log, FailsafeChanged, LinkChanged, SetTimer)}

    def step(event) -> list:
        return run_core(rules, [event], handlers)

    assert step(Started(0.0)) == [SetTimer(5.0)]  # H15/H8: lost 5 s after start-up
    assert step(StickFrame(1.0, 'yaw_deg')) == [SetTimer(5.0)]  # three sticks never heard
    for name in ('pitch_deg', 'roll_deg'):
        step(StickFrame(1.0, name))
    done = step(StickFrame(1.0, 'altitude_m'))
    assert [type(a) for a in done] == [Log, LinkChanged, SetTimer]  # the link up
    assert done[-1] == SetTimer(6.0)
    assert step(BatteryReading(2.0, 0.5))[-1] == SetTimer(6.0)  # stale at 12 s: later
    assert step(Tick(5.99)) == [SetTimer(6.0)]
    done = step(Tick(6.0))
    assert [type(a) for a in done] == [Log, FailsafeChanged, LinkChanged, SetTimer]
    assert done[1].failsafe.action == ACTION_RETURN_TO_HOME
    assert done[-1] == SetTimer(12.0)  # the link lost: only the battery is due
    done = step(Reconfigured(7.0, battery_timeout_s=4.0))  # H25: stale at once
    assert [type(a) for a in done] == [Log, FailsafeChanged]  # nothing left to be due
    assert done[1].failsafe.battery_stale
    with pytest.raises(TypeError):
        rules.step(object())
