"""Wire format of the OriginMan board: golden frames, CRC, encoders, decoders, stream decoders."""

import struct

from hypothesis import given, settings, strategies as st
import pytest

from originman_board_ros import protocol as p
from originman_board_ros.protocol import (BoardParser, BusSub, Function, ProtocolRangeError,
                                          StreamDecoder)


def h(text: str) -> bytes:
    return bytes.fromhex(text)


def board_view(frame: bytes):
    """What the firmware's handler reads from ``frame`` (exactly one command expected)."""
    (host_frame,) = BoardParser().feed(frame)
    return p.decode_host_command(host_frame)


# ----- CRC (O1) --------------------------------------------------------------------------------

def test_o1_crc_is_the_table_algorithm_with_init_0_and_no_final_xor():
    assert p.crc8(b'123456789') == 0xA1
    assert list(p.CRC8_TABLE[:16]) == [0, 94, 188, 226, 97, 63, 221, 131, 194, 156, 126, 32,
                                       163, 253, 31, 65]
    assert list(p.CRC8_TABLE[-16:]) == [116, 42, 200, 150, 21, 75, 169, 247, 182, 232, 10, 84,
                                        215, 137, 107, 53]


def test_o1_the_pdf_appendix_variant_would_reject_the_pdf_examples():
    # Init 0xFF with an inverted result, as the PDF's appendix describes it.
    def appendix_crc(data):
        c = 0xFF
        for b in data:
            c = p.CRC8_TABLE[c ^ b]
        return c ^ 0xFF
    frames = [h(x) for x in PDF_EXAMPLES.values()]
    assert all(p.crc8(f[2:-1]) == f[-1] for f in frames)
    assert not any(appendix_crc(f[2:-1]) == f[-1] for f in frames)


# ----- golden frames ---------------------------------------------------------------------------

def test_e1_seed_led_example_is_0x37():
    assert p.encode_led(1, 100, 100, 5) == h('AA 55 01 07 01 64 00 64 00 05 00 37')


def test_e2_seed_buzzer_example():
    assert p.encode_buzzer(2400, 100, 900, 1) == h('AA 55 02 08 60 09 64 00 84 03 01 00 1D')


def test_e3_o28_seed_motor_example_gets_crc_0x2a():
    frame = p.encode_motor_speeds([(i, -1.0) for i in range(4)])
    assert frame == h('AA 55 03 16 01 04 00 00 00 80 BF 01 00 00 80 BF 02 00 00 80 BF '
                      '03 00 00 80 BF 2A')
    # The seed prints the frame without its CRC: the board would wait for one more byte.
    assert BoardParser().feed(frame[:-1]) == []


def test_e4_bus_servo_read_position():
    assert p.encode_bus_read_position(1) == h('AA 55 05 02 05 01 6F')
    assert p.encode_bus_read(BusSub.READ_POSITION, 1) == h('AA 55 05 02 05 01 6F')


def test_e5_bus_servo_position_reply():
    frame = h('AA 55 05 05 05 05 00 41 03 CC')
    assert p.encode_bus_reply(5, BusSub.READ_POSITION, 833) == frame
    reply = p.decode_board_bytes(frame)
    assert reply == p.BusServoReply(5, 0x05, 0, 833, frame) and reply.ok


def test_e6_o9_battery_report_is_millivolts():
    frame = h('AA 55 00 03 04 E8 1C 2B')
    assert p.encode_battery_report(7400) == frame
    assert p.decode_board_bytes(frame) == p.BatteryReport(7400, frame)


def test_e7_key_pressed():
    frame = h('AA 55 06 02 01 01 DC')
    assert p.encode_key_report(1, p.KeyEvent.PRESSED) == frame
    report = p.decode_board_bytes(frame)
    assert (report.key_id, report.event, report.event_name) == (1, 1, 'pressed')


def test_e8_o12_pwm_offset_example_corrected_to_function_4():
    assert p.encode_pwm_set_offset(2, 10) == h('AA 55 04 03 07 02 0A 02')
    # The PDF's example 11 is a MOTOR frame (FUNCTION 3) with sub-command 0x07: ignored.
    command = board_view(h(PDF_EXAMPLES[11]))
    assert isinstance(command, p.IgnoredCommand) and command.function == Function.MOTOR


