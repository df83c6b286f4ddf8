"""DPS-S protocol layer: golden frames from the vendor document, decisions P1-P20, properties."""

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

from dps_parachute_ros import protocol as p
from support import split


def h(text: str) -> bytes:
    """Bytes from a hex string with spaces, as the document prints frames."""
    return bytes.fromhex(text)


def decode_stream(data: bytes, layout: str = 'table') -> list:
    """Decode a whole capture (fed at once, then flushed) into typed messages."""
    decoder = p.StreamDecoder()
    frames = decoder.feed(data) + decoder.flush()
    return [p.decode_module_frame(f, layout) for f in frames]


# ---------------------------------------------------------------------------------------------
# Golden host frames: every host example of the document (P1, P4)
# ---------------------------------------------------------------------------------------------

HOST_GOLDEN = [
    (p.encode_heartbeat, (), '42 61 01 a5 5a 00'),
    (p.encode_arm, (True,), '42 61 10 02 01 13'),
    (p.encode_arm, (False,), '42 61 10 02 00 12'),
    (p.encode_deploy, (True,), '42 61 11 02 01 14'),
    (p.encode_deploy, (False,), '42 61 11 02 00 13'),
    (p.encode_shutdown, (), '42 61 12 02 01 15'),
    (p.encode_streaming, (True,), '42 61 13 02 01 16'),
    (p.encode_streaming, (False,), '42 61 13 02 00 15'),
    (p.encode_light_level_query, (), '42 61 14 01 01 16'),
    (p.encode_light_threshold_set, (1.8,), '42 61 15 02 12 29'),
    (p.encode_light_threshold_query, (), '42 61 15 01 00 16'),
    (p.encode_attitude_trigger, (False,), '42 61 16 02 01 19'),
    (p.encode_attitude_trigger, (True,), '42 61 16 02 00 18'),
    (p.encode_freefall_trigger, (False,), '42 61 17 02 01 1a'),
    (p.encode_freefall_trigger, (True,), '42 61 17 02 00 19'),
    (p.encode_attitude_threshold_set, (60,), '42 61 20 02 3c 5e'),
    (p.encode_attitude_threshold_query, (), '42 61 20 01 00 21'),
    (p.encode_freefall_threshold_set, (0.5,), '42 61 21 02 05 28'),
    (p.encode_freefall_threshold_query, (), '42 61 21 01 00 22'),
    (p.encode_freefall_time_set, (1.6,), '42 61 22 02 a0 c4'),
    (p.encode_freefall_time_query, (), '42 61 22 01 00 23'),
    (p.encode_boot_count_query, (), '42 61 23 01 00 24'),
    (p.encode_baud_rate_set, (115200,), '42 61 24 02 06 2c'),
    (p.encode_sensor_zero, (), '42 61 25 01 00 26'),
    (p.encode_armed_query, (), '42 61 30 01 00 31'),
    (p.encode_triggered_query, (), '42 61 31 01 00 32'),
    (p.encode_status_query, (), '42 61 32 01 00 33'),
    (p.encode_charging_query, (), '42 61 33 01 00 34'),
    (p.encode_cell_voltage_query, (), '42 61 34 01 00 35'),
    (p.encode_trigger_records_query, (), '42 61 35 01 00 36'),
    (p.encode_trigger_confirm, (), '42 61 39 a5 01 df'),
    (p.encode_auto_trigger_query, (), '42 61 16 01 00 17'),
]


@pytest.mark.parametrize('encoder,args,expected', HOST_GOLDEN,
                         ids=[f'{e.__name__}{a}' for e, a, _ in HOST_GOLDEN])
def test_host_encoders_match_document(encoder, args, expected):
    frame = encoder(*args)
    assert frame == h(expected)
    # Every documented host frame also passes the P1 rule and our own parser.
    assert p.parse_frame(frame).raw == frame


def test_host_control_byte_is_02_for_set_and_01_for_query():
    """P4: set commands carry 0x02 in D3, queries 0x01."""
    assert p.encode_attitude_threshold_set(70)[3] == p.CTRL_SET
    assert p.encode_attitude_threshold_query()[3] == p.CTRL_QUERY
    assert p.encode_light_threshold_set(1.0)[3] == 0x02
    assert p.encode_cell_voltage_query()[3] == 0x01


