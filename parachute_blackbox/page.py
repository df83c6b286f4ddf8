"""The report's HTML page: facts, counts, warnings, tables and the embedded pictures."""

from __future__ import annotations

import base64
import os
import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

from parachute_blackbox.analysis import FlightAnalysis
from parachute_blackbox.containers import Deployment
from parachute_blackbox.names import LANE_TITLES, LANES, SETTING_NAMES
from parachute_blackbox.read import FileInfo
from parachute_blackbox.summary import (DESIRED_PARAMETERS, escape, MAX_EVENT_ROWS, ReportSummary,
                                        span, wall)


def _setting_fact(a: FlightAnalysis, key: str, unit: str) -> str:
    history = a.settings[key]
    if not history:
        return 'not read'
    values = [v for _, v in history]
    text = f'{values[-1]:g}{unit}'
    if len(values) > 1:
        text += ' (over the run: ' + ' → '.join(f'{v:g}' for v in values[-6:]) + ')'
    return text


def run_facts(a: FlightAnalysis, files: List[FileInfo], start: Optional[float],
              end: Optional[float]) -> Dict[str, str]:
    """Return the facts at the top of the report: run, module, settings, policy."""
    facts: Dict[str, str] = {}
    facts['Run start'] = wall(start)
    facts['Run end'] = wall(end)
    facts['Duration'] = span((end or 0) - (start or 0)) if start is not None else 'unknown'
    facts['Files'] = f'{len(files)}: ' + ', '.join(f.name for f in files[:8]) + (
        ' …' if len(files) > 8 else '')
    timed = [f for f in files if f.first_time is not None and f.last_time is not None]
    gaps = [f'{span(nxt.first_time - prev.last_time)} between {prev.name} and {nxt.name}'
            for prev, nxt in zip(timed, timed[1:]) if nxt.first_time - prev.last_time > 0.5]
    if gaps:
        facts['No black box (gaps between files)'] = '; '.join(gaps[:8]) + (
            ' …' if len(gaps) > 8 else '')
    if a.runs:
        run = a.runs[0]
        facts['Driver'] = (f'port {run.get("port")}, {run.get("baud")} baud'
                           + (f', {len(a.runs)} driver starts' if len(a.runs) > 1 else ''))
    else:
        facts['Driver'] = 'no start record (the beginning of the black box is missing)'
    if a.policy_changes:
        facts['Trigger-request policy'] = ' → '.join(p for _, p in a.policy_changes[:10])
    if a.runs and a.runs[0]['parameters']:
        params = a.runs[0]['parameters']
        desired = [f'{k} {v}' for k, v in params.items()
                   if k in DESIRED_PARAMETERS and v not in (-1, -1.0, 'keep')]
        facts['Desired settings (driver parameters)'] = (
            ', '.join(desired) if desired else "none: the module's own are kept")
    if a.boot_counts:
        counts = [c for _, c in a.boot_counts]
        changes = len(counts) - 1
        facts['Module boot count'] = (f'{counts[0]}' if not changes else
                                      f'{counts[0]} → {counts[-1]} ({changes} change'
                                      f'{"s" if changes > 1 else ""})')
    else:
        facts['Module boot count'] = 'not read'
    for _, (key, name, unit, _) in sorted(SETTING_NAMES.items()):
        facts[name[0].upper() + name[1:]] = _setting_fact(a, key, unit)
    flags = a.flags
    facts['Auto triggers'] = ', '.join(
        f'{name} {"unknown" if flags[key] is None else ("on" if flags[key] else "off")}'
        for key, name in (('attitude', 'attitude'), ('freefall', 'free fall')))
    baud = a.module_baud or (a.runs[0].get('baud') if a.runs else None)
    facts['Baud rate'] = f'{baud}' if baud else 'unknown'
    if a.last_mismatch is not None:
        facts['Settings verified'] = ('yes (the last initialization read back every desired '
                                      'setting)' if not a.last_mismatch else
                                      'NO: ' + '; '.join(map(str, a.last_mismatch))[:300])
    if a.preflight is not None:
        t, ok, lines = a.preflight
        failed = [line[4:].strip() for line in lines if line.startswith('FAIL')]
        verdict = 'GO' if ok else 'NO-GO: ' + '; '.join(failed)
        facts['Last preflight check'] = f'+{t - a.t0:.1f} s: {verdict}'[:400]
    if a.cell_voltage is not None:
        lo, hi, last = a.cell_voltage
        facts['Cell / charging voltage'] = (f'{last:.2f} V last, {lo:.2f}..{hi:.2f} V; '
                                            + ('charging' if a.charging else 'on battery'
                                               if a.charging is not None else ''))
    return facts