PDF_EXAMPLES = {
    1: 'AA5502087805640064000500F0', 2: 'AA550208E803F4012C010A008B',
    3: 'AA55010701F4012C010A0004', 4: 'AA5501070164006400050037',
    5: 'AA5503060001000080BFDA', 6: 'AA550302020108',
    7: 'AA55030C010201000080BF0200000040FB', 8: 'AA5503020305AD',
    9: 'AA55040A01D0070201DC0502C409C8', 10: 'AA55040603e80301e803e4',
    11: 'AA55030307020A53', 12: 'AA55050A01E8030201410302E8039F',
    13: 'AA55050A01E80302010000020000D2', 14: 'AA5505020B01B3', 15: 'AA5505020C01DD',
    16: 'AA55050310010268',
}
PDF_ENCODED = {
    1: lambda: p.encode_buzzer(1400, 100, 100, 5),
    2: lambda: p.encode_buzzer(1000, 500, 300, 10),
    3: lambda: p.encode_led(1, 500, 300, 10),
    4: lambda: p.encode_led(1, 100, 100, 5),
    5: lambda: p.encode_motor_speed(1, -1.0),
    6: lambda: p.encode_motor_stop(1),
    7: lambda: p.encode_motor_speeds([(1, -1.0), (2, 2.0)]),
    8: lambda: p.encode_motor_stop_mask(0b0101),
    9: lambda: p.encode_pwm_move(2000, [(1, 1500), (2, 2500)]),
    10: lambda: p.encode_pwm_move_one(1000, 1, 1000),
    12: lambda: p.encode_bus_move(1000, [(1, 833), (2, 1000)]),
    13: lambda: p.encode_bus_move(1000, [(1, 0), (2, 0)]),
    14: lambda: p.encode_bus_unload(1),
    15: lambda: p.encode_bus_load(1),
    16: lambda: p.encode_bus_write_id(1, 2),
}


@pytest.mark.parametrize('number', sorted(PDF_EXAMPLES))
def test_every_pdf_example_has_a_correct_length_and_crc(number):
    frame = p.parse_frame(h(PDF_EXAMPLES[number]))
    assert len(frame.raw) == len(frame.data) + p.FRAME_OVERHEAD


@pytest.mark.parametrize('number', sorted(PDF_ENCODED))
def test_o27_every_pdf_example_is_what_our_encoder_builds(number):
    # The layouts come from the firmware's packed structs, whatever the PDF's numbering says.
    assert PDF_ENCODED[number]() == h(PDF_EXAMPLES[number])


def test_o3_pdf_motor_examples_address_wire_ids_so_motor_1_means_motor_2():
    assert board_view(h(PDF_EXAMPLES[5])) == p.SetMotorSpeeds(0, ((1, -1.0),))
    assert board_view(h(PDF_EXAMPLES[6])) == p.StopMotors(2, (1,))
    assert board_view(h(PDF_EXAMPLES[7])).items == ((1, -1.0), (2, 2.0))


def test_o4_stop_mask_bit_i_is_wire_id_i():
    assert board_view(h(PDF_EXAMPLES[8])) == p.StopMotors(3, (0, 2))
    assert board_view(p.encode_frame(Function.MOTOR, b'\x03\xf0')) == p.StopMotors(3, ())


# ----- encoders refuse what the board would misread --------------------------------------------

