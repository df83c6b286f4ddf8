"""Handset link protocol: golden frames, decisions H1-H7 and H10, stream-decoder properties."""

from dataclasses import replace
import json
import math
import struct

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

from handset_link_ros import protocol as p
from support import split

T = p.CommandType


def h(text: str) -> bytes:
    """Bytes from a hex string with spaces, as the document prints frames."""
    return bytes.fromhex(text)


def decode_all(data: bytes) -> list:
    """Decode a whole capture (fed at once, then flushed)."""
    decoder = p.StreamDecoder()
    return decoder.feed(data) + decoder.flush()


def commands(results: list) -> list:
    return [(r.type, r.value, r.encoding) for r in results if isinstance(r, p.Command)]


def kinds(results: list) -> list:
    return [type(r).__name__ for r in results]


YAW_90_INT8 = h('AA 03 01 5A F2 55')
YAW_90_JSON = h('AA 0D 01 7B 22 79 61 77 22 3A 20 39 30 7D DC 55')
PITCH_M45_JSON = h('AA 10 02 7B 22 70 69 74 63 68 22 3A 20 2D 34 35 7D EE 55')


# ---------------------------------------------------------------------------------------------
# H1 frame, H2 checksum: the golden frames
# ---------------------------------------------------------------------------------------------

def test_h2_golden_frames_are_built_by_the_encoders():
    assert p.encode_set_yaw(90, 'int8') == YAW_90_INT8
    assert p.encode_set_yaw(90) == YAW_90_JSON
    assert p.encode_set_pitch(-45) == PITCH_M45_JSON


@pytest.mark.parametrize('frame,type_,value,encoding', [
    (YAW_90_INT8, T.SET_YAW, 90.0, 'int8'),
    (YAW_90_JSON, T.SET_YAW, 90.0, 'json'),
    (PITCH_M45_JSON, T.SET_PITCH, -45.0, 'json'),
])
def test_h2_golden_frames_decode(frame, type_, value, encoding):
    result = p.decode_frame(frame)
    assert isinstance(result, p.Command)
    assert (result.type, result.value, result.encoding, result.raw) == \
        (type_, value, encoding, frame)
    assert commands(decode_all(frame)) == [(type_, value, encoding)]


OUR_GOLDEN = [
    (T.SET_YAW, -180, 'int16', 'AA 04 01 4C FF 1C 55'),
    (T.SET_ALTITUDE, 12.5, 'float32', 'AA 06 04 00 00 48 41 A1 55'),
    (T.SET_LIGHTS, 75, 'int8', 'AA 03 05 4B E7 55'),
    (T.SET_ROLL, -12, 'int8', 'AA 03 03 F4 5E 55'),
    (T.SET_CAMERA_RECORD, True, 'json',
     'AA 12 07 7B 22 72 65 63 6F 72 64 22 3A 20 74 72 75 65 7D B8 55'),
    (T.SET_CAMERA_ANGLE, -30, 'json',
     'AA 17 06 7B 22 63 61 6D 65 72 61 5F 61 6E 67 6C 65 22 3A 20 2D 33 30 7D AE 55'),
]


@pytest.mark.parametrize('type_,value,encoding,frame', OUR_GOLDEN,
                         ids=[f'{t.name}-{e}' for t, _, e, _ in OUR_GOLDEN])
def test_h5_golden_frames_of_the_other_encodings(type_, value, encoding, frame):
    # Not from the document: pinned from the rules (docs/protocols.md), so they cannot drift.
    assert p.encode_command(type_, value, encoding) == h(frame)
    result = p.decode_frame(h(frame))
    assert (result.type, result.value, result.encoding) == (type_, value, encoding)


def test_h2_checksum_is_the_xor_of_everything_before_it_start_byte_included():
    assert p.checksum(YAW_90_INT8[:4]) == 0xF2
    # Leaving the start byte out gives another value: the document's code includes it.
    assert p.checksum(YAW_90_INT8[1:4]) == 0xF2 ^ 0xAA
    for frame in (YAW_90_JSON, PITCH_M45_JSON):
        assert p.checksum(frame[:-2]) == frame[-2]


