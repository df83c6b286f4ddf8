"""``blackbox_report``: a black box made readable after an incident.

``blackbox_report <file.jsonl> [more files of one flight ...] [-o report.html]`` (and
``build_report()``) reads the parachute driver's black-box files (``read``), works out what
happened (``analysis``) and writes one self-contained HTML file (``page``; plots embedded as PNG,
nothing fetched from anywhere) and a PNG of the main timeline (``plots``) beside it:

- a summary: the run's start and end, the module's firmware facts and settings, counts of
  requests, deployments, refusals and lost frames, and a paragraph per deployment saying what
  triggered it, who decided and how long each step took;
- the timeline (matplotlib, Agg): tilt and acceleration with the module's thresholds, state
  bands, and every trigger request, deployment step, reboot, setting, link problem and
  black-box problem, against seconds since the start (bottom) and UTC wall clock (top);
- close-ups of the seconds around each deployment, the events, the files and how each ends,
  and every record kind or field this version does not know.

Memory stays bounded whatever the size of the files (they are streamed; see ``read`` and
``analysis``). No ROS here: it runs on any machine with Python and matplotlib.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any, Callable, Optional, Sequence, Tuple

from parachute_blackbox.analysis import FlightAnalysis
from parachute_blackbox.names import LANES
from parachute_blackbox.page import run_facts, field_name, page_html, warnings_of
from parachute_blackbox.plots import timeline_png, zoom_png
from parachute_blackbox.read import FlightFiles, not_a_blackbox
from parachute_blackbox.summary import (deployment_paragraph, DeploymentSummary,
                                        PROGRESS_MIN_BYTES, ProgressArg, ReportSummary, span, wall)


# ---------------------------------------------------------------------------------------------
# Progress
# ---------------------------------------------------------------------------------------------

class _ProgressBar:
    """A one-line progress bar on stderr: percent, MB, MB/s and time left."""

    def __init__(self, total: int, stream: Any = None) -> None:
        self.total = max(1, total)
        self.stream = stream or sys.stderr
        self.start = time.monotonic()
        self.shown = False

    def __call__(self, done: int, total: int) -> None:
        elapsed = max(1e-6, time.monotonic() - self.start)
        frac = min(1.0, done / self.total)
        rate = done / elapsed
        left = (self.total - done) / rate if rate > 0 else 0.0
        width = 30
        bar = '#' * int(frac * width) + '-' * (width - int(frac * width))
        self.stream.write(f'\rblackbox_report [{bar}] {frac * 100:5.1f} % '
                          f'{done / 1e6:8.1f}/{self.total / 1e6:.1f} MB '
                          f'{rate / 1e6:5.1f} MB/s, {left:4.0f} s left ')
        self.stream.flush()
        self.shown = True

    def close(self, text: str = '') -> None:
        if self.shown:
            self.stream.write('\r\033[K' + text)
            self.stream.flush()


def _progress_callback(progress: ProgressArg, total: int
                       ) -> Tuple[Optional[Callable[[int, int], None]], Optional[_ProgressBar]]:
    if callable(progress):
        return progress, None
    if progress is None:
        progress = total >= PROGRESS_MIN_BYTES and sys.stderr.isatty()
    if not progress:
        return None, None
    bar = _ProgressBar(total)
    return bar, bar


# ---------------------------------------------------------------------------------------------
# Entry points
# ---------------------------------------------------------------------------------------------

def default_output(path: str) -> str:
    """Return the default report path for a black-box file: beside it, ``-report.html``."""
    base = path[:-len('.jsonl')] if path.endswith('.jsonl') else path
    return base + '-report.html'


def analyse(paths: Sequence[str], progress: ProgressArg = None
            ) -> Tuple[FlightAnalysis, FlightFiles]:
    """Read the files of one flight and work out what happened (no drawing)."""
    flight = FlightFiles([str(p) for p in paths])
    callback, bar = _progress_callback(progress, flight.total_bytes)
    report_progress = (lambda done: callback(done, flight.total_bytes)) if callback else None
    analysis: Optional[FlightAnalysis] = None
    try:
        for info, line, t, record in flight.records(report_progress):
            if analysis is None:
                analysis = FlightAnalysis(t if t is not None else 0.0)
            analysis.feed(info.index, line, t, record)
    finally:
        if bar is not None:
            bar.close()
    if analysis is None:
        analysis = FlightAnalysis(0.0)
    analysis.finish()
    return analysis, flight


def build_report(paths: Sequence[str], output_html: Optional[str] = None,
                 png_path: Optional[str] = None, progress: ProgressArg = None
                 ) -> ReportSummary:
    """Write the HTML report (and the timeline PNG beside it) of one flight's black boxes.

    ``paths``: one or more black-box files of one flight, in any order. ``output_html``:
    default beside the first file (``<name>-report.html``). ``png_path``: default the HTML
    path with ``.png``. ``progress``: None = a bar on stderr for large files when it is a
    terminal, True/False = always/never, or a callable ``(bytes done, bytes total)``.
    """
    started = time.monotonic()
    if isinstance(paths, (str, os.PathLike)):
        paths = [str(paths)]
    paths = [str(p) for p in paths]
    output_html = str(output_html or default_output(paths[0]))
    png_path = str(png_path or os.path.splitext(output_html)[0] + '.png')
    a, flight = analyse(paths, progress)
    files = flight.files
    firsts = [f.first_time for f in files if f.first_time is not None]
    lasts = [f.last_time for f in files if f.last_time is not None]
    start = min(firsts) if firsts else None
    end = max(lasts) if lasts else None
    t0 = a.t0 if start is None else min(a.t0, start)
    a.t0 = t0
    t_end = end if end is not None else t0
    summary = ReportSummary(html_path=output_html, png_path=png_path, files=files, start=start,
                            end=end, counts=dict(a.counts), deployments=[], events=[],
                            reboots=[t - t0 for t in a.reboots],
                            unknown_kinds={str(k): v[0] for k, v in a.unknown_kinds.items()},
                            unknown_fields={field_name(k): v[0]
                                            for k, v in a.unknown_fields.items()},
                            unknown_decisions={field_name(k): v[0]
                                               for k, v in a.unknown_whats.items()})
    for dep in a.deployments:
        text, steps = deployment_paragraph(dep, t0)
        summary.deployments.append(DeploymentSummary(dep.number, dep.t, dep.t - t0, dep.origin,
                                                     dep.outcome, dep.source, text, steps))
    summary.events = [(ev.t - t0, ev.lane, ev.level, ev.text) for ev in sorted(
        (ev for lane in LANES for ev in a.lanes[lane].kept()), key=lambda e: e.t)]
    summary.facts = run_facts(a, files, start, end)
    summary.warnings = warnings_of(a, files)
    title = (f'{files[0].name if len(files) == 1 else f"{len(files)} black-box files"}: '
             f'{wall(start)} – {wall(end)} ({span(t_end - t0)})')
    timeline = timeline_png(a, files, t0, t_end, title)
    zooms = [(zoom.deployment, zoom_png(a, zoom, files, t_end)) for zoom in a.zooms]
    for directory in {os.path.dirname(os.path.abspath(x)) for x in (output_html, png_path)}:
        os.makedirs(directory, exist_ok=True)
    with open(png_path, 'wb') as handle:
        handle.write(timeline)
    summary.elapsed_s = time.monotonic() - started
    text = page_html(summary, a, timeline, zooms)
    with open(output_html, 'w', encoding='utf-8') as handle:
        handle.write(text)
    return summary


def runs_in(directory: str, limit: int = 10) -> str:
    """List the black-box files (``*.jsonl``) in a directory, newest last, to pick from."""
    try:
        names = [n for n in os.listdir(directory) if n.endswith('.jsonl')]
    except OSError as exc:
        return f'  (cannot list it: {exc.strerror or exc})'
    if not names:
        return '  it holds no black-box file (*.jsonl)'
    paths = sorted((os.path.join(directory, n) for n in names), key=_mtime)
    lines = [f'  it holds {len(paths)} black-box file(s); give one, or several of one flight'
             + (f' (the {limit} newest):' if len(paths) > limit else ':')]
    for path in paths[-limit:]:
        size = os.path.getsize(path) if os.path.isfile(path) else 0
        lines.append(f'    {path}  ({size} bytes, last written {wall(_mtime(path), ms=False)})')
    return '\n'.join(lines)


def _mtime(path: str) -> float:
    try:
        return os.path.getmtime(path)
    except OSError:
        return 0.0


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run ``blackbox_report``; return the exit code."""
    parser = argparse.ArgumentParser(
        prog='blackbox_report',
        description='Write a readable HTML report (timeline, deployments, summary) of the '
                    'parachute driver\'s black-box files of one flight.')
    parser.add_argument('files', nargs='+', help='black-box files (.jsonl) of one flight')
    parser.add_argument('-o', '--output', help='HTML file to write (default: beside the first '
                        'file, <name>-report.html)')
    parser.add_argument('--png', help='timeline PNG to write (default: the HTML path, .png)')
    bar = parser.add_mutually_exclusive_group()
    bar.add_argument('--progress', dest='progress', action='store_true', default=None,
                     help='always show the progress bar on stderr')
    bar.add_argument('--no-progress', dest='progress', action='store_false',
                     help='never show the progress bar')
    argv = list(sys.argv[1:] if argv is None else argv)
    if '--ros-args' in argv:
        # A launch file or `ros2 run ... --ros-args` adds ROS arguments; none are ours.
        start = argv.index('--ros-args')
        end = argv.index('--', start) + 1 if '--' in argv[start:] else len(argv)
        argv = argv[:start] + argv[end:]
    args = parser.parse_args(argv)
    refused = False
    for path in args.files:
        why = not_a_blackbox(path)
        if why:
            refused = True
            print(f'blackbox_report: {path} {why}', file=sys.stderr)
            if why == 'is a directory':
                print(runs_in(path), file=sys.stderr)
    if refused:
        # Nothing is written: a report of something that is no black box would only mislead.
        return 2
    try:
        summary = build_report(args.files, args.output, args.png, args.progress)
    except (OSError, ValueError) as exc:
        print(f'blackbox_report: {exc}', file=sys.stderr)
        return 1
    c = summary.counts
    print(f'blackbox_report: {summary.html_path}')
    print(f'blackbox_report: timeline {summary.png_path}')
    print(f'blackbox_report: {len(summary.files)} file(s), {span(summary.duration_s)}, '
          f'{c.get("deployments", 0)} deployments, {c.get("trigger requests", 0)} trigger '
          f'requests, {c.get("reboots", 0)} reboots, {c.get("unanswered requests", 0)} lost '
          f'frames; {summary.elapsed_s:.1f} s')
    for text in summary.warnings:
        print(f'blackbox_report: note: {text}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
