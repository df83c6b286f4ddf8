"""Behaviour of the simulated Desheng servo bus, driven through its wire protocol."""

import pytest

from desheng_servo_ros import protocol as p
from desheng_servo_ros import registers as r
from desheng_servo_ros import simulation as s
from desheng_servo_ros.simulation import ServoBusSim


def send(sim: ServoBusSim, frame: bytes, now: float) -> list[p.Reply]:
    """Feed one request and parse every reply (raises if a reply is malformed)."""
    return [p.parse_reply(raw) for raw in sim.feed(frame, now)]


def read(sim: ServoBusSim, servo_id: int, name: str, now: float):
    """Read a register over the wire and decode it."""
    reg = r.by_name(name)
    (reply,) = send(sim, p.encode_read(servo_id, reg.address, reg.size), now)
    assert reply.servo_id == servo_id
    return r.decode_value(reg, reply.params)


def write(sim: ServoBusSim, servo_id: int, name: str, value, now: float) -> list[p.Reply]:
    """Write a register over the wire."""
    reg = r.by_name(name)
    return send(sim, p.encode_write(servo_id, reg.address, r.encode_value(reg, value)), now)


def torque_on(sim: ServoBusSim, servo_id: int, now: float) -> None:
    """Enable torque and check the acknowledgement."""
    (reply,) = write(sim, servo_id, 'torque_enable', 1, now)
    assert reply.servo_id == servo_id


# ----- register file and addressing ----------------------------------------------------------

def test_defaults_of_the_document_in_one_read():
    sim = ServoBusSim()
    (reply,) = send(sim, p.encode_read(2, 0x03, p.MAX_READ_LENGTH), 0.0)
    values = r.decode_block(0x03, reply.params)
    assert values['firmware_version'] == 'v1.28'
    assert {k: values[k] for k in (
        'id', 'stall_protection_time', 'min_angle_limit', 'max_angle_limit', 'max_torque',
        'speed_adjust', 'unload_condition', 'center_offset', 'preset_position_1',
        'preset_position_2', 'preset_position_3', 'torque_enable', 'present_position',
        'target_position', 'run_time', 'lock_flag', 'present_speed', 'reg_write_flag')} == {
        'id': 2, 'stall_protection_time': 3, 'min_angle_limit': 0, 'max_angle_limit': 4095,
        'max_torque': 800, 'speed_adjust': 30, 'unload_condition': 0, 'center_offset': 0,
        'preset_position_1': 2048, 'preset_position_2': 2048, 'preset_position_3': 2048,
        'torque_enable': 0, 'present_position': 2048, 'target_position': 2048, 'run_time': 0,
        'lock_flag': 0, 'present_speed': 0, 'reg_write_flag': 0}
    assert values['temperature'] == 25
    assert values['current'] == s.IDLE_CURRENT_MA


def test_read_example_gets_big_endian_position():
    sim = ServoBusSim([1])
    sim.move_by_hand(1, 0x07FF)
    assert sim.feed(bytes.fromhex('FF FF 01 04 02 38 02 BE'), 0.0) == [
        bytes.fromhex('FF F5 01 04 00 07 FF F4')]


def test_ping_answers_only_from_the_addressed_servo():
    sim = ServoBusSim([1, 2, 3])
    assert [x.servo_id for x in send(sim, p.encode_ping(3), 0.0)] == [3]
    assert sim.feed(p.encode_ping(4), 0.0) == []


@pytest.mark.parametrize('frame', [
    p.encode_request(254, p.Instruction.PING),
    p.encode_request(254, p.Instruction.READ, b'\x38\x02'),
    p.encode_request(254, p.Instruction.REG_WRITE, b'\x2a\x00\x10\x00\x00'),
    p.encode_request(1, p.Instruction.ACTION),
    p.encode_request(1, p.Instruction.SYNC_WRITE, b'\x2a\x04\x01\x00\x10\x00\x00'),
    p.encode_request(1, p.Instruction.READ, b'\x38\x00'),
    p.encode_request(1, p.Instruction.READ, b'\x03\x41'),
    p.encode_request(254, p.Instruction.SYNC_WRITE, b'\x2a\x04\x01\x00\x10'),
])
def test_forbidden_or_malformed_requests_get_silence_and_change_nothing(frame):
    sim = ServoBusSim([1, 2])
    torque_on(sim, 1, 0.0)
    assert sim.feed(frame, 0.0) == []
    assert sim.requests_ignored == 1
    sim.advance(5.0)
    assert sim.servo(1).position_ticks == 2048
    assert sim.servo(1).pending is None