def test_heartbeat_checksum_is_the_p1_sum():
    """P4: the fixed 00 of the heartbeat is the low byte of 0x01 + 0xa5 + 0x5a = 0x100."""
    assert p.checksum(h('01 a5 5a')) == 0x00
    assert p.encode_heartbeat()[-1] == 0x00
    assert p.encode_module_heartbeat() == h('41 75 01 a5 5a 00')


# ---------------------------------------------------------------------------------------------
# Golden module frames
# ---------------------------------------------------------------------------------------------

def test_module_heartbeat_decodes():
    assert isinstance(p.decode_module_bytes(h('41 75 01 a5 5a 00')), p.Heartbeat)


def test_module_heartbeat_with_other_payload_is_not_a_heartbeat():
    msg = p.decode_module_bytes(p.build_frame(p.MODULE_HEADER, 0x01, b'\x01\x00'))
    assert isinstance(msg, p.UnknownFrame)


@pytest.mark.parametrize('text,armed', [('41 75 10 01 01 12', True), ('41 75 10 01 00 11', False)])
def test_arm_reply(text, armed):
    msg = p.decode_module_bytes(h(text))
    assert isinstance(msg, p.ArmReply) and msg.armed is armed
    assert msg.raw == h(text)


@pytest.mark.parametrize('text,ok', [('41 75 11 01 01 13', True), ('41 75 11 01 00 12', False)])
def test_deploy_ack(text, ok):
    msg = p.decode_module_bytes(h(text))
    assert isinstance(msg, p.DeployAck) and msg.success is ok


def test_shutdown_ack():
    assert isinstance(p.decode_module_bytes(h('41 75 12 01 01 14')), p.ShutdownAck)


@pytest.mark.parametrize('text,on', [('41 75 13 01 01 15', True), ('41 75 13 01 00 14', False)])
def test_streaming_reply(text, on):
    msg = p.decode_module_bytes(h(text))
    assert isinstance(msg, p.StreamingReply) and msg.enabled is on


def test_light_level_reply_is_tenths_of_a_volt():
    msg = p.decode_module_bytes(p.module_frame(0x14, 0x21))
    assert isinstance(msg, p.LightLevel) and msg.volts == pytest.approx(3.3)


@pytest.mark.parametrize('text,volts', [('41 75 15 01 12 28', 1.8), ('41 75 15 01 0c 22', 1.2)])
def test_light_threshold_reply(text, volts):
    msg = p.decode_module_bytes(h(text))
    assert isinstance(msg, p.LightThreshold) and msg.volts == pytest.approx(volts)


def test_attitude_threshold_reply():
    msg = p.decode_module_bytes(h('41 75 20 01 3c 5d'))
    assert isinstance(msg, p.AttitudeThreshold) and msg.degrees == 60


def test_freefall_threshold_and_time_replies():
    g = p.decode_module_bytes(h('41 75 21 01 05 27'))
    t = p.decode_module_bytes(h('41 75 22 01 a0 c3'))
    assert isinstance(g, p.FreefallThreshold) and g.g == pytest.approx(0.5)
    assert isinstance(t, p.FreefallTime) and t.seconds == pytest.approx(1.6)


def test_boot_count_and_baud_replies():
    boot = p.decode_module_bytes(p.module_frame(0x23, 0x07))
    baud = p.decode_module_bytes(h('41 75 24 01 06 2b'))
    assert isinstance(boot, p.BootCount) and boot.count == 7
    assert isinstance(baud, p.BaudRate) and baud.baud == 115200 and baud.code == 6
    assert p.decode_module_bytes(p.module_frame(0x24, 9)).baud is None


def test_zero_ack():
    msg = p.decode_module_bytes(h('41 75 25 01 01 27'))
    assert isinstance(msg, p.ZeroAck) and msg.success


@pytest.mark.parametrize('text,armed', [('41 75 30 01 01 32', True), ('41 75 30 01 00 31', False)])
def test_p7_query_armed_01_means_armed(text, armed):
    """P7: the document labels both values "active"; 0x01 is armed, as for 0x10."""
    msg = p.decode_module_bytes(h(text))
    assert isinstance(msg, p.ArmedState) and msg.armed is armed


