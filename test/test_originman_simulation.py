"""The OriginMan board model, driven through its wire protocol with a caller's clock."""

import struct

import pytest

from originman_board_ros import protocol as p
from originman_board_ros import simulation as s
from originman_board_ros.protocol import BusSub, KeyEvent
from originman_board_ros.simulation import VirtualOriginManBoardModel


def quiet(**kwargs) -> VirtualOriginManBoardModel:
    """A board without IMU stream and with a far battery report, to see replies alone."""
    kwargs.setdefault('imu_rate_hz', 0)
    kwargs.setdefault('battery_period_s', 1000.0)
    return VirtualOriginManBoardModel(0.0, **kwargs)


def decode(data: bytes) -> list:
    return [p.decode_board_frame(f) for f in p.StreamDecoder().feed(data)]


def run(sim, until: float, dt: float = 0.001) -> list:
    """Step to ``until`` in small steps; return (time, message) for everything sent."""
    out, dec = [], p.StreamDecoder()
    start = sim.now
    steps = max(1, round((until - start) / dt))
    for k in range(1, steps + 1):
        # Times from the grid, not summed, so a report due at a grid time is seen there.
        t = start + (until - start) * k / steps
        out += [(t, p.decode_board_frame(f)) for f in dec.feed(sim.step(t))]
    return out


def ask(sim, frame: bytes, wait: float = 0.01) -> list:
    """Send a frame now and return the messages the board sends within ``wait``."""
    now = sim.now
    got = decode(sim.receive(frame, now))
    return got + [m for _, m in run(sim, now + wait)]


# ----- reports ----------------------------------------------------------------------------------

def test_o8_imu_streams_at_the_set_rate_in_g_and_deg_per_s():
    sim = VirtualOriginManBoardModel(0.0, battery_period_s=1000.0)
    imu = [m for _, m in run(sim, 1.001, 0.001) if isinstance(m, p.ImuReport)]
    assert len(imu) == 50
    assert imu[0].accel_g == (0.0, 0.0, 1.0) and imu[0].gyro_dps == (0.0, 0.0, 0.0)
    sim.set_imu(accel_g=(0.5, 0, 0.8), gyro_dps=(0, 0, 45), rate_hz=100)
    imu = [m for _, m in run(sim, 2.0015, 0.0005) if isinstance(m, p.ImuReport)]
    assert len(imu) == 100 and imu[-1].accel_g == pytest.approx((0.5, 0, 0.8))
    sim.set_imu(rate_hz=0)
    assert run(sim, 3.0, 0.01) == []


def test_an_imu_source_gives_each_report_its_values():
    sim = VirtualOriginManBoardModel(0.0, imu_rate_hz=100.0, battery_period_s=1000.0)
    sim.set_imu_source(lambda t: ((0.0, 0.0, 1.0), (round(t * 1000), 0.0, 0.0)))
    reports = [(t, m) for t, m in run(sim, 0.1, 0.001) if isinstance(m, p.ImuReport)]
    # Each report carries the source's values at its own time: every 10 ms.
    assert [m.gyro_dps[0] for _, m in reports] == [10.0 * k for k in range(1, 11)]
    sim.set_imu_source(None)
    last = sim.gyro_dps
    assert all(m.gyro_dps == last for _, m in run(sim, 0.2) if isinstance(m, p.ImuReport))


def test_o9_battery_report_every_1_05_s_in_millivolts():
    sim = quiet(battery_period_s=s.BATTERY_PERIOD_S, battery_mv=7800)
    reports = [(t, m) for t, m in run(sim, 4.3, 0.001) if isinstance(m, p.BatteryReport)]
    assert [t for t, _ in reports] == pytest.approx([1.05, 2.1, 3.15, 4.2], abs=0.0011)
    assert {m.millivolts for _, m in reports} == {7800}


def test_o2_o15_o16_sbus_gamepad_and_asr_reports():
    sim = quiet()
    sim.set_sbus([992] * 16, signal_loss=True)
    frames = [m for _, m in run(sim, 0.1) if isinstance(m, p.SbusReport)]
    assert len(frames) == 8 and frames[0].signal_loss and frames[0].channels == (992,) * 16
    sim.set_sbus(None)
    sim.send_gamepad(buttons=0x0100, hat=9, lx=-128)
    sim.send_asr(b'\xbb\xcc\x01\x02\x03')
    got = [m for _, m in run(sim, 0.2)]
    assert [type(m) for m in got] == [p.GamepadReport, p.AsrReport]
    assert got[1].raw[2] == 12


