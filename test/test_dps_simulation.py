"""The virtual DPS-S module: what a host sees on the wire, driven by an injected clock."""

import pytest

from dps_parachute_ros import protocol as p
from dps_parachute_ros.simulation import VirtualParachute


def h(text: str) -> bytes:
    """Bytes from a hex string with spaces."""
    return bytes.fromhex(text)


def msgs(data: bytes, layout: str = 'table') -> list:
    """Type every frame in ``data`` (a complete capture: the decoder is flushed)."""
    decoder = p.StreamDecoder()
    return [p.decode_module_frame(f, layout) for f in decoder.feed(data) + decoder.flush()]


def one(data: bytes, layout: str = 'table'):
    """The single message in ``data``."""
    found = msgs(data, layout)
    assert len(found) == 1, found
    return found[0]


def booted(**kwargs) -> VirtualParachute:
    """A module that has been on for a second (power-up heartbeats already read)."""
    sim = VirtualParachute(**kwargs)
    sim.step(1.0)
    return sim


def armed(**kwargs) -> VirtualParachute:
    sim = booted(**kwargs)
    assert sim.receive(p.encode_arm(True)) == h('41 75 10 01 01 12')
    return sim


# ---------------------------------------------------------------------------------------------
# Power-up, heartbeat, defaults
# ---------------------------------------------------------------------------------------------

def test_two_heartbeats_50ms_apart_at_power_up():
    sim = VirtualParachute(now=10.0)
    assert sim.step(10.0) == h('41 75 01 a5 5a 00')
    assert sim.step(10.049) == b''
    assert sim.step(10.05) == h('41 75 01 a5 5a 00')
    assert sim.step(20.0) == b''  # then it only answers
    assert sim.receive(p.encode_heartbeat()) == h('41 75 01 a5 5a 00')


def test_first_boot_count_is_one_and_wraps_after_255():
    sim = booted()
    assert one(sim.receive(p.encode_boot_count_query())).count == 1
    sim = booted(boot_count=254)
    assert sim.boot_count == 255
    sim.power_cycle()
    assert sim.boot_count == 0
    sim.step(2.0)
    assert one(sim.receive(p.encode_boot_count_query())).count == 0


def test_documented_defaults_are_reported():
    sim = booted()
    assert sim.receive(p.encode_attitude_threshold_query()) == h('41 75 20 01 3c 5d')
    assert sim.receive(p.encode_freefall_threshold_query()) == h('41 75 21 01 05 27')
    assert sim.receive(p.encode_freefall_time_query()) == h('41 75 22 01 a0 c3')
    assert sim.receive(p.encode_light_threshold_query()) == h('41 75 15 01 0c 22')
    assert sim.receive(p.encode_auto_trigger_query()) == h('41 75 16 01 00 17')
    assert sim.receive(p.encode_armed_query()) == h('41 75 30 01 00 31')  # starts locked
    assert sim.receive(p.encode_triggered_query()) == h('41 75 31 01 00 32')
    assert sim.baud == 115200


def test_status_query_reports_tilt_accel_and_states():
    sim = armed()
    sim.set_tilt(7)
    assert sim.receive(p.encode_status_query()) == h('41 75 32 07 0a 00 01 44')


# ---------------------------------------------------------------------------------------------
# Settings (P6, P8, P9)
# ---------------------------------------------------------------------------------------------

def test_set_replies_echo_the_value_and_read_back_matches():
    sim = booted()
    cases = [
        (p.encode_attitude_threshold_set(75), p.encode_attitude_threshold_query()),
        (p.encode_freefall_threshold_set(0.3), p.encode_freefall_threshold_query()),
        (p.encode_freefall_time_set(0.8), p.encode_freefall_time_query()),
        (p.encode_light_threshold_set(1.8), p.encode_light_threshold_query()),
    ]
    for set_frame, query in cases:
        reply = one(sim.receive(set_frame))
        assert p.is_set_ack(reply, set_frame[4])
        assert reply.value == set_frame[4]  # the simulated module echoes (P6)
        assert one(sim.receive(query)).value == set_frame[4]
    assert sim.receive(p.encode_light_threshold_set(1.8)) == h('41 75 15 01 12 28')