@pytest.mark.parametrize('build, field', [
    (lambda: p.encode_motor_speed(4, 1.0), 'motor wire id'),
    (lambda: p.encode_motor_speeds([(0, 1.0), (4, 1.0)]), 'motor wire id'),
    (lambda: p.encode_motor_speed(0, float('nan')), 'motor speed'),
    (lambda: p.encode_motor_speed(0, 6.5), 'motor speed'),
    (lambda: p.encode_motor_speeds([]), 'motor list'),
    (lambda: p.encode_motor_speeds([(1, 1.0), (1, 2.0)]), 'motor wire ids'),
    (lambda: p.encode_motor_stop_mask(0x10), 'motor stop mask'),
    (lambda: p.encode_motor_type(4), 'motor type'),
    (lambda: p.encode_pwm_move(1000, [(0, 1500)]), 'PWM servo id'),
    (lambda: p.encode_pwm_move(1000, [(5, 1500)]), 'PWM servo id'),
    (lambda: p.encode_pwm_move(1000, [(1, 499)]), 'PWM pulse'),
    (lambda: p.encode_pwm_move(19, [(1, 1500)]), 'PWM move duration'),
    (lambda: p.encode_pwm_move_one(30001, 1, 1500), 'PWM move duration'),
    (lambda: p.encode_pwm_set_offset(1, 101), 'PWM offset'),
    (lambda: p.encode_pwm_read_pulse(0), 'PWM servo id'),
    (lambda: p.encode_bus_move(1000, [(1, 1001)]), 'bus servo position'),
    (lambda: p.encode_bus_move(65536, [(1, 500)]), 'bus servo move duration'),
    (lambda: p.encode_bus_move(100, [(255, 500)]), 'bus servo id'),
    (lambda: p.encode_bus_write_id(1, 254), 'new bus servo id'),
    (lambda: p.encode_bus_set_offset(1, 126), 'bus servo offset'),
    (lambda: p.encode_bus_set_angle_limits(1, 600, 500), 'bus servo max position'),
    (lambda: p.encode_bus_set_voltage_limits(1, 4000, 9000), 'bus servo min voltage'),
    (lambda: p.encode_bus_set_voltage_limits(1, 5000, 15000), 'bus servo max voltage'),
    (lambda: p.encode_bus_set_temperature_limit(1, 101), 'bus servo max temperature'),
    (lambda: p.encode_bus_read(0x40, 1), 'bus servo read sub-command'),
    (lambda: p.encode_led(0, 1, 1, 1), 'led_id'),
    (lambda: p.encode_led(3, 1, 1, 1), 'led_id'),
    (lambda: p.encode_led(1, 65536, 1, 1), 'LED on time'),
    (lambda: p.encode_buzzer(-1, 1, 1, 1), 'buzzer frequency'),
    (lambda: p.encode_oled(3, 'x'), 'OLED line'),
    (lambda: p.encode_oled(1, 'x' * 24), 'OLED text'),
    (lambda: p.encode_rgb([(2, 0, 0, 0)]), 'RGB pixel index'),
    (lambda: p.encode_rgb([(0, 256, 0, 0)]), 'RGB red'),
    (lambda: p.encode_battery_limit(70000), 'battery limit'),
    (lambda: p.encode_led(True, 1, 1, 1), 'led_id'),
])
def test_out_of_range_values_are_refused_with_the_field_named(build, field):
    with pytest.raises(ProtocolRangeError) as info:
        build()
    assert info.value.field.startswith(field)
    assert field in str(info.value)


def test_o3_motor_wire_id_4_is_never_encoded():
    with pytest.raises(ProtocolRangeError, match='0..3'):
        p.encode_motor_stop(4)


def test_o30_pwm_id_0_is_never_encoded():
    for build in (p.encode_pwm_read_pulse, p.encode_pwm_read_offset,
                  lambda i: p.encode_pwm_move_one(100, i, 1500)):
        with pytest.raises(ProtocolRangeError, match='1..4'):
            build(0)


def test_o19_oled_text_counts_utf8_bytes_and_sends_no_terminator():
    assert p.encode_oled(2, '192.168.1.10') == p.encode_frame(10, b'\x02\x0c192.168.1.10')
    p.encode_oled(1, 'ü' * 11)  # 22 bytes
    with pytest.raises(ProtocolRangeError, match='24'):
        p.encode_oled(1, 'ü' * 12)


def test_o25_led_ids_are_1_and_2():
    assert p.encode_led(2, 0, 0, 0)[4] == 2
    with pytest.raises(ProtocolRangeError, match='1..2'):
        p.encode_led(3, 0, 0, 0)


def test_o6_torque_on_is_0x0c():
    assert p.encode_bus_torque(1, True) == h(PDF_EXAMPLES[15])
    assert p.encode_bus_torque(1, False) == h(PDF_EXAMPLES[14])
    assert board_view(p.encode_bus_torque(3, True)) == p.BusTorque(3, True)
    assert board_view(p.encode_bus_torque(3, False)) == p.BusTorque(3, False)


def test_o5_sub_0x05_is_the_motor_type():
    assert p.encode_motor_type(p.MotorType.JGA27) == p.encode_frame(3, b'\x05\x02')
    # The SDK's set_motor_duty sends [0x05, n, ...]: the board takes n as the type.
    duty = p.encode_frame(3, b'\x05\x01' + struct.pack('<Bf', 0, 0.5))
    assert board_view(duty) == p.SetMotorType(1)