# ----- keys (O17, O36, §8) ----------------------------------------------------------------------

def key_events(sim, until):
    return [m.event for _, m in run(sim, until, 0.005) if isinstance(m, p.KeyReport)]


E = KeyEvent


def test_o17_click_double_triple_and_long_press_sequences():
    sim = quiet()
    sim.press_key(1, 'click')
    assert key_events(sim, 1.0) == [E.PRESSED, E.RELEASE_FROM_SHORT_PRESS, E.CLICK]
    sim.press_key(2, 'double')
    assert key_events(sim, 2.0) == [E.PRESSED, E.RELEASE_FROM_SHORT_PRESS, E.CLICK,
                                    E.PRESSED, E.DOUBLE_CLICK, E.RELEASE_FROM_SHORT_PRESS,
                                    E.CLICK]
    sim.press_key(1, 'triple')
    assert key_events(sim, 3.0)[7:] == [E.PRESSED, E.TRIPLE_CLICK,
                                        E.RELEASE_FROM_SHORT_PRESS, E.CLICK]
    sim.press_key(1, 'long', hold_s=2.5)
    assert key_events(sim, 6.0) == [E.PRESSED, E.LONG_PRESS, E.LONG_PRESS_REPEAT,
                                    E.LONG_PRESS_REPEAT, E.RELEASE_FROM_LONG_PRESS]


def test_o17_long_press_timing_follows_the_30_ms_scan():
    sim = quiet()
    sim.press_key(1, 'down')
    events = [(t, m.event) for t, m in run(sim, 2.5, 0.005) if isinstance(m, p.KeyReport)]
    (t_press, _), (t_long, long_press), (t_repeat, repeat) = events[:3]
    assert (long_press, repeat) == (E.LONG_PRESS, E.LONG_PRESS_REPEAT)
    assert 1.5 < t_long - t_press <= 1.5 + 2 * s.KEY_SCAN_S
    assert 0.4 < t_repeat - t_long <= 0.4 + 2 * s.KEY_SCAN_S


def test_o36_the_multi_click_count_clears_after_the_window():
    sim = quiet()
    for _ in range(2):
        sim.press_key(1, 'triple')
        run(sim, sim.now + 1.5)
    sim.press_key(1, 'double')
    assert E.DOUBLE_CLICK in key_events(sim, sim.now + 1.0)


def test_every_click_makes_the_board_beep():
    sim = quiet()
    sim.press_key(2, 'double')
    run(sim, 1.0)
    assert [(b.source, b.frequency_hz, b.on_ms, b.off_ms, b.repeat) for b in sim.buzzer_log] \
        == [('click', 2000, 50, 50, 1)] * 2


def test_low_battery_alarm_uses_the_sys_threshold():
    sim = quiet(battery_mv=6000)
    run(sim, 9.9, 0.1)
    assert sim.low_battery_alarms == 0
    run(sim, 20.05, 0.1)
    assert sim.low_battery_alarms == 2
    assert {(b.source, b.frequency_hz, b.on_ms, b.off_ms, b.repeat) for b in sim.buzzer_log} \
        == {('low_battery', 2100, 800, 200, 5)}
    sim.receive(p.encode_battery_limit(5800), sim.now)
    run(sim, 40.0, 0.1)
    assert sim.low_battery_alarms == 2 and sim.battery_limit_mv == 5800
    sim.set_battery_mv(4800)  # below the floor: no alarm either
    sim.receive(p.encode_battery_limit(6300), sim.now)
    run(sim, 60.0, 0.1)
    assert sim.low_battery_alarms == 2


# ----- the parser (O21, O22, O33) ---------------------------------------------------------------