def test_broadcast_write_applies_to_all_without_reply():
    sim = ServoBusSim([1, 2, 3])
    assert sim.feed(p.encode_write(254, 0x28, b'\x01'), 0.0) == []
    assert [read(sim, i, 'torque_enable', 0.0) for i in (1, 2, 3)] == [1, 1, 1]


def test_broadcast_set_id_example_makes_every_servo_id_1():
    sim = ServoBusSim([4, 5], collisions=False)
    assert sim.feed(bytes.fromhex('FF FF FE 04 03 05 01 F4'), 0.0) == []
    assert sim.ids == [1, 1]
    # Both answer; with collisions off each reply comes whole, in bus order.
    assert len(send(sim, p.encode_ping(1), 0.0)) == 2


def test_two_servos_at_one_id_collide_into_a_mostly_garbled_reply():
    # S24: their replies go out together; the host reads the AND of both, a little apart.
    sim = ServoBusSim([1, 2])
    sim.move_by_hand(2, 1000)
    write(sim, 2, 'id', 1, 0.0)
    assert sim.ids == [1, 1]
    outcomes = []
    for k in range(200):
        out = sim.feed(p.encode_read(1, 0x38, 2), 0.01 * k)
        assert len(out) == 1
        decoded = p.StreamDecoder('reply').feed(out[0])
        outcomes.append('clean' if decoded and decoded[0].raw == out[0] else 'garbled')
    # Different positions never come through clean; identical replies do, when they start
    # within half a bit of each other (about 1 in 4).
    assert outcomes.count('garbled') == 200
    pings = [sim.feed(p.encode_ping(1), 3.0) for _ in range(200)]
    clean = sum(1 for (frame,) in pings if frame == p.encode_reply(1, 0))
    assert 20 <= clean <= 100
    assert sim.replies_collided == 800
    # Seeded (S25): the same inputs give the same bytes.
    runs = []
    for _ in range(2):
        twin = ServoBusSim([1], seed=5)
        twin.add_servo(1, allow_duplicate=True, position_ticks=3000)
        runs.append([twin.feed(p.encode_read(1, 0x38, 2), 0.01 * k) for k in range(20)])
    assert runs[0] == runs[1]


def test_write_to_read_only_register_is_ignored_but_acknowledged():
    sim = ServoBusSim([1])
    (reply,) = send(sim, p.encode_write(1, 0x38, b'\x00\x10'), 0.0)
    assert reply.status == 0 and reply.params == b''
    assert read(sim, 1, 'present_position', 0.0) == 2048


def test_invalid_id_write_is_ignored():
    sim = ServoBusSim([1])
    send(sim, p.encode_write(1, 0x05, b'\xfe'), 0.0)
    assert sim.ids == [1]


def test_set_id_replies_from_old_id_then_answers_to_new_one():
    sim = ServoBusSim([1, 2])
    (reply,) = write(sim, 1, 'id', 7, 0.0)
    assert reply.servo_id == 1
    assert sim.feed(p.encode_ping(1), 0.1) == []
    assert [x.servo_id for x in send(sim, p.encode_ping(7), 0.1)] == [7]


def test_factory_reset_restores_defaults_including_id():
    sim = ServoBusSim([5])
    write(sim, 5, 'stall_protection_time', 9, 0.0)
    write(sim, 5, 'max_angle_limit', 3000, 0.0)
    torque_on(sim, 5, 0.0)
    (reply,) = send(sim, p.encode_reset(5), 0.0)
    assert reply.servo_id == 5
    assert sim.ids == [1]
    assert read(sim, 1, 'stall_protection_time', 0.0) == 3
    assert read(sim, 1, 'max_angle_limit', 0.0) == 4095
    assert read(sim, 1, 'torque_enable', 0.0) == 0


