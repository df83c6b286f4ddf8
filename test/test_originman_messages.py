"""The OriginMan message builders and diagnostics fillers: pure functions, no node."""

import math

from builtin_interfaces.msg import Time
from originman_board_ros import messages as m
from originman_board_ros import protocol as p
from originman_board_ros.core import (AsrSample, BatterySample, BusServoStatus, gamepad_axes,
                                      gamepad_buttons, GamepadSample, ImuSample, imu_to_si,
                                      OriginManSnapshot, SbusSample, sbus_normalize)
import pytest
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu
from uav_serial_common.diagnostics import ERROR, OK, STALE, Status, WARN

STAMP = Time(sec=1700000000, nanosec=123456789)


def sample(accel=(0.1, -0.2, 1.0), gyro=(90.0, 0.0, -45.0)):
    report = p.ImuReport(accel, gyro)
    return ImuSample(0.0, *imu_to_si(report), report)


def test_o7_imu_message_is_si_with_unknown_orientation():
    msg = m.imu_msg(sample(), STAMP, 'imu_link')
    assert msg.header.stamp == STAMP and msg.header.frame_id == 'imu_link'
    assert msg.orientation_covariance[0] == -1.0
    assert msg.linear_acceleration.z == pytest.approx(9.80665)
    assert msg.angular_velocity.x == pytest.approx(math.pi / 2)
    assert list(msg.angular_velocity_covariance) == [0.0] * 9


@pytest.mark.parametrize('frame_id', ['', 'a', 'imu_link', 'abcdefg', 'imu_link_01', 'ñandú'])
def test_the_packed_imu_is_the_imu_message_serialized(frame_id):
    s = sample((0.5, 1e-3, -2.0), (1000.0, -0.001, 3.0))
    packer = m.ImuPacker('other')
    packer.set_frame_id(frame_id)
    got = deserialize_message(packer.pack(s, STAMP.sec, STAMP.nanosec), Imu)
    assert got == m.imu_msg(s, STAMP, frame_id)


def test_battery_is_volts_and_nan_where_not_measured():
    msg = m.battery_msg(BatterySample(0.0, 7.4, 7400, False), STAMP, 'board')
    assert msg.voltage == pytest.approx(7.4) and msg.present
    assert all(math.isnan(v) for v in (msg.current, msg.charge, msg.capacity,
                                       msg.design_capacity, msg.percentage, msg.temperature))


def test_o16_sbus_message_keeps_raw_and_normalized():
    raw = tuple([172, 992, 1811, 2047] + [992] * 12)
    msg = m.sbus_msg(SbusSample(0.0, raw, tuple(sbus_normalize(c) for c in raw), True, False,
                                False, True), STAMP, 'board')
    assert list(msg.channels) == list(raw) and msg.ch17 and msg.failsafe
    assert [round(float(v), 3) for v in msg.normalized[:4]] == [-1.0, 0.0, 0.999, 1.0]


def test_o15_joy_and_o2_asr_messages():
    report = p.GamepadReport(buttons=0b101, hat=9, lx=127, ly=-128, rx=0, ry=64)
    msg = m.joy_msg(GamepadSample(0.0, tuple(gamepad_axes(report)),
                                  tuple(gamepad_buttons(report)), report), STAMP, 'board')
    assert list(msg.axes) == pytest.approx([1.0, -1.0, 0.0, 64 / 127, 1.0, 0.0])
    assert list(msg.buttons) == [1, 0, 1] + [0] * 13
    assert list(m.asr_msg(AsrSample(0.0, b'\xbb\xcc\x01\x02\x03')).data) == [
        0xBB, 0xCC, 1, 2, 3]


def test_joint_states_hold_only_online_servos_named_bus_servo_id():
    statuses = [BusServoStatus(1, True, 800, math.radians(72.0)),
                BusServoStatus(2, False, 0),
                BusServoStatus(3, True, 500, 0.0)]
    msg = m.joint_states_msg(statuses, STAMP, 'board')
    assert msg.name == ['bus_servo_1', 'bus_servo_3']
    assert list(msg.position) == pytest.approx([math.radians(72.0), 0.0])
    assert m.joint_states_msg([BusServoStatus(2)], STAMP, 'board') is None
    array = m.bus_servo_states_msg(statuses, STAMP, 'board')
    assert [s.online for s in array.servos] == [True, False, True]


def test_o23_bus_servo_state_takes_positions_outside_0_1000():
    state = m.bus_servo_state(BusServoStatus(5, True, -40, failed_reads=2, last_error='x'))
    assert (state.position, state.failed_reads, state.error) == (-40, 2, 'x')
    assert math.isnan(state.voltage_v) and math.isnan(state.min_voltage_v)


def test_report_rates_over_a_window():
    rates = m.ReportRates(window_s=5.0)
    assert math.isnan(rates.update(0.0, {'imu': 0})['imu'])
    assert rates.update(1.0, {'imu': 50})['imu'] == pytest.approx(50.0)
    for t in range(2, 12):
        last = rates.update(float(t), {'imu': 100 * t - 50})
    assert last['imu'] == pytest.approx(100.0)


def snapshot(**changes):
    base = dict(port_open=True, online=True, status='frames arriving', port_error='',
                last_frame_age_s=0.01, battery_mv=7400, battery_low=False, battery_warn_mv=6300,
                frames_decoded=10, checksum_errors=0, bytes_discarded=0, unknown_functions=0,
                unknown_frames=0, unexpected_replies=0, reports={'imu': 5, 'battery': 1},
                reads=3, read_timeouts=0, read_failures=0, reconnects=0,
                refusals={'out_of_range': 2, 'offline': 1}, watchdog_stops=0, settings_ok=True,
                settings_message='no desired settings',
                bus_servos=(BusServoStatus(1, True, 500, 0.0),))
    base.update(changes)
    return OriginManSnapshot(**base)


def fill(task, *args):
    """Run a status task; return (level as its byte, message, values)."""
    stat = Status()
    task(stat, *args)
    return bytes([stat.level]), stat.message, dict(stat.values)


def test_link_status_is_error_offline_and_counts_refusals_by_cause():
    level, _, values = fill(m.link_status, snapshot(), {'imu': 50.0}, 1000000, 0)
    assert level == OK and values['refused commands'] == '3'
    assert values['refused: out_of_range'] == '2' and values['imu rate [Hz]'] == '50.0'
    level, message, _ = fill(m.link_status, snapshot(online=False, status='no frame'), {},
                             1000000, 0)
    assert level == ERROR and 'no frame' in message
    level, _, _ = fill(m.link_status, snapshot(settings_ok=False), {}, 1000000, 0)
    assert level == WARN


def test_battery_status_warns_below_the_threshold():
    assert fill(m.battery_status, snapshot())[0] == OK
    assert fill(m.battery_status, snapshot(battery_mv=6200, battery_low=True))[0] == WARN
    assert fill(m.battery_status, snapshot(battery_mv=None))[0] == STALE


def test_bus_servo_status_names_offline_servos():
    level, message, _ = fill(m.bus_servo_status, snapshot(bus_servos=(
        BusServoStatus(1, True, 500, 0.0), BusServoStatus(4, False, failed_reads=3))))
    assert level == WARN and '[4]' in message
    assert fill(m.bus_servo_status, snapshot(bus_servos=()))[0] == OK
