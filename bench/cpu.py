"""CPU of each driver process at its nominal load, in percent of one core.

- ``cpu_servo_pct``: ``servo_bus_node`` with 12 servos at ``publish_rate_hz`` 50 (default
  telemetry period 1 s) on a virtual bus at 115200 baud.
- ``cpu_parachute_pct``: ``parachute_node`` with the module's status stream at 20 Hz.
- ``cpu_handset_pct``: ``handset_link_node`` with the handset at 50 Hz (four stick frames per
  tick, JSON, auxiliary once a second), 200 ``~/setpoint`` messages/s with one subscriber.
- ``cpu_originman_pct``: ``originman_board_node`` with the board's IMU at 100 Hz and 3 bus servos
  polled at 10 Hz (default telemetry period 2 s), 1 Mbaud.

CPU = (utime + stime of every thread, from ``/proc/<pid>/stat``) / wall time of the window,
after a warm-up. The virtual devices run in this process, so they are not counted.
"""

from __future__ import annotations

import time
from typing import Dict

from bench.common import CpuMeter, OriginManRig, ParachuteRig, ServoRig, workdir


def servo_cpu(duration_s: float = 10.0, warmup_s: float = 2.0, n_servos: int = 12,
              rate_hz: float = 50.0) -> Dict[str, float]:
    """Return the servo driver's CPU percent and the position-read rate it achieved."""
    ids = list(range(1, n_servos + 1))
    with workdir() as directory, \
            ServoRig(directory, ids, 115200, {'publish_rate_hz': rate_hz}) as rig:
        rig.wait_ready()
        time.sleep(warmup_s)
        meter = CpuMeter(rig.node.pid)
        t0 = time.monotonic()
        time.sleep(duration_s)
        pct = meter.percent()
        reads = len(rig.position_transactions(t0))
        elapsed = time.monotonic() - t0
    return {'cpu_pct': pct, 'cycles_s': reads / n_servos / elapsed}


def parachute_cpu(duration_s: float = 10.0, warmup_s: float = 2.0,
                  stream_hz: float = 20.0) -> Dict[str, float]:
    """Return the parachute driver's CPU percent with the status stream at `stream_hz`."""
    with workdir() as directory, \
            ParachuteRig(directory, stream_period_s=1.0 / stream_hz) as rig:
        rig.wait_ready()
        time.sleep(warmup_s)
        meter = CpuMeter(rig.node.pid)
        time.sleep(duration_s)
        pct = meter.percent()
    return {'cpu_pct': pct}


def handset_cpu(duration_s: float = 10.0, warmup_s: float = 2.0) -> Dict[str, float]:
    """Return the handset driver's CPU percent at 50 Hz, and the setpoints/s it published."""
    from bench.common import HandsetRig, ros_client
    from uav_serial_drivers.msg import HandsetSetpoint
    count = [0]
    with workdir() as directory, HandsetRig(directory) as rig, \
            ros_client('bench_cpu_handset') as client:
        client.subscribe(HandsetSetpoint, '/handset_link/setpoint',
                         lambda m: count.__setitem__(0, count[0] + 1))
        rig.wait_ready()
        time.sleep(warmup_s)
        meter = CpuMeter(rig.node.pid)
        start, t0 = count[0], time.monotonic()
        time.sleep(duration_s)
        pct = meter.percent()
        rate = (count[0] - start) / (time.monotonic() - t0)
    return {'cpu_pct': pct, 'setpoints_s': rate}


def originman_cpu(duration_s: float = 10.0, warmup_s: float = 2.0,
                  imu_rate_hz: float = 100.0, poll_hz: float = 10.0) -> Dict[str, float]:
    """Return the OriginMan driver's CPU percent: IMU at `imu_rate_hz`, 3 servos at `poll_hz`."""
    with workdir() as directory, \
            OriginManRig(directory, {'bus_servo_poll_hz': poll_hz},
                         imu_rate_hz=imu_rate_hz) as rig:
        rig.wait_ready()
        time.sleep(warmup_s)
        meter = CpuMeter(rig.node.pid)
        t0 = time.monotonic()
        imu0 = rig.tap.imu_count
        time.sleep(duration_s)
        pct = meter.percent()
        elapsed = time.monotonic() - t0
        reads = len(rig.tap.bus_replies(t0))
        imu = rig.tap.imu_count - imu0
    return {'cpu_pct': pct, 'imu_hz': imu / elapsed, 'servo_reads_s': reads / elapsed}


def run(duration_s: float = 10.0) -> Dict[str, float]:
    """Measure the drivers one after the other; return the ``cpu_*`` figures."""
    servo = servo_cpu(duration_s)
    parachute = parachute_cpu(duration_s)
    handset = handset_cpu(duration_s)
    board = originman_cpu(duration_s)
    return {'cpu_servo_pct': servo['cpu_pct'], 'cpu_servo_cycles_s': servo['cycles_s'],
            'cpu_parachute_pct': parachute['cpu_pct'], 'cpu_handset_pct': handset['cpu_pct'],
            'cpu_handset_setpoints_s': handset['setpoints_s'],
            'cpu_originman_pct': board['cpu_pct'], 'cpu_originman_imu_hz': board['imu_hz'],
            'cpu_originman_servo_reads_s': board['servo_reads_s']}


if __name__ == '__main__':
    import sys
    print(run(float(sys.argv[1]) if len(sys.argv) > 1 else 10.0))