def test_o22_quirks_lose_frames_and_nothing_is_ever_answered():
    sim = quiet()
    read = p.encode_pwm_read_pulse(1)
    assert ask(sim, b'\xaa' + read) == []                        # AA AA 55 ...
    assert ask(sim, p.encode_frame(12, b'\x05\x01')) == []         # FUNCTION 12 dropped
    assert ask(sim, read[:-1] + bytes([read[-1] ^ 1])) == []       # bad CRC: no NAK
    assert ask(sim, read[:4] + read) == []                         # truncated swallows next
    assert sim.parser.checksum_errors == 2 and sim.parser.functions_dropped == 1
    assert sim.parser.idle
    assert ask(sim, read) == [p.PwmPulseReply(1, 1500, p.encode_pwm_pulse_reply(1, 1500))]


def test_o21_o33_short_frame_fields_read_the_crc_then_zeros():
    sim = quiet()
    frame = p.encode_frame(1, b'\x02')  # LED 2, no times: on_ms = CRC byte, off 0
    sim.receive(frame, 0.0)
    assert (sim.leds[2].on_ms, sim.leds[2].off_ms, sim.leds[2].repeat) == (frame[-1], 0, 0)
    sim.receive(p.encode_frame(1, struct.pack('<BHHH', 1, 100, 0, 0) + b'\x01\x02'), 0.0)
    assert sim.leds[1].on_ms == 100 and sim.leds[1].active_at(50.0)


def test_frames_to_report_functions_are_ignored():
    sim = quiet()
    for function in (6, 7, 8, 9):
        assert ask(sim, p.encode_frame(function, b'\x01\x01')) == []
    assert sim.commands_ignored == 4


# ----- motors (O3, O4, O5) ----------------------------------------------------------------------

def test_o3_motor_wire_ids_0_to_3_and_id_4_is_ignored_and_counted():
    sim = quiet()
    assert not sim.motors_initialized
    sim.receive(p.encode_motor_speeds([(0, 1.0), (3, -1.0)]), 0.0)
    assert sim.motors_initialized and sim.motor_set_points == [1.0, 0.0, 0.0, -1.0]
    sim.receive(p.encode_frame(3, b'\x00\x04' + struct.pack('<f', 1.0)), 0.0)
    sim.receive(p.encode_frame(3, b'\x02\x07'), 0.0)
    assert sim.bad_motor_ids == 2 and sim.motor_set_points == [1.0, 0.0, 0.0, -1.0]


def test_o4_stop_mask_and_single_stop():
    sim = quiet()
    sim.receive(p.encode_motor_speeds([(i, 1.0) for i in range(4)]), 0.0)
    sim.receive(p.encode_motor_stop_mask(0b0101), 0.0)
    assert sim.motor_set_points == [0.0, 1.0, 0.0, 1.0]
    sim.receive(p.encode_motor_stop(1), 0.0)
    assert sim.motor_set_points == [0.0, 0.0, 0.0, 1.0]


def test_o5_motor_type_clamps_the_speed_and_unknown_types_are_jgb520():
    sim = quiet()
    sim.receive(p.encode_motor_speed(0, 5.0), 0.0)
    assert sim.motor_speed(0) == 1.5
    sim.receive(p.encode_motor_type(p.MotorType.JGA27), 0.0)
    assert sim.motor_speed(0) == 5.0
    sim.receive(p.encode_frame(3, b'\x05\x09'), 0.0)
    assert sim.motor_type == p.MotorType.JGB520


# ----- PWM servos (O10, O11, O30) ---------------------------------------------------------------

def test_pwm_servo_moves_linearly_in_20_ms_steps_and_answers_reads():
    sim = quiet()
    sim.receive(p.encode_pwm_move(100, [(1, 2000)]), 0.0)
    pulses = [sim.pwm_servos[1].pulse_at(t / 1000) for t in (0, 10, 20, 40, 60, 80, 99, 100)]
    assert pulses == [1500, 1500, 1600, 1700, 1800, 1900, 1900, 2000]
    run(sim, 0.05)
    (reply,) = ask(sim, p.encode_pwm_read_pulse(1))
    assert reply.pulse_us == 1700


