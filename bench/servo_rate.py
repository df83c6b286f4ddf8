"""Full-bus position reads per second of ``servo_bus_node``, as a fraction of the wire limit.

The servo bus is ``desheng_servo_ros.simulation.ServoBusSim`` (the core of
``virtual_servo_bus``) behind ``VirtualDeviceRunner`` in this process, with the same wire
timing: a request reaches the model only once its last byte would have arrived at the baud
rate, and the reply is paced out at that rate. ``servo_bus_node`` runs as a process with
``publish_rate_hz`` far above what the wire allows, so it reads as fast as it can, and the
slow telemetry reads pushed out of the window (``telemetry_period_s`` = 1 h).

From the device side of the wire over a window of ``duration_s`` after warm-up:
``achieved`` = position-read transactions (READ covering 0x38 and its reply) / N / s;
``wire limit`` = baud / (10 x mean request+reply bytes) / N; ratio = achieved / limit, i.e. the
fraction of the window the wire spent carrying position reads.
"""

from __future__ import annotations

import time
from typing import Dict, Optional

from bench.common import CpuMeter, percentile, ServoRig, workdir
from uav_serial_common.pty_port import wire_time


def measure(n_servos: int, baud: int = 115200, duration_s: float = 5.0,
            warmup_s: float = 1.0, publish_rate_hz: float = 1000.0,
            telemetry_period_s: float = 3600.0,
            extra_parameters: Optional[Dict] = None) -> Dict[str, float]:
    """Run one rate measurement; return ratio, cycles/s, wire limit and node CPU."""
    ids = list(range(1, n_servos + 1))
    params = {'publish_rate_hz': float(publish_rate_hz),
              'telemetry_period_s': float(telemetry_period_s)}
    params.update(extra_parameters or {})
    with workdir() as directory, ServoRig(directory, ids, baud, params) as rig:
        rig.wait_ready()
        time.sleep(warmup_s)
        cpu = CpuMeter(rig.node.pid)
        t0 = time.monotonic()
        time.sleep(duration_s)
        t1 = time.monotonic()
        cpu_pct = cpu.percent()
        window = [t for t in rig.position_transactions(t0) if t[0] < t1]
        alive = rig.node.alive()
    if not window:
        raise RuntimeError(f'no position reads in the window ({n_servos} servos, {baud} baud)')
    nbytes = sum(len(req.raw) + len(rep.raw) for _, _, req, rep in window)
    elapsed = t1 - t0
    per_tx = nbytes / len(window)
    achieved = len(window) / n_servos / elapsed
    limit = baud / (10.0 * per_tx) / n_servos
    # Where the time between wire bytes goes: the emulated device (request fully arrived ->
    # last reply byte written, minus the reply's wire time) and the host (last reply byte
    # written -> next request read by the device, i.e. driver turnaround + pty wake-up).
    device = [t_rep - t_req - wire_time(len(rep.raw), baud) for t_req, t_rep, _, rep in window]
    host = [window[i + 1][0] - wire_time(len(window[i + 1][2].raw), baud) - window[i][1]
            for i in range(len(window) - 1)]
    busy = nbytes * 10.0 / baud
    return {
        'ratio': achieved / limit,
        'ratio_host_only': busy / max(1e-9, elapsed - sum(device)),
        'device_p50_ms': percentile(device, 50) * 1e3,
        'host_gap_p50_ms': percentile(host, 50) * 1e3,
        'host_gap_p99_ms': percentile(host, 99) * 1e3,
        'cycles_s': achieved,
        'limit_cycles_s': limit,
        'bytes_per_read': per_tx,
        'cpu_pct': cpu_pct,
        'alive': alive,
    }


if __name__ == '__main__':
    import sys
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 12
    baud = int(sys.argv[2]) if len(sys.argv) > 2 else 115200
    print(measure(n, baud))