def test_p8_flag_replies_follow_the_table_and_0x17_is_answered_with_0x16():
    sim = booted()
    assert sim.receive(p.encode_freefall_trigger(False)) == h('41 75 16 01 10 27')
    assert sim.receive(p.encode_attitude_trigger(False)) == h('41 75 16 01 11 28')
    assert sim.receive(p.encode_freefall_trigger(True)) == h('41 75 16 01 01 18')
    flags = one(sim.receive(p.encode_auto_trigger_query()))
    assert (flags.attitude_enabled, flags.freefall_enabled) == (False, True)
    # P14: the query form of 0x17 answers too and changes nothing.
    assert sim.receive(h('42 61 17 01 00 18')) == h('41 75 16 01 01 18')


def test_p8_prose_hardware_is_read_correctly_with_the_prose_layout():
    sim = booted(flag_layout='prose')
    reply = sim.receive(p.encode_freefall_trigger(False))
    assert reply == h('41 75 16 01 01 18')
    flags = one(reply, layout='prose')
    assert (flags.attitude_enabled, flags.freefall_enabled) == (True, False)
    assert one(reply, layout='table').attitude_enabled is False  # the wrong reading


def test_baud_rate_change_is_answered_at_the_old_rate_then_applied():
    sim = booted()
    assert sim.receive(p.encode_baud_rate_set(9600)) == h('41 75 24 01 02 27')
    assert sim.baud == 9600
    assert sim.receive(p.host_frame(0x24, 0x02, 7)) == b''  # no such code: no reply
    assert sim.baud == 9600


def test_settings_survive_a_power_cycle_but_arming_does_not():
    sim = armed()
    sim.receive(p.encode_attitude_threshold_set(80))
    sim.receive(p.encode_attitude_trigger(False))
    sim.power_cycle()
    sim.step(2.0)
    assert one(sim.receive(p.encode_attitude_threshold_query())).degrees == 80
    assert one(sim.receive(p.encode_auto_trigger_query())).attitude_enabled is False
    assert one(sim.receive(p.encode_armed_query())).armed is False


def test_malformed_or_undocumented_commands_get_no_reply():
    sim = booted()
    assert sim.receive(p.host_frame(0x10, 0x02, 0x05)) == b''  # arm with D4 = 5
    assert sim.receive(p.host_frame(0x5a, 0x01, 0x00)) == b''  # unknown code
    assert sim.receive(p.host_frame(0x20, 0x03, 0x3c)) == b''  # neither set nor query
    assert sim.receive(h('42 61 30 01 00 30')) == b''  # bad checksum
    assert sim.decoder.checksum_errors == 1
    assert sim.receive(b'\x00\xff' + p.encode_armed_query()) == h('41 75 30 01 00 31')


# ---------------------------------------------------------------------------------------------
# Streaming
# ---------------------------------------------------------------------------------------------

def test_stream_sends_status_frames_at_the_configured_rate_until_turned_off():
    sim = armed(stream_period_s=0.05)
    assert sim.receive(p.encode_streaming(True), 2.0) == h('41 75 13 01 01 15')
    sim.set_tilt(20)
    stream = msgs(sim.step(3.0))
    assert len(stream) == 20
    assert all(isinstance(m, p.Status) and m.tilt_deg == 20 and m.armed for m in stream)
    sim.set_accel(0.8)
    assert one(sim.step(3.05)).accel_g == pytest.approx(0.8)
    assert sim.receive(p.encode_streaming(False)) == h('41 75 13 01 00 14')
    assert sim.step(5.0) == b''


# ---------------------------------------------------------------------------------------------
# Auto triggers and the trigger request (P10, P12)
# ---------------------------------------------------------------------------------------------

def test_p10_confirmation_deploys_and_writes_a_record():
    sim = armed()
    sim.receive(p.encode_attitude_threshold_set(70))
    sim.set_tilt(71)
    assert sim.step(1.0) == h('41 75 39 02 01 3c')
    assert sim.receive(p.encode_trigger_confirm(), 1.9) == b''
    assert sim.triggered and not sim.armed  # deployed, then locked itself
    assert one(sim.receive(p.encode_triggered_query())).triggered
    records = [m for m in msgs(sim.receive(p.encode_trigger_records_query()))]
    assert len(records) == 8
    first = records[0]
    assert first.attitude_trigger and first.source == p.SOURCE_ATTITUDE
    assert first.attitude_threshold_deg == 70 and first.boot_count == 1
    assert first.uptime_s == 1 and first.charging and first.serial_link
    assert first.cell_voltage_v == pytest.approx(4.2)  # charging voltage on external power
    assert all(r.is_empty for r in records[1:])


