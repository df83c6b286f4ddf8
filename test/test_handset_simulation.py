"""The virtual handset model: tick schedule, auxiliary commands, encodings, radio link, H11."""

import math

import pytest

from handset_link_ros import protocol as p
from handset_link_ros.simulation import VirtualHandset

T = p.CommandType
STICKS = [T.SET_YAW, T.SET_PITCH, T.SET_ROLL, T.SET_ALTITUDE]
AUX = [T.SET_LIGHTS, T.SET_CAMERA_ANGLE, T.SET_CAMERA_RECORD]


def decode(data: bytes) -> list:
    """Decode the model's output; every frame it sends on its own must be accepted."""
    decoder = p.StreamDecoder()
    results = decoder.feed(data) + decoder.flush()
    assert decoder.bytes_discarded == 0
    return results


def types(results: list) -> list:
    return [r.type for r in results]


def test_h22_h7_every_tick_carries_the_four_stick_commands_at_50_hz():
    sim = VirtualHandset(now=100.0)
    results = decode(sim.step(100.999))
    assert all(isinstance(r, p.Command) for r in results)
    assert sim.ticks == 50
    for type_ in STICKS:
        assert types(results).count(type_) == 50
    assert types(results)[:4] == STICKS  # in this order, every tick


def test_h22_the_first_tick_carries_the_auxiliary_commands_then_once_a_second():
    sim = VirtualHandset(now=0.0)
    first = decode(sim.step(0.0))
    assert types(first) == STICKS + AUX
    later = decode(sim.step(2.5))
    for type_ in AUX:
        assert types(later).count(type_) == 2  # at 1.0 s and 2.0 s
    assert sim.frames_by_type[T.SET_LIGHTS] == 3


def test_h22_an_auxiliary_change_goes_out_in_the_next_tick_alone():
    sim = VirtualHandset(now=0.0)
    sim.step(0.3)
    sim.set_lights(40)
    assert sim.next_event_time() == pytest.approx(0.32)
    tick = decode(sim.step(0.32))
    assert types(tick) == STICKS + [T.SET_LIGHTS]
    assert tick[-1].value == 40
    assert types(decode(sim.step(0.34))) == STICKS  # sent once, not again until the second


def test_every_auxiliary_value_changes_on_the_wire():
    sim = VirtualHandset(now=0.0)
    sim.step(0.0)
    sim.set_camera_angle(-30.5)
    sim.set_camera_recording(True)
    values = {r.type: r.value for r in decode(sim.step(0.02))}
    assert values[T.SET_CAMERA_ANGLE] == -30.5 and values[T.SET_CAMERA_RECORD] is True


@pytest.mark.parametrize('encoding,expected', [
    ('json', [12.5, -2.5, 89.75, 999.5]),
    ('float32', [12.5, -2.5, 89.75, 999.5]),
    # H23: whole units, rounded halves away from zero.
    ('int16', [13.0, -3.0, 90.0, 1000.0]),
    # H23: int8 also saturates (the altitude 999.5 goes out as 127).
    ('int8', [13.0, -3.0, 90.0, 127.0]),
])
def test_h23_h5_each_encoding_carries_the_sticks(encoding, expected):
    sim = VirtualHandset(now=0.0, encoding=encoding)
    sim.set_sticks(yaw_deg=12.5, pitch_deg=-2.5, roll_deg=89.75, altitude_m=999.5)
    results = decode(sim.step(0.0))
    assert {r.encoding for r in results} == {encoding}
    assert [r.value for r in results[:4]] == expected


def test_h23_int8_saturates_a_yaw_it_cannot_carry():
    sim = VirtualHandset(now=0.0, encoding='int8')
    sim.set_sticks(yaw_deg=-150.0)
    assert decode(sim.step(0.0))[0].value == -128.0


def test_the_encoding_switches_at_the_next_tick():
    sim = VirtualHandset(now=0.0)
    sim.step(0.0)
    sim.set_encoding('int16')
    assert {r.encoding for r in decode(sim.step(0.02))} == {'int16'}
    with pytest.raises(ValueError):
        sim.set_encoding('int32')


def test_values_outside_the_ranges_are_sent_as_they_are_for_the_driver_to_refuse():
    sim = VirtualHandset(now=0.0)
    sim.set_sticks(yaw_deg=200.0)
    sim.set_lights(50.5)
    results = decode(sim.step(0.0))
    refused = {r.type: r for r in results if isinstance(r, p.OutOfRange)}
    assert refused[T.SET_YAW].value == 200.0 and refused[T.SET_LIGHTS].value == 50.5


@pytest.mark.parametrize('bad', [math.nan, math.inf, '1', None, True])
def test_setters_take_finite_numbers_only(bad):
    sim = VirtualHandset()
    with pytest.raises(ValueError):
        sim.set_lights(bad)
    with pytest.raises(ValueError):
        sim.set_camera_angle(bad)
    if bad is not None:  # None leaves a stick as it is
        with pytest.raises(ValueError):
            sim.set_sticks(yaw_deg=bad)


def test_radio_link_down_stops_transmitting_and_resumes_with_the_auxiliary_commands():
    sim = VirtualHandset(now=0.0)
    sim.step(0.5)
    sim.set_radio_link(False)
    assert sim.next_event_time() is None
    assert sim.step(10.0) == b''
    sim.set_radio_link(True)
    assert sim.next_event_time() == 10.0
    assert types(decode(sim.step(10.0))) == STICKS + AUX


def test_send_raw_goes_out_at_once_even_with_the_radio_link_down():
    sim = VirtualHandset(now=0.0, radio_link=False)
    sim.send_raw(b'\xaa\x03\x01')
    assert sim.next_event_time() == 0.0
    assert sim.step(0.0) == b'\xaa\x03\x01'
    assert sim.raw_bytes_sent == 3 and sim.next_event_time() is None


def test_send_raw_keeps_its_place_before_the_next_tick():
    sim = VirtualHandset(now=0.0)
    sim.step(0.0)
    sim.send_raw(b'\x00\x01')
    assert sim.step_frames(0.02)[0] == b'\x00\x01'


def test_h11_bytes_from_the_host_are_ignored_and_counted():
    sim = VirtualHandset(now=0.0)
    reference = VirtualHandset(now=0.0)
    out = sim.receive(p.encode_set_yaw(90) + b'\x00' * 10, now=0.04)
    assert sim.bytes_ignored == 26
    assert out == reference.step(0.04)
    assert sim.yaw_deg == 0.0


def test_time_never_runs_backwards():
    sim = VirtualHandset(now=5.0)
    sim.step(6.0)
    ticks = sim.ticks
    assert sim.step(5.5) == b'' and sim.ticks == ticks and sim.now == 6.0


def test_a_rate_change_keeps_the_next_tick_and_spaces_the_following():
    sim = VirtualHandset(now=0.0)
    sim.step(0.0)
    sim.set_rate(10.0)
    assert sim.next_event_time() == pytest.approx(0.02)
    sim.step(0.02)
    assert sim.next_event_time() == pytest.approx(0.12)
    with pytest.raises(ValueError):
        sim.set_rate(0)


def test_a_long_step_sends_every_tick_due_without_drift():
    sim = VirtualHandset(now=0.0, rate_hz=50.0)
    sim.step(60.0)
    assert sim.ticks == 3001
    assert sim.next_event_time() == pytest.approx(60.02)
