"""Short variants of the fault campaign of ``make bench`` (bench/), as ordinary tests.

They run the same code as the benchmark with tiny sizes and assert only correctness figures
(no exception, every clean frame recovered, no crash, nothing leaked, every bad request
refused with nothing sent, the deploy record on disk), never timing. Each benchmark claims its
own ROS domain, different from this session's.
"""

import math

from bench import bad_inputs, blackbox_kill9, fuzz, reconnects, soak
import pytest


@pytest.mark.parametrize('decoder', ['dps_from_module', 'dps_from_host', 'servo_reply',
                                     'servo_request', 'handset', 'originman_from_board'])
def test_fuzzed_decoder_never_raises_and_recovers_every_clean_frame(decoder):
    r = fuzz.fuzz_one(decoder, 20000, seed=3)
    assert r['exceptions'] == 0
    assert r['valid'] > 5000
    assert r['recovered'] == r['valid'] - r['overlapped']
    assert r['recovered_pct'] == 100.0


@pytest.mark.parametrize('device', ['servo', 'parachute', 'handset', 'originman'])
def test_unplug_replug_cycles_recover_without_crash_or_leak(device):
    r = getattr(reconnects, device)(cycles=6, unplug_s=0.2)
    assert r['crashes'] == 0
    assert r['cycles'] == 6
    assert r['not_recovered'] == 0, r['details']
    assert r['fd_leak'] <= 0 and r['pty_fd_leak'] <= 0
    assert r['thread_leak'] <= 0


def test_short_soak_on_lossy_wires_keeps_every_driver_alive_and_publishing():
    r = soak.run(duration_s=5.0, sample_s=1.0)
    assert r['soak_crashes'] == 0 and r['alive']
    assert r['soak_joint_states_msgs'] > 0 and r['soak_status_msgs'] > 0
    assert r['soak_setpoint_msgs'] > 0 and r['soak_imu_msgs'] > 0
    assert math.isfinite(r['soak_max_gap_s_imu'])
    assert math.isfinite(r['soak_max_gap_s_joint_states'])
    assert math.isfinite(r['soak_max_gap_s_status'])
    assert math.isfinite(r['soak_max_gap_s_setpoint'])


def test_sigkill_right_after_deploy_acknowledgement_leaves_the_record_on_disk():
    r = blackbox_kill9.run(rounds=2, wire_rounds=0)
    assert r['errors'] == []
    assert r['kill9_record_on_disk'] == 2


@pytest.mark.parametrize('driver', ['servo', 'parachute', 'handset', 'originman'])
def test_malformed_service_requests_are_refused_with_nothing_on_the_wire(driver):
    # The background window must hold every kind of frame the driver polls: the board's bus
    # servo telemetry comes every 2 s (its default period), so it gets half a period more.
    r = getattr(bad_inputs, driver)(observe_s=3.0 if driver == 'originman' else 2.0)
    assert r['errors'] == []
    assert r['accepted'] == []
    assert r['refused'] == r['cases']
    assert r['bytes_on_wire'] == []
