"""The UART line model: a receiver at the wrong speed, and two senders at once."""

from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

from uav_serial_common.uart import collide, receive, reframe, Transmission

FRAME = bytes.fromhex('FF FF 01 04 02 38 04 BA')


@settings(max_examples=200, deadline=None)
@given(data=st.binary(min_size=1, max_size=70),
       drift=st.floats(min_value=-0.04, max_value=0.04))
def test_a_receiver_within_a_few_percent_of_the_sender_reads_every_byte(data, drift):
    # UARTs resynchronise on every start bit: a few percent of clock error never shows.
    assert reframe(data, 115200, 115200 * (1 + drift)) == data
    assert receive([Transmission(0.0, 1 / 9600, data)], 1 / 9600) == data


def test_a_receiver_at_the_wrong_speed_reads_garbage():
    # Fast bits read slowly: the whole request is a byte or two of nonsense.
    slow = reframe(FRAME, 115200, 9600)
    assert slow != FRAME and len(slow) < len(FRAME)
    # Slow bits read fast: start bits and zeros become runs of 0x00 (framing errors).
    fast = reframe(FRAME, 9600, 115200)
    assert fast != FRAME and len(fast) >= len(FRAME) and set(fast) <= {0x00, 0x80, 0xC0, 0xE0,
                                                                       0xF0, 0xF8, 0xFC, 0xFE}


def test_a_missing_stop_bit_is_a_framing_error_delivered_as_zero():
    # A sender that holds the line low through the stop bit: the receiver gets 0x00.
    held_low = [Transmission(0.0, 1.0, b'\x00'), Transmission(9.0, 1.0, b'\x00')]
    assert receive(held_low, 1.0)[0] == 0x00


@pytest.mark.parametrize('offset, clean', [(0.0, True), (0.4, True), (0.6, False),
                                           (1.0, False), (1.7, False)])
def test_two_senders_at_once_are_read_as_the_and_of_their_bits(offset, clean):
    reply = bytes.fromhex('FF F5 02 02 00 FB')
    got = collide([reply, reply], [0.0, offset])
    assert (got == reply) is clean
    other = bytes.fromhex('FF F5 02 06 00 03 E8 00 00 0C')
    mine = bytes.fromhex('FF F5 02 06 00 08 00 00 00 EF')
    # Different replies never come through as either of them.
    assert collide([mine, other], [0.0, offset]) not in (mine, other)
