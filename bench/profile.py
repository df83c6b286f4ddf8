"""Where a driver's CPU goes under the CPU benchmark's load: py-spy's top functions by own time.

``python bench/profile.py [servo|parachute|handset ...] [--seconds N]`` starts each driver as
``bench/cpu.py`` does (servo: 12 servos at ``publish_rate_hz`` 50; parachute: status stream at
20 Hz; handset: 50 Hz with one ``~/setpoint`` subscriber), samples it with
``py-spy record --nonblocking --format raw`` (no pause of the process, so the profile does not
change what it measures) and prints the functions
with the most samples of their own, in % of all samples of threads that were not idle, and the
process's CPU over the same window. py-spy is not a dependency of the package: install it into
the environment first (``pip install py-spy``); the machine needs ptrace rights on the driver.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Tuple

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import (CpuMeter, HandsetRig, ParachuteRig, ros_client,  # noqa: E402
                          ServoRig, workdir)


def top_functions(raw: str, count: int) -> Tuple[int, List[Tuple[float, str]]]:
    """Return the samples and the `count` functions with the most own samples (% of all)."""
    own: Dict[str, int] = collections.Counter()
    total = 0
    for line in raw.splitlines():
        stack, _, n = line.rpartition(' ')
        if not stack or not n.isdigit():
            continue
        frames = stack.split(';')
        own[frames[-1]] += int(n)
        total += int(n)
    ranked = sorted(own.items(), key=lambda item: -item[1])[:count]
    return total, [(100.0 * n / max(total, 1), name) for name, n in ranked]


def _record(pid: int, seconds: float) -> str:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / 'profile.txt'
        subprocess.run([shutil.which('py-spy') or 'py-spy', 'record', '--nonblocking',
                        '--format', 'raw', '--rate', '200', '--duration', str(int(seconds)),
                        '--pid', str(pid), '--output', str(out)],
                       check=True, capture_output=True, timeout=seconds + 60)
        return out.read_text()


def profile(driver: str, seconds: float, count: int) -> None:
    """Profile one driver under load and print its top functions."""
    with workdir() as directory, contextlib.ExitStack() as stack:
        if driver == 'servo':
            rig = ServoRig(directory, list(range(1, 13)), 115200, {'publish_rate_hz': 50.0})
        elif driver == 'handset':
            from uav_serial_drivers.msg import HandsetSetpoint
            rig = HandsetRig(directory)
            client = stack.enter_context(ros_client('bench_profile_handset'))
            client.subscribe(HandsetSetpoint, '/handset_link/setpoint', lambda _m: None)
        else:
            rig = ParachuteRig(directory, stream_period_s=0.05)
        with rig:
            rig.wait_ready()
            time.sleep(2.0)
            meter = CpuMeter(rig.node.pid)
            raw = _record(rig.node.pid, seconds)
            cpu = meter.percent()
    total, top = top_functions(raw, count)
    print(f'{driver}: {cpu:.2f} % of a core; {total} samples of busy threads')
    for share, name in top:
        print(f'  {share:5.1f} %  {name}')


def main(argv: List[str] = None) -> int:
    """Profile the drivers named on the command line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('drivers', nargs='*', default=['servo', 'parachute'],
                        choices=['servo', 'parachute', 'handset'])
    parser.add_argument('--seconds', type=float, default=20.0)
    parser.add_argument('--top', type=int, default=8)
    a = parser.parse_args(argv)
    for driver in a.drivers:
        profile(driver, a.seconds, a.top)
    return 0


if __name__ == '__main__':
    sys.exit(main())