def test_p10_unanswered_request_means_no_deployment():
    sim = armed()
    sim.set_tilt(80)
    assert sim.step(1.0) == h('41 75 39 02 01 3c')
    sim.step(1.999)
    assert sim.pending_request
    sim.step(2.0)
    assert not sim.pending_request and sim.requests_expired == 1
    assert sim.receive(p.encode_trigger_confirm(), 2.1) == b''  # too late: ignored
    assert not sim.triggered and sim.armed


def test_attitude_trigger_re_arms_only_10_degrees_below_the_threshold():
    sim = armed()
    sim.set_tilt(70)
    assert sim.step(1.0) == h('41 75 39 02 01 3c')
    sim.step(3.0)  # refused by silence
    sim.set_tilt(51)
    sim.set_tilt(75)
    assert sim.step(4.0) == b''  # never came back to 50 deg: no new request
    sim.set_tilt(50)
    sim.set_tilt(65)
    assert sim.step(5.0) == h('41 75 39 02 01 3c')


def test_locking_while_a_request_is_pending_prevents_the_deployment():
    sim = armed()
    sim.set_tilt(80)
    assert sim.step(1.1) == h('41 75 39 02 01 3c')
    sim.receive(p.encode_arm(False), 1.2)
    assert sim.receive(p.encode_trigger_confirm(), 1.3) == b''
    assert not sim.triggered and sim.requests_confirmed == 1


def test_arming_during_tilt_and_free_fall_fires_at_once_with_both_source_bits():
    sim = booted(external_power=False)
    sim.set_tilt(80)
    sim.start_free_fall(5.0)
    sim.step(3.0)
    assert not sim.triggered  # locked
    sim.receive(p.encode_arm(True), 3.1)
    assert sim.triggered
    record = msgs(sim.receive(p.encode_trigger_records_query()))[0]
    assert record.source == p.SOURCE_ATTITUDE | p.SOURCE_FREEFALL


def test_host_header_variant_of_the_request():
    sim = armed(trigger_request_header=p.HOST_HEADER)
    sim.set_tilt(90)
    request = sim.step(1.0)
    assert request == h('42 61 39 02 01 3c')
    assert isinstance(one(request), p.TriggerRequest)


def test_on_battery_the_module_deploys_without_asking():
    sim = armed(external_power=False)
    sim.set_tilt(85)
    out = msgs(sim.step(1.0))
    assert not any(isinstance(m, p.TriggerRequest) for m in out)
    assert sim.triggered
    assert one(sim.receive(p.encode_charging_query())).charging is False


def test_losing_external_power_while_asking_deploys_at_once():
    sim = armed()
    sim.set_tilt(85)
    sim.step(1.2)
    assert sim.pending_request
    sim.set_external_power(False)
    assert sim.triggered


def test_p12_locked_module_never_auto_deploys():
    sim = booted(external_power=False)
    sim.set_tilt(89)
    sim.start_free_fall(5.0)
    assert sim.step(10.0) == b''
    assert not sim.triggered


def test_free_fall_must_last_the_free_fall_time():
    sim = armed(external_power=False)
    sim.start_free_fall(1.5)  # shorter than 1.6 s
    sim.step(3.0)
    assert not sim.triggered
    sim.start_free_fall(2.0)
    sim.step(4.599)
    assert not sim.triggered
    sim.step(4.6)
    assert sim.triggered
    record = msgs(sim.receive(p.encode_trigger_records_query()))[0]
    assert record.freefall_trigger and not record.attitude_trigger
    assert record.uptime_s == 4 and record.charging is False
    assert record.cell_voltage_v == pytest.approx(3.9)