def test_factory_reset_can_keep_the_id():
    sim = ServoBusSim([5], reset_keeps_id=True)
    write(sim, 5, 'stall_protection_time', 9, 0.0)
    send(sim, p.encode_reset(5), 0.0)
    assert read(sim, 5, 'stall_protection_time', 0.0) == 3


def test_power_cycle_keeps_persisted_registers_only():
    sim = ServoBusSim([1])
    write(sim, 1, 'speed_adjust', 50, 0.0)
    write(sim, 1, 'run_time', 700, 0.0)
    torque_on(sim, 1, 0.0)
    sim.power_cycle()
    assert read(sim, 1, 'speed_adjust', 0.0) == 50
    assert read(sim, 1, 'run_time', 0.0) == 0
    assert read(sim, 1, 'torque_enable', 0.0) == 0


# ----- motion --------------------------------------------------------------------------------

def test_target_with_torque_off_is_stored_but_servo_stays_limp():
    sim = ServoBusSim([1])
    send(sim, p.encode_write_position(1, 3000, 500), 0.0)
    sim.advance(2.0)
    assert read(sim, 1, 'target_position', 2.0) == 3000
    assert read(sim, 1, 'present_position', 2.0) == 2048
    # S19: enabling torque holds the present position instead of jumping to the stale target.
    torque_on(sim, 1, 2.0)
    sim.advance(4.0)
    assert read(sim, 1, 'present_position', 4.0) == 2048
    assert read(sim, 1, 'target_position', 4.0) == 2048


def test_move_takes_the_run_time_and_reports_speed_and_current():
    sim = ServoBusSim([1])
    torque_on(sim, 1, 0.0)
    send(sim, p.encode_write_position(1, 3048, 1000), 1.0)
    assert read(sim, 1, 'present_position', 1.5) == 2548
    assert read(sim, 1, 'present_speed', 1.5) == 1000
    moving_current = read(sim, 1, 'current', 1.5)
    assert moving_current > s.HOLD_CURRENT_MA
    assert read(sim, 1, 'present_position', 1.999) < 3048
    assert read(sim, 1, 'present_position', 2.0) == 3048
    assert read(sim, 1, 'present_speed', 2.1) == 0
    assert read(sim, 1, 'current', 2.1) == s.HOLD_CURRENT_MA


def test_run_time_zero_moves_at_maximum_speed():
    sim = ServoBusSim([1])
    torque_on(sim, 1, 0.0)
    send(sim, p.encode_write_position(1, 2048 + 1024, 0), 0.0)
    full_time = 1024 / s.MAX_SPEED_TICKS_PER_S
    assert 0.29 < full_time < 0.31  # 90 degrees at 0.2 s per 60 degrees
    assert read(sim, 1, 'present_position', full_time * 0.5) == 2048 + 512
    assert read(sim, 1, 'present_position', full_time) == 3072


def test_too_short_run_time_is_limited_by_maximum_speed():
    sim = ServoBusSim([1])
    torque_on(sim, 1, 0.0)
    send(sim, p.encode_write_position(1, 0, 10), 0.0)
    assert read(sim, 1, 'present_position', 0.1) > 0
    assert read(sim, 1, 'present_speed', 0.1) == round(s.MAX_SPEED_TICKS_PER_S)
    assert read(sim, 1, 'present_position', 2048 / s.MAX_SPEED_TICKS_PER_S) == 0


def test_target_is_clamped_to_the_angle_limits():
    sim = ServoBusSim([1])
    write(sim, 1, 'max_angle_limit', 3000, 0.0)
    torque_on(sim, 1, 0.0)
    send(sim, p.encode_write(1, 0x2A, b'\x0f\xa0\x00\x00'), 0.0)  # 4000
    assert read(sim, 1, 'target_position', 0.0) == 3000
    assert read(sim, 1, 'present_position', 5.0) == 3000
    send(sim, p.encode_write(1, 0x2A, b'\xff\xff'), 5.0)  # beyond 4095: clamped, not wrapped
    assert read(sim, 1, 'target_position', 5.0) == 3000