def test_pwm_clamps_offsets_and_the_output():
    sim = quiet()
    sim.receive(p.encode_frame(4, struct.pack('<BHBH', 3, 5, 2, 3000)), 0.0)
    sim.receive(p.encode_frame(4, struct.pack('<BBb', 7, 2, -128)), 0.0)
    run(sim, 0.1)
    assert sim.pwm_pulse(2) == 2500 and sim.pwm_servos[2].offset_us == -100
    assert sim.pwm_servos[2].output_at(sim.now) == 2400


def test_o11_offset_reply_and_o30_no_reply_for_id_0_or_5():
    sim = quiet()
    sim.receive(p.encode_pwm_set_offset(3, -12), 0.0)
    (reply,) = ask(sim, p.encode_pwm_read_offset(3))
    assert reply == p.PwmOffsetReply(3, -12, p.encode_pwm_offset_reply(3, -12))
    assert ask(sim, p.encode_frame(4, b'\x05\x00')) == []
    assert ask(sim, p.encode_frame(4, b'\x09\x05')) == []
    assert sim.bad_pwm_ids == 2


def test_o10_a_multi_servo_0x03_moves_only_the_first():
    sim = quiet()
    sim.receive(p.encode_frame(4, struct.pack('<BHBHBH', 3, 20, 1, 600, 3, 2400)), 0.0)
    run(sim, 0.1)
    assert (sim.pwm_pulse(1), sim.pwm_pulse(3)) == (600, 1500)


# ----- bus servos -------------------------------------------------------------------------------

def test_bus_read_is_answered_after_the_servo_and_an_absent_servo_fails_after_5_ms():
    sim = quiet()
    sim.receive(p.encode_bus_read_position(2), 0.0)
    ((t, reply),) = run(sim, 0.02, 0.0001)
    assert reply.ok and reply.value == 500
    assert t == pytest.approx(s._servo_bus_time(6) + s.SERVO_ANSWER_S, abs=2e-4)
    sim.receive(p.encode_bus_read_position(9), sim.now)
    start = sim.now
    ((t, reply),) = run(sim, start + 0.02, 0.0001)
    assert (reply.servo_id, reply.ok, reply.value) == (9, False, None)
    assert t - start == pytest.approx(s._servo_bus_time(6) + s.SERVO_TIMEOUT_S, abs=2e-4)
    assert reply.raw == p.encode_bus_reply(9, BusSub.READ_POSITION, None, -1)  # O14: zeros


def test_handlers_run_one_at_a_time_so_replies_queue_behind_a_timeout():
    sim = quiet()
    data = p.encode_bus_read_position(9) + p.encode_pwm_read_pulse(1)
    sim.receive(data, 0.0)
    got = run(sim, 0.02, 0.0001)
    assert [type(m) for _, m in got] == [p.BusServoReply, p.PwmPulseReply]
    assert got[1][0] >= s.SERVO_TIMEOUT_S


def test_o13_broadcast_read_echoes_0xfe_and_answers_only_with_one_servo():
    sim = quiet(bus_servo_ids=[4])
    (reply,) = ask(sim, p.encode_bus_read_id())
    assert (reply.servo_id, reply.ok, reply.value) == (0xFE, True, 4)
    sim.add_bus_servo(5)
    (reply,) = ask(sim, p.encode_bus_read_id())
    assert (reply.servo_id, reply.ok) == (0xFE, False)


def test_o23_o32_a_move_clamps_to_1000_loads_and_takes_its_time():
    sim = quiet()
    assert not sim.bus_servo(1).loaded
    sim.receive(p.encode_frame(5, struct.pack('<BHBBH', 1, 1000, 1, 1, 1200)), 0.0)
    servo = sim.bus_servo(1)
    assert servo.loaded and servo.target == 1000
    assert servo.position_at(0.5) == pytest.approx(750, abs=2)
    run(sim, 1.1)
    (reply,) = ask(sim, p.encode_bus_read_position(1))
    assert reply.value == 1000
    (reply,) = ask(sim, p.encode_bus_read_load(1))
    assert reply.value is True