def test_free_fall_asks_first_on_external_power():
    sim = armed()
    sim.receive(p.encode_freefall_time_set(0.5))
    sim.start_free_fall(1.0)
    assert sim.step(1.49) == b''
    assert sim.step(1.5) == h('41 75 39 02 01 3c')


def test_acceleration_at_the_threshold_is_not_free_fall():
    sim = armed(external_power=False)
    sim.set_accel(0.5)
    sim.step(5.0)
    assert not sim.triggered
    sim.set_accel(0.49)
    sim.step(6.7)
    assert sim.triggered


def test_disabled_auto_triggers_do_not_fire():
    sim = armed(external_power=False)
    sim.receive(p.encode_attitude_trigger(False))
    sim.receive(p.encode_freefall_trigger(False))
    sim.set_tilt(90)
    sim.start_free_fall(3.0)
    sim.step(5.0)
    assert not sim.triggered
    sim.receive(p.encode_attitude_trigger(True))
    assert sim.triggered  # still tilted beyond the threshold


def test_light_level_rises_when_the_bay_opens():
    sim = armed()
    dark = one(sim.receive(p.encode_light_level_query()))
    assert dark.volts < 1.2
    sim.receive(p.encode_deploy())
    bright = one(sim.receive(p.encode_light_level_query()))
    assert bright.volts > 1.2
    sim.set_light(0.7)
    assert sim.receive(p.encode_light_level_query()) == p.module_frame(0x14, 7)


# ---------------------------------------------------------------------------------------------
# Serial deploy, locking, protection (P11, P12)
# ---------------------------------------------------------------------------------------------

def test_p11_serial_deploy_is_acknowledged_then_the_module_locks():
    sim = armed()
    assert sim.receive(p.encode_deploy(), 2.0) == h('41 75 11 01 01 13')
    assert sim.receive(p.encode_armed_query()) == h('41 75 30 01 00 31')
    assert sim.receive(p.encode_triggered_query()) == h('41 75 31 01 01 33')
    record = msgs(sim.receive(p.encode_trigger_records_query()))[0]
    assert record.serial_trigger and record.source == p.SOURCE_SERIAL and record.uptime_s == 2


def test_p12_locked_module_refuses_serial_deploy_with_00():
    sim = booted()
    assert sim.receive(p.encode_deploy()) == h('41 75 11 01 00 12')
    assert not sim.triggered and sim.failed_attempts == 1


def test_p11_three_unsuccessful_attempts_put_the_module_into_protection():
    sim = booted()
    for _ in range(3):
        assert sim.receive(p.encode_deploy()) == h('41 75 11 01 00 12')
    assert sim.protection
    sim.receive(p.encode_arm(True))
    assert sim.receive(p.encode_deploy()) == h('41 75 11 01 00 12')
    sim.set_external_power(False)
    sim.set_tilt(90)
    assert not sim.triggered
    assert sim.receive(p.encode_armed_query()) == h('41 75 30 01 01 32')  # other commands work
    sim.power_cycle()
    sim.step(2.0)
    sim.set_tilt(0)
    sim.receive(p.encode_arm(True))
    assert sim.receive(p.encode_deploy()) == h('41 75 11 01 01 13')


def test_a_success_resets_the_failure_count():
    sim = booted()
    sim.receive(p.encode_deploy())
    sim.receive(p.encode_deploy())
    sim.receive(p.encode_arm(True))
    assert sim.receive(p.encode_deploy()) == h('41 75 11 01 01 13')
    assert sim.failed_attempts == 0 and not sim.protection


def test_igniter_fault_attempts_fail_and_count():
    sim = armed()
    sim.igniter_fault = True
    for _ in range(2):
        assert sim.receive(p.encode_deploy()) == h('41 75 11 01 00 12')
    assert sim.armed and not sim.protection
    assert sim.receive(p.encode_deploy()) == h('41 75 11 01 00 12')
    assert sim.protection


def test_forbid_trigger_is_acknowledged_and_changes_nothing():
    sim = armed()
    assert sim.receive(p.encode_deploy(False)) == h('41 75 11 01 00 12')
    assert sim.armed and not sim.triggered and sim.failed_attempts == 0