def test_torque_off_stops_a_move_where_it_is():
    sim = ServoBusSim([1])
    torque_on(sim, 1, 0.0)
    send(sim, p.encode_write_position(1, 3048, 1000), 0.0)
    write(sim, 1, 'torque_enable', 0, 0.5)
    assert read(sim, 1, 'present_position', 3.0) == 2548


def test_lock_flag_stops_and_refuses_motion_until_cleared():
    sim = ServoBusSim([1])
    torque_on(sim, 1, 0.0)
    send(sim, p.encode_write_position(1, 3048, 1000), 0.0)
    write(sim, 1, 'lock_flag', 1, 0.25)
    send(sim, p.encode_write_position(1, 0, 0), 0.5)
    assert read(sim, 1, 'present_position', 3.0) == 2298
    write(sim, 1, 'lock_flag', 0, 3.0)
    send(sim, p.encode_write_position(1, 2400, 0), 3.0)
    assert read(sim, 1, 'present_position', 4.0) == 2400


def test_hand_moved_servo_with_torque_returns_to_target():
    sim = ServoBusSim([1])
    torque_on(sim, 1, 0.0)
    sim.move_by_hand(1, 1000)
    assert read(sim, 1, 'present_position', 0.0) == 1000
    assert read(sim, 1, 'present_position', 1.0) == 2048


# ----- presets, REG WRITE / ACTION, SYNC WRITE ----------------------------------------------

def test_preset_position_stores_present_position_and_run_preset_goes_there():
    sim = ServoBusSim([1])
    sim.move_by_hand(1, 1000)
    (reply,) = send(sim, p.encode_write(1, 0x16), 0.0)
    assert reply.servo_id == 1
    assert read(sim, 1, 'preset_position_1', 0.0) == 1000
    # Data bytes sent along are ignored: the servo captures its own position (S12).
    send(sim, p.encode_write(1, 0x18, b'\x00\x05'), 0.0)
    assert read(sim, 1, 'preset_position_2', 0.0) == 1000
    sim.move_by_hand(1, 3000)
    torque_on(sim, 1, 0.0)
    write(sim, 1, 'run_time', 2000, 0.0)
    send(sim, p.encode_write(1, 0x3C), 0.0)
    assert read(sim, 1, 'present_position', 1.0) == 2000
    assert read(sim, 1, 'present_position', 2.0) == 1000
    send(sim, p.encode_write(1, 0x3E), 2.0)
    assert read(sim, 1, 'present_position', 4.0) == 2048


def test_reg_write_then_action_example_starts_both_servos_together():
    sim = ServoBusSim([1, 2, 3])
    sim.feed(p.encode_write(254, 0x28, b'\x01'), 0.0)
    send(sim, p.encode_write_position(2, 2048, 0), 0.0)
    (r1,) = send(sim, bytes.fromhex('FF FF 01 07 04 2A 07 D0 03 E8 07'), 0.0)
    (r3,) = send(sim, bytes.fromhex('FF FF 03 07 04 2A 03 E8 07 D0 05'), 0.0)
    assert (r1.servo_id, r3.servo_id) == (1, 3)
    assert read(sim, 1, 'reg_write_flag', 0.5) == 1
    assert read(sim, 1, 'present_position', 0.5) == 2048
    assert sim.feed(bytes.fromhex('FF FF FE 02 05 FA'), 1.0) == []
    assert read(sim, 1, 'reg_write_flag', 1.0) == 0
    assert read(sim, 1, 'present_position', 2.0) == 2000
    assert read(sim, 3, 'present_position', 2.0) == 2048 - (2048 - 1000) // 2
    assert read(sim, 3, 'present_position', 3.0) == 1000
    assert read(sim, 2, 'present_position', 3.0) == 2048


def test_newer_reg_write_replaces_the_staged_one():
    sim = ServoBusSim([1])
    torque_on(sim, 1, 0.0)
    send(sim, p.encode_reg_write_position(1, 100, 0), 0.0)
    send(sim, p.encode_reg_write_position(1, 3000, 0), 0.0)
    sim.feed(p.encode_action(), 0.0)
    assert read(sim, 1, 'present_position', 2.0) == 3000
    # ACTION with nothing staged changes nothing.
    sim.feed(p.encode_action(), 2.0)
    assert read(sim, 1, 'present_position', 4.0) == 3000


