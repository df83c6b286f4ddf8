"""Release latencies through the autopilot link (issue 23), timed on the module's side of the wire.

- ``mavlink_release``: a ground station (this process, on loopback UDP) sends
  MAV_CMD_DO_PARACHUTE RELEASE to ``parachute_mavlink`` (``stop_motors_before_release`` off);
  the time runs from the moment the datagram left to the arrival of the deploy frame at the
  virtual module's port (``parachute_mavlink`` -> ``~/deploy`` -> ``parachute_node`` -> the
  release gate -> the wire).
- ``mavlink_stop_release``: the module raises a trigger request (armed, on external power,
  tilted); ``parachute_node`` asks its release gate, ``parachute_mavlink`` sends the forced
  disarm to the autopilot (this process, which answers ACCEPTED at once), and the confirmation
  follows; the time runs from the request's last byte leaving the module to the confirmation's
  last byte arriving there. Every trial also checks that the motor stop reached the autopilot
  before the confirmation reached the module.

The module is `VirtualParachute` in this process (``bench.common.ParachuteRig``), re-armed and
levelled between trials as in ``bench.latency``.
"""

from __future__ import annotations

import contextlib
import os
import socket
import threading
import time
from typing import Dict, List, Optional

from bench.common import node_process, ParachuteRig, percentile, workdir
from bench.latency import _is_confirm, _is_deploy, _rearm, _trigger_request_sent_at

os.environ.setdefault('MAVLINK20', '1')
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

GATE = 'parachute_mavlink/release_gate'


