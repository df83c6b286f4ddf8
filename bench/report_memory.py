"""blackbox_report on a 500 MB black box: peak memory (RSS) and time.

``write_synthetic_blackbox`` writes a black box as the parachute driver does (the same record
kinds and fields, frames built with the protocol's encoders): a 20 Hz status stream with tilt
and acceleration moving, the driver's 1 s polls, and every few minutes of flight a trigger
request and its deployment, a deploy call, lost replies, a reboot, a reconnect, the link's
counters after checksum errors, records of a kind the report does not know. 500 MB is about 30
hours of such a flight. ``report_peak_rss`` runs ``build_report`` in a child process and reads
its peak RSS (``getrusage``), so the figure is the report's alone. Figures:
``report_500mb_peak_mb``, ``report_500mb_s``.

Standalone: ``python bench/report_memory.py [--mb 500]``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path
import random
import subprocess
import sys
import tempfile
import time
from typing import Any, Dict

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from dps_parachute_ros import protocol as p  # noqa: E402

_HEX = {}


def _hex(frame: bytes) -> str:
    text = _HEX.get(frame)
    if text is None:
        text = _HEX[frame] = frame.hex(' ')
    return text


def write_synthetic_blackbox(path: str, size_bytes: int, seed: int = 1) -> Dict[str, int]:
    """Write a black box of about ``size_bytes``; return how many of each event it holds."""
    rng = random.Random(seed)
    wall0, mono0 = 1_790_000_000.0, 1000.0
    t = 0.0
    made = {'deployments': 0, 'lost': 0, 'reboots': 0, 'reconnects': 0, 'unknown': 0,
            'checksum_errors': 0}
    poll = [(p.encode_light_level_query(), 'LightLevel', p.module_frame(p.CMD_LIGHT_LEVEL, 2)),
            (p.encode_charging_query(), 'Charging', p.module_frame(p.CMD_CHARGING, 1)),
            (p.encode_cell_voltage_query(), 'CellVoltage', p.module_frame(0x35, 210))]
    boot = 1
    lines = []
    written = 0

    def rec(kind: str, body: str) -> None:
        nonlocal written
        line = f'{{{body}"t":{wall0 + t:.6f},"mono":{mono0 + t:.9f},"kind":"{kind}"}}\n'
        lines.append(line)
        written += len(line)

    def frame(direction: str, data: bytes) -> None:
        rec('frame', f'"dir":"{direction}","hex":"{_hex(data)}",')

    def request(data: bytes, expect: str) -> None:
        rec('request', f'"hex":"{_hex(data)}","expect":"{expect}",')
        frame('tx', data)

    with open(path, 'w', encoding='utf-8', buffering=1 << 20) as out:
        rec('start', '"port":"/dev/parachute","baud":115200,"config":{"trigger_request_'
            'policy":"confirm","attitude_threshold_deg":70,"request_timeout_s":1.0},')
        rec('state', '"port_open":true,"reason":"port open",')
        rec('state', '"online":true,"reason":"",')
        for query, expect, reply in (
                (p.encode_boot_count_query(), 'BootCount', p.module_frame(p.CMD_BOOT_COUNT, boot)),
                (p.encode_streaming(True), 'StreamingReply', p.module_frame(p.CMD_STREAMING, 1)),
                (p.encode_attitude_threshold_query(), 'AttitudeThreshold',
                 p.module_frame(p.CMD_ATTITUDE_THRESHOLD, 70)),
                (p.encode_freefall_threshold_query(), 'FreefallThreshold',
                 p.module_frame(p.CMD_FREEFALL_THRESHOLD, 5))):
            request(query, expect)
            frame('rx', reply)
        armed = True
        n = 0
        while written < size_bytes:
            n += 1
            t += 0.05
            tilt = int(abs(20 * math.sin(t / 7.0)) + rng.random() * 3)
            accel = 10 + rng.randint(-1, 1)
            frame('rx', p.encode_status_frame(tilt, accel, False, armed))
            if n % 20 == 0:
                for query, expect, reply in poll:
                    request(query, expect)
                    if n % 740 == 0 and expect == 'Charging' and \
                            n % 12000 not in (0, 100, 6000, 6100) and n % 30000 != 15000:
                        made['lost'] += 1  # no reply (and no reboot right after): lost
                    else:
                        frame('rx', reply)
            if n % 12000 == 0:  # every 10 min of flight: a trigger request and its deployment
                frame('rx', p.encode_trigger_request())
                frame('tx', p.encode_trigger_confirm())
                rec('decision', '"what":"trigger request","decision":"confirmed","policy":'
                    '"confirm","reason":"policy confirm: confirmed at once","latency_ms":0.05,')
                t += 0.05
                frame('rx', p.encode_status_frame(tilt, 0, True, False))
                rec('state', '"triggered":true,"via":"status",')
                rec('trigger_event', '"source":"freefall","via":"status","record":null,')
                made['deployments'] += 1
            if n % 12000 == 6000:  # a deploy call, acknowledged
                rec('request', '"what":"deploy","token_ok":true,"arm_if_locked":true,')
                rec('decision', '"what":"deploy: sending the deploy frame","attempt":1,')
                request(p.encode_deploy(), 'DeployAck')
                t += 0.002
                frame('rx', p.module_frame(p.CMD_DEPLOY, 1))
                rec('decision', '"what":"deploy acknowledged","hex":"41 75 11 01 01 13",'
                    '"latency_ms":2.1,"attempts":1,')
                rec('decision', '"what":"deploy","outcome":"deployed","success":true,"reason":'
                    '"deployed: acknowledged after 1 attempt(s), 2.1 ms",')
                made['deployments'] += 1
            if n % 12000 == 3000:  # a reply with a bad checksum: the link's counters (D10)
                made['checksum_errors'] += 1
                rec('link', f'"frames_in":{n},"frames_out":{n // 7},"checksum_errors":'
                    f'{made["checksum_errors"]},"bytes_discarded":0,"timeouts":{made["lost"]},'
                    '"reconnects":0,')
            if n % 12000 in (100, 6100):  # the module reboots (two heartbeats, P5)
                boot = (boot + 1) & 0xFF
                frame('rx', p.encode_module_heartbeat())
                rec('state', '"event":"module reboot (unsolicited heartbeat)",')
                request(p.encode_boot_count_query(), 'BootCount')
                frame('rx', p.module_frame(p.CMD_BOOT_COUNT, boot))
                request(p.encode_streaming(True), 'StreamingReply')
                frame('rx', p.module_frame(p.CMD_STREAMING, 1))
                made['reboots'] += 1
            if n % 30000 == 15000:  # the cable pulled for 2 s
                rec('state', '"port_open":false,"reason":"device disconnected",')
                rec('state', '"online":false,"reason":"port closed",')
                t += 2.0
                rec('state', '"port_open":true,"reason":"port open",')
                rec('state', '"online":true,"reason":"",')
                made['reconnects'] += 1
            if n % 50000 == 25000:
                rec('health_v2', '"cpu":0.3,')
                made['unknown'] += 1
            if len(lines) > 2000:
                out.write(''.join(lines))
                lines.clear()
        t += 2.0  # the driver stops later than any reply could come
        rec('stop', '')
        out.write(''.join(lines))
    return made


# The child's peak is its own high-water mark (VmHWM of its memory after exec): ru_maxrss keeps
# the maximum across exec, so a child forked from a large benchmark process would report the
# parent's size.
_CHILD = """
import json, sys, time
def hwm_mb():
    with open('/proc/self/status') as status:
        for line in status:
            if line.startswith('VmHWM:'):
                return int(line.split()[1]) / 1024