def test_reg_write_outside_the_position_block_is_acknowledged_but_not_staged():
    sim = ServoBusSim([1])
    (reply,) = send(sim, p.encode_reg_write(1, 0x28, b'\x01'), 0.0)
    assert reply.servo_id == 1
    sim.feed(p.encode_action(), 0.0)
    assert read(sim, 1, 'torque_enable', 0.0) == 0


def test_sync_write_example_moves_both_servos_without_reply():
    sim = ServoBusSim([1, 2, 3])
    sim.feed(p.encode_write(254, 0x28, b'\x01'), 0.0)
    frame = bytes.fromhex('FF FF FE 0E 83 2A 04 01 07 D0 03 E8 03 07 D0 03 E8 BA')
    assert sim.feed(frame, 0.0) == []
    assert [read(sim, i, 'present_position', 1.0) for i in (1, 2, 3)] == [2000, 2048, 2000]


def test_sync_write_with_misprinted_checksum_moves_nothing():
    sim = ServoBusSim([1, 3])
    sim.feed(p.encode_write(254, 0x28, b'\x01'), 0.0)
    sim.feed(bytes.fromhex('FF FF FE 0E 83 2A 04 01 07 D0 03 E8 03 07 D0 03 E8 8B'), 0.0)
    assert sim.decoder.checksum_errors == 1
    assert [read(sim, i, 'present_position', 1.0) for i in (1, 3)] == [2048, 2048]


def test_sync_write_to_other_registers_is_ignored():
    sim = ServoBusSim([1])
    sim.feed(p.encode_sync_write(0x28, 1, [(1, b'\x01')]), 0.0)
    assert read(sim, 1, 'torque_enable', 0.0) == 0


# ----- faults --------------------------------------------------------------------------------

def test_stall_raises_current_then_trips_overload_and_releases_torque():
    sim = ServoBusSim([1])
    torque_on(sim, 1, 0.0)
    send(sim, p.encode_write_position(1, 3000, 0), 0.0)
    sim.advance(0.1)
    sim.stall(1)
    (reply,) = send(sim, p.encode_ping(1), 2.9)
    assert not reply.overload
    assert read(sim, 1, 'current', 2.9) == s.STALL_CURRENT_MA
    stuck_at = read(sim, 1, 'present_position', 2.9)
    assert read(sim, 1, 'present_position', 3.0) == stuck_at
    (reply,) = send(sim, p.encode_ping(1), 3.11)
    assert reply.overload and reply.status == 0x20
    assert read(sim, 1, 'torque_enable', 3.11) == 0
    assert read(sim, 1, 'current', 3.11) == s.IDLE_CURRENT_MA
    # Re-enabling torque clears the latched overload; still blocked, it trips again 3 s later.
    (reply,) = write(sim, 1, 'torque_enable', 1, 4.0)
    assert not reply.overload
    (reply,) = send(sim, p.encode_ping(1), 7.01)
    assert reply.overload


def test_stall_protection_time_zero_trips_at_once():
    sim = ServoBusSim([1])
    write(sim, 1, 'stall_protection_time', 0, 0.0)
    torque_on(sim, 1, 0.0)
    sim.stall(1)
    (reply,) = send(sim, p.encode_ping(1), 0.0)
    assert reply.overload


def test_freed_servo_finishes_its_move():
    sim = ServoBusSim([1])
    torque_on(sim, 1, 0.0)
    send(sim, p.encode_write_position(1, 3048, 1000), 0.0)
    sim.advance(0.5)
    sim.stall(1)
    sim.advance(1.5)
    sim.stall(1, active=False)
    assert read(sim, 1, 'present_position', 1.5) == 2548
    assert read(sim, 1, 'present_position', 2.5) == 3048


def test_temperature_rises_with_current_and_cools_afterwards():
    sim = ServoBusSim([1])
    write(sim, 1, 'stall_protection_time', 255, 0.0)
    torque_on(sim, 1, 0.0)
    sim.stall(1)
    hot = read(sim, 1, 'temperature', 240.0)
    assert 45 <= hot <= 55  # towards 25 + 0.02 * 1500 = 55 degC
    sim.stall(1, active=False)
    assert read(sim, 1, 'temperature', 840.0) <= 27