@pytest.mark.parametrize('text,trig', [('41 75 31 01 01 33', True), ('41 75 31 01 00 32', False)])
def test_triggered_reply(text, trig):
    msg = p.decode_module_bytes(h(text))
    assert isinstance(msg, p.TriggeredState) and msg.triggered is trig


def test_status_frame_example():
    """P2: the 8-byte 0x32 frame of the document: 7 deg, 1.0 g, not triggered, armed."""
    msg = p.decode_module_bytes(h('41 75 32 07 0a 00 01 44'))
    assert msg == p.Status(tilt_deg=7, accel_g=1.0, triggered=False, armed=True,
                           raw=h('41 75 32 07 0a 00 01 44'))


@pytest.mark.parametrize('text,on', [('41 75 33 01 01 35', True), ('41 75 33 01 00 34', False)])
def test_charging_reply(text, on):
    msg = p.decode_module_bytes(h(text))
    assert isinstance(msg, p.Charging) and msg.charging is on


@pytest.mark.parametrize('raw,volts', [(0xbe, 3.8), (0xc8, 4.0), (0xd2, 4.2)])
@pytest.mark.parametrize('code', [0x34, 0x35])
def test_p3_cell_voltage_with_either_code(code, raw, volts):
    """P3, P9: the document's examples be=3.8 V, c8=4.0 V, d2=4.2 V, coded 0x34 or 0x35."""
    msg = p.decode_module_bytes(p.module_frame(code, raw))
    assert isinstance(msg, p.CellVoltage)
    assert msg.volts == pytest.approx(volts) and msg.code == code


def test_p2_trigger_record_example_decodes_by_byte_position():
    """P2: the document's record; D11=00 and D12=01 decide, not the annotation under them."""
    raw = h('41 75 35 01 01 00 6c 02 3c 05 a0 00 01 0c eb 7e')
    msg = p.decode_module_bytes(raw)
    assert isinstance(msg, p.TriggerRecord)
    assert msg.boot_count == 1
    assert msg.uptime_s == 108  # 1 min 48 s
    assert msg.source == 0x02 and msg.attitude_trigger
    assert not (msg.serial_trigger or msg.pwm_trigger or msg.freefall_trigger)
    assert msg.attitude_threshold_deg == 60
    assert msg.freefall_threshold_g == pytest.approx(0.5)
    assert msg.freefall_time_s == pytest.approx(1.6)
    assert msg.serial_link is False
    assert msg.charging is True
    assert msg.light_threshold_v == pytest.approx(1.2)
    assert msg.cell_voltage_v == pytest.approx(4.70)
    assert msg.raw == raw and not msg.is_empty


def test_trigger_record_builder_round_trips_all_source_bits():
    raw = p.encode_trigger_record(200, 65535, 0x0f, 75, 7, 255, True, False, 30, 0xd2)
    msg = p.decode_module_bytes(raw)
    assert (msg.boot_count, msg.uptime_s) == (200, 65535)
    assert msg.serial_trigger and msg.attitude_trigger and msg.pwm_trigger
    assert msg.freefall_trigger
    assert (msg.serial_link, msg.charging) == (True, False)
    assert msg.freefall_time_s == pytest.approx(2.55)
    assert msg.cell_voltage_v == pytest.approx(4.2)


# ---------------------------------------------------------------------------------------------
# P1: misprinted examples are judged by the rule
# ---------------------------------------------------------------------------------------------

def test_p1_misprinted_attitude_query_reply_is_rejected():
    with pytest.raises(p.ChecksumError):
        p.parse_frame(h('41 75 20 01 3c 50'))
    decoder = p.StreamDecoder()
    assert decoder.feed(h('41 75 20 01 3c 50')) + decoder.flush() == []
    assert decoder.checksum_errors == 1
    assert decoder.bytes_discarded == 6


def test_p1_corrected_attitude_query_reply_is_accepted():
    assert decode_stream(h('41 75 20 01 3c 5d'))[0].degrees == 60


def test_p1_misprinted_trigger_request_rejected_and_corrected_accepted():
    with pytest.raises(p.ChecksumError):
        p.parse_frame(h('42 61 39 02 01 3b'))
    assert decode_stream(h('42 61 39 02 01 3b')) == []
    msgs = decode_stream(h('42 61 39 02 01 3c'))
    assert len(msgs) == 1 and isinstance(msgs[0], p.TriggerRequest)