def test_o10_one_pwm_frame_for_several_servos_and_0x03_for_exactly_one():
    assert board_view(p.encode_pwm_move(500, [(1, 600), (3, 2400)])) == \
        p.PwmMove(1, 500, ((1, 600), (3, 2400)))
    # The S6 SDK's multi-servo 0x03 without a count: the board reads the first servo only.
    frame = p.encode_frame(4, struct.pack('<BHBHBH', 3, 500, 1, 600, 3, 2400))
    assert board_view(frame) == p.PwmMove(3, 500, ((1, 600),))


def test_o11_pwm_offset_reply_carries_sub_0x09():
    frame = p.encode_pwm_offset_reply(2, -7)
    assert frame[5] == 0x09
    assert p.decode_board_bytes(frame) == p.PwmOffsetReply(2, -7, frame)
    # A reply with the PDF's 0x05 and 3 bytes is not an offset reply.
    wrong = p.encode_frame(4, struct.pack('<BBb', 2, 0x05, -7))
    assert isinstance(p.decode_board_bytes(wrong), p.UnknownFrame)


def test_o13_o14_a_failed_read_has_no_value_whatever_its_arguments():
    frame = p.encode_frame(5, struct.pack('<BBbh', 0xFE, 0x05, -1, 777))
    reply = p.decode_board_bytes(frame)
    assert reply.servo_id == 0xFE and not reply.ok and reply.value is None
    for sub in p.BUS_READ_FORMATS:
        failed = p.decode_board_bytes(p.encode_bus_reply(9, sub, None, p.BUS_FAILURE))
        assert (failed.ok, failed.value, failed.success) == (False, None, -1)


@pytest.mark.parametrize('sub, value', [
    (BusSub.READ_POSITION, -20), (BusSub.READ_POSITION, 1010), (BusSub.READ_VOLTAGE, 12100),
    (BusSub.READ_TEMPERATURE, 41), (BusSub.READ_LOAD, True), (BusSub.READ_LOAD, False),
    (BusSub.READ_ID, 7), (BusSub.READ_OFFSET, -125), (BusSub.READ_ANGLE_LIMITS, (10, 990)),
    (BusSub.READ_VOLTAGE_LIMITS, (4500, 14000)), (BusSub.READ_TEMPERATURE_LIMIT, 85),
])
def test_every_bus_read_reply_decodes_to_its_typed_value(sub, value):
    reply = p.decode_board_bytes(p.encode_bus_reply(3, sub, value))
    assert (reply.servo_id, reply.sub, reply.ok, reply.value) == (3, sub, True, value)


def test_o23_negative_positions_decode():
    assert p.decode_board_bytes(p.encode_bus_reply(1, 5, -3)).value == -3


def test_o7_imu_report_is_g_and_deg_per_s():
    frame = p.encode_imu_report((0.0, 0.5, 1.0), (10.0, -20.0, 90.0))
    report = p.decode_board_bytes(frame)
    assert report.accel_g == (0.0, 0.5, 1.0) and report.gyro_dps == (10.0, -20.0, 90.0)
    assert len(frame) == 24 + 5


def test_o15_gamepad_is_function_8_hb4b():
    frame = p.encode_gamepad_report(0x4001, 9, -128, 127, 0, -1)
    assert frame[2] == 8 and frame[3] == 7
    assert p.decode_board_bytes(frame) == p.GamepadReport(0x4001, 9, -128, 127, 0, -1, frame)


def test_o16_sbus_values_are_raw():
    channels = list(range(172, 172 + 16))
    frame = p.encode_sbus_report(channels, ch17=True, failsafe=True)
    report = p.decode_board_bytes(frame)
    assert report.channels == tuple(channels)
    assert (report.ch17, report.ch18, report.signal_loss, report.failsafe) == \
        (True, False, False, True)


def test_o17_every_key_event_has_its_contract_name():
    assert p.KEY_EVENT_NAMES == {
        0x01: 'pressed', 0x02: 'long_press', 0x04: 'long_press_repeat',
        0x08: 'release_from_long_press', 0x10: 'release_from_short_press', 0x20: 'click',
        0x40: 'double_click', 0x80: 'triple_click'}
    assert p.KeyReport(1, 0x03).event_name == 'unknown_0x03'


def test_o18_rgb_indices_are_0_based_with_cmd_byte_1():
    assert p.encode_rgb([(0, 255, 0, 0), (1, 0, 0, 9)]) == \
        p.encode_frame(11, bytes((1, 2, 0, 255, 0, 0, 1, 0, 0, 9)))
    assert board_view(p.encode_rgb([(1, 1, 2, 3)])) == p.SetRgb(((1, 1, 2, 3),))