def test_overheat_sets_status_bit_2_until_cooled():
    sim = ServoBusSim([1, 2])
    sim.advance(1.0)
    sim.overheat(2, 85.0)
    (reply,) = send(sim, p.encode_ping(2), 1.0)
    assert reply.over_temperature and reply.status == 0x04
    assert read(sim, 2, 'temperature', 60.0) >= 85
    assert not send(sim, p.encode_ping(1), 60.0)[0].over_temperature
    sim.cool(2)
    (reply,) = send(sim, p.encode_ping(2), 600.0)
    assert not reply.over_temperature


def test_over_temperature_limit_is_injectable():
    sim = ServoBusSim([1], over_temperature_limit_c=20.0)
    assert send(sim, p.encode_ping(1), 0.0)[0].over_temperature
    sim.set_over_temperature_limit(30.0)
    assert not send(sim, p.encode_ping(1), 0.0)[0].over_temperature


def test_voltage_fault_sets_bit_0_on_every_servo():
    sim = ServoBusSim([1, 2])
    sim.set_voltage_fault(True)
    assert [send(sim, p.encode_ping(i), 0.0)[0].status for i in (1, 2)] == [1, 1]
    sim.set_voltage_fault(False, servo_id=2)
    assert [send(sim, p.encode_ping(i), 0.0)[0].status for i in (1, 2)] == [1, 0]


def test_removed_servo_falls_silent_and_added_servo_answers_with_defaults():
    sim = ServoBusSim([1, 2])
    sim.remove_servo(2)
    assert sim.feed(p.encode_ping(2), 0.0) == []
    with pytest.raises(KeyError):
        sim.remove_servo(2)
    sim.add_servo(9)
    assert read(sim, 9, 'firmware_version', 0.0) == 'v1.28'
    with pytest.raises(ValueError):
        sim.add_servo(9)
    with pytest.raises(ValueError):
        sim.add_servo(254)


# ----- stream handling, time, determinism ----------------------------------------------------

def test_requests_split_bytewise_with_garbage_get_replies_when_complete():
    sim = ServoBusSim([1, 2])
    stream = b'\x00\xff\x07' + p.encode_ping(1) + b'\xff\xfe' + p.encode_read(2, 0x05, 1)
    replies = []
    completed_at = []
    for i, b in enumerate(stream):
        out = sim.feed(bytes((b,)), 0.0)
        if out:
            completed_at.append(i)
        replies += out
    assert [p.parse_reply(x).servo_id for x in replies] == [1, 2]
    assert p.parse_reply(replies[1]).params == b'\x02'
    assert completed_at == [3 + 6 - 1, len(stream) - 1]


def test_time_going_backwards_is_ignored():
    sim = ServoBusSim([1])
    torque_on(sim, 1, 0.0)
    send(sim, p.encode_write_position(1, 3048, 1000), 0.0)
    assert read(sim, 1, 'present_position', 0.5) == 2548
    assert read(sim, 1, 'present_position', 0.2) == 2548
    assert sim.now == 0.5


def test_runs_are_deterministic():
    def run() -> list[bytes]:
        sim = ServoBusSim([1, 2, 3])
        out = []
        t = 0.0
        sim.feed(p.encode_write(254, 0x28, b'\x01'), t)
        sim.feed(p.encode_sync_write_positions([(1, 100, 700), (2, 4000, 0), (3, 3000, 2500)]), t)
        sim.stall(2)
        for _ in range(200):
            t += 0.02
            for i in (1, 2, 3):
                out += sim.feed(p.encode_read(i, 0x2E, 0x40 - 0x2E), t)
        return out
    first, second = run(), run()
    assert first == second and len(first) == 600


def test_broadcast_reset_resets_every_servo_silently():
    sim = ServoBusSim([4, 5], reset_keeps_id=True)
    sim.feed(p.encode_write(254, 0x06, b'\x09'), 0.0)
    assert sim.feed(p.encode_request(254, p.Instruction.RESET), 0.0) == []
    assert [read(sim, i, 'stall_protection_time', 0.0) for i in (4, 5)] == [3, 3]
