"""Safety-path latencies of ``parachute_node``, timed on the module's side of the wire.

- ``confirm``: the virtual module (``VirtualParachute`` behind ``VirtualDeviceRunner`` in this
  process, 115200 baud) raises a crash trigger request (armed, on external power, tilt above the
  threshold); the time runs from the moment its last byte left the module's port to the moment
  the last byte of the driver's confirmation ``42 61 39 a5 01 df`` arrived there. After each
  request the module is re-armed and levelled again.
- ``deploy``: from the benchmark's ``~/deploy`` service call (``call_async``) to the arrival of
  the deploy frame (``42 61 11 02 01 ..``) at the module's port, with the module armed.

Both run while ``servo_bus_node`` polls 12 servos at full rate on a virtual bus in another
process (``bench.device_proc``), so the driver competes for the two cores as on a drone.

The handset's frame-to-``~/setpoint`` latency (``run_handset``) and the OriginMan board's
report-to-``~/imu`` latency (``imu_run``) are measured the same way, with ``parachute_node``
and ``virtual_parachute`` (status stream at 20 Hz) running beside the servo bus as well
(``_background``).
"""

from __future__ import annotations

import contextlib
import time
from typing import Dict, List

from bench.common import (node_process, ParachuteRig, percentile, ros_client,
                          workdir)
from bench.device_proc import servo_bus_process


def _background(stack: contextlib.ExitStack, directory, parachute: bool = True) -> List:
    """Start the other drivers as processes in `stack`; return their `node_process` handles.

    ``servo_bus_node`` polls 12 servos at full rate on a virtual bus in another process; with
    `parachute`, ``parachute_node`` runs on ``virtual_parachute`` streaming at 20 Hz.
    """
    servo_link = str(directory / 'bg-servo.pty')
    ids = list(range(1, 13))
    stack.enter_context(servo_bus_process(servo_link, 115200, ids))
    nodes = [stack.enter_context(node_process(
        'servo_bus_node', directory, {'port': servo_link, 'baud': 115200,
                                      'servo_ids': ids, 'publish_rate_hz': 1000.0},
        tag='bg_servo_bus_node'))]
    if parachute:
        chute_link = str(directory / 'bg-parachute.pty')
        nodes.append(stack.enter_context(node_process(
            'virtual_parachute', directory, {'link': chute_link, 'stream_rate_hz': 20.0},
            tag='bg_virtual_parachute')))
        nodes.append(stack.enter_context(node_process(
            'parachute_node', directory, {'port': chute_link,
                                          'blackbox_dir': str(directory / 'bg-blackbox')},
            tag='bg_parachute_node')))
    return nodes


def _is_confirm(frame) -> bool:
    from dps_parachute_ros import protocol as p
    return frame.code == p.CMD_TRIGGER_REQUEST and frame.data == p.CONFIRM_PAYLOAD


def _is_deploy(frame) -> bool:
    from dps_parachute_ros import protocol as p
    return frame.code == p.CMD_DEPLOY and frame.data[1:2] == b'\x01'


def _rearm(rig: ParachuteRig) -> None:
    with rig.runner.locked():
        sim = rig.sim
        sim.set_tilt(0.0)
        sim.triggered = False
        sim.protection = False
        sim.armed = True


def _trigger_request_sent_at(rig: ParachuteRig, start: int, timeout: float):
    from dps_parachute_ros import protocol as p
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for t, frame in rig.tap.tx[start:]:
            if frame.code == p.CMD_TRIGGER_REQUEST:
                return t
        time.sleep(0.0005)
    return None


def confirm_latencies(rig: ParachuteRig, count: int, gap_s: float = 0.15) -> Dict:
    """Raise `count` trigger requests; return confirmation latencies (ms) and misses."""
    latencies: List[float] = []
    missed = 0
    for _ in range(count):
        _rearm(rig)
        time.sleep(gap_s)
        tx_start, rx_start = len(rig.tap.tx), len(rig.tap.rx)
        with rig.runner.locked():
            rig.sim.set_tilt(80.0)
        sent = _trigger_request_sent_at(rig, tx_start, 1.0)
        got = rig.tap.wait_rx(_is_confirm, rx_start, 1.5)
        if sent is None or got is None:
            missed += 1
            continue
        latencies.append((got[0] - sent) * 1000.0)
    _rearm(rig)
    return {'latencies_ms': latencies, 'missed': missed}


