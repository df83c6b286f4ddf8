"""Unplug/replug cycles of each virtual device under its running driver.

Each cycle pulls the cable (``VirtualDeviceRunner.unplug``: the pty closes and its path
vanishes, as a USB adapter does), waits ``unplug_s``, plugs it back at the same path and times
the recovery on the device's side of the wire: from the replug to the first complete
transaction of the driver on the new port (servo: a position READ answered; parachute: a host
frame answered by the module; handset, whose driver never writes: the first ``~/setpoint`` this
process receives after the replug; OriginMan board: a bus servo read answered). The driver's
open file descriptors, pty descriptors and threads are sampled after every cycle; a leak is
growth in the second half of the cycles beyond the high-water mark of the first half (pools that
start threads lazily are not leaks); ``crashes`` counts driver processes that died.
"""

from __future__ import annotations

import time
from typing import Dict, List

from bench.common import (fd_count, median, OriginManRig, ParachuteRig, pty_fds, ServoRig,
                          thread_count, wait_for, workdir)


def _resources(pid: int) -> Dict[str, int]:
    return {'fds': fd_count(pid), 'pty_fds': pty_fds(pid), 'threads': thread_count(pid)}


def _settled(pid: int, baseline: Dict[str, int], timeout: float = 3.0) -> Dict[str, int]:
    """Give transient descriptors/threads up to `timeout` s to go; return the final counts."""
    deadline = time.monotonic() + timeout
    while True:
        now = _resources(pid)
        if all(now[k] <= baseline[k] for k in now) or time.monotonic() > deadline:
            return now
        time.sleep(0.1)


def _servo_recovered(rig: ServoRig, since: float) -> float:
    for t_req, t_rep, _, _ in rig.position_transactions(since):
        return t_rep
    return 0.0


def _parachute_recovered(rig: ParachuteRig, since: float) -> float:
    tap = rig.tap
    with tap._cond:
        first_rx = next((t for t, _ in tap.rx if t >= since), None)
        if first_rx is None:
            return 0.0
        return next((t for t, f in tap.tx if t >= first_rx and f.from_module), 0.0)


def _originman_recovered(rig: OriginManRig, since: float) -> float:
    replies = rig.tap.bus_replies(since)
    return replies[0][0] if replies else 0.0


def _cycles(rig, recovered, cycles: int, unplug_s: float, timeout_s: float) -> Dict:
    pid = rig.node.pid
    times: List[float] = []
    failures = 0
    series: List[Dict[str, int]] = []
    details: List[str] = []
    for _ in range(cycles):
        rig.runner.unplug()
        time.sleep(unplug_s)
        t_plug = time.monotonic()
        rig.runner.replug()
        try:
            t_ok = wait_for(lambda: recovered(rig, t_plug), timeout_s, interval=0.005,
                            what='recovery')
            times.append(t_ok - t_plug)
        except TimeoutError:
            failures += 1
            details.append(f'cycle {len(times) + failures}: not recovered after {timeout_s} s; '
                           f'driver log tail:\n{rig.node.output()[-1500:]}')
        if not rig.node.alive():
            break
        # After the first cycle, give once-per-second timers time to run their first
        # reconnect-related callbacks (which may start a pool thread) before sampling.
        time.sleep(1.5 if not series else 0.1)
        series.append(_resources(pid))
    alive = rig.node.alive()
    leaks = {'fds': 0, 'pty_fds': 0, 'threads': 0}
    if alive and series:
        # Executors and pools start some threads lazily, on the first burst of concurrent
        # callbacks: the reference is the high-water mark of the first half of the cycles, and
        # a leak is what the second half adds beyond it (a per-cycle leak adds every cycle).
        first = series[:max(1, len(series) // 2)]
        reference = {k: max(r[k] for r in first) for k in leaks}
        final = _settled(pid, reference)
        leaks = {k: final[k] - reference[k] for k in leaks}
    return {
        'cycles': len(times) + failures,
        'crashes': 0 if alive else 1,
        'not_recovered': failures,
        'details': details,
        'median_s': median(times),
        'max_s': max(times) if times else float('nan'),
        'fd_leak': leaks['fds'],
        'pty_fd_leak': leaks['pty_fds'],
        'thread_leak': leaks['threads'],
        'threads': (min(r['threads'] for r in series), max(r['threads'] for r in series))
        if series else (0, 0),
        'fds': (min(r['fds'] for r in series), max(r['fds'] for r in series))
        if series else (0, 0),
    }


def servo(cycles: int = 100, unplug_s: float = 0.3, timeout_s: float = 10.0) -> Dict:
    """Unplug/replug the servo bus `cycles` times under ``servo_bus_node``."""
    with workdir() as directory, ServoRig(directory, [1, 2, 3], 115200) as rig:
        rig.wait_ready()
        return _cycles(rig, _servo_recovered, cycles, unplug_s, timeout_s)


def parachute(cycles: int = 100, unplug_s: float = 0.3, timeout_s: float = 10.0) -> Dict:
    """Unplug/replug the parachute module `cycles` times under ``parachute_node``."""
    with workdir() as directory, ParachuteRig(directory) as rig:
        rig.wait_ready()
        return _cycles(rig, _parachute_recovered, cycles, unplug_s, timeout_s)


def handset(cycles: int = 100, unplug_s: float = 0.3, timeout_s: float = 10.0) -> Dict:
    """Unplug/replug the handset's modem `cycles` times under ``handset_link_node``."""
    from bench.common import HandsetRig, ros_client
    from uav_serial_drivers.msg import HandsetSetpoint
    received: List[float] = []

    def recovered(rig: HandsetRig, since: float) -> float:
        return next((t for t in received[-400:] if t >= since), 0.0)
    with workdir() as directory, HandsetRig(directory) as rig, \
            ros_client('bench_reconnects_handset') as client:
        client.subscribe(HandsetSetpoint, '/handset_link/setpoint',
                         lambda m: received.append(time.monotonic()))
        rig.wait_ready()
        wait_for(lambda: received, 20, what='the first setpoint')
        return _cycles(rig, recovered, cycles, unplug_s, timeout_s)


def originman(cycles: int = 100, unplug_s: float = 0.3, timeout_s: float = 10.0) -> Dict:
    """Unplug/replug the OriginMan board `cycles` times under ``originman_board_node``."""
    with workdir() as directory, OriginManRig(directory) as rig:
        rig.wait_ready()
        return _cycles(rig, _originman_recovered, cycles, unplug_s, timeout_s)


def run(cycles: int = 100) -> Dict:
    """Every device; return per-device results and the summary figures."""
    results = {'servo': servo(cycles), 'parachute': parachute(cycles),
               'handset': handset(cycles), 'originman': originman(cycles)}
    return {
        'per_device': results,
        'reconnect_cycles': min(r['cycles'] for r in results.values()),
        'reconnect_crashes': sum(r['crashes'] for r in results.values()),
        'reconnect_not_recovered': sum(r['not_recovered'] for r in results.values()),
        'reconnect_median_s': max(r['median_s'] for r in results.values()),
        'reconnect_max_s': max(r['max_s'] for r in results.values()),
        'reconnect_fd_leak': sum(max(0, r['fd_leak']) for r in results.values()),
        'reconnect_thread_leak': sum(max(0, r['thread_leak']) for r in results.values()),
    }


if __name__ == '__main__':
    import sys
    print(run(int(sys.argv[1]) if len(sys.argv) > 1 else 10))