class Peer:
    """The autopilot and the ground station in one UDP socket: heartbeats, ACKs motor stops."""

    def __init__(self, node_port: int) -> None:
        self.address = ('127.0.0.1', node_port)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(('127.0.0.1', 0))
        self.sock.settimeout(0.1)
        self.autopilot = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.stops: List[float] = []
        self.acks: List[tuple] = []
        self.heard = threading.Event()
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._read, daemon=True),
                         threading.Thread(target=self._beat, daemon=True)]
        for thread in self._threads:
            thread.start()

    def _send(self, msg, mav) -> float:
        data = msg.pack(mav)
        t = time.monotonic()
        self.sock.sendto(data, self.address)
        return t

    def _beat(self) -> None:
        while not self._stop.wait(0.5):
            self._send(mavlink.MAVLink_heartbeat_message(2, 12, 129, 0, 4, 3), self.autopilot)

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65535)
            except OSError:
                continue
            t = time.monotonic()
            for msg in self.parser.parse_buffer(data) or []:
                kind = msg.get_type()
                if kind == 'HEARTBEAT' and msg.type == mavlink.MAV_TYPE_PARACHUTE:
                    self.heard.set()
                elif kind == 'COMMAND_LONG' and msg.command == \
                        mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                    self._send(mavlink.MAVLink_command_ack_message(
                        msg.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0, 1, 161), self.autopilot)
                    with self._cond:
                        self.stops.append(t)
                elif kind == 'COMMAND_ACK' and msg.command == mavlink.MAV_CMD_DO_PARACHUTE:
                    with self._cond:
                        self.acks.append((t, msg.result))
                        self._cond.notify_all()

    def release(self) -> float:
        """Send DO_PARACHUTE RELEASE as the ground station; return when it left."""
        return self._send(mavlink.MAVLink_command_long_message(
            1, 161, mavlink.MAV_CMD_DO_PARACHUTE, 0, 2, 0, 0, 0, 0, 0, 0), self.gcs)

    def final_ack(self, start: int, timeout: float) -> Optional[int]:
        """Wait for a final DO_PARACHUTE ACK after index `start`; return its result."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for _, result in self.acks[start:]:
                    if result != mavlink.MAV_RESULT_IN_PROGRESS:
                        return result
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(1.0)
        self.sock.close()


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(('127.0.0.1', 0))
        return sock.getsockname()[1]


@contextlib.contextmanager
def _link(directory, stop: str):
    port = _free_port()
    params = {'mavlink_url': f'udpin:127.0.0.1:{port}', 'stop_motors_before_release': stop,
              'preflight_period_s': 3600.0}
    with node_process('parachute_mavlink', directory, params, tag=f'parachute_mavlink_{stop}') \
            as proc:
        peer = Peer(port)
        try:
            if not peer.heard.wait(30.0):
                raise RuntimeError(f'parachute_mavlink did not heartbeat:\n{proc.output()}')
            yield proc, peer
        finally:
            peer.close()


def release_latencies(rig: ParachuteRig, peer: Peer, count: int, gap_s: float = 0.25,
                      warm_up: int = 20) -> Dict:
    """Send `count` RELEASEs to an armed module; return command-to-deploy-frame latencies.

    First, up to `warm_up` uncounted RELEASEs until one is ACCEPTED: right after it starts,
    parachute_mavlink may not have discovered ``~/deploy`` yet (it answers DENIED, 6).
    """
    for _ in range(warm_up):
        if _release_trial(rig, peer, gap_s) is not None:
            break
    latencies: List[float] = []
    failed = 0
    for _ in range(count):
        latency = _release_trial(rig, peer, gap_s)
        if latency is None:
            failed += 1
        else:
            latencies.append(latency)
    _rearm(rig)
    return {'latencies_ms': latencies, 'failed': failed}


def _release_trial(rig: ParachuteRig, peer: Peer, gap_s: float) -> Optional[float]:
    """One RELEASE: its latency (ms), or None when it was not deployed and ACCEPTED."""
    _rearm(rig)
    time.sleep(gap_s)  # a few status frames: the driver sees the module armed
    rx_start, acks = len(rig.tap.rx), len(peer.acks)
    t0 = peer.release()
    got = rig.tap.wait_rx(_is_deploy, rx_start, 2.0)
    result = peer.final_ack(acks, 5.0)
    if got is None or result != mavlink.MAV_RESULT_ACCEPTED:
        return None
    return (got[0] - t0) * 1000.0


def stop_release_latencies(rig: ParachuteRig, peer: Peer, count: int,
                           gap_s: float = 0.25, warm_up: int = 20) -> Dict:
    """Raise `count` trigger requests; return request-to-confirmation latencies with the stop.

    First, up to `warm_up` uncounted requests until one has its motor stop first: right after
    parachute_mavlink starts, parachute_node may not have discovered its gate service yet, and
    then releases without a stop, as it must.
    """
    for _ in range(warm_up):
        if _stop_release_trial(rig, peer, gap_s)[1] is False:
            break
    latencies: List[float] = []
    missed = 0
    late_stops: List[int] = []
    for trial in range(count):
        latency, late = _stop_release_trial(rig, peer, gap_s)
        if latency is None:
            missed += 1
            continue
        if late:
            late_stops.append(trial)
        latencies.append(latency)
    _rearm(rig)
    return {'latencies_ms': latencies, 'missed': missed, 'late_stops': late_stops}


def _stop_release_trial(rig: ParachuteRig, peer: Peer, gap_s: float) -> tuple:
    """One trigger request: (latency ms or None, whether the confirmation beat the stop)."""
    _rearm(rig)
    time.sleep(gap_s)
    tx_start, rx_start, stops = len(rig.tap.tx), len(rig.tap.rx), len(peer.stops)
    with rig.runner.locked():
        rig.sim.set_tilt(80.0)
    sent = _trigger_request_sent_at(rig, tx_start, 1.0)
    got = rig.tap.wait_rx(_is_confirm, rx_start, 1.5)
    if sent is None or got is None:
        return None, None
    late = len(peer.stops) <= stops or peer.stops[stops] > got[0]
    return (got[0] - sent) * 1000.0, late


def run(release_count: int = 200, stop_count: int = 200) -> Dict:
    """Measure both figures; return them."""
    with workdir() as directory, contextlib.ExitStack() as stack:
        rig = stack.enter_context(ParachuteRig(directory, parameters={
            'release_gate': GATE, 'trigger_request_policy': 'confirm'}))
        rig.wait_ready()
        time.sleep(1.0)
        with _link(directory, 'off') as (proc, peer):
            release = release_latencies(rig, peer, release_count)
            alive = proc.alive()
        with _link(directory, 'disarm') as (proc, peer):
            stop = stop_release_latencies(rig, peer, stop_count)
            alive = alive and proc.alive() and rig.node.alive()
    r, s = release['latencies_ms'], stop['latencies_ms']
    return {
        'mavlink_release_n': len(r), 'mavlink_release_failed': release['failed'],
        'mavlink_release_p50_ms': percentile(r, 50),
        'mavlink_release_p99_ms': percentile(r, 99),
        'mavlink_release_max_ms': max(r) if r else float('nan'),
        'mavlink_stop_release_n': len(s), 'mavlink_stop_release_missed': stop['missed'],
        'mavlink_stop_release_late_stops': len(stop['late_stops']),
        'mavlink_stop_release_late_trials': stop['late_stops'],
        'mavlink_stop_release_p50_ms': percentile(s, 50),
        'mavlink_stop_release_p99_ms': percentile(s, 99),
        'mavlink_stop_release_max_ms': max(s) if s else float('nan'),
        'alive': alive,
    }