def test_h1_len_counts_payload_plus_checksum_and_end_byte_not_the_type():
    for frame in (YAW_90_INT8, YAW_90_JSON, PITCH_M45_JSON):
        payload = frame[3:-2]
        assert frame[1] == len(payload) + 2
        assert len(frame) == frame[1] + 3
        assert (frame[0], frame[-1]) == (0xAA, 0x55)


def test_h1_payload_is_at_most_253_bytes():
    longest = p.build_frame(0x01, bytes(253))
    assert longest[1] == 255 and len(longest) == 258
    with pytest.raises(p.ProtocolError):
        p.build_frame(0x01, bytes(254))
    # The longest frame is sound, its payload is not a yaw (H5).
    result = decode_all(longest)
    assert kinds(result) == ['Malformed'] and result[0].type == T.SET_YAW


@pytest.mark.parametrize('length', [0, 1])
def test_h1_len_below_2_is_invalid(length):
    decoder = p.StreamDecoder()
    results = decoder.feed(bytes([0xAA, length]) + YAW_90_INT8)
    assert kinds(results) == ['Malformed', 'Command']
    assert f'LEN {length}' in results[0].reason
    assert decoder.frames_malformed == 1 and decoder.frames_accepted == 1


def test_h1_empty_payload_is_a_sound_frame_but_no_command():
    frame = p.build_frame(0x01, b'')
    assert frame == h('AA 02 01 A9 55')
    result = p.decode_frame(frame)
    assert isinstance(result, p.Malformed) and result.type == T.SET_YAW


# ---------------------------------------------------------------------------------------------
# H3 receiving: resynchronisation, truncation, silence
# ---------------------------------------------------------------------------------------------

def test_h3_garbage_before_a_frame_is_skipped():
    decoder = p.StreamDecoder()
    results = decoder.feed(h('00 13 55 FF 7B') + YAW_90_JSON)
    assert commands(results) == [(T.SET_YAW, 90.0, 'json')]
    assert decoder.frames_malformed == 0 and decoder.bytes_discarded == 5


def test_h3_resync_after_truncated_frame_finds_the_good_frame_behind_it():
    # The start of a yaw frame, cut after its TYPE: the next frame begins inside its 6 bytes.
    decoder = p.StreamDecoder()
    results = decoder.feed(h('AA 03 01') + YAW_90_INT8)
    assert kinds(results) == ['Malformed', 'Command']
    assert 'end byte' in results[0].reason
    assert commands(results) == [(T.SET_YAW, 90.0, 'int8')]


def test_h12_h3_resync_after_truncated_long_frame_does_not_wait_for_its_length():
    # A cut JSON frame announces 16 bytes; the good frame inside them is delivered at once.
    decoder = p.StreamDecoder()
    results = decoder.feed(YAW_90_JSON[:5] + YAW_90_INT8)
    assert kinds(results) == ['Malformed', 'Command']
    assert 'truncated' in results[0].reason
    assert decoder.pending == 0


def test_h12_a_false_start_in_noise_does_not_delay_the_frames_behind_it():
    # Noise AA FF announces a 258-byte frame; the real frame after it is taken at once.
    decoder = p.StreamDecoder()
    results = decoder.feed(h('00 AA FF 13') + YAW_90_INT8)
    assert kinds(results) == ['Malformed', 'Command'] and decoder.pending == 0


def test_h12_a_complete_false_start_whose_checksum_matches_by_chance_keeps_the_frame_inside():
    # The model search's finding: 21 bytes of truncated frames and noise whose end byte and XOR
    # checksum happen to be right; its payload is malformed, and the yaw frame inside is taken.
    for chunks in ([h('AA 12 04 3B 44 AE 25 77 95 E7 EB AA 0D 01 AA 04 01 2D 00 82 55')],
                   [h('AA 12 04'), h('3B 44 AE'), h('25 77 95 E7 EB'), h('AA 0D 01'),
                    h('AA 04 01 2D 00 82 55')]):
        decoder = p.StreamDecoder()
        results = [r for chunk in chunks for r in decoder.feed(chunk)]
        assert commands(results) == [(T.SET_YAW, 45.0, 'int16')]
        assert decoder.pending == 0 and decoder.frames_accepted == 1


