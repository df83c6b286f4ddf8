"""How fast ``servo_bus_node`` answers: scans, commands under load, and how old its positions are.

The bus is the virtual servo bus in this process (``ServoRig``: wire timing at 115200 baud, taps
on both directions), the driver a process. Every figure is taken from the wire:

- ``scan_s``: the ``~/scan`` service over ids 1..250 with 12 servos (1..12) on the bus, while the
  driver reads them at 50 Hz; call -> response in this process, the longest of 3 calls.
- ``scan_startup_s``: the driver started with empty ``servo_ids`` on the same bus: from the
  first byte of the first PING on the wire to the first byte of the read loop's first READ.
- ``scan_slow_s`` (information): ``~/scan`` of 1..250 on a bus of 3 servos (5, 100, 250) that
  answer 25 ms after a request (``response_delay_s``), far beyond the reply margin of a pty;
  ``scan_slow_found`` says whether all three were found.
- ``command_p99_ms``: 12 servos read at full rate (``publish_rate_hz`` 1000, telemetry every
  1 s); 200 ``~/command`` messages published at random moments (15-35 ms apart), each with its
  own target, from a process of its own (``bench.servo_client``: no GIL shared with the virtual
  bus); from just before ``publish()`` to the first byte of the SYNC WRITE carrying that target
  arriving at the bus.
- ``write_positions_p99_ms``: the same with 200 ``~/write_positions`` calls (``call_async``,
  10-30 ms after the previous answer) to the first byte of their SYNC WRITE; the notes give the
  call's round trip.
- ``joint_states_age_p99_ms``: same load; each position READ is answered with a position of its
  own (a counter per servo), so each ``joint_states`` message names the replies it carries. A
  subscriber in a process of its own (``bench.topic_receiver``) records the middleware's source
  timestamp of each message (when the driver published it); the age is that time minus the
  arrival (last byte at the driver's port) of the newest reply in the message, over a 10 s
  window. The notes give the read cycle (median time between two READs of one servo) and where
  the header stamp lies: stamp minus the arrival of the oldest reply in the message.
"""

from __future__ import annotations

import json
import math
import time
from bisect import bisect_right
from typing import Any, Dict, List, Tuple

from bench.common import (is_position_read, percentile, POSITION_ADDRESS, ros_client, ServoRig,
                          workdir)
from uav_serial_common.pty_port import wire_time

BAUD = 115200
IDS = list(range(1, 13))
TWO_PI = 2.0 * math.pi


def _numbered_bus_class() -> Any:
    from desheng_servo_ros.protocol import Instruction, StreamDecoder
    from desheng_servo_ros.virtual_node import VirtualServoBus

    class NumberedServoBus(VirtualServoBus):
        """A virtual bus whose servos answer each position READ with a position of its own."""

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self._requests = StreamDecoder('request')
            self.counts: Dict[int, int] = {}

        def _on_input(self, data: bytes, now: float) -> List[bytes]:
            for req in self._requests.feed(data):
                if req.instruction == Instruction.READ and is_position_read(req) and \
                        req.servo_id in self.sim.ids:
                    count = self.counts.get(req.servo_id, 0) + 1
                    self.counts[req.servo_id] = count
                    self.sim.move_by_hand(req.servo_id, 1 + count % 4000)
            return self.sim.feed(data, now)
    return NumberedServoBus


def _ticks(rad: float) -> int:
    return int(round(2048 + rad * 4096 / TWO_PI))


def _rad(ticks: int) -> float:
    return (ticks - 2048) * TWO_PI / 4096


def _first_byte(t_last: float, frame: bytes) -> float:
    """Return when the first byte of `frame` arrived, its last having arrived at `t_last`."""
    return t_last - wire_time(len(frame), BAUD)


def _sync_writes(rig: ServoRig, since: float) -> Dict[int, float]:
    """Return {target ticks of servo 1: first byte on the wire} of the SYNC WRITEs since."""
    from desheng_servo_ros import protocol as proto
    _, requests = rig.tap.snapshot()
    out: Dict[int, float] = {}
    for t, req in requests:
        if t < since or req.instruction != proto.Instruction.SYNC_WRITE:
            continue
        _, _, items = proto.parse_sync_write(bytes(req.params))
        for servo_id, data in items:
            if servo_id == 1:
                out.setdefault(int.from_bytes(data[:2], 'big'), _first_byte(t, req.raw))
    return out