def test_pwm_trigger_deploys_when_armed_only():
    sim = booted()
    assert sim.trigger_pwm() is False
    sim.receive(p.encode_arm(True))
    assert sim.trigger_pwm() is True
    record = msgs(sim.receive(p.encode_trigger_records_query()))[0]
    assert record.pwm_trigger and record.source == p.SOURCE_PWM


def test_record_ring_keeps_the_last_eight_oldest_first():
    sim = booted()
    for boot in range(10):
        sim.receive(p.encode_arm(True))
        sim.receive(p.encode_deploy())
        sim.power_cycle()
    sim.step(2.0)
    records = msgs(sim.receive(p.encode_trigger_records_query()))
    assert [r.boot_count for r in records] == list(range(3, 11))


# ---------------------------------------------------------------------------------------------
# Shutdown, external power, voltage
# ---------------------------------------------------------------------------------------------

def test_shutdown_replies_then_the_module_is_silent_until_switched_on():
    sim = armed(stream_period_s=0.1)
    sim.receive(p.encode_streaming(True))
    assert sim.receive(p.encode_shutdown(), 1.0) == h('41 75 12 01 01 14')
    assert sim.receive(p.encode_heartbeat(), 1.5) == b''
    assert sim.step(5.0) == b''
    sim.power_on()
    assert sim.step(5.05) == h('41 75 01 a5 5a 00') * 2
    assert sim.boot_count == 2
    assert sim.receive(p.encode_armed_query()) == h('41 75 30 01 00 31')


def test_external_power_wakes_a_module_that_shut_down():
    sim = booted(external_power=False)
    sim.receive(p.encode_shutdown())
    sim.set_external_power(True)
    assert sim.step(1.05) == h('41 75 01 a5 5a 00') * 2
    assert one(sim.receive(p.encode_charging_query())).charging


def test_p3_voltage_reply_is_coded_0x35_by_default_and_0x34_optionally():
    sim = booted()
    reply = sim.receive(p.encode_cell_voltage_query())
    assert reply == p.module_frame(0x35, 210)  # 4.2 V charging voltage
    sim.set_external_power(False)
    assert one(sim.receive(p.encode_cell_voltage_query())).volts == pytest.approx(3.9)
    sim = booted(voltage_reply_code=0x34, cell_voltage_v=3.8, external_power=False)
    assert sim.receive(p.encode_cell_voltage_query()) == p.module_frame(0x34, 0xbe)


def test_sensor_zeroing_takes_the_present_tilt_as_level():
    sim = booted()
    sim.set_tilt(12)
    assert sim.receive(p.encode_sensor_zero()) == h('41 75 25 01 01 27')
    assert one(sim.receive(p.encode_status_query())).tilt_deg == 0
    sim.set_tilt(30)
    assert one(sim.receive(p.encode_status_query())).tilt_deg == 18


# ---------------------------------------------------------------------------------------------
# Faults of the module and clock
# ---------------------------------------------------------------------------------------------

def test_host_bytes_split_across_reads_are_reassembled():
    sim = booted()
    frame = p.encode_armed_query()
    assert sim.receive(frame[:4]) == b''
    assert sim.receive(frame[4:]) == h('41 75 30 01 00 31')


def test_an_earlier_time_is_taken_as_the_current_time():
    sim = booted(stream_period_s=0.2)
    sim.receive(p.encode_streaming(True))
    assert sim.step(0.5) == b'' and sim.now == pytest.approx(1.0)
    assert len(msgs(sim.advance(0.2))) == 1 and sim.now == pytest.approx(1.2)


def test_a_lost_command_never_reaches_the_module():
    sim = armed()
    sim.lost_commands = {p.CMD_DEPLOY}
    assert sim.receive(p.encode_deploy()) == b'' and not sim.triggered
    assert sim.failed_attempts_total == 0
    sim.lost_commands = set()
    assert sim.receive(p.encode_deploy()) == h('41 75 11 01 01 13') and sim.triggered


def test_constructor_rejects_unknown_options():
    with pytest.raises(ValueError):
        VirtualParachute(flag_layout='other')
    with pytest.raises(ValueError):
        VirtualParachute(voltage_reply_code=0x36)
    with pytest.raises(ValueError):
        VirtualParachute(stream_period_s=0)
