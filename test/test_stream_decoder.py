"""The shared stream decoder (issue 22, item 5): resync, garbage, split frames, counters.

A toy protocol exercises the base alone: ``A5 5A LEN PAYLOAD[LEN] SUM`` with ``SUM`` the low
byte of the sum of LEN and the payload; LEN over 16 is no frame. A second toy adds a header of
the other direction (``5B 5B``, fixed 4-byte frames) to exercise the two-header loop.
"""

from hypothesis import given, settings, strategies as st
import pytest

from uav_serial_common import stream_decoder as sd

HEADER = b'\xa5\x5a'
OTHER = b'\x5b\x5b'


def frame(payload: bytes) -> bytes:
    """A toy frame carrying ``payload``."""
    body = bytes([len(payload)]) + payload
    return HEADER + body + bytes([sum(body) & 0xFF])


def other(value: int) -> bytes:
    """A toy frame of the second header: ``5B 5B VALUE ~VALUE``."""
    return OTHER + bytes([value, ~value & 0xFF])


class Toy(sd.StreamDecoder):
    """The toy protocol's decoder: delivers each frame's raw bytes."""

    headers = (HEADER,)

    def _candidate(self, buf, pos, n, final, out):
        if n - pos < 3:
            return sd.WAIT
        length = buf[pos + 2]
        if length > 16:
            return sd.DROP
        end = pos + length + 4
        if end > n:
            return sd.WAIT
        if sum(buf[pos + 2:end - 1]) & 0xFF != buf[end - 1]:
            return sd.BAD_CHECKSUM
        out.append(bytes(buf[pos:end]))
        return end - pos


class TwoHeaders(Toy):
    """The toy decoder that also takes the second header's frames."""

    headers = (HEADER, OTHER)

    def _candidate(self, buf, pos, n, final, out):
        if buf[pos] == HEADER[0]:
            return super()._candidate(buf, pos, n, final, out)
        if n - pos < 4:
            return sd.WAIT
        if buf[pos + 2] ^ buf[pos + 3] != 0xFF:
            return sd.BAD_CHECKSUM
        out.append(bytes(buf[pos:pos + 4]))
        return 4


FRAMES = [frame(b''), frame(b'\x01\x02\x03'), frame(bytes(range(16))), frame(HEADER * 3)]


def feed_all(decoder, chunks):
    out = []
    for chunk in chunks:
        out += decoder.feed(chunk)
    return out


def accounted(decoder, frames, total):
    """Every byte fed is in a frame, discarded or still pending."""
    return sum(len(f) for f in frames) + decoder.bytes_discarded + decoder.pending == total


def test_clean_frames_are_delivered_in_order_with_nothing_discarded():
    dec = Toy()
    stream = b''.join(FRAMES)
    assert dec.feed(stream) == FRAMES
    assert (dec.frames_decoded, dec.checksum_errors, dec.bytes_discarded, dec.pending) == \
        (4, 0, 0, 0)


def test_garbage_between_frames_is_counted_and_skipped():
    dec = Toy()
    noise = [b'\x00\x11', b'\xa5\xa5\x00', b'\x5a\x5a\xff', b'\xa5']
    stream = b''.join(n + f for n, f in zip(noise, FRAMES))
    assert dec.feed(stream) == FRAMES
    assert dec.bytes_discarded == sum(len(n) for n in noise)
    assert dec.checksum_errors == 0 and accounted(dec, FRAMES, len(stream))


def test_a_trailing_first_header_byte_is_held_for_the_next_chunk():
    dec = Toy()
    assert dec.feed(b'\x00\x00' + HEADER[:1]) == []
    assert dec.pending == 1 and dec.bytes_discarded == 2
    assert dec.feed(FRAMES[1][1:]) == [FRAMES[1]]
    assert dec.pending == 0


@pytest.mark.parametrize('decoder', [Toy, TwoHeaders])
def test_issue22_5_split_frames_decode_the_same_at_every_byte_boundary(decoder):
    stream = b'\x00' + FRAMES[1] + b'\xa5' + FRAMES[2] + b'\x5a\xa5' + FRAMES[3] + FRAMES[0]
    whole = decoder().feed(stream)
    assert whole == [FRAMES[1], FRAMES[2], FRAMES[3], FRAMES[0]]
    for cut in range(len(stream) + 1):
        dec = decoder()
        assert feed_all(dec, [stream[:cut], stream[cut:]]) == whole, cut
        assert dec.bytes_discarded == 4 and dec.pending == 0, cut
    dec = decoder()
    assert feed_all(dec, [bytes([b]) for b in stream]) == whole
    assert dec.bytes_discarded == 4


def test_issue22_5_resync_after_a_bad_checksum_finds_the_frame_behind_it():
    dec = Toy()
    bad = bytearray(FRAMES[2])
    bad[-1] ^= 0xFF
    stream = bytes(bad) + FRAMES[1]
    assert dec.feed(stream) == [FRAMES[1]]
    assert dec.checksum_errors == 1
    assert dec.bytes_discarded == len(bad)
    assert accounted(dec, [FRAMES[1]], len(stream))


