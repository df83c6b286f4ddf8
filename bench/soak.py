"""The drivers for a while on lossy wires: no crash, bounded memory, no stalled topic.

``servo_bus_node`` (12 servos, 50 Hz, 115200 baud), ``parachute_node`` (status stream at
20 Hz), ``handset_link_node`` (the handset at 50 Hz) and ``originman_board_node`` (IMU at 50 Hz,
3 bus servos polled at 10 Hz, 1 Mbaud) run side by side against their virtual devices in this
process; each device drops 1 % and corrupts (checksum) 1 % of its replies at random
(``WireFaults``; the handset, which only talks, of its frames; the OriginMan board: of every
frame it sends, its reports included). A subscriber in a private rclpy context records every
``/joint_states`` of the servo bus, ``/parachute/status``, ``/handset_link/setpoint`` and
``/originman_board/imu`` message. Figures:
crashes, RSS growth of each driver from the end of the warm-up (``min(30 s, 10 %)``) to the
end, and the longest gap between two consecutive messages of each topic by their header stamps
(the driver's publish times; the gap as received here is reported too).
"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Dict, List

from bench.common import (HandsetRig, OriginManRig, ParachuteRig, ros_client, rss_bytes, ServoRig,
                          workdir)


class _DeviceProbe:
    """A runner tap: how late the device thread runs behind the wire, and output silences."""

    def __init__(self) -> None:
        self.max_lag = 0.0
        self.max_lag_at = 0.0
        self.max_tx_gap = 0.0
        self.max_tx_gap_at = 0.0
        self._last_tx = None

    def __call__(self, direction: str, data: bytes, t: float) -> None:
        now = time.monotonic()
        if now - t > self.max_lag:
            self.max_lag, self.max_lag_at = now - t, now
        if direction == 'tx':
            if self._last_tx is not None and t - self._last_tx > self.max_tx_gap:
                self.max_tx_gap, self.max_tx_gap_at = t - self._last_tx, t
            self._last_tx = t

    def reset(self) -> None:
        self.max_lag = self.max_tx_gap = 0.0


class _Watchdog:
    """A thread of this process that sleeps 5 ms at a time and keeps its longest oversleep."""

    def __init__(self, period_s: float = 0.005) -> None:
        self.period = period_s
        self.max_late = 0.0
        self.max_late_at = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='soak-watchdog', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            time.sleep(self.period)
            late = time.monotonic() - t0 - self.period
            if late > self.max_late:
                self.max_late, self.max_late_at = late, time.monotonic()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(1.0)


_LOG_MARKERS = ('offline', 'stopped answering', 're-initializ', 'back online', 'online',
                'failed', 'timed out', 'timeout', 'link lost', 'regained')


def _log_events(text: str) -> List[str]:
    return [line.strip()[-160:] for line in text.splitlines()
            if any(m in line for m in _LOG_MARKERS)]


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
        self.max_gap_at = 0.0
        self.count = 0
        self.lock = threading.Lock()

    def __call__(self, msg) -> None:
        now = time.monotonic()
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        with self.lock:
            if self.last is not None:
                if stamp - self.last > self.max_gap:
                    self.max_gap, self.max_gap_at = stamp - self.last, now
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
    """Soak the drivers for `duration_s`; return the figures."""
    from sensor_msgs.msg import Imu, JointState
    from uav_serial_drivers.msg import HandsetSetpoint, ParachuteStatus
    warmup = min(30.0, 0.1 * duration_s)
    with workdir() as directory, contextlib.ExitStack() as stack:
        servo = stack.enter_context(ServoRig(directory, list(range(1, 13)), 115200,
                                             {'publish_rate_hz': 50.0}, seed=11))
        chute = stack.enter_context(ParachuteRig(directory, stream_period_s=0.05, seed=12))
        handset = stack.enter_context(HandsetRig(directory, seed=13))
        board = stack.enter_context(OriginManRig(directory, seed=14))
        rigs = {'servo': servo, 'parachute': chute, 'handset': handset, 'originman': board}
        probes = {name: _DeviceProbe() for name in rigs}
        for name, rig in rigs.items():
            rig.runner.add_tap(probes[name])
        watchdog = _Watchdog()
        stack.callback(watchdog.stop)
        client = stack.enter_context(ros_client('bench_soak'))
        joints, status, setpoints, imu = _Gaps(), _Gaps(), _Gaps(), _Gaps()
        # The board's bus servos (bus_servo_<id>) share /joint_states with the servo bus.
        client.subscribe(JointState, '/joint_states', lambda msg: None if msg.name and
                         msg.name[0].startswith('bus_servo_') else joints(msg))
        client.subscribe(ParachuteStatus, '/parachute/status', status)
        client.subscribe(HandsetSetpoint, '/handset_link/setpoint', setpoints, depth=100)
        client.subscribe(Imu, '/originman_board/imu', imu)
        for rig in rigs.values():
            rig.wait_ready()
        for rig in rigs.values():
            rig.runner.faults.drop_probability = drop
            rig.runner.faults.corrupt_probability = corrupt
        pids = {name: rig.node.pid for name, rig in rigs.items()}
        time.sleep(min(warmup, 5.0))
        start = time.monotonic()
        joints.reset()
        status.reset()
        setpoints.reset()
        imu.reset()
        for probe in probes.values():
            probe.reset()
        watchdog.max_late = 0.0
        logs_at_start = {name: len(rig.node.output()) for name, rig in rigs.items()}
        rss: Dict[str, List[float]] = {k: [] for k in pids}
        baseline: Dict[str, int] = {}
        end = start + duration_s
        alive = True
        while time.monotonic() < end:
            time.sleep(min(sample_s, max(0.0, end - time.monotonic())))
            alive = all(rig.node.alive() for rig in rigs.values())
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
                  for name, rig in rigs.items()}
        result = {
            'soak_s': round(t_end - start, 1),
            'soak_crashes': sum(1 for rig in rigs.values() if not rig.node.alive()),
            'soak_rss_growth_mb_servo': growth['servo'],
            'soak_rss_growth_mb_parachute': growth['parachute'],
            'soak_rss_growth_mb_handset': growth['handset'],
            'soak_rss_growth_mb_originman': growth['originman'],
            'soak_max_gap_s_joint_states': joints.final(t_end),
            'soak_max_gap_s_status': status.final(t_end),
            'soak_max_gap_s_setpoint': setpoints.final(t_end),
            'soak_max_gap_s_imu': imu.final(t_end),
            'soak_rx_gap_s_joint_states': joints.max_rx_gap,
            'soak_rx_gap_s_status': status.max_rx_gap,
            'soak_rx_gap_s_setpoint': setpoints.max_rx_gap,
            'soak_rx_gap_s_imu': imu.max_rx_gap,
            'soak_joint_states_msgs': joints.count,
            'soak_status_msgs': status.count,
            'soak_setpoint_msgs': setpoints.count,
            'soak_imu_msgs': imu.count,
            'soak_faults': faults,
            'soak_stalls': {
                # Times are seconds after the start of the measured window.
                **{f'{name}_device_lag_s': (round(pr.max_lag, 3), round(pr.max_lag_at - start, 1))
                   for name, pr in probes.items()},
                **{f'{name}_device_silence_s': (round(pr.max_tx_gap, 3),
                                                round(pr.max_tx_gap_at - start, 1))
                   for name, pr in probes.items()},
                'bench_process_oversleep_s': (round(watchdog.max_late, 3),
                                              round(watchdog.max_late_at - start, 1)),
                'joint_states_gap_ended_at': round(joints.max_gap_at - start, 1),
                'status_gap_ended_at': round(status.max_gap_at - start, 1),
                'setpoint_gap_ended_at': round(setpoints.max_gap_at - start, 1),
                'imu_gap_ended_at': round(imu.max_gap_at - start, 1),
            },
            'soak_driver_log': {
                name: _log_events(rig.node.output()[logs_at_start[name]:])
                for name, rig in rigs.items()},
            'alive': alive,
        }
    return result


if __name__ == '__main__':
    import sys
    print(run(float(sys.argv[1]) if len(sys.argv) > 1 else 30.0))