def test_h3_resync_after_bad_checksum():
    bad = bytearray(YAW_90_JSON)
    bad[-2] ^= 0x01
    decoder = p.StreamDecoder()
    results = decoder.feed(bytes(bad) + PITCH_M45_JSON)
    assert kinds(results) == ['Malformed', 'Command']
    assert 'checksum 0xDD, expected 0xDC' in results[0].reason
    assert commands(results) == [(T.SET_PITCH, -45.0, 'json')]


def test_h3_resync_after_bad_end_byte():
    bad = YAW_90_INT8[:-1] + b'\x54'
    decoder = p.StreamDecoder()
    results = decoder.feed(bad + YAW_90_INT8)
    assert kinds(results) == ['Malformed', 'Command']
    assert 'end byte 0x54' in results[0].reason


def test_h3_a_bad_frame_is_never_half_applied():
    # The corrupted payload byte makes the checksum fail: nothing of the frame is delivered.
    bad = bytearray(YAW_90_JSON)
    bad[11] = ord('1')
    results = decode_all(bytes(bad))
    assert commands(results) == [] and kinds(results) == ['Malformed']


def test_h3_resync_inside_a_bad_frame_with_a_start_byte_in_its_payload():
    # An int8 value of -86 is the byte AA: the failed frame's payload is tried as a start.
    bad = bytearray(p.encode_set_yaw(-86, 'int8'))
    bad[-2] ^= 0xFF
    decoder = p.StreamDecoder()
    results = decoder.feed(bytes(bad) + YAW_90_INT8)
    assert commands(results) == [(T.SET_YAW, 90.0, 'int8')]
    assert decoder.pending == 0


def test_h3_partial_frame_then_0_1_s_of_silence_is_malformed():
    decoder = p.StreamDecoder()
    assert decoder.feed(YAW_90_JSON[:7], now=10.0) == []
    assert decoder.flush(10.099) == []
    assert decoder.pending == 7
    results = decoder.flush(10.1)
    assert kinds(results) == ['Malformed'] and 'silence' in results[0].reason
    assert decoder.pending == 0 and decoder.frames_malformed == 1


def test_h3_partial_frame_then_silence_then_bytes_settles_the_partial_first():
    decoder = p.StreamDecoder()
    decoder.feed(YAW_90_JSON[:7], now=10.0)
    # The rest comes too late: the partial is malformed, and the late tail is no frame.
    results = decoder.feed(YAW_90_JSON[7:] + YAW_90_INT8, now=10.2)
    assert kinds(results) == ['Malformed', 'Command']
    assert commands(results) == [(T.SET_YAW, 90.0, 'int8')]


def test_h3_a_frame_split_by_less_than_0_1_s_is_whole():
    decoder = p.StreamDecoder()
    assert decoder.feed(YAW_90_JSON[:7], now=10.0) == []
    assert decoder.flush(10.05) == []
    results = decoder.feed(YAW_90_JSON[7:], now=10.09)
    assert commands(results) == [(T.SET_YAW, 90.0, 'json')]


def test_h3_flush_without_a_time_settles_at_once():
    decoder = p.StreamDecoder()
    decoder.feed(b'\xaa')
    assert decoder.idle_deadline() is None  # no time given, nothing to schedule
    results = decoder.flush()
    assert kinds(results) == ['Malformed'] and decoder.pending == 0


def test_h3_idle_deadline_is_0_1_s_after_the_last_bytes():
    decoder = p.StreamDecoder()
    decoder.feed(YAW_90_JSON[:3], now=5.0)
    assert decoder.idle_deadline() == pytest.approx(5.1)
    decoder.feed(YAW_90_JSON[3:], now=5.05)
    assert decoder.idle_deadline() is None