def test_a_frame_hidden_inside_a_false_candidate_is_found():
    # The false header says LEN 9: its checksum fails once the real frame inside completes it.
    dec = Toy()
    false = HEADER + b'\x09'
    stream = false + FRAMES[1] + b'\x00' * 6
    assert dec.feed(stream) == [FRAMES[1]]
    assert dec.checksum_errors == 1 and dec.bytes_discarded == len(false) + 6


def test_an_impossible_length_is_dropped_at_once_without_a_checksum_error():
    dec = Toy()
    stream = HEADER + b'\xff' + FRAMES[0]
    assert dec.feed(stream) == [FRAMES[0]]
    assert dec.checksum_errors == 0 and dec.bytes_discarded == 3


def test_flush_abandons_a_waiting_candidate_and_finds_what_it_hid():
    dec = Toy()
    # A false candidate (LEN 12) that the line leaves incomplete, holding a whole frame.
    stream = HEADER + b'\x0c' + FRAMES[0] + b'\x01'
    assert dec.feed(stream) == []
    assert dec.pending == len(stream)
    assert dec.flush() == [FRAMES[0]]
    assert dec.pending == 0 and dec.bytes_discarded == 4
    assert dec.flush() == []


def test_flush_discards_a_trailing_half_header():
    dec = Toy()
    dec.feed(HEADER[:1])
    assert dec.pending == 1
    assert dec.flush() == [] and dec.pending == 0 and dec.bytes_discarded == 1


def test_reset_forgets_held_bytes_and_keeps_the_counters():
    dec = Toy()
    dec.feed(b'\x00' + FRAMES[1][:4])
    dec.reset()
    assert dec.pending == 0 and dec.bytes_discarded == 1
    assert dec.feed(FRAMES[1]) == [FRAMES[1]] and dec.frames_decoded == 1


def test_input_that_is_not_bytes_is_ignored():
    dec = Toy()
    assert dec.feed(None) == [] and dec.pending == 0


def test_a_decoder_without_headers_is_refused():
    class NoHeader(sd.StreamDecoder):
        pass

    with pytest.raises(ValueError):
        NoHeader()


def test_two_headers_interleave_in_wire_order():
    dec = TwoHeaders()
    stream = other(1) + FRAMES[1] + b'\x5b' + other(2) + FRAMES[0] + b'\x5b\x5b\x03\x03' + other(4)
    assert dec.feed(stream) == [other(1), FRAMES[1], other(2), FRAMES[0], other(4)]
    # The lone 5B makes a false candidate (5B 5B 5B 02) before the real one behind it.
    assert dec.checksum_errors == 2 and dec.bytes_discarded == 1 + 4


chunks = st.lists(st.integers(1, 40), min_size=1, max_size=30)
pieces = st.lists(st.tuples(st.binary(max_size=8), st.sampled_from(FRAMES)), max_size=12)