def test_p1_checksum_covers_d2_to_the_byte_before_it_in_long_frames():
    # A change in D14 of a record or D6 of a status frame must break the checksum.
    record = bytearray(h('41 75 35 01 01 00 6c 02 3c 05 a0 00 01 0c eb 7e'))
    record[14] ^= 0x01
    status = bytearray(h('41 75 32 07 0a 00 01 44'))
    status[6] = 0
    for frame in (record, status):
        with pytest.raises(p.ChecksumError):
            p.parse_frame(frame)


def test_parse_frame_rejects_wrong_header_and_length():
    with pytest.raises(p.FrameError):
        p.parse_frame(h('41 76 30 01 00 31'))
    with pytest.raises(p.FrameError):
        p.parse_frame(h('41 75 30 01 00 31 00'))


# ---------------------------------------------------------------------------------------------
# P3: 0x34/0x35 collision in the stream decoder
# ---------------------------------------------------------------------------------------------

RECORD = h('41 75 35 01 01 00 6c 02 3c 05 a0 00 01 0c eb 7e')
VOLTAGE35 = p.module_frame(0x35, 0xc8)
STATUS = h('41 75 32 07 0a 00 01 44')


def test_p3_voltage_then_record_then_voltage():
    msgs = decode_stream(VOLTAGE35 + RECORD + VOLTAGE35)
    assert [type(m) for m in msgs] == [p.CellVoltage, p.TriggerRecord, p.CellVoltage]


def test_p3_lone_voltage_reply_waits_for_idle_then_is_delivered():
    decoder = p.StreamDecoder()
    assert decoder.feed(VOLTAGE35) == []  # could still become a 16-byte record
    frames = decoder.flush()
    assert [f.raw for f in frames] == [VOLTAGE35]


def test_p3_voltage_reply_followed_by_a_frame_needs_no_flush():
    decoder = p.StreamDecoder()
    frames = decoder.feed(VOLTAGE35 + STATUS)
    assert [f.raw for f in frames] == [VOLTAGE35, STATUS]


def test_p3_record_whose_first_six_bytes_also_check_is_read_as_record():
    """P16: uptime high byte 0x37 makes `41 75 35 01 01 37` a valid 6-byte frame too."""
    record = p.encode_trigger_record(1, 0x3712, 0x08, 60, 5, 160, True, True, 12, 0xd2)
    assert p.checksum(record[2:5]) == record[5]
    decoder = p.StreamDecoder()
    assert decoder.feed(record[:6]) == []
    assert decoder.feed(record[6:12]) == []
    frames = decoder.feed(record[12:])
    assert [f.raw for f in frames] == [record]
    assert p.decode_module_frame(frames[0]).uptime_s == 0x3712


def test_p3_sixteen_byte_candidate_failing_checksum_falls_back_to_voltage():
    # A voltage reply followed by ten bytes of noise that are not a record.
    noise = bytes(range(0x80, 0x8a))
    msgs = decode_stream(VOLTAGE35 + noise)
    assert [type(m) for m in msgs] == [p.CellVoltage]


def test_stream_waits_for_partial_long_frames():
    decoder = p.StreamDecoder()
    assert decoder.feed(RECORD[:15]) == []
    assert decoder.pending == 15
    assert [f.raw for f in decoder.feed(RECORD[15:])] == [RECORD]
    assert decoder.feed(STATUS[:7]) == []
    assert [f.raw for f in decoder.feed(STATUS[7:])] == [STATUS]


def test_status_length_is_dictated_by_code_not_by_a_lucky_6_byte_checksum():
    # 41 75 32 01 01 34 would pass as a 6-byte frame; the 8-byte status frame must win.
    lucky = p.build_frame(p.MODULE_HEADER, 0x32, b'\x01\x01')
    decoder = p.StreamDecoder()
    frames = decoder.feed(lucky + b'\x00\x00') + decoder.flush()
    assert frames == []  # 6-byte 0x32 frames do not exist; 8 bytes fail the checksum


def test_garbage_starting_with_a_header_does_not_stall_the_stream():
    # `41 75 35` followed by noise, then a real reply: resolved once 16 bytes are in.
    reply = p.module_frame(0x30, 1)
    decoder = p.StreamDecoder()
    frames = decoder.feed(h('41 75 35 99') + reply + STATUS + STATUS)
    assert [f.raw for f in frames] == [reply, STATUS, STATUS]
    assert decoder.checksum_errors == 1
    assert decoder.bytes_discarded == 4