def move_latencies(rig: ServoRig, mode: str, count: int, first_ticks: int) -> Dict[str, Any]:
    """Send `count` moves (`mode` 'command' or 'write_positions'); return send -> wire (ms)."""
    from bench.servo_client import run_client
    start = time.monotonic()
    out = run_client(mode, count, first_ticks, IDS)
    time.sleep(0.2)
    wire = _sync_writes(rig, start)
    latencies = [(wire[t] - t0) * 1000.0 for t, t0 in out['sent'] if t in wire]
    return {'latencies_ms': latencies, 'missed': len(out['sent']) - len(latencies),
            'failed': out['failed'], 'round_trip_ms': out['round_trip_ms']}


def _replies_by_servo(rig: ServoRig) -> Dict[int, Tuple[List[float], List[int]]]:
    """Return {id: (arrival times, positions)} of every position reply so far, in order."""
    transactions, _ = rig.tap.snapshot()
    out: Dict[int, Tuple[List[float], List[int]]] = {}
    for _, t_rep, req, rep in transactions:
        if not is_position_read(req):
            continue
        at = POSITION_ADDRESS - req.params[0]
        times, values = out.setdefault(rep.servo_id, ([], []))
        times.append(t_rep)
        values.append(int.from_bytes(bytes(rep.params[at:at + 2]), 'big'))
    return out


def joint_states_ages(rig: ServoRig, directory: Any, duration_s: float) -> Dict[str, Any]:
    """Return how old the newest position of each ``joint_states`` message was when it left."""
    from bench.topic_receiver import topic_receiver
    out = directory / 'joint_states.json'
    with topic_receiver('sensor_msgs/msg/JointState', '/joint_states', out,
                        fields=('header.stamp', 'name', 'position')) as offset:
        time.sleep(0.5)
        t0 = time.monotonic()
        time.sleep(duration_s)
        t1 = time.monotonic()
        time.sleep(0.3)
    received = json.loads(out.read_text())
    replies = _replies_by_servo(rig)
    ages: List[float] = []
    stamp_offsets: List[float] = []
    unmatched = 0
    for fields, _, source_s in received:
        leave = source_s - offset
        if not t0 <= leave <= t1 or not fields['name']:
            continue
        arrivals = []
        for name, rad in zip(fields['name'], fields['position']):
            times, values = replies.get(int(name.rsplit('_', 1)[1]), ([], []))
            ticks = _ticks(rad)
            # The latest reply of that servo with that position, at or before the message left.
            k = bisect_right(times, leave + 0.0005)
            while k > 0 and values[k - 1] != ticks:
                k -= 1
            if k == 0:
                arrivals = []
                break
            arrivals.append(times[k - 1])
        if not arrivals:
            unmatched += 1
            continue
        ages.append((leave - max(arrivals)) * 1000.0)
        stamp_offsets.append((fields['header.stamp'] - offset - min(arrivals)) * 1000.0)
    cycle = [b - a for a, b in zip(replies.get(1, ([], []))[0], replies.get(1, ([], []))[0][1:])
             if t0 <= a <= t1]
    return {'ages_ms': ages, 'unmatched': unmatched, 'stamp_offsets_ms': stamp_offsets,
            'cycle_ms': percentile(cycle, 50) * 1000.0}


def scan_times(count: int = 3) -> Dict[str, Any]:
    """Time ``~/scan`` 1..250 `count` times with 12 servos on the bus, read at 50 Hz."""
    from uav_serial_drivers.srv import ScanBus
    times: List[float] = []
    found: List[List[int]] = []
    with workdir() as directory, \
            ServoRig(directory, IDS, BAUD, {'publish_rate_hz': 50.0}) as rig, \
            ros_client('bench_servo_scan') as client:
        rig.wait_ready()
        service = client.client(ScanBus, '/servo_bus/scan')
        for _ in range(count):
            t0 = time.monotonic()
            response = client.call(service, ScanBus.Request(first_id=1, last_id=250),
                                   timeout=60.0)
            times.append(time.monotonic() - t0)
            found.append(list(response.ids))
    return {'times_s': times, 'all_found': all(f == IDS for f in found)}