@settings(max_examples=150, deadline=None)
@given(pieces, st.binary(max_size=5), chunks)
def test_any_chunking_of_noise_and_frames_loses_no_byte(pieces, tail, cuts):
    stream = b''.join(n + f for n, f in pieces) + tail
    dec = Toy()
    out = []
    pos = 0
    for size in cuts * (len(stream) // max(sum(cuts), 1) + 1):
        out += dec.feed(stream[pos:pos + size])
        pos += size
    out += dec.feed(stream[pos:])
    assert accounted(dec, out, len(stream))
    out += dec.flush()
    assert dec.pending == 0
    assert sum(len(f) for f in out) + dec.bytes_discarded == len(stream)
    # Noise can start a false candidate (and, rarely, complete one); noise that cannot start
    # one leaves every real frame to be found, whole and in order.
    if all(HEADER[0] not in n for n, _ in pieces):
        assert out[:len(pieces)] == [f for _, f in pieces]


def test_issue22_5_every_driver_decoder_is_one_base_with_one_set_of_counter_names():
    from desheng_servo_ros import protocol as servo
    from dps_parachute_ros import protocol as dps
    from handset_link_ros import protocol as handset
    from originman_board_ros import protocol as originman
    for decoder in (dps.StreamDecoder('from_module'), dps.StreamDecoder('from_host'),
                    servo.StreamDecoder('reply'), servo.StreamDecoder('request'),
                    originman.StreamDecoder(), handset.StreamDecoder()):
        assert isinstance(decoder, sd.StreamDecoder), decoder
        for name in ('frames_decoded', 'checksum_errors', 'bytes_discarded', 'pending'):
            assert getattr(decoder, name) == 0, (decoder, name)
        for old in ('crc_errors', 'buffered'):
            assert not hasattr(decoder, old), (decoder, old)
        assert decoder.feed(b'') == [] and decoder.flush() == []


def _driver_streams():
    """Per driver: (decoder factory, good frames, a frame to corrupt, the checksum byte index)."""
    from desheng_servo_ros import protocol as servo
    from dps_parachute_ros import protocol as dps
    from handset_link_ros import protocol as handset
    from originman_board_ros import protocol as originman
    return {
        'dps': (lambda: dps.StreamDecoder('from_module'),
                [dps.encode_status_frame(12, 3, False, True), dps.module_frame(dps.CMD_ARMED, 1),
                 dps.encode_trigger_request(dps.HOST_HEADER),
                 dps.module_frame(dps.CMD_CELL_VOLTAGE, 0x2A)],
                dps.module_frame(dps.CMD_BOOT_COUNT, 7), -1),
        'servo': (lambda: servo.StreamDecoder('reply'),
                  [servo.encode_reply(1, 0, b'\x08\x00'), servo.encode_reply(12, 0x20),
                   servo.encode_reply(3, 0, bytes(range(10)))],
                  servo.encode_reply(2, 0, b'\x01\x02'), -1),
        'originman': (originman.StreamDecoder,
                      [originman.encode_imu_report([0.1, -0.2, 1.0], [1.0, 2.0, -3.0]),
                       originman.encode_battery_report(7400),
                       originman.encode_key_report(originman.KEY_IDS[0],
                                                   list(originman.KeyEvent)[0])],
                      originman.encode_battery_report(8000), -1),
        'handset': (handset.StreamDecoder,
                    [handset.encode_command(handset.CommandType.SET_YAW, 90),
                     handset.encode_command(handset.CommandType.SET_PITCH, -12.5, 'float32'),
                     handset.encode_command(handset.CommandType.SET_LIGHTS, 40, 'int8')],
                    handset.encode_command(handset.CommandType.SET_ROLL, 5, 'int16'), -2),
    }


def _frames_of(results):
    # The handset also reports rejected candidates (Malformed, no type): they are no frames.
    return [r.raw for r in results if not (type(r).__name__ == 'Malformed' and r.type is None)]


@pytest.mark.parametrize('driver', ['dps', 'servo', 'originman', 'handset'])
def test_issue22_5_every_driver_resyncs_and_splits_the_same_on_the_base(driver):
    make, good, victim, check = _driver_streams()[driver]
    bad = bytearray(victim)
    bad[check] ^= 0x5A
    stream = b'\x00\x13' + good[0] + bytes(bad) + good[1] + b'\x07' * 3 + good[2] + good[0]
    whole = make()
    frames = _frames_of(whole.feed(stream) + whole.flush())
    assert frames == [good[0], good[1], good[2], good[0]]
    assert whole.checksum_errors == 1 and whole.frames_decoded == 4
    assert whole.bytes_discarded == 2 + len(bad) + 3 and whole.pending == 0
    for cut in range(1, len(stream)):
        dec = make()
        out = dec.feed(stream[:cut]) + dec.feed(stream[cut:]) + dec.flush()
        assert _frames_of(out) == frames, cut
        assert (dec.checksum_errors, dec.frames_decoded, dec.bytes_discarded, dec.pending) == \
            (1, 4, whole.bytes_discarded, 0), cut


def _parsers():
    """Per driver: (decoder factory, the headers it hunts, its one-frame parser)."""
    from desheng_servo_ros import protocol as servo
    from dps_parachute_ros import protocol as dps
    from handset_link_ros import protocol as handset
    from originman_board_ros import protocol as originman

    def handset_parse(raw):
        result = handset.decode_frame(raw)
        assert not isinstance(result, handset.Malformed) or result.type is not None, result

    return {
        'dps_from_module': (lambda: dps.StreamDecoder('from_module'),
                            [dps.MODULE_HEADER, dps.HOST_HEADER], dps.parse_frame),
        'dps_from_host': (lambda: dps.StreamDecoder('from_host'), [dps.HOST_HEADER],
                          dps.parse_frame),
        'servo_reply': (lambda: servo.StreamDecoder('reply'), [servo.REPLY_HEADER],
                        servo.parse_reply),
        'servo_request': (lambda: servo.StreamDecoder('request'), [servo.REQUEST_HEADER],
                          servo.parse_request),
        'originman': (originman.StreamDecoder, [originman.HEADER], originman.parse_frame),
        'handset': (handset.StreamDecoder, [bytes([handset.START])], handset_parse),
    }


# Header-started junk: a header, then a code/length byte from the ones that matter, then bytes.
_junk = st.tuples(st.integers(0, 1), st.sampled_from([0x01, 0x02, 0x05, 0x32, 0x34, 0x35, 0x39]),
                  st.binary(max_size=18))


@pytest.mark.parametrize('driver', ['dps_from_module', 'dps_from_host', 'servo_reply',
                                    'servo_request', 'originman', 'handset'])
@settings(max_examples=60, deadline=None)
@given(pieces=st.lists(_junk, max_size=25), cut=st.integers(1, 64))
def test_issue22_5_every_frame_a_driver_decoder_delivers_is_one_its_parser_accepts(driver, pieces,
                                                                                   cut):
    make, headers, parse = _parsers()[driver]
    stream = b''.join(headers[h % len(headers)] + bytes([code]) + rest
                      for h, code, rest in pieces)
    dec = make()
    out = []
    for i in range(0, len(stream), cut):
        out += dec.feed(stream[i:i + cut])
    out += dec.flush()
    frames = _frames_of(out)
    for raw in frames:
        parse(raw)
    assert sum(len(raw) for raw in frames) + dec.bytes_discarded == len(stream)