def test_flush_drops_an_incomplete_frame_and_keeps_later_ones():
    reply = p.module_frame(0x31, 0)
    decoder = p.StreamDecoder()
    assert decoder.feed(h('41 75 35 07') + reply) == []  # could be a 16-byte record
    frames = decoder.flush()
    assert [f.raw for f in frames] == [reply]
    assert decoder.pending == 0


def test_header_split_across_feeds():
    decoder = p.StreamDecoder()
    assert decoder.feed(b'\x00\x41') == []
    assert decoder.pending == 1
    assert [f.raw for f in decoder.feed(STATUS[1:])] == [STATUS]


def test_unknown_code_with_valid_checksum_is_delivered_and_counted():
    odd = p.module_frame(0x77, 0x05)
    decoder = p.StreamDecoder()
    frames = decoder.feed(odd + STATUS)
    assert [f.raw for f in frames] == [odd, STATUS]
    assert decoder.unknown_frames == 1 and decoder.frames_decoded == 2
    msg = p.decode_module_frame(frames[0])
    assert isinstance(msg, p.UnknownFrame) and msg.code == 0x77


def test_echoed_host_frames_never_look_like_module_replies():
    """An echo of our own heartbeat must not read as an unsolicited module heartbeat (P5)."""
    msgs = decode_stream(p.encode_heartbeat() + p.encode_trigger_confirm() + p.encode_arm(True))
    assert all(isinstance(m, p.UnknownFrame) for m in msgs) and len(msgs) == 3


def test_host_direction_decoder_reads_host_frames_only():
    decoder = p.StreamDecoder('from_host')
    data = STATUS + b'\x13' + p.encode_arm(True) + p.encode_heartbeat()
    frames = decoder.feed(data)
    assert [f.raw for f in frames] == [p.encode_arm(True), p.encode_heartbeat()]
    with pytest.raises(ValueError):
        p.StreamDecoder('sideways')


# ---------------------------------------------------------------------------------------------
# P6, P8, P10, reply matching
# ---------------------------------------------------------------------------------------------

def test_p6_echo_or_01_is_an_acknowledgement():
    echo = p.decode_module_bytes(h('41 75 21 01 05 27'))
    one = p.decode_module_bytes(p.module_frame(0x21, 0x01))
    other = p.decode_module_bytes(p.module_frame(0x21, 0x07))
    assert p.is_set_ack(echo, 0x05)
    assert p.is_set_ack(one, 0x05)
    assert not p.is_set_ack(other, 0x05)
    assert not p.is_set_ack(p.decode_module_bytes(STATUS), 0x05)


TABLE = [('10', True, False), ('00', True, True), ('11', False, False), ('01', False, True)]


@pytest.mark.parametrize('d4,attitude,freefall', TABLE)
def test_p8_flag_table_of_the_document(d4, attitude, freefall):
    raw = p.build_frame(p.MODULE_HEADER, 0x16, bytes((0x01, int(d4, 16))))
    # The document prints these checksums: 27, 17, 28, 18.
    assert raw[-1] == {'10': 0x27, '00': 0x17, '11': 0x28, '01': 0x18}[d4]
    table = p.decode_module_bytes(raw)
    prose = p.decode_module_bytes(raw, layout='prose')
    assert (table.attitude_enabled, table.freefall_enabled) == (attitude, freefall)
    assert (prose.attitude_enabled, prose.freefall_enabled) == (freefall, attitude)
    assert table.layout == 'table' and prose.layout == 'prose'


def test_p8_layout_must_be_known():
    with pytest.raises(ValueError):
        p.decode_auto_trigger_flags(0x10, layout='other')


@pytest.mark.parametrize('layout', ['table', 'prose'])
@pytest.mark.parametrize('attitude', [True, False])
@pytest.mark.parametrize('freefall', [True, False])
def test_p8_flag_byte_round_trip(layout, attitude, freefall):
    value = p.encode_auto_trigger_flags(attitude, freefall, layout)
    assert p.decode_auto_trigger_flags(value, layout) == (attitude, freefall)