def test_h13_h3_counters_tell_the_kinds_of_rejection_apart():
    too_far = p.encode_command(T.SET_YAW, 200, check=False)
    bad_checksum = YAW_90_INT8[:-2] + b'\x00\x55'
    data = YAW_90_INT8 + p.build_frame(0x09, b'\x01') + too_far + bad_checksum
    decoder = p.StreamDecoder()
    decoder.feed(data)
    assert (decoder.frames_accepted, decoder.frames_unknown_type, decoder.frames_out_of_range,
            decoder.frames_malformed) == (1, 1, 1, 1)


# ---------------------------------------------------------------------------------------------
# H4 types and ranges
# ---------------------------------------------------------------------------------------------

RANGES = [
    (T.SET_YAW, -180, 180), (T.SET_PITCH, -90, 90), (T.SET_ROLL, -90, 90),
    (T.SET_ALTITUDE, -100, 1000), (T.SET_LIGHTS, 0, 100), (T.SET_CAMERA_ANGLE, -90, 90),
    (T.SET_CAMERA_RECORD, 0, 1),
]


def test_h4_the_seven_types_and_their_codes():
    assert [(int(t), t.name) for t in T] == [
        (1, 'SET_YAW'), (2, 'SET_PITCH'), (3, 'SET_ROLL'), (4, 'SET_ALTITUDE'),
        (5, 'SET_LIGHTS'), (6, 'SET_CAMERA_ANGLE'), (7, 'SET_CAMERA_RECORD')]
    assert [(s.type, s.lo, s.hi) for s in p.SPECS.values()] == RANGES


@pytest.mark.parametrize('type_,lo,hi', RANGES, ids=[t.name for t, _, _ in RANGES])
def test_h4_range_ends_are_accepted_and_beyond_them_refused(type_, lo, hi):
    for value in (lo, hi):
        assert isinstance(p.decode_frame(p.encode_command(type_, value, 'int16')), p.Command)
    for value in (lo - 1, hi + 1):
        result = p.decode_frame(p.encode_command(type_, value, 'int16', check=False))
        assert isinstance(result, p.OutOfRange) and result.type == type_
        assert result.value == value


@pytest.mark.parametrize('code', [0x00, 0x08, 0x55, 0xAA, 0xFF])
def test_h4_unknown_type_is_counted_and_ignored(code):
    decoder = p.StreamDecoder()
    results = decoder.feed(p.build_frame(code, b'\x01') + YAW_90_INT8)
    assert isinstance(results[0], p.UnknownType) and results[0].type == code
    assert commands(results) == [(T.SET_YAW, 90.0, 'int8')]
    assert decoder.frames_unknown_type == 1 and decoder.frames_malformed == 0


# ---------------------------------------------------------------------------------------------
# H5 payload encodings
# ---------------------------------------------------------------------------------------------

def json_frame(type_: int, text: str) -> bytes:
    return p.build_frame(type_, text.encode())


@pytest.mark.parametrize('type_,key', [(s.type, s.key) for s in p.SPECS.values()])
def test_h5_json_takes_the_one_key_of_its_type(type_, key):
    result = p.decode_frame(json_frame(type_, f'{{"{key}": 1}}'))
    assert isinstance(result, p.Command) and result.field == key and result.encoding == 'json'
    other = 'yaw' if key != 'yaw' else 'pitch'
    assert isinstance(p.decode_frame(json_frame(type_, f'{{"{other}": 1}}')), p.Malformed)


@pytest.mark.parametrize('text,value', [('{"record": true}', True), ('{"record": false}', False),
                                        ('{"record": 1}', True), ('{"record": 0}', False),
                                        ('{"record":1.0}', True)])
def test_h5_record_takes_true_false_and_one_zero(text, value):
    result = p.decode_frame(json_frame(T.SET_CAMERA_RECORD, text))
    assert isinstance(result, p.Command) and result.value is value