def test_o6_unload_and_load_and_stop_holds_the_position():
    sim = quiet()
    sim.receive(p.encode_bus_move(1000, [(2, 900)]), 0.0)
    run(sim, 0.5)
    sim.receive(p.encode_bus_stop([2]), sim.now)
    here = sim.bus_servo(2).read_position(sim.now)
    run(sim, 1.5)
    assert sim.bus_servo(2).read_position(sim.now) == here and 600 < here < 800
    sim.receive(p.encode_bus_unload(2), sim.now)
    assert not sim.bus_servo(2).loaded
    (reply,) = ask(sim, p.encode_bus_read_load(2))
    assert reply.value is False
    sim.receive(p.encode_bus_load(2), sim.now)
    assert sim.bus_servo(2).loaded


def test_o35_bus_offset_out_of_range_is_ignored_and_save_keeps_it():
    sim = quiet()
    sim.receive(p.encode_bus_set_offset(1, -40) + p.encode_bus_save_offset(1), 0.0)
    sim.receive(p.encode_frame(5, struct.pack('<BBb', 0x20, 1, 127)), 0.0)
    run(sim, 0.01)
    servo = sim.bus_servo(1)
    assert (servo.offset, servo.saved_offset) == (-40, -40)
    (reply,) = ask(sim, p.encode_bus_read_offset(1))
    assert reply.value == -40


def test_o24_limit_clamps_then_swap():
    sim = quiet()
    frames = (p.encode_frame(5, struct.pack('<BBHH', 0x34, 1, 15000, 4000)) +
              p.encode_frame(5, struct.pack('<BBHH', 0x30, 1, 1200, 300)) +
              p.encode_frame(5, struct.pack('<BBB', 0x38, 1, 150)))
    sim.receive(frames, 0.0)
    run(sim, 0.01)
    servo = sim.bus_servo(1)
    assert servo.voltage_limits == (4000, 15000)
    assert servo.angle_limits == (300, 1000)
    assert servo.temperature_limit_c == 100
    (reply,) = ask(sim, p.encode_bus_read_voltage_limits(1))
    assert reply.value == (4000, 15000)


def test_angle_limits_bound_moves():
    sim = quiet()
    sim.receive(p.encode_bus_set_angle_limits(3, 200, 800), 0.0)
    sim.receive(p.encode_bus_move(0, [(3, 100)]), 0.01)
    run(sim, 1.0)
    assert sim.bus_servo(3).read_position(sim.now) == 200


def test_write_id_and_every_read_of_a_servo():
    sim = quiet(bus_servo_ids=[1])
    sim.bus_servo(1).temperature_c = 44
    sim.set_battery_mv(7900)
    sim.receive(p.encode_bus_write_id(0xFE, 12), 0.0)
    run(sim, 0.01)
    values = {}
    for sub in p.BUS_READ_FORMATS:
        (reply,) = ask(sim, p.encode_bus_read(sub, 12))
        assert reply.ok and reply.servo_id == 12
        values[sub] = reply.value
    assert values == {BusSub.READ_POSITION: 500, BusSub.READ_VOLTAGE: 7900,
                      BusSub.READ_TEMPERATURE: 44, BusSub.READ_LOAD: False, BusSub.READ_ID: 12,
                      BusSub.READ_OFFSET: 0, BusSub.READ_ANGLE_LIMITS: (0, 1000),
                      BusSub.READ_VOLTAGE_LIMITS: (4500, 14000),
                      BusSub.READ_TEMPERATURE_LIMIT: 85}
    (reply,) = ask(sim, p.encode_bus_read_position(1))
    assert not reply.ok


def test_o29_hx_sub_commands_do_nothing():
    sim = quiet()
    assert ask(sim, p.encode_frame(5, b'\x40\x01')) == []
    assert sim.commands_ignored == 1


# ----- LED, buzzer, OLED, RGB, SYS --------------------------------------------------------------

def test_o25_o31_led_patterns():
    sim = quiet()
    sim.receive(p.encode_led(1, 100, 100, 0) + p.encode_led(2, 100, 100, 2) +
                p.encode_frame(1, struct.pack('<BHHH', 3, 100, 0, 0)), 0.0)
    run(sim, 0.01)
    assert sim.commands_ignored == 1
    assert sim.leds[1].active_at(100.05)      # repeat 0: forever
    assert sim.leds[2].active_at(0.25) and not sim.leds[2].active_at(0.45)
    sim.receive(p.encode_buzzer(0, 100, 0, 0), sim.now)
    assert not sim.buzzer.active_at(sim.now + 0.05)
    assert sim.buzzer_log[-1].source == 'host'