def test_reply_matching_knows_the_odd_reply_codes():
    flags = p.decode_module_bytes(h('41 75 16 01 10 27'))
    assert p.reply_matches(p.encode_freefall_trigger(False), flags)  # P8: 0x17 -> 0x16
    assert p.reply_matches(p.encode_cell_voltage_query(), p.decode_module_bytes(VOLTAGE35))
    assert not p.reply_matches(p.encode_armed_query(), p.decode_module_bytes(STATUS))
    # An echo of the command itself is not its reply.
    echo = p.parse_frame(p.encode_armed_query())
    assert not p.reply_matches(p.encode_armed_query(), echo)


@pytest.mark.parametrize('header', [p.MODULE_HEADER, p.HOST_HEADER])
def test_p10_trigger_request_with_either_header(header):
    raw = p.encode_trigger_request(header)
    assert raw[2:] == h('39 02 01 3c')
    msgs = decode_stream(b'\x00' + raw + STATUS)
    assert isinstance(msgs[0], p.TriggerRequest) and msgs[0].header == header
    assert isinstance(msgs[1], p.Status)


# ---------------------------------------------------------------------------------------------
# Encoder ranges and rounding (P9, P13)
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize('encoder,value,words', [
    (p.encode_attitude_threshold_set, 9, ['9', 'deg', '10..90']),
    (p.encode_attitude_threshold_set, 91, ['91', 'deg', '10..90']),
    (p.encode_attitude_threshold_set, 60.5, ['60.5', 'deg', '10..90']),
    (p.encode_attitude_threshold_set, True, ['deg']),
    (p.encode_freefall_threshold_set, 0.04, ['0.04', 'g', '0.1..0.9']),
    (p.encode_freefall_threshold_set, 0.95, ['0.95', 'g', '0.1..0.9']),
    (p.encode_freefall_threshold_set, float('nan'), ['nan', 'g', '0.1..0.9']),
    (p.encode_freefall_time_set, 0.004, ['0.004', 's', '0.01..2.55']),
    (p.encode_freefall_time_set, 2.56, ['2.56', 's', '0.01..2.55']),
    (p.encode_freefall_time_set, -1.0, ['-1', 's']),
    (p.encode_light_threshold_set, 25.6, ['25.6', 'V', '0..25.5']),
    (p.encode_light_threshold_set, -0.1, ['-0.1', 'V']),
    (p.encode_light_threshold_set, '1.2', ['V']),
    (p.encode_baud_rate_set, 100000, ['100000', 'bit/s', '115200']),
])
def test_out_of_range_values_are_refused_with_value_unit_and_range(encoder, value, words):
    with pytest.raises(p.ProtocolRangeError) as info:
        encoder(value)
    assert isinstance(info.value, ValueError)
    for word in words:
        assert word in str(info.value)


@pytest.mark.parametrize('g,raw', [(0.55, 6), (0.45, 5), (0.14, 1), (0.9, 9), (0.7, 7)])
def test_freefall_threshold_rounds_to_nearest_tenth_halves_up(g, raw):
    assert p.encode_freefall_threshold_set(g)[4] == raw


@pytest.mark.parametrize('s,raw', [(1.605, 161), (0.01, 1), (2.55, 255), (0.3, 30), (1.0, 100)])
def test_freefall_time_rounds_to_hundredths(s, raw):
    assert p.encode_freefall_time_set(s)[4] == raw


def test_attitude_threshold_accepts_whole_float_degrees_and_range_ends():
    assert p.encode_attitude_threshold_set(75.0)[4] == 75
    assert p.encode_attitude_threshold_set(10)[4] == 10
    assert p.encode_attitude_threshold_set(90)[4] == 90


@pytest.mark.parametrize('baud,code', sorted((b, c) for c, b in p.BAUD_CODES.items()))
def test_every_documented_baud_code(baud, code):
    frame = p.encode_baud_rate_set(baud)
    assert frame[4] == code
    assert p.decode_module_bytes(p.module_frame(0x24, code)).baud == baud


@given(st.integers(1, 9))
def test_every_freefall_threshold_step_round_trips(raw):
    assert p.freefall_threshold_to_raw(raw / 10) == raw
    assert p.decode_module_bytes(p.module_frame(0x21, raw)).g == pytest.approx(raw / 10)


@given(st.integers(1, 255))
def test_every_freefall_time_step_round_trips(raw):
    assert p.freefall_time_to_raw(raw / 100) == raw
    assert p.freefall_time_to_raw(raw * 0.01) == raw