@pytest.mark.parametrize('text', [
    '{"yaw": NaN}', '{"yaw": Infinity}', '{"yaw": -Infinity}', '{"yaw": 1e400}',
    '{"yaw": -1e309}', '{"yaw": 1' + '0' * 240 + 'e99}', '{"yaw": "90"}', '{"yaw": true}',
    '{"yaw": null}', '{"yaw": [90]}', '{"yaw": {"v": 90}}', '{"yaw": 90, "pitch": 1}',
    '{"yaw": 90, "yaw": 91}', '{}', '{"Yaw": 90}', '{"yaw": 90,}', "{'yaw': 90}",
    '{"yaw": 090}', '{"yaw": 90} {"yaw": 1}', '{"yaw": +90}',
])
def test_h5_json_is_strict_and_anything_else_is_malformed(text):
    result = p.decode_frame(json_frame(T.SET_YAW, text))
    assert isinstance(result, p.Malformed), result
    assert result.type == T.SET_YAW


def test_h5_json_that_is_not_utf8_is_malformed():
    result = p.decode_frame(p.build_frame(T.SET_YAW, b'{"yaw": 9\xff}'))
    assert isinstance(result, p.Malformed) and 'UTF-8' in result.reason


def test_h5_json_must_start_and_end_with_braces():
    # Whitespace outside the braces makes it binary, whose length then fits no binary form.
    for text in (' {"yaw": 90}', '{"yaw": 90} ', '[ 90 ]'):
        result = p.decode_frame(json_frame(T.SET_YAW, text))
        assert isinstance(result, p.Malformed) and 'neither JSON nor' in result.reason


def test_h5_json_numbers_keep_their_fraction():
    result = p.decode_frame(json_frame(T.SET_YAW, '{"yaw": -12.75}'))
    assert result.value == -12.75


@pytest.mark.parametrize('type_,payload,encoding,value', [
    (T.SET_YAW, h('5A'), 'int8', 90.0), (T.SET_YAW, h('D3'), 'int8', -45.0),
    (T.SET_YAW, h('80'), 'int8', -128.0), (T.SET_YAW, h('B4 00'), 'int16', 180.0),
    (T.SET_YAW, h('4C FF'), 'int16', -180.0), (T.SET_ALTITUDE, h('E8 03'), 'int16', 1000.0),
    (T.SET_ALTITUDE, struct.pack('<f', 12.5), 'float32', 12.5),
    (T.SET_YAW, struct.pack('<f', -179.75), 'float32', -179.75),
])
def test_h5_binary_by_payload_length_little_endian(type_, payload, encoding, value):
    result = p.decode_frame(p.build_frame(type_, payload))
    assert isinstance(result, p.Command)
    assert (result.value, result.encoding) == (value, encoding)


@pytest.mark.parametrize('length', [0, 3, 5, 8, 16])
def test_h5_binary_of_another_length_is_malformed(length):
    result = p.decode_frame(p.build_frame(T.SET_YAW, bytes(length)))
    assert isinstance(result, p.Malformed) and result.type == T.SET_YAW


def test_h5_braces_in_binary_never_hide_a_valid_value():
    # A 2- or 4-byte payload 7B .. 7D is read as JSON; as binary it would be out of every range.
    assert struct.unpack('<h', h('7B 7D'))[0] == 32123
    assert abs(struct.unpack('<f', h('7B 00 00 7D'))[0]) > 1e36
    assert isinstance(p.decode_frame(p.build_frame(T.SET_ALTITUDE, h('7B 7D'))), p.Malformed)


@pytest.mark.parametrize('encoding', p.ENCODINGS)
def test_h5_the_encoders_write_every_encoding(encoding):
    frame = p.encode_set_roll(-12, encoding)
    result = p.decode_frame(frame)
    assert isinstance(result, p.Command) and result.encoding == encoding
    assert result.value == -12.0


# ---------------------------------------------------------------------------------------------
# H6 validation
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize('value', [math.nan, math.inf, -math.inf])
def test_h6_nan_and_inf_float32_are_out_of_range(value):
    result = p.decode_frame(p.encode_command(T.SET_YAW, value, 'float32', check=False))
    assert isinstance(result, p.OutOfRange) and 'finite' in result.reason