def _count_rows(a: FlightAnalysis) -> List[Tuple[str, str]]:
    c = a.counts
    decisions = ('confirmed', 'denied', 'timed_out', 'not answered')
    decided = ', '.join(f'{c[f"trigger requests {d}"]} {d.replace("_", " ")}'
                        for d in decisions if c[f'trigger requests {d}'])
    undecided = c['trigger requests'] - sum(c[f'trigger requests {d}'] for d in decisions)
    outcomes: Dict[str, int] = {}
    for dep in a.deployments:
        outcomes[dep.outcome] = outcomes.get(dep.outcome, 0) + 1
    rows = [
        ('Trigger requests from the module', f'{c["trigger requests"]}'
         + (f' ({decided})' if decided else '')
         + (f'; {undecided} with no decision recorded' if undecided > 0 else '')),
        ('Deployments and attempts', f'{c["deployments"]}' + (
            ' (' + ', '.join(f'{n} {o}' for o, n in sorted(outcomes.items())) + ')'
            if outcomes else '')),
        ('~/deploy calls', f'{c["deploy calls"]} ({c["deploy calls refused"]} refused before '
         f'anything was sent, {c["deploy calls answered already deployed"]} answered "already '
         f'deployed", {c["deploy frames sent"]} deploy frames sent, '
         f'{c["deploy frames unacknowledged"]} unacknowledged)'),
        ('Deploy outcomes unknown', f'{c["deploys with unknown outcome"]} when the call ended, '
         f'{c["unknown deploy outcomes resolved"]} read later (D12)'),
        ('Refusals', f'{c["deploy calls refused"] + c["deploys refused by the module"]} '
         f'deploy refusals ({c["deploys refused by the module"]} by the module), '
         f'{c["parameter changes refused"]} parameter sets refused '
         f'({c["settings put back"]} settings put back, {c["settings not put back"]} could '
         f'not be), {c["settings changes refused (would deploy)"]} settings changes that would '
         'deploy at once refused, '
         f'{c["trigger requests denied"] + c["trigger requests timed_out"]} trigger requests '
         'not confirmed'),
        ('Preflight checks', f'{c["preflight checks"]} ({c["preflight checks NO-GO"]} NO-GO)'),
        ('Requests to the module', f'{c["requests to the module"]} ({c["answered requests"]} '
         f'answered, {c["requests answered after a retry"]} only after a retry, '
         f'{c["requests cut short"]} cut short by a stop, a closed port or a reboot)'),
        ('Lost frames (unanswered requests)', f'{c["unanswered requests"]}'),
        ('Module reboots', f'{c["reboots"]}'),
        ('Link', f'{c["offline"]} times offline, {c["port closed"]} port closed, '
         f'{c["reconnects"]} reconnects, {c["checksum errors"]} checksum errors, '
         f'{c["bytes of noise discarded"]} bytes of noise, '
         f'{c["request timeouts (as the driver counted)"]} request timeouts (as the driver '
         'counted)'),
        ('Settings written and verified', f'{c["settings written and verified"]} '
         f'({c["settings not verified"]} read back otherwise, '
         f'{c["settings writes not confirmed"]} writes not confirmed)'),
        ('Status frames', f'{c["status frames"]}'),
        ('Black box', f'{c["records"]} records; {c["record gaps"]} gaps while streaming; '
         f'{c["black-box write failures"]} write failures recorded, '
         f'{c["black-box records lost"]} records lost (as the driver counted)'),
    ]
    return rows