def test_o26_sys_has_only_the_battery_limit_host_command():
    assert p.encode_battery_limit(6800) == p.encode_frame(0, b'\x01\x90\x1a')
    assert board_view(p.encode_battery_limit(6800)) == p.SetBatteryLimit(6800)
    assert isinstance(board_view(p.encode_frame(0, b'\x02\x01')), p.IgnoredCommand)


def test_o29_hx_sub_commands_are_ignored_by_the_board():
    for sub in (0x40, 0x41, 0x42, 0x43, 0x50, 0x51):
        command = board_view(p.encode_frame(5, bytes((sub, 1, 0))))
        assert isinstance(command, p.IgnoredCommand) and command.sub == sub


def test_o2_host_commands_use_functions_0_to_11_only():
    frames = [build() for build in PDF_ENCODED.values()] + [
        p.encode_battery_limit(6300), p.encode_oled(1, 'a'), p.encode_rgb([(0, 1, 2, 3)]),
        p.encode_motor_type(0), p.encode_pwm_read_offset(1), p.encode_bus_read_id()]
    assert {f[2] for f in frames} <= set(range(12))


# ----- the host's stream decoder (§2.4) --------------------------------------------------------

def test_o2_host_decoder_takes_function_12_as_asr_and_skips_higher_ones():
    asr = p.encode_asr_report(b'\xbb\xcc\x01\x02\x03')
    future = p.encode_frame(13, b'\x01\x02')
    dec = StreamDecoder()
    (frame,) = dec.feed(future + asr)
    assert p.decode_board_frame(frame) == p.AsrReport(b'\xbb\xcc\x01\x02\x03', asr)
    assert dec.unknown_functions == 1 and dec.checksum_errors == 0


def test_o50_a_crc_valid_function_13_is_noise_and_frames_inside_it_are_found():
    key = p.encode_key_report(1, 0x20)
    # FUNCTION 0xE3 with a LENGTH that covers the key report, and a CRC that checks.
    body = bytes([0xE3, len(key) + 2, 0x00]) + key + b'\x00'
    noise = p.HEADER + body + bytes([p.crc8(body)])
    dec = StreamDecoder()
    assert [f.raw for f in dec.feed(noise)] == [key]
    assert dec.unknown_functions == 1 and dec.checksum_errors == 0


def test_decoder_finds_frames_in_garbage_split_anywhere():
    frames = [p.encode_battery_report(7000), p.encode_key_report(2, 0x20),
              p.encode_imu_report((0, 0, 1), (0, 0, 0)), p.encode_bus_reply(1, 5, 500)]
    stream = b'\x00\xaa\x13\x55' + frames[0] + b'\xaa' + frames[1] + b'\xaa\x55' + \
        b'\x07\x02\x00' + frames[2] + frames[3]
    for cut in range(1, len(stream)):
        dec = StreamDecoder()
        got = dec.feed(stream[:cut]) + dec.feed(stream[cut:])
        assert [f.raw for f in got] == frames, cut


def test_decoder_resyncs_after_a_crc_failure_inside_the_bad_frame():
    good = p.encode_key_report(1, 1)
    # A false header whose "frame" swallows the real one, with a CRC that fails.
    false = b'\xaa\x55\x06\x09' + good[:4]
    dec = StreamDecoder()
    assert [f.raw for f in dec.feed(false + good + b'\x00' * 8)] == [good]
    # The false frame and the copy of the real header inside it: two candidates, two failures.
    assert dec.checksum_errors == 2 and dec.bytes_discarded == len(false) + 8


def test_o34_a_false_header_with_a_huge_length_does_not_hold_the_decoder():
    good = p.encode_battery_report(7400)
    dec = StreamDecoder()
    assert [f.raw for f in dec.feed(b'\xaa\x55\x00\xff' + good)] == [good]
    assert dec.pending == 0


def test_decoder_keeps_a_trailing_header_byte_and_reset_forgets_it():
    dec = StreamDecoder()
    frame = p.encode_key_report(1, 0x10)
    assert dec.feed(frame[:1]) == [] and dec.pending == 1
    assert [f.raw for f in dec.feed(frame[1:])] == [frame]
    dec.feed(frame[:5])
    dec.reset()
    assert dec.feed(frame[5:]) == []