@pytest.mark.parametrize('type_,encoding,value', [
    (T.SET_LIGHTS, 'json', 50.5), (T.SET_LIGHTS, 'float32', 50.5),
    (T.SET_CAMERA_RECORD, 'json', 0.5), (T.SET_CAMERA_RECORD, 'float32', 0.25),
])
def test_h6_fraction_for_a_whole_field_is_out_of_range_not_rounded(type_, encoding, value):
    result = p.decode_frame(p.encode_command(type_, value, encoding, check=False))
    assert isinstance(result, p.OutOfRange) and 'whole' in result.reason
    assert result.value == value


def test_h6_whole_values_in_any_form_are_fine_for_whole_fields():
    for frame in (p.encode_command(T.SET_LIGHTS, 50.0, 'float32'),
                  json_frame(T.SET_LIGHTS, '{"lights": 50.0}'),
                  p.encode_set_lights(50, 'int8')):
        result = p.decode_frame(frame)
        assert isinstance(result, p.Command) and result.value == 50
        assert isinstance(result.value, int)


@pytest.mark.parametrize('type_,value', [(T.SET_YAW, 180.5), (T.SET_ALTITUDE, -100.01),
                                         (T.SET_PITCH, 127), (T.SET_LIGHTS, -1)])
def test_h6_out_of_range_is_refused_whole_never_clamped(type_, value):
    decoder = p.StreamDecoder()
    results = decoder.feed(p.encode_command(type_, value, 'json', check=False))
    assert kinds(results) == ['OutOfRange'] and results[0].value == value
    assert decoder.frames_out_of_range == 1 and decoder.frames_accepted == 0


@pytest.mark.parametrize('type_,value,encoding', [
    (T.SET_YAW, 181, 'json'), (T.SET_YAW, math.nan, 'float32'), (T.SET_LIGHTS, 1.5, 'json'),
    (T.SET_YAW, 90.5, 'int8'), (T.SET_YAW, 150, 'int8'), (T.SET_PITCH, True, 'json'),
    (T.SET_YAW, '90', 'json'),
])
def test_h6_encoders_refuse_what_the_driver_would_refuse(type_, value, encoding):
    with pytest.raises(p.ProtocolRangeError):
        p.encode_command(type_, value, encoding)


def test_h6_unknown_type_and_encoding_are_refused_by_the_encoder():
    with pytest.raises(p.ProtocolError):
        p.encode_command(0x08, 1)
    with pytest.raises(p.ProtocolError):
        p.encode_command(T.SET_YAW, 1, 'int32')


# ---------------------------------------------------------------------------------------------
# H7 delivery, H10 nothing flown here
# ---------------------------------------------------------------------------------------------

def test_h7_a_frame_is_returned_by_the_feed_that_completes_it():
    # No waiting for a following byte or an idle flush: the last byte settles the frame.
    decoder = p.StreamDecoder()
    for frame in (YAW_90_INT8, YAW_90_JSON, PITCH_M45_JSON):
        assert decoder.feed(frame[:-1], now=1.0) == []
        assert commands(decoder.feed(frame[-1:], now=1.001))
        assert decoder.pending == 0


def test_h7_bytes_after_tells_how_far_behind_the_read_a_frame_ended():
    results = p.StreamDecoder().feed(YAW_90_INT8 + PITCH_M45_JSON + b'\xaa\x0d')
    assert [r.bytes_after for r in results] == [len(PITCH_M45_JSON) + 2, 2]


def test_h10_tilt_beyond_30_deg_is_passed_on_unchanged():
    # Stabilising beyond 30 deg is the flight controller's (H10): the link neither limits nor
    # refuses such angles.
    for type_ in (T.SET_PITCH, T.SET_ROLL):
        for value in (45.0, -80.0, 90.0):
            assert p.decode_frame(p.encode_command(type_, value, 'float32')).value == value


# ---------------------------------------------------------------------------------------------
# Properties
# ---------------------------------------------------------------------------------------------