def deploy_latencies(rig: ParachuteRig, client, count: int, gap_s: float = 0.25) -> Dict:
    """Call ``~/deploy`` `count` times with the module armed; return frame latencies (ms)."""
    from uav_serial_drivers.srv import Deploy
    service = client.client(Deploy, '/parachute/deploy')
    latencies: List[float] = []
    service_ms: List[float] = []
    failed = 0
    for _ in range(count):
        _rearm(rig)
        time.sleep(gap_s)  # a few status frames: the driver sees the module armed
        rx_start = len(rig.tap.rx)
        request = Deploy.Request(confirm='DEPLOY', arm_if_locked=False)
        t0 = time.monotonic()
        response = client.call(service, request, timeout=10.0)
        t_resp = time.monotonic()
        got = rig.tap.wait_rx(_is_deploy, rx_start, 0.5)
        if got is None or not response.success:
            failed += 1
            continue
        latencies.append((got[0] - t0) * 1000.0)
        service_ms.append((t_resp - t0) * 1000.0)
    _rearm(rig)
    return {'latencies_ms': latencies, 'service_ms': service_ms, 'failed': failed}


def run(confirm_count: int = 200, deploy_count: int = 200, background: bool = True) -> Dict:
    """Measure both latencies with the servo driver as background load; return figures."""
    with workdir() as directory, contextlib.ExitStack() as stack:
        bg = _background(stack, directory, parachute=False) if background else []
        rig = stack.enter_context(ParachuteRig(directory))
        client = stack.enter_context(ros_client('bench_latency'))
        rig.wait_ready()
        time.sleep(1.0)
        confirm = confirm_latencies(rig, confirm_count)
        deploy = deploy_latencies(rig, client, deploy_count)
        alive = rig.node.alive() and all(p.alive() for p in bg)
    c, d = confirm['latencies_ms'], deploy['latencies_ms']
    return {
        'confirm_n': len(c), 'confirm_missed': confirm['missed'],
        'confirm_p50_ms': percentile(c, 50), 'confirm_p99_ms': percentile(c, 99),
        'confirm_max_ms': max(c) if c else float('nan'),
        'deploy_n': len(d), 'deploy_failed': deploy['failed'],
        'deploy_p50_ms': percentile(d, 50), 'deploy_p99_ms': percentile(d, 99),
        'deploy_max_ms': max(d) if d else float('nan'),
        'deploy_service_p99_ms': percentile(deploy['service_ms'], 99),
        'alive': alive,
    }


# -- the handset link -----------------------------------------------------------------------------

def _handset_key(field: str, value: float) -> tuple:
    return field, round(value, 4)


def handset_latencies(rig, directory, duration_s: float) -> Dict:
    """Record `duration_s` of numbered ticks; return frame-to-``~/setpoint`` latencies (ms).

    A frame's time is when its last byte arrived at the driver's port (the runner's pacing); a
    message's time is when a subscriber in a process of its own received it
    (``bench.topic_receiver``: this process runs the handset, and its GIL would be in the
    figure). Each stick frame carries a value unique to its tick, so each is matched to the
    message that carries it.
    """
    import json
    from bench.topic_receiver import topic_receiver
    out = directory / 'setpoints_received.json'
    sticks = ('yaw_deg', 'pitch_deg', 'roll_deg', 'altitude_m')
    with topic_receiver('uav_serial_drivers/msg/HandsetSetpoint', '/handset_link/setpoint', out,
                        fields=('updated',) + sticks):
        time.sleep(0.5)
        t0 = time.monotonic()
        time.sleep(duration_s)
        t1 = time.monotonic()
        time.sleep(0.5)  # the last frames' messages
    arrivals: Dict[tuple, float] = {}
    for fields, t_rx, _ in json.loads(out.read_text()):
        for field in fields['updated']:
            if field in sticks:
                arrivals.setdefault(_handset_key(field, fields[field]), t_rx)
    latencies: List[float] = []
    missed = 0
    for t_wire, cmd in rig.tap.snapshot():
        if not t0 <= t_wire <= t1 or cmd.field not in ('yaw', 'pitch', 'roll', 'altitude'):
            continue
        field = {'yaw': 'yaw_deg', 'pitch': 'pitch_deg', 'roll': 'roll_deg',
                 'altitude': 'altitude_m'}[cmd.field]
        t_rx = arrivals.get(_handset_key(field, float(cmd.value)))
        if t_rx is None:
            missed += 1
        else:
            latencies.append((t_rx - t_wire) * 1000.0)
    return {'latencies_ms': latencies, 'missed': missed}