def startup_scan_time() -> Dict[str, Any]:
    """Time the start-up scan of 1..250 (empty ``servo_ids``) with 12 servos on the bus."""
    from desheng_servo_ros.protocol import Instruction
    with workdir() as directory, \
            ServoRig(directory, IDS, BAUD, {'publish_rate_hz': 50.0, 'servo_ids': [],
                                            'joint_names': []}) as rig:
        rig.wait_ready(timeout=60.0)
        _, requests = rig.tap.snapshot()
    pings = [(t, r) for t, r in requests if r.instruction == Instruction.PING]
    reads = [(t, r) for t, r in requests if is_position_read(r)]
    if not pings or not reads:
        raise RuntimeError('no start-up scan seen on the wire')
    first_ping = _first_byte(pings[0][0], pings[0][1].raw)
    first_read = _first_byte(reads[0][0], reads[0][1].raw)
    return {'time_s': first_read - first_ping, 'pings': len(pings)}


def slow_scan_time(delay_s: float = 0.025) -> Dict[str, Any]:
    """Time ``~/scan`` 1..250 on a bus of 3 servos answering `delay_s` after each request."""
    from uav_serial_drivers.srv import ScanBus
    ids = [5, 100, 250]
    with workdir() as directory, \
            ServoRig(directory, ids, BAUD, {'publish_rate_hz': 50.0},
                     response_delay_s=delay_s) as rig, \
            ros_client('bench_servo_slow_scan') as client:
        rig.wait_ready(timeout=60.0)
        service = client.client(ScanBus, '/servo_bus/scan')
        t0 = time.monotonic()
        response = client.call(service, ScanBus.Request(first_id=1, last_id=250), timeout=60.0)
        elapsed = time.monotonic() - t0
    return {'time_s': elapsed, 'found': list(response.ids) == ids}


def run(count: int = 200, age_window_s: float = 10.0, scans: int = 3) -> Dict[str, Any]:
    """Measure every figure of this module; return them."""
    out: Dict[str, Any] = {}
    with workdir() as directory, \
            ServoRig(directory, IDS, BAUD, {'publish_rate_hz': 1000.0},
                     bus_class=_numbered_bus_class()) as rig:
        rig.wait_ready()
        time.sleep(1.0)
        age = joint_states_ages(rig, directory, age_window_s)
        cmd = move_latencies(rig, 'command', count, 100)
        wp = move_latencies(rig, 'write_positions', count, 2100)
        alive = rig.node.alive()
    out.update({
        'joint_states_age_p50_ms': percentile(age['ages_ms'], 50),
        'joint_states_age_p99_ms': percentile(age['ages_ms'], 99),
        'joint_states_age_n': len(age['ages_ms']), 'joint_states_unmatched': age['unmatched'],
        'joint_states_stamp_offset_p50_ms': percentile(age['stamp_offsets_ms'], 50),
        'joint_states_stamp_offset_max_ms': max(age['stamp_offsets_ms'], default=math.nan),
        'read_cycle_ms': age['cycle_ms'],
        'command_p50_ms': percentile(cmd['latencies_ms'], 50),
        'command_p99_ms': percentile(cmd['latencies_ms'], 99),
        'command_max_ms': max(cmd['latencies_ms'], default=math.nan),
        'command_n': len(cmd['latencies_ms']), 'command_missed': cmd['missed'],
        'write_positions_p50_ms': percentile(wp['latencies_ms'], 50),
        'write_positions_p99_ms': percentile(wp['latencies_ms'], 99),
        'write_positions_max_ms': max(wp['latencies_ms'], default=math.nan),
        'write_positions_n': len(wp['latencies_ms']),
        'write_positions_missed': wp['missed'] + wp['failed'],
        'write_positions_round_trip_p99_ms': percentile(wp['round_trip_ms'], 99),
        'alive': alive,
    })
    scan = scan_times(scans)
    out['scan_s'] = max(scan['times_s'])
    out['scan_found_all'] = scan['all_found']
    startup = startup_scan_time()
    out['scan_startup_s'] = startup['time_s']
    slow = slow_scan_time()
    out['scan_slow_s'] = slow['time_s']
    out['scan_slow_found'] = slow['found']
    return out


if __name__ == '__main__':
    import sys
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 200
    for key, value in run(n).items():
        print(f'{key} = {value:.3f}' if isinstance(value, float) else f'{key} = {value}')