def _values(spec: p.CommandSpec, encoding: str):
    lo, hi = int(spec.lo), int(spec.hi)
    if encoding == 'int8':
        return st.integers(max(lo, -128), min(hi, 127))
    if encoding == 'int16' or spec.whole:
        ints = st.integers(lo, hi)
        if encoding == 'float32':
            return ints.map(float)
        if encoding == 'json' and spec.type == T.SET_CAMERA_RECORD:
            return st.one_of(ints, st.booleans())
        return ints
    if encoding == 'float32':
        return st.floats(lo, hi, width=32)
    return st.one_of(st.integers(lo, hi), st.floats(lo, hi, allow_nan=False))


type_encoding = st.sampled_from(list(p.SPECS.values())).flatmap(
    lambda spec: st.sampled_from(p.ENCODINGS).flatmap(
        lambda enc: st.tuples(st.just(spec), st.just(enc), _values(spec, enc))))


@settings(max_examples=500)
@given(type_encoding)
def test_every_type_and_encoding_round_trips(case):
    spec, encoding, value = case
    frame = p.encode_command(spec.type, value, encoding)
    result = p.decode_frame(frame)
    assert isinstance(result, p.Command), result
    assert (result.type, result.field, result.encoding) == (spec.type, spec.key, encoding)
    assert result.value == p.normalize(spec.type, value)
    assert type(result.value) is type(p.normalize(spec.type, value))
    assert commands(decode_all(frame)) == [(spec.type, result.value, encoding)]


valid_frames = type_encoding.map(lambda c: p.encode_command(c[0].type, c[2], c[1]))
noise = st.binary(max_size=12).map(lambda b: bytes(x for x in b if x != 0xAA))


@settings(max_examples=300)
@given(st.lists(st.tuples(noise, valid_frames), max_size=20), noise,
       st.lists(st.integers(0, 10_000), max_size=30))
def test_frames_in_noise_split_anywhere_are_all_recovered_in_order(pieces, tail, cuts):
    data = b''.join(n + f for n, f in pieces) + tail
    decoder = p.StreamDecoder()
    results = []
    for chunk in split(data, cuts):
        results += decoder.feed(chunk)
    results += decoder.flush()
    assert [r.raw for r in results] == [f for _, f in pieces]
    assert all(isinstance(r, p.Command) for r in results)
    assert decoder.frames_malformed == 0
    assert decoder.bytes_discarded == sum(len(n) for n, _ in pieces) + len(tail)


@settings(max_examples=300)
@given(st.binary(max_size=600), st.lists(st.integers(0, 10_000), max_size=20))
def test_h13_random_bytes_never_raise_and_every_byte_is_accounted_for(data, cuts):
    decoder = p.StreamDecoder()
    results = []
    for chunk in split(data, cuts):
        results += decoder.feed(chunk)
    results += decoder.flush()
    assert decoder.pending == 0
    sound = [r for r in results if not (isinstance(r, p.Malformed) and r.type is None)]
    assert sum(len(r.raw) for r in sound) + decoder.bytes_discarded == len(data)
    for result in sound:
        assert p.decode_frame(result.raw) == replace(result, bytes_after=0)


@settings(max_examples=100)
@given(st.binary(min_size=1, max_size=40), st.lists(valid_frames, min_size=1, max_size=8))
def test_frames_after_any_garbage_and_a_quiet_line_are_recovered(garbage, frames):
    # Whatever the garbage, the line going quiet settles it; every frame after that is taken.
    decoder = p.StreamDecoder()
    decoder.feed(garbage, now=0.0)
    results = decoder.feed(b''.join(frames), now=0.2)
    assert [r.raw for r in results if isinstance(r, p.Command)] == frames


def test_json_encoder_writes_what_the_document_writes():
    assert p.encode_payload(T.SET_YAW, 90) == json.dumps({'yaw': 90}).encode()
    assert p.encode_payload(T.SET_CAMERA_RECORD, True) == b'{"record": true}'
    assert p.encode_payload(T.SET_LIGHTS, 40.0) == b'{"lights": 40}'