def test_o19_oled_keeps_23_bytes_and_o18_rgb_ignores_index_2():
    sim = quiet()
    assert sim.oled_text(1) == '---.---.---.---'
    sim.receive(p.encode_frame(10, b'\x02\x1e' + b'x' * 30), 0.0)
    sim.receive(p.encode_rgb([(1, 1, 2, 3)]) + p.encode_frame(11, b'\x01\x01\x02\x09\x09\x09'),
                0.0)
    run(sim, 0.01)
    assert sim.oled_text(2) == 'x' * 23
    assert sim.rgb == [(0, 0, 0), (1, 2, 3)]


def test_o26_sys_0x02_gets_no_answer():
    sim = quiet()
    assert ask(sim, p.encode_frame(0, b'\x02\x01')) == []
    sim.receive(p.encode_battery_limit(7000), sim.now)
    assert sim.battery_limit_mv == 7000


# ----- power ------------------------------------------------------------------------------------

def test_a_reboot_forgets_every_setting_and_restarts_the_reports():
    sim = VirtualOriginManBoardModel(0.0, battery_period_s=1.05, imu_rate_hz=10)
    sim.receive(p.encode_battery_limit(5000) + p.encode_motor_type(2) +
                p.encode_pwm_set_offset(1, 20) + p.encode_motor_speed(0, 1.0), 0.0)
    run(sim, 0.5, 0.01)
    assert (sim.battery_limit_mv, sim.motor_type, sim.pwm_servos[1].offset_us) == (5000, 2, 20)
    sim.power_off()
    assert run(sim, 2.0, 0.01) == [] and sim.next_event_time() is None
    assert sim.receive(p.encode_pwm_read_pulse(1), 2.0) == b''
    sim.power_on()
    assert (sim.battery_limit_mv, sim.motor_type, sim.pwm_servos[1].offset_us,
            sim.motor_set_points[0]) == (6300, 0, 0, 0.0)
    kinds = [type(m) for _, m in run(sim, 3.15, 0.01)]
    assert kinds.count(p.ImuReport) == 11 and kinds.count(p.BatteryReport) == 1


def test_next_event_time_names_the_next_report():
    sim = VirtualOriginManBoardModel(0.0, imu_rate_hz=50)
    assert sim.next_event_time() == pytest.approx(0.02)
    sim.receive(p.encode_bus_read_position(1), 0.001)
    assert sim.next_event_time() == pytest.approx(0.001 + s._servo_bus_time(6)
                                                  + s.SERVO_ANSWER_S)


# ----- faults and the servo bus's capacity (issue 21 items 6, 7) -------------------------------

def test_a_board_that_stops_answering_reads_still_streams_and_obeys():
    sim = VirtualOriginManBoardModel(0.0, battery_period_s=1000.0)
    sim.answer_reads = False
    got = ask(sim, p.encode_bus_read(BusSub.READ_POSITION, 1), 0.1)
    got += ask(sim, p.encode_pwm_read_pulse(1), 0.1)
    assert not [m for m in got if not isinstance(m, p.ImuReport)]
    assert len([m for m in got if isinstance(m, p.ImuReport)]) >= 8
    sim.receive(p.encode_motor_speeds([(0, 1.5)]), sim.now)
    run(sim, sim.now + 0.01)
    assert sim.motor_speed(0) == 1.5
    sim.answer_reads = True
    assert any(isinstance(m, p.BusServoReply) for m in
               ask(sim, p.encode_bus_read(BusSub.READ_POSITION, 1)))


def test_commands_wait_behind_the_servo_bus_work_of_the_frames_before_them():
    sim = quiet(bus_servo_ids=range(20))
    move = p.encode_bus_move(20, [(i, 600) for i in range(20)])  # 20 x 10 bytes at 115200
    sim.receive(move * 10 + p.encode_motor_stop_mask(0xF), 0.0)
    run(sim, 1.0)
    arrived, handled, cmd = sim.queue_log[-1]
    assert isinstance(cmd, p.StopMotors)
    assert handled - arrived == pytest.approx(10 * 20 * 10 * 10 / 115200, rel=0.01)
