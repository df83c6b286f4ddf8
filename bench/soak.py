"""Both drivers for a while on lossy wires: no crash, bounded memory, no stalled topic.

``servo_bus_node`` (12 servos, 50 Hz, 115200 baud) and ``parachute_node`` (status stream at
20 Hz) run side by side against their virtual devices in this process; each device drops 1 %
and corrupts (checksum) 1 % of its replies at random (``WireFaults``). A subscriber in a private
rclpy context records every ``/joint_states`` and ``/parachute/status`` message. Figures:
crashes, RSS growth of each driver from the end of the warm-up (``min(30 s, 10 %)``) to the
end, and the longest gap between two consecutive messages of each topic by their header stamps
(the driver's publish times; the gap as received here is reported too).
"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Dict, List

from bench.common import ParachuteRig, ros_client, rss_bytes, ServoRig, workdir


class _Gaps:
    """Longest gap between consecutive messages, by their header stamps (publish time).

    Stamps measure the driver's cadence whatever this process's own scheduling does; the
    receive-time gap is kept too, for information.
    """

    def __init__(self) -> None:
        self.last = None
        self.last_rx = None
        self.max_gap = 0.0
        self.max_rx_gap = 0.0
        self.count = 0
        self.lock = threading.Lock()

    def __call__(self, msg) -> None:
        now = time.monotonic()
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        with self.lock:
            if self.last is not None:
                self.max_gap = max(self.max_gap, stamp - self.last)
                self.max_rx_gap = max(self.max_rx_gap, now - self.last_rx)
            self.last, self.last_rx = stamp, now
            self.count += 1

    def reset(self) -> None:
        with self.lock:
            self.last = self.last_rx = None
            self.max_gap = self.max_rx_gap = 0.0
            self.count = 0

    def final(self, end: float) -> float:
        """Return the longest stamp gap, or the time since the last message if longer."""
        with self.lock:
            tail = end - self.last_rx if self.last_rx is not None else float('inf')
            return max(self.max_gap, tail)


def run(duration_s: float = 300.0, drop: float = 0.01, corrupt: float = 0.01,
        sample_s: float = 2.0) -> Dict:
    """Soak both drivers for `duration_s`; return the figures."""
    from sensor_msgs.msg import JointState
    from uav_serial_drivers.msg import ParachuteStatus
    warmup = min(30.0, 0.1 * duration_s)
    with workdir() as directory, contextlib.ExitStack() as stack:
        servo = stack.enter_context(ServoRig(directory, list(range(1, 13)), 115200,
                                             {'publish_rate_hz': 50.0}, seed=11))
        chute = stack.enter_context(ParachuteRig(directory, stream_period_s=0.05, seed=12))
        client = stack.enter_context(ros_client('bench_soak'))
        joints, status = _Gaps(), _Gaps()
        client.subscribe(JointState, '/joint_states', joints)
        client.subscribe(ParachuteStatus, '/parachute/status', status)
        servo.wait_ready()
        chute.wait_ready()
        for rig in (servo, chute):
            rig.runner.faults.drop_probability = drop
            rig.runner.faults.corrupt_probability = corrupt
        pids = {'servo': servo.node.pid, 'parachute': chute.node.pid}
        time.sleep(min(warmup, 5.0))
        start = time.monotonic()
        joints.reset()
        status.reset()
        rss: Dict[str, List[float]] = {k: [] for k in pids}
        baseline: Dict[str, int] = {}
        end = start + duration_s
        alive = True
        while time.monotonic() < end:
            time.sleep(min(sample_s, max(0.0, end - time.monotonic())))
            alive = servo.node.alive() and chute.node.alive()
            if not alive:
                break
            for name, pid in pids.items():
                rss[name].append(rss_bytes(pid))
            if not baseline and time.monotonic() - start >= warmup:
                baseline = {name: rss[name][-1] for name in pids}
        t_end = time.monotonic()
        growth = {name: (rss[name][-1] - baseline.get(name, rss[name][0])) / 1e6
                  if rss[name] else float('nan') for name in pids}
        faults = {name: (rig.runner.replies_dropped, rig.runner.replies_corrupted)
                  for name, rig in (('servo', servo), ('parachute', chute))}
        result = {
            'soak_s': round(t_end - start, 1),
            'soak_crashes': sum(1 for rig in (servo, chute) if not rig.node.alive()),
            'soak_rss_growth_mb_servo': growth['servo'],
            'soak_rss_growth_mb_parachute': growth['parachute'],
            'soak_max_gap_s_joint_states': joints.final(t_end),
            'soak_max_gap_s_status': status.final(t_end),
            'soak_rx_gap_s_joint_states': joints.max_rx_gap,
            'soak_rx_gap_s_status': status.max_rx_gap,
            'soak_joint_states_msgs': joints.count,
            'soak_status_msgs': status.count,
            'soak_faults': faults,
            'alive': alive,
        }
    return result


if __name__ == '__main__':
    import sys
    print(run(float(sys.argv[1]) if len(sys.argv) > 1 else 30.0))