def test_unexpected_lengths_and_sub_commands_become_unknown_frames():
    for frame in (p.encode_frame(0, b'\x04\x01'), p.encode_frame(6, b'\x01'),
                  p.encode_frame(7, bytes(20)), p.encode_frame(5, b'\x01\x99\x00\x00'),
                  p.encode_frame(3, b'\x00'), p.encode_frame(9, bytes(35))):
        assert isinstance(p.decode_board_bytes(frame), p.UnknownFrame), frame.hex()


def test_parse_frame_names_the_defect():
    with pytest.raises(p.ProtocolError, match='CRC'):
        p.parse_frame(h('AA 55 06 02 01 01 DD'))
    with pytest.raises(p.ProtocolError, match='LENGTH'):
        p.parse_frame(h('AA 55 06 03 01 01 DC'))


# ----- the board's parser (O21, O22, O33) ------------------------------------------------------

def test_o22_a_second_aa_before_55_loses_the_frame():
    frame = p.encode_led(1, 100, 100, 5)
    parser = BoardParser()
    assert parser.feed(b'\xaa' + frame) == []
    # The host's decoder would have found it.
    assert len(StreamDecoder().feed(b'\xaa' + frame)) == 1
    assert len(parser.feed(frame)) == 1


def test_o22_function_12_and_above_is_dropped_without_reexamining_the_byte():
    parser = BoardParser()
    assert parser.feed(p.encode_frame(12, b'\x01')) == []
    assert parser.functions_dropped == 1
    # FUNCTION 0xAA: the dropped byte is not taken as the start of a new frame.
    frame = p.encode_key_report(1, 1)
    assert parser.feed(b'\xaa\x55\xaa\x55' + frame[2:]) == []


def test_o22_a_truncated_frame_swallows_the_next_one_and_a_bad_crc_is_silent():
    led = p.encode_led(1, 100, 100, 5)
    buzzer = p.encode_buzzer(2400, 100, 900, 1)
    parser = BoardParser()
    assert parser.feed(led[:6] + buzzer) == []
    assert parser.checksum_errors == 1
    assert len(parser.feed(led)) == 1


def test_o21_o33_a_short_frame_reads_its_crc_then_zeros_and_extra_bytes_are_ignored():
    # LED frame with LENGTH 2: led_id, low byte of on_ms; the high byte is the CRC.
    short = p.encode_frame(1, b'\x02\x10')
    command = board_view(short)
    assert command == p.SetLed(2, 0x10 | short[-1] << 8, 0, 0)
    longer = p.encode_frame(1, struct.pack('<BHHH', 1, 5, 6, 7) + b'\xff\xff')
    assert board_view(longer) == p.SetLed(1, 5, 6, 7)
    assert board_view(p.encode_frame(5, b'\x05')) == p.BusRead(5, p.encode_frame(5, b'\x05')[-1])


def test_o21_counts_are_taken_as_sent():
    # Motor count 3 with one element: the rest reads the CRC and zeros (wire id 0 at 0 r/s).
    frame = p.encode_frame(3, b'\x01\x03' + struct.pack('<Bf', 1, 1.5))
    items = board_view(frame).items
    assert len(items) == 3 and items[0] == (1, 1.5)


# ----- round trips ------------------------------------------------------------------------------