def run_handset(duration_s: float = 20.0, background: bool = True) -> Dict:
    """Measure the handset's frame-to-setpoint latency with the other drivers running."""
    from bench.common import HandsetRig
    with workdir() as directory, contextlib.ExitStack() as stack:
        bg = _background(stack, directory) if background else []
        rig = stack.enter_context(HandsetRig(directory, numbered=True))
        rig.wait_ready()
        r = handset_latencies(rig, directory, duration_s)
        alive = rig.node.alive() and all(p.alive() for p in bg)
    lat = r['latencies_ms']
    return {
        'handset_latency_n': len(lat), 'handset_latency_missed': r['missed'],
        'handset_latency_p50_ms': percentile(lat, 50),
        'handset_latency_p99_ms': percentile(lat, 99),
        'handset_latency_max_ms': max(lat) if lat else float('nan'),
        'alive': alive,
    }


# -- the OriginMan board's IMU: the report's last byte on the wire -> ~/imu received --------------

def imu_latencies(rig, directory, duration_s: float) -> Dict:
    """Receive ``~/imu`` for `duration_s`; return latencies (ms) of the reports of the window.

    Every report carries its own gyro x (a counter, from the model's IMU source), so a message
    is matched to the wire time of exactly its report. The receiver is a process of its own
    (``bench.topic_receiver``): this one runs the board, and its GIL would be in the figure.
    """
    import json
    from bench.topic_receiver import topic_receiver
    out = directory / 'imu_received.json'
    with topic_receiver('sensor_msgs/msg/Imu', '/originman_board/imu', out,
                        fields=('angular_velocity.x', 'header.stamp')) as wall_offset:
        t0 = time.monotonic() + 0.5
        time.sleep(duration_s + 0.5)
        t1 = time.monotonic()
        time.sleep(0.5)  # the last reports of the window arrive
    received = {f['angular_velocity.x']: (t, f['header.stamp'] - wall_offset)
                for f, t, _ in json.loads(out.read_text())}
    with rig.tap._lock:
        sent = {k: t for k, t in rig.tap.imu_times.items() if t0 <= t <= t1}
    latencies = [(received[k][0] - t) * 1000.0 for k, t in sent.items() if k in received]
    # Information: the driver's share, to its publish (the header stamp, wall clock).
    driver = [(received[k][1] - t) * 1000.0 for k, t in sent.items() if k in received]
    return {'latencies_ms': latencies, 'driver_ms': driver, 'sent': len(sent),
            'missed': len(sent) - len(latencies)}


def imu_run(duration_s: float = 30.0, rate_hz: float = 100.0,
            background: bool = True) -> Dict:
    """IMU latency of ``originman_board_node`` beside the other drivers; return figures."""
    import itertools
    from bench.common import OriginManRig
    with workdir() as directory, contextlib.ExitStack() as stack:
        bg = _background(stack, directory) if background else []
        counter = itertools.count(1)

        def marked(t: float) -> tuple:
            return (0.0, 0.0, 1.0), (float(next(counter)), 0.0, 0.0)
        rig = stack.enter_context(OriginManRig(directory, keep_imu=True, imu_rate_hz=rate_hz))
        with rig.runner.locked():
            rig.model.set_imu_source(marked)
        rig.wait_ready()
        r = imu_latencies(rig, directory, duration_s)
        alive = rig.node.alive() and all(p.alive() for p in bg)
    lat = r['latencies_ms']
    return {'imu_latency_n': len(lat), 'imu_latency_missed': r['missed'],
            'imu_latency_p50_ms': percentile(lat, 50), 'imu_latency_p99_ms': percentile(lat, 99),
            'imu_latency_max_ms': max(lat) if lat else float('nan'),
            'imu_latency_driver_p50_ms': percentile(r['driver_ms'], 50),
            'imu_latency_driver_p99_ms': percentile(r['driver_ms'], 99), 'alive': alive}
