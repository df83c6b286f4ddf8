"""Run every benchmark and the fault campaign; print a table and one ``bench:`` line.

``make bench`` runs this with the defaults (5 min soak). ``--quick`` shrinks every figure to
seconds (for development; its numbers are not the reported ones), ``--soak-s`` sets the soak
length (the documented long run is ``--soak-s 3600``), ``--only`` picks benchmark families.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import traceback
from pathlib import Path
from typing import Callable, Dict, List, Tuple

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import (bad_inputs, blackbox_kill9, cpu, decoders, fuzz, latency,  # noqa: E402
                   mavlink_latency, models, originman_stop, reconnects, report_memory,
                   servo_latency, servo_rate, soak)
from bench.common import claim_domain_id  # noqa: E402

Row = Tuple[str, str, str, str]  # name, value, goal, verdict


def _fmt(value) -> str:
    if isinstance(value, float):
        if math.isnan(value):
            return 'nan'
        return f'{value:.3f}' if abs(value) < 10 else f'{value:.1f}'
    return str(value)


def _verdict(ok) -> str:
    return '' if ok is None else ('met' if ok else 'MISSED')


class Results:
    """Figures of one run: the table rows and the ``bench:`` line."""

    def __init__(self) -> None:
        self.rows: List[Row] = []
        self.figures: Dict[str, object] = {}
        self.notes: List[str] = []

    def add(self, name: str, value, goal: str = '', ok=None, line: bool = True) -> None:
        """Add one figure; `ok` None means no goal."""
        self.rows.append((name, _fmt(value), goal, _verdict(ok)))
        if line:
            self.figures[name] = _fmt(value)

    def note(self, text: str) -> None:
        """Add a line printed under the table."""
        self.notes.append(text)


def bench_decoders(res: Results, a: argparse.Namespace) -> None:
    r = decoders.run(n_frames=5000 if a.quick else 40000)
    for kind in ('dps', 'servo', 'originman', 'handset'):
        x = r[f'decoder_x_1mbit_{kind}']
        res.add(f'decoder_mb_s_{kind}', r[f'decoder_mb_s_{kind}'])
        res.add(f'decoder_x_1mbit_{kind}', x, '>= 10', x >= 10)


def bench_models(res: Results, a: argparse.Namespace) -> None:
    n = 500 if a.quick else 20000
    r = models.run(examples=n)
    for device in models.MODELS:
        count = r[f'model_sequences_{device}']
        res.add(f'model_sequences_{device}', count, f'>= {n}', count >= n)
        failure = r.get(f'model_failure_{device}')
        if failure:
            res.note(f'model {device}: a violation (or an error); the end of its run:\n{failure}')
    res.add('model_violations', r['model_violations'], '== 0', r['model_violations'] == 0)


def bench_fuzz(res: Results, a: argparse.Namespace) -> None:
    r = fuzz.run(segments=20000 if a.quick else 1_000_000)
    res.add('fuzz_frames', r['fuzz_frames'], '>= 10^6 per decoder',
            min(d['frames'] for d in r['per_decoder'].values()) >= 1_000_000)
    res.add('fuzz_exceptions', r['fuzz_exceptions'], '0', r['fuzz_exceptions'] == 0)
    res.add('fuzz_recovered_pct', r['fuzz_recovered_pct'], '100',
            r['fuzz_recovered_pct'] == 100.0)
    res.add('fuzz_overlapped', r['fuzz_overlapped'], line=False)
    for name, d in r['per_decoder'].items():
        res.note(f'fuzz {name}: {d["frames"]} frames, {d["valid"]} valid, {d["spurious"]} found '
                 f'in noise, {d["overlapped"]} overlapped by those, {d["recovered"]} recovered '
                 f'({d["recovered_pct"]:.3f} % of the rest), {d["exceptions"]} exceptions')


def bench_servo_rate(res: Results, a: argparse.Namespace) -> None:
    duration = 2.0 if a.quick else 5.0
    for baud in (115200, 1000000):
        suffix = '' if baud == 115200 else '_1m'
        for n in (1, 6, 12):
            r = servo_rate.measure(n, baud, duration)
            ok = r['ratio'] >= 0.90 if baud == 115200 else None
            res.add(f'servo_read_ratio_{n}{suffix}', r['ratio'], '>= 0.90' if ok is not None
                    else '', ok)
            res.note(f'servo rate {n} servos @ {baud}: {r["cycles_s"]:.1f} full-bus reads/s of '
                     f'{r["limit_cycles_s"]:.1f} wire limit ({r["bytes_per_read"]:.0f} B per '
                     f'READ+reply); node CPU {r["cpu_pct"]:.0f} %; host turnaround p50 '
                     f'{r["host_gap_p50_ms"]:.3f} ms, device p50 {r["device_p50_ms"]:.3f} ms; '
                     f'ratio without the emulator\'s own time {r["ratio_host_only"]:.3f}')
            if not r['alive']:
                res.note(f'servo_bus_node DIED during the rate run ({n} servos, {baud})')


def bench_latency(res: Results, a: argparse.Namespace) -> None:
    n = 30 if a.quick else 200
    r = latency.run(confirm_count=n, deploy_count=n)
    res.add('confirm_p50_ms', r['confirm_p50_ms'])
    res.add('confirm_p99_ms', r['confirm_p99_ms'], '<= 20', r['confirm_p99_ms'] <= 20.0)
    res.add('confirm_n', r['confirm_n'], f'>= {n}, 0 missed',
            r['confirm_n'] >= n and r['confirm_missed'] == 0)
    res.add('deploy_p99_ms', r['deploy_p99_ms'], '<= 20', r['deploy_p99_ms'] <= 20.0)
    res.add('deploy_n', r['deploy_n'], f'{n}, 0 failed', r['deploy_failed'] == 0)
    res.note(f'confirm max {r["confirm_max_ms"]:.2f} ms; deploy p50 {r["deploy_p50_ms"]:.2f} '
             f'ms, max {r["deploy_max_ms"]:.2f} ms; deploy service round trip p99 '
             f'{r["deploy_service_p99_ms"]:.1f} ms (call -> response, includes the module ack)')
    h = latency.run_handset(duration_s=3.0 if a.quick else 20.0)
    res.add('handset_latency_p50_ms', h['handset_latency_p50_ms'])
    res.add('handset_latency_p99_ms', h['handset_latency_p99_ms'], '<= 5',
            h['handset_latency_p99_ms'] <= 5.0)
    res.add('handset_latency_n', h['handset_latency_n'], '0 missed',
            h['handset_latency_missed'] == 0 and h['alive'])
    res.note(f'handset latency max {h["handset_latency_max_ms"]:.2f} ms over '
             f'{h["handset_latency_n"]} stick frames, {h["handset_latency_missed"]} missed '
             f'(the document allows 20 ms)')


def bench_mavlink(res: Results, a: argparse.Namespace) -> None:
    n = 30 if a.quick else 200
    r = mavlink_latency.run(release_count=n, stop_count=n)
    res.add('mavlink_release_p99_ms', r['mavlink_release_p99_ms'], '<= 50',
            r['mavlink_release_p99_ms'] <= 50.0)
    res.add('mavlink_release_n', r['mavlink_release_n'], f'{n}, 0 failed',
            r['mavlink_release_failed'] == 0)
    res.add('mavlink_stop_release_p99_ms', r['mavlink_stop_release_p99_ms'], '<= 300',
            r['mavlink_stop_release_p99_ms'] <= 300.0)
    res.add('mavlink_stop_release_n', r['mavlink_stop_release_n'],
            f'{n}, 0 missed, stop first', r['mavlink_stop_release_missed'] == 0
            and r['mavlink_stop_release_late_stops'] == 0 and r['alive'])
    res.note(f'mavlink release (DO_PARACHUTE RELEASE -> deploy frame, no motor stop): p50 '
             f'{r["mavlink_release_p50_ms"]:.1f} ms, max {r["mavlink_release_max_ms"]:.1f} ms; '
             f'stop + release (trigger request -> disarm ACCEPTED -> confirmation): p50 '
             f'{r["mavlink_stop_release_p50_ms"]:.1f} ms, max '
             f'{r["mavlink_stop_release_max_ms"]:.1f} ms, '
             f'{r["mavlink_stop_release_late_stops"]} confirmations before their motor stop '
             f'(trials {r["mavlink_stop_release_late_trials"][:10]})')


def bench_imu_latency(res: Results, a: argparse.Namespace) -> None:
    r = latency.imu_run(duration_s=5.0 if a.quick else 30.0)
    res.add('imu_latency_p50_ms', r['imu_latency_p50_ms'])
    res.add('imu_latency_p99_ms', r['imu_latency_p99_ms'], '<= 5',
            r['imu_latency_p99_ms'] <= 5.0)
    res.add('imu_latency_n', r['imu_latency_n'], '0 missed', r['imu_latency_missed'] == 0)
    res.note(f'imu latency (100 Hz, servo_bus_node at full rate and parachute_node beside): '
             f'max {r["imu_latency_max_ms"]:.2f} ms; the driver\'s share (wire -> its publish, '
             f'by the header stamp) p50 {r["imu_latency_driver_p50_ms"]:.2f} ms, p99 '
             f'{r["imu_latency_driver_p99_ms"]:.2f} ms; {r["imu_latency_missed"]} missed'
             + ('' if r['alive'] else '; A DRIVER DIED'))


def bench_servo_latency(res: Results, a: argparse.Namespace) -> None:
    n = 50 if a.quick else 200
    r = servo_latency.run(count=n, age_window_s=3.0 if a.quick else 10.0,
                          scans=1 if a.quick else 3)
    res.add('scan_s', r['scan_s'], '<= 1.5, all found', r['scan_s'] <= 1.5 and r['scan_found_all'])
    res.add('scan_startup_s', r['scan_startup_s'], '<= 1.5', r['scan_startup_s'] <= 1.5)
    res.add('scan_slow_s', r['scan_slow_s'], 'all found', r['scan_slow_found'])
    res.add('command_p99_ms', r['command_p99_ms'], '<= 3, 0 missed',
            r['command_p99_ms'] <= 3.0 and r['command_missed'] == 0)
    res.add('write_positions_p99_ms', r['write_positions_p99_ms'], '<= 3, 0 missed',
            r['write_positions_p99_ms'] <= 3.0 and r['write_positions_missed'] == 0)
    cycle = r['read_cycle_ms']
    res.add('joint_states_age_p99_ms', r['joint_states_age_p99_ms'],
            f'<= cycle + 2 = {cycle + 2:.1f}',
            r['joint_states_age_p99_ms'] <= cycle + 2.0 and r['joint_states_unmatched'] == 0)
    res.note(f'servo latency: command p50 {r["command_p50_ms"]:.2f} ms, max '
             f'{r["command_max_ms"]:.2f} ms over {r["command_n"]} ({r["command_missed"]} not seen '
             f'on the wire); write_positions p50 {r["write_positions_p50_ms"]:.2f} ms, max '
             f'{r["write_positions_max_ms"]:.2f} ms, call round trip p99 '
             f'{r["write_positions_round_trip_p99_ms"]:.1f} ms; joint_states age p50 '
             f'{r["joint_states_age_p50_ms"]:.2f} ms over {r["joint_states_age_n"]} messages '
             f'(read cycle {cycle:.1f} ms), stamp - oldest reply p50 '
             f'{r["joint_states_stamp_offset_p50_ms"]:.2f} ms, max '
             f'{r["joint_states_stamp_offset_max_ms"]:.2f} ms; a bus of 3 servos answering '
             f'25 ms late scanned in {r["scan_slow_s"]:.2f} s'
             + ('' if r['alive'] else '; servo_bus_node DIED'))


def bench_originman_stop(res: Results, a: argparse.Namespace) -> None:
    r = originman_stop.run(stops=15 if a.quick else 40, watchdog_stops=8 if a.quick else 20)
    for name in ('originman_stop', 'originman_watchdog_stop', 'originman_stop_write',
                 'originman_watchdog_stop_write'):
        for stat in ('p50_ms', 'p99_ms', 'max_ms', 'n'):
            res.add(f'{name}_{stat}', r[f'{name}_{stat}'])
    res.add('originman_stop_frames_ahead_max', r['originman_stop_frames_ahead_max'])
    res.add('originman_stop_writes_ahead_max', r['originman_stop_writes_ahead_max'])
    res.note(f'originman stop (stop_all_motors() -> the stop at the board, bus servo and LED/PWM '
             f'floods from two threads): call returned p50 '
             f'{r["originman_stop_return_p50_ms"]:.2f} ms, p99 '
             f'{r["originman_stop_return_p99_ms"]:.2f} ms, max '
             f'{r["originman_stop_return_max_ms"]:.2f} ms; at most '
             f'{r["originman_stop_frames_ahead_max"]} frames reached the board between the call '
             'and its stop (the one being written, and one on its way)')


def bench_cpu(res: Results, a: argparse.Namespace) -> None:
    r = cpu.run(duration_s=5.0 if a.quick else 20.0)
    res.add('cpu_servo_pct', r['cpu_servo_pct'], '<= 4.0', r['cpu_servo_pct'] <= 4.0)
    res.add('cpu_parachute_pct', r['cpu_parachute_pct'], '<= 2.0',
            r['cpu_parachute_pct'] <= 2.0)
    res.add('cpu_handset_pct', r['cpu_handset_pct'], '<= 3', r['cpu_handset_pct'] <= 3.0)
    res.add('cpu_originman_pct', r['cpu_originman_pct'], '<= 5',
            r['cpu_originman_pct'] <= 5.0)
    res.note(f'cpu_handset: {r["cpu_handset_setpoints_s"]:.0f} setpoints/s published (50 Hz '
             'x 4 stick frames, JSON)')
    res.note(f'cpu_originman: IMU at {r["cpu_originman_imu_hz"]:.1f} Hz, '
             f'{r["cpu_originman_servo_reads_s"]:.1f} bus servo reads/s (3 servos at 10 Hz, '
             'telemetry every 2 s)')
    res.note(f'cpu_servo: 12 servos asked for 50 Hz, got {r["cpu_servo_cycles_s"]:.1f} full-bus '
             'reads/s (115200 baud cannot carry 50 Hz x 12 position reads plus telemetry)')


def bench_reconnects(res: Results, a: argparse.Namespace) -> None:
    r = reconnects.run(cycles=5 if a.quick else 100)
    res.add('reconnects', r['reconnect_cycles'], '>= 100 per device',
            r['reconnect_cycles'] >= 100)
    res.add('reconnect_crashes', r['reconnect_crashes'], '0', r['reconnect_crashes'] == 0)
    res.add('reconnect_not_recovered', r['reconnect_not_recovered'], '0',
            r['reconnect_not_recovered'] == 0)
    res.add('reconnect_median_s', r['reconnect_median_s'])
    res.add('reconnect_max_s', r['reconnect_max_s'], '<= 2', r['reconnect_max_s'] <= 2.0)
    res.add('reconnect_fd_leak', r['reconnect_fd_leak'], '0', r['reconnect_fd_leak'] == 0)
    res.add('reconnect_thread_leak', r['reconnect_thread_leak'], '0',
            r['reconnect_thread_leak'] == 0)
    for name, d in r['per_device'].items():
        res.note(f'reconnects {name}: {d["cycles"]} cycles, median {d["median_s"]:.3f} s, max '
                 f'{d["max_s"]:.3f} s, fd {d["fd_leak"]:+d} (pty {d["pty_fd_leak"]:+d}), '
                 f'threads {d["thread_leak"]:+d}, {d["not_recovered"]} not recovered')
        for text in d['details'][:2]:
            res.note(f'reconnects {name}: {text}')


def bench_soak(res: Results, a: argparse.Namespace) -> None:
    r = soak.run(duration_s=a.soak_s)
    res.add('soak_s', r['soak_s'])
    res.add('soak_crashes', r['soak_crashes'], '0', r['soak_crashes'] == 0)
    for name in ('servo', 'parachute', 'handset', 'originman'):
        v = r[f'soak_rss_growth_mb_{name}']
        res.add(f'soak_rss_growth_mb_{name}', v, '< 5', v < 5.0)
    topics = ('joint_states', 'status', 'setpoint', 'imu')
    for name in topics:
        v = r[f'soak_max_gap_s_{name}']
        res.add(f'soak_max_gap_s_{name}', v, '<= 1', v <= 1.0)
    res.note('soak: gaps as received here '
             + ' / '.join(f'{r[f"soak_rx_gap_s_{name}"]:.2f} s' for name in topics) + '; '
             + ', '.join(f'{r[f"soak_{name}_msgs"]} {name}' for name in topics)
             + ' messages; replies (handset: frames; OriginMan board: every frame it sends) '
             f'dropped/corrupted by the wire: {r["soak_faults"]}')
    res.note('soak stalls (value s, at s into the window): ' + ', '.join(
        f'{k} {v}' for k, v in r['soak_stalls'].items()))
    for name, lines in r['soak_driver_log'].items():
        res.note(f'soak {name} driver log: {len(lines)} lines about lost replies/offline'
                 + ''.join(f'\n    {line}' for line in lines[:8]))


def bench_kill9(res: Results, a: argparse.Namespace) -> None:
    rounds = 3 if a.quick else 20
    r = blackbox_kill9.run(rounds=rounds, wire_rounds=2 if a.quick else 10)
    res.add('blackbox_kill9', f'{r["kill9_record_on_disk"]}/{r["kill9_rounds"]}',
            'all on disk', r['kill9_record_on_disk'] == r['kill9_rounds'])
    res.add('blackbox_kill9_wire', f'{r["kill9_wire_request_on_disk"]}/{r["kill9_wire_rounds"]}',
            '(info)')
    for error in r['errors'][:5]:
        res.note(f'kill9: {error}')


def bench_bad_inputs(res: Results, a: argparse.Namespace) -> None:
    r = bad_inputs.run()
    res.add('bad_inputs', f'{r["bad_inputs_refused"]}/{r["bad_inputs_cases"]}', 'all refused',
            r['bad_inputs_refused'] == r['bad_inputs_cases'] and not r['bad_inputs_errors'])
    res.add('bad_inputs_bytes_on_wire', r['bad_inputs_bytes_on_wire'], '0',
            r['bad_inputs_bytes_on_wire'] == 0)
    h = r['per_driver']['handset']
    res.add('bad_inputs_handset', f'{h["refused"]}/{h["cases"]}', 'all refused',
            h['refused'] == h['cases'] and not h['errors'] and not h['bytes_on_wire'])
    for name, d in r['per_driver'].items():
        for text in d['accepted'] + d['bytes_on_wire'] + d['errors']:
            res.note(f'bad_inputs {name}: {text}')


def bench_report(res: Results, a: argparse.Namespace) -> None:
    mb = 50 if a.quick else 500
    r = report_memory.run(size_mb=mb)
    peak, seconds = r[f'report_{mb}mb_peak_mb'], r[f'report_{mb}mb_s']
    res.add(f'report_{mb}mb_peak_mb', peak, '<= 256', peak <= 256)
    res.add(f'report_{mb}mb_s', seconds)
    c = r['report_counts']
    res.note(f'report: {r["report_file_mb"]:.0f} MB black box ({c.get("records")} records, '
             f'{c.get("deployments")} deployments, {c.get("unanswered requests")} lost frames, '
             f'{c.get("reboots")} reboots) reported at {r["report_mb_s"]:.1f} MB/s; HTML '
             f'{r["report_html_kb"]:.0f} kB')


FAMILIES: Dict[str, Callable[[Results, argparse.Namespace], None]] = {
    'decoders': bench_decoders,
    'fuzz': bench_fuzz,
    'models': bench_models,
    'servo_rate': bench_servo_rate,
    'latency': bench_latency,
    'imu_latency': bench_imu_latency,
    'mavlink': bench_mavlink,
    'servo_latency': bench_servo_latency,
    'originman_stop': bench_originman_stop,
    'cpu': bench_cpu,
    'reconnects': bench_reconnects,
    'soak': bench_soak,
    'kill9': bench_kill9,
    'bad_inputs': bench_bad_inputs,
    'report': bench_report,
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--quick', action='store_true', help='seconds, not minutes')
    parser.add_argument('--soak-s', type=float, default=None,
                        help='soak duration in s (default 300, --quick 20)')
    parser.add_argument('--only', default='', help='comma-separated families: '
                        + ','.join(FAMILIES))
    a = parser.parse_args(argv)
    if a.soak_s is None:
        a.soak_s = 20.0 if a.quick else 300.0
    chosen = [f for f in a.only.split(',') if f] or list(FAMILIES)
    unknown = [f for f in chosen if f not in FAMILIES]
    if unknown:
        parser.error(f'unknown families {unknown}; choose from {list(FAMILIES)}')
    print(f'bench: ROS_DOMAIN_ID={claim_domain_id()}, {os.cpu_count()} cores, '
          f'{"quick" if a.quick else "full"} run', flush=True)
    res = Results()
    failed = []
    t_start = time.monotonic()
    for name in chosen:
        t0 = time.monotonic()
        print(f'bench: {name} ...', flush=True)
        try:
            FAMILIES[name](res, a)
        except Exception:  # noqa: BLE001 - one broken family must not hide the others
            failed.append(name)
            res.note(f'{name} FAILED:\n{traceback.format_exc()}')
        print(f'bench: {name} done in {time.monotonic() - t0:.0f} s', flush=True)
    width = max([len(r[0]) for r in res.rows] + [6])
    print()
    print(f'| {"figure":<{width}} | {"value":>10} | {"goal":<20} | verdict |')
    print(f'|{"-" * (width + 2)}|{"-" * 12}|{"-" * 22}|---------|')
    for name, value, goal, verdict in res.rows:
        print(f'| {name:<{width}} | {value:>10} | {goal:<20} | {verdict:<7} |')
    print()
    for text in res.notes:
        print(f'- {text}')
    print(f'- total {time.monotonic() - t_start:.0f} s'
          + (f'; FAILED families: {", ".join(failed)}' if failed else ''))
    print('bench: ' + ' '.join(f'{k}={v}' for k, v in res.figures.items()), flush=True)
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