ids4 = st.lists(st.integers(1, 4), min_size=1, max_size=4, unique=True)


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_every_host_command_round_trips_through_the_board_parser(data):
    kind = data.draw(st.sampled_from(['led', 'buzzer', 'motors', 'mask', 'pwm', 'bus', 'limits',
                                      'oled', 'rgb', 'offset', 'read']))
    u16 = st.integers(0, 0xFFFF)
    if kind == 'led':
        args = (data.draw(st.integers(1, 2)), data.draw(u16), data.draw(u16), data.draw(u16))
        frame, expected = p.encode_led(*args), p.SetLed(*args)
    elif kind == 'buzzer':
        args = tuple(data.draw(u16) for _ in range(4))
        frame, expected = p.encode_buzzer(*args), p.SetBuzzer(*args)
    elif kind == 'motors':
        ids = data.draw(st.lists(st.integers(0, 3), min_size=1, max_size=4, unique=True))
        speeds = [data.draw(st.floats(-6, 6, width=32)) for _ in ids]
        frame, expected = p.encode_motor_speeds(list(zip(ids, speeds))), \
            p.SetMotorSpeeds(1, tuple(zip(ids, speeds)))
    elif kind == 'mask':
        mask = data.draw(st.integers(0, 15))
        frame = p.encode_motor_stop_mask(mask)
        expected = p.StopMotors(3, tuple(i for i in range(4) if mask >> i & 1))
    elif kind == 'pwm':
        ids = data.draw(ids4)
        items = tuple((i, data.draw(st.integers(500, 2500))) for i in ids)
        ms = data.draw(st.integers(20, 30000))
        frame, expected = p.encode_pwm_move(ms, items), p.PwmMove(1, ms, items)
    elif kind == 'bus':
        ids = data.draw(st.lists(st.integers(0, 254), min_size=1, max_size=83, unique=True))
        items = tuple((i, data.draw(st.integers(0, 1000))) for i in ids)
        ms = data.draw(u16)
        frame, expected = p.encode_bus_move(ms, items), p.BusMove(ms, items)
    elif kind == 'limits':
        lo = data.draw(st.integers(4500, 14000))
        hi = data.draw(st.integers(lo, 14000))
        frame = p.encode_bus_set_voltage_limits(7, lo, hi)
        expected = p.BusSetLimits(BusSub.SET_VOLTAGE_LIMITS, 7, lo, hi)
    elif kind == 'oled':
        text = data.draw(st.text(max_size=23).filter(lambda t: len(t.encode()) <= 23))
        line = data.draw(st.integers(1, 2))
        frame, expected = p.encode_oled(line, text), p.SetOledText(line, text.encode())
    elif kind == 'rgb':
        idx = data.draw(st.lists(st.integers(0, 1), min_size=1, max_size=2, unique=True))
        pixels = tuple((i, *(data.draw(st.integers(0, 255)) for _ in range(3))) for i in idx)
        frame, expected = p.encode_rgb(pixels), p.SetRgb(pixels)
    elif kind == 'offset':
        servo, value = data.draw(st.integers(0, 254)), data.draw(st.integers(-125, 125))
        frame, expected = p.encode_bus_set_offset(servo, value), p.BusSetOffset(servo, value)
    else:
        sub = data.draw(st.sampled_from(sorted(p.BUS_READ_FORMATS)))
        servo = data.draw(st.integers(0, 254))
        frame, expected = p.encode_bus_read(sub, servo), p.BusRead(sub, servo)
    assert board_view(frame) == expected
    assert p.parse_frame(frame).raw == frame


board_frames = st.one_of(
    st.integers(0, 0xFFFF).map(p.encode_battery_report),
    st.tuples(st.integers(1, 2), st.sampled_from(list(p.KeyEvent))).map(
        lambda a: p.encode_key_report(*a)),
    st.tuples(st.lists(st.floats(-16, 16, width=32), min_size=3, max_size=3),
              st.lists(st.floats(-2000, 2000, width=32), min_size=3, max_size=3)).map(
        lambda a: p.encode_imu_report(*a)),
    st.tuples(st.sampled_from(sorted(p.BUS_READ_FORMATS)), st.integers(0, 254)).map(
        lambda a: p.encode_bus_reply(a[1], a[0], None, -1)),
    st.tuples(st.integers(1, 4), st.integers(500, 2500)).map(
        lambda a: p.encode_pwm_pulse_reply(*a)),
    st.lists(st.integers(0, 2047), min_size=16, max_size=16).map(p.encode_sbus_report),
    st.binary(min_size=5, max_size=5).map(p.encode_asr_report),
)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(board_frames, st.binary(max_size=6)), min_size=1, max_size=8),
       st.lists(st.integers(1, 40), max_size=6))
def test_board_frames_survive_garbage_and_any_split(items, cuts):
    stream = b''.join(garbage.replace(b'\xaa', b'\x00') + frame for frame, garbage in items)
    dec = StreamDecoder()
    got, pos = [], 0
    for cut in cuts + [len(stream)]:
        got += dec.feed(stream[pos:pos + cut])
        pos += cut
    got += dec.feed(stream[pos:])
    assert [f.raw for f in got] == [frame for frame, _ in items]
    for frame in got:
        assert not isinstance(p.decode_board_frame(frame), p.UnknownFrame)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300))
def test_decoders_never_raise_on_noise(noise):
    for frame in StreamDecoder().feed(noise):
        p.decode_board_frame(frame)
    for frame in BoardParser().feed(noise):
        p.decode_host_command(frame)