_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;margin:24px auto;
max-width:1700px;color:#212121;line-height:1.45;padding:0 16px}
h1{font-size:1.5em;margin-bottom:.2em}h2{border-bottom:1px solid #cfd8dc;margin-top:1.6em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #e0e0e0;padding:3px 8px;
vertical-align:top;text-align:left;font-size:.92em}th{background:#f5f5f5}
.lead{color:#455a64}.warn{background:#fff3e0;border-left:5px solid #ef6c00;padding:8px 12px;
margin:8px 0}.bad{background:#ffebee;border-left:5px solid #c62828;padding:8px 12px;margin:8px 0}
.dep{background:#fafafa;border:1px solid #e0e0e0;padding:8px 12px;margin:10px 0}
img{max-width:100%;height:auto;border:1px solid #eceff1}
.lvl-ok{color:#2e7d32}.lvl-warn{color:#ef6c00}.lvl-bad{color:#c62828;font-weight:600}
.lvl-unknown{color:#7b1fa2;font-weight:600}.lvl-info{color:#546e7a}
.mono{font-family:ui-monospace,Menlo,Consolas,monospace;font-size:.9em}
.cols{display:flex;gap:32px;flex-wrap:wrap}.times td:nth-child(-n+2){white-space:nowrap}
"""


def _table(rows: Sequence[Sequence[Any]], header: Optional[Sequence[str]] = None,
           raw: bool = False, cls: str = '') -> str:
    out = [f'<table class="{cls}">' if cls else '<table>']
    if header:
        out.append('<tr>' + ''.join(f'<th>{escape(h)}</th>' for h in header) + '</tr>')
    for row in rows:
        out.append('<tr>' + ''.join(f'<td>{cell if raw else escape(cell)}</td>' for cell in row)
                   + '</tr>')
    out.append('</table>')
    return '\n'.join(out)


def _img(png: bytes, alt: str) -> str:
    return (f'<img alt="{escape(alt)}" src="data:image/png;base64,'
            f'{base64.b64encode(png).decode("ascii")}">')


def page_html(summary: ReportSummary, a: FlightAnalysis, timeline: bytes,
              zooms: List[Tuple[Deployment, bytes]]) -> str:
    """Return the whole HTML page of the report, its pictures embedded."""
    t0 = a.t0
    title = summary.files[0].name if len(summary.files) == 1 else \
        f'{len(summary.files)} files of one flight'
    out = [f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
           f'<title>Black-box report: {escape(title)}</title><style>{_CSS}</style></head><body>',
           f'<h1>Parachute black-box report: {escape(title)}</h1>',
           f'<p class="lead">From {escape(wall(summary.start))} to {escape(wall(summary.end))} '
           f'({escape(span(summary.duration_s))}). Times below are seconds since the start '
           f'(+s) and UTC wall clock. Written by blackbox_report at '
           f'{escape(wall(time.time(), ms=False))}.</p>']
    for text in summary.warnings:
        cls = 'bad' if 'TRUNCATED' in text or 'UNKNOWN' in text else 'warn'
        out.append(f'<div class="{cls}">{escape(text)}</div>')
    out.append('<h2>Summary</h2><div class="cols"><div><h3>Run and module</h3>')
    out.append(_table(list(summary.facts.items())))
    out.append('</div><div><h3>Counts</h3>')
    out.append(_table(_count_rows(a)))
    out.append('</div></div>')
    out.append(f'<h2>Deployments ({a.counts["deployments"]})</h2>')
    if not summary.deployments:
        out.append('<p>No deployment, no deploy frame and no triggered module in this black '
                   'box.</p>')
    for dep in summary.deployments:
        out.append(f'<div class="dep" id="deployment-{dep.number}"><p>{escape(dep.paragraph)}</p>')
        out.append(_table([(f'+{s:.4f} s', wall(t0 + s), text) for s, text in dep.steps],
                          ('time', 'wall clock', 'step'), cls='times'))
        out.append('</div>')
    if a.counts['deployments'] > len(summary.deployments):
        out.append(f'<p>{a.counts["deployments"] - len(summary.deployments)} more deployments '
                   'are counted but not described one by one.</p>')
    out.append('<h2>Timeline</h2>')
    out.append(f'<p>Also written beside this file as <span class="mono">'
               f'{escape(os.path.basename(summary.png_path))}</span>. Tilt and acceleration are '
               f'drawn per {escape(span(a.tilt.width))} (line: mean, band: min..max). Red lines: '
               'deployments; dotted purple lines: module reboots; grey areas: no black box '
               '(between files).</p>')
    out.append(_img(timeline, 'timeline of the flight'))
    if zooms:
        out.append('<h2>Close-ups of the deployments</h2>')
        for dep, png in zooms:
            out.append(f'<h3>Deployment {dep.number}</h3>')
            out.append(_img(png, f'the seconds around deployment {dep.number}'))
    out.append('<h2>Events</h2>')
    rows = []
    events = sorted((ev for lane in LANES for ev in a.lanes[lane].kept()), key=lambda e: e.t)
    for ev in events[:MAX_EVENT_ROWS]:
        rows.append((f'+{ev.t - t0:.3f}', escape(wall(ev.t)), escape(LANE_TITLES[ev.lane]),
                     f'<span class="lvl-{ev.level}">{escape(ev.text)}</span>',
                     escape(ev.line if len(summary.files) == 1 else
                            f'{summary.files[ev.file].name}:{ev.line}')))
    dropped = sum(a.lanes[lane].dropped for lane in LANES) + max(0, len(events)
                                                                 - MAX_EVENT_ROWS)
    if dropped:
        out.append(f'<p>{dropped} events are not listed (the first and last ones of each lane '
                   'are); every count above is complete.</p>')
    out.append(_table(rows, ('+s', 'wall clock', 'lane', 'event',
                             'line' if len(summary.files) == 1 else 'file:line'), raw=True,
                      cls='times'))
    out.append('<h2>Files</h2>')
    file_rows = []
    for info in summary.files:
        file_rows.append((info.name, f'{info.size:,} B', f'{info.lines:,}', f'{info.records:,}',
                          f'{info.bad_lines:,}', wall(info.first_time), wall(info.last_time),
                          info.ending()))
    out.append(_table(file_rows, ('file', 'size', 'lines', 'records', 'unreadable lines',
                                  'first record', 'last record', 'how it ends')))
    bad_rows = [(info.name, b.line, b.offset, b.reason, b.excerpt)
                for info in summary.files for b in info.bad_samples]
    if bad_rows:
        out.append('<h3>Unreadable lines (a sample)</h3>')
        out.append(_table(bad_rows, ('file', 'line', 'byte', 'why', 'begins with')))
    out.append('<h2>Records this report does not know</h2>')
    if not (a.unknown_kinds or a.unknown_fields or a.unknown_whats):
        out.append('<p>None: every record kind and field is known to this version.</p>')
    else:
        out.append('<p>From another version of the driver, or damaged. They are shown on the '
                   'timeline in the lane "unknown records" and counted here; nothing else '
                   'depends on them.</p>')
        rows = [('kind', k, v[0], f'{summary.files[v[1]].name}:{v[2]}', v[3])
                for k, v in a.unknown_kinds.items()]
        rows += [('field', field_name(k), v[0], f'{summary.files[v[1]].name}:{v[2]}', v[3])
                 for k, v in a.unknown_fields.items()]
        rows += [('decision', field_name(k), v[0], f'{summary.files[v[1]].name}:{v[2]}', v[3])
                 for k, v in a.unknown_whats.items()]
        out.append(_table(rows, ('what', 'name', 'count', 'first at', 'example')))
    out.append('<h2>All counts</h2>')
    out.append(_table(sorted((k, f'{v:,}') for k, v in a.counts.items()), ('count', 'value')))
    out.append(f'<p class="lead">Report made in {summary.elapsed_s:.1f} s from '
               f'{sum(f.size for f in summary.files):,} bytes.</p></body></html>')
    return '\n'.join(out)


def field_name(key: Any) -> str:
    """Name an unknown field or decision: ``kind.field``."""
    """Name an unknown field ``kind.field`` (or the catch-all past the listed ones)."""
    return '.'.join(map(str, key)) if isinstance(key, tuple) else str(key)


def warnings_of(a: FlightAnalysis, files: List[FileInfo]) -> List[str]:
    """Return what the reader must know before trusting the report (damage, gaps, lost records)."""
    out = []
    for info in files:
        if info.truncated or info.error:
            out.append(f'{info.name}: {info.ending()}. Everything after that point is '
                       'missing from this report.')
        elif not info.clean_end:
            out.append(f'{info.name}: {info.ending()}.')
        mid = info.bad_lines - info.tail_lines
        if mid > 0:
            out.append(f'{info.name}: {mid} unreadable lines inside the file were skipped '
                       '(listed under Files).')
        if info.bad_times:
            out.append(f'{info.name}: {info.bad_times} records with a damaged time were placed '
                       'at the time of the record before them.')
        if info.clock_steps:
            out.append(f'{info.name}: the wall clock was stepped {info.clock_steps} times (up '
                       f'to {info.clock_step_max_s:.1f} s); times here follow the monotonic '
                       'clock from the first record.')
    unknown = sum(v[0] for v in a.unknown_kinds.values())
    if unknown:
        out.append(f'{unknown} records of kinds this version does not know '
                   f'({", ".join(list(map(str, a.unknown_kinds))[:6])}); see "Records this '
                   'report does not know".')
    unknown = a.counts['deploys with unknown outcome']
    open_ = unknown - a.counts['unknown deploy outcomes resolved']
    if open_ > 0:
        out.append(f'{open_} deploy attempts with an UNKNOWN outcome the driver never '
                   'resolved: see the deployments.')
    elif unknown:
        out.append(f'{unknown} deploy calls ended with an unknown outcome; the driver read '
                   'what became of each later: see the deployments.')
    return out