@given(st.integers(0, 255))
def test_every_light_threshold_step_round_trips(raw):
    assert p.light_threshold_to_raw(raw / 10) == raw
    assert p.light_threshold_to_raw(raw * 0.1) == raw


# ---------------------------------------------------------------------------------------------
# Stream decoder properties
# ---------------------------------------------------------------------------------------------

@settings(max_examples=300)
@given(st.binary(max_size=400), st.lists(st.integers(0, 10_000), max_size=20),
       st.sampled_from(['from_module', 'from_host']))
def test_random_bytes_never_raise_and_every_byte_is_accounted_for(data, cuts, direction):
    decoder = p.StreamDecoder(direction)
    frames = []
    for chunk in split(data, cuts):
        frames += decoder.feed(chunk)
    in_frames = sum(len(f.raw) for f in frames)
    assert in_frames + decoder.bytes_discarded + decoder.pending == len(data)
    frames += decoder.flush()
    assert decoder.pending == 0
    assert sum(len(f.raw) for f in frames) + decoder.bytes_discarded == len(data)
    for frame in frames:
        assert p.parse_frame(frame.raw) == frame
        p.decode_module_frame(frame)  # typing a delivered frame never raises either


byte = st.integers(0, 255)
bit = st.booleans()

module_frames = st.one_of(
    st.builds(p.module_frame, st.sampled_from(sorted(p.MODULE_CODES - {0x32, 0x35, 0x01})), byte),
    st.builds(p.module_frame, st.sampled_from([0x34, 0x35]), byte),
    st.builds(p.encode_status_frame, byte, byte, bit, bit),
    st.builds(p.encode_trigger_record, byte, st.integers(0, 0xFFFF), st.integers(0, 15),
              byte, byte, byte, bit, bit, byte, byte),
    st.builds(p.encode_trigger_request, st.sampled_from([p.MODULE_HEADER, p.HOST_HEADER])),
    st.just(p.encode_module_heartbeat()),
)
host_frames = st.builds(p.host_frame, st.sampled_from(sorted(p.HOST_CODES)),
                        st.sampled_from([1, 2]), byte)
# Noise that cannot hold a header, nor pose as the source/link bytes of a record (P16).
noise = st.binary(max_size=12).map(
    lambda b: bytes(x for x in b if x >= 0x10 and x not in (0x41, 0x42)))


@settings(max_examples=300)
@given(st.lists(st.tuples(noise, module_frames), max_size=25), noise,
       st.lists(st.integers(0, 10_000), max_size=30))
def test_module_frames_in_noise_split_anywhere_are_all_recovered(pieces, tail, cuts):
    data = b''.join(n + f for n, f in pieces) + tail
    decoder = p.StreamDecoder()
    frames = []
    for chunk in split(data, cuts):
        frames += decoder.feed(chunk)
    frames += decoder.flush()
    assert [f.raw for f in frames] == [f for _, f in pieces]
    assert decoder.checksum_errors == 0
    assert decoder.bytes_discarded == sum(len(n) for n, _ in pieces) + len(tail)


@settings(max_examples=200)
@given(st.lists(st.tuples(noise, host_frames), max_size=25),
       st.lists(st.integers(0, 10_000), max_size=30))
def test_host_frames_in_noise_split_anywhere_are_all_recovered(pieces, cuts):
    data = b''.join(n + f for n, f in pieces)
    decoder = p.StreamDecoder('from_host')
    frames = []
    for chunk in split(data, cuts):
        frames += decoder.feed(chunk)
    assert [f.raw for f in frames] == [f for _, f in pieces]
    assert decoder.pending == 0 or decoder.flush() == []


@settings(max_examples=100)
@given(st.lists(module_frames, min_size=1, max_size=10), st.binary(min_size=1, max_size=30))
def test_frames_after_arbitrary_garbage_are_recovered_once_resynced(frames, garbage):
    # Arbitrary garbage may swallow at most what follows it until a status frame resyncs;
    # frames after three consecutive status frames are always recovered.
    sync = STATUS * 3
    data = garbage + sync + b''.join(frames)
    decoder = p.StreamDecoder()
    got = [f.raw for f in decoder.feed(data) + decoder.flush()]
    assert got[-len(frames):] == frames