t0 = time.monotonic()
from parachute_blackbox.report import build_report
s = build_report([sys.argv[1]], sys.argv[2], progress=sys.argv[3] == '1')
print(json.dumps({'seconds': time.monotonic() - t0,
                  'peak_mb': hwm_mb(),
                  'counts': s.counts, 'deployments_listed': len(s.deployments),
                  'unknown_kinds': s.unknown_kinds}))
"""


def report_peak_rss(path: str, output_html: str, progress: bool = False) -> Dict[str, Any]:
    """Run ``build_report`` in a child process; return its time, peak RSS (MB) and counts."""
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([str(ROOT)] + [x for x in sys.path if x])
    result = subprocess.run([sys.executable, '-c', _CHILD, path, output_html,
                             '1' if progress else '0'],
                            stdout=subprocess.PIPE, stderr=None if progress else subprocess.PIPE,
                            text=True, timeout=3600, env=env, check=False)
    if result.returncode != 0:
        raise RuntimeError(f'blackbox report failed: {result.stderr}')
    return json.loads(result.stdout.strip().splitlines()[-1])


def run(size_mb: int = 500, progress: bool = False) -> Dict[str, Any]:
    """Generate a black box of ``size_mb`` MB and report it; return the figures."""
    with tempfile.TemporaryDirectory(prefix='report-memory-') as tmp:
        path = os.path.join(tmp, 'parachute-synthetic.jsonl')
        t0 = time.monotonic()
        made = write_synthetic_blackbox(path, size_mb * 1_000_000)
        generate_s = time.monotonic() - t0
        size = os.path.getsize(path)
        r = report_peak_rss(path, os.path.join(tmp, 'report.html'), progress)
        html_bytes = os.path.getsize(os.path.join(tmp, 'report.html'))
    return {
        f'report_{size_mb}mb_peak_mb': r['peak_mb'],
        f'report_{size_mb}mb_s': r['seconds'],
        'report_mb_s': size / 1e6 / r['seconds'],
        'report_file_mb': size / 1e6,
        'report_generate_s': generate_s,
        'report_html_kb': html_bytes / 1000,
        'report_counts': r['counts'],
        'report_made': made,
        'report_deployments_listed': r['deployments_listed'],
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--mb', type=int, default=500, help='size of the black box in MB')
    parser.add_argument('--progress', action='store_true', help='show the report progress bar')
    a = parser.parse_args(argv)
    r = run(a.mb, a.progress)
    c = r['report_counts']
    print(f'{r["report_file_mb"]:.0f} MB black box written in {r["report_generate_s"]:.0f} s '
          f'({r["report_made"]}); report in {r[f"report_{a.mb}mb_s"]:.1f} s '
          f'({r["report_mb_s"]:.1f} MB/s), peak RSS {r[f"report_{a.mb}mb_peak_mb"]:.0f} MB, '
          f'HTML {r["report_html_kb"]:.0f} kB; counted {c.get("records")} records, '
          f'{c.get("deployments")} deployments ({r["report_deployments_listed"]} described), '
          f'{c.get("unanswered requests")} lost frames, {c.get("reboots")} reboots')
    print(f'bench: report_{a.mb}mb_peak_mb={r[f"report_{a.mb}mb_peak_mb"]:.1f} '
          f'report_{a.mb}mb_s={r[f"report_{a.mb}mb_s"]:.1f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
