"""``blackbox_report``: a black box made readable after an incident.

``blackbox_report <file.jsonl> [more files of one flight ...] [-o report.html]`` (and
``build_report()``) reads the parachute driver's black-box files (``blackbox_read``), works out
what happened (``blackbox_events``) and writes one self-contained HTML file (plots embedded as
PNG, nothing fetched from anywhere) and a PNG of the main timeline beside it:

- a summary: the run's start and end, the module's firmware facts and settings, counts of
  requests, deployments, refusals and lost frames, and a paragraph per deployment saying what
  triggered it, who decided and how long each step took;
- the timeline (matplotlib, Agg): tilt and acceleration with the module's thresholds, state
  bands, and every trigger request, deployment step, reboot, setting, link problem and
  black-box problem, against seconds since the start (bottom) and UTC wall clock (top);
- close-ups of the seconds around each deployment, the events, the files and how each ends,
  and every record kind or field this version does not know.

Memory stays bounded whatever the size of the files (they are streamed; see the two modules
above). No ROS here: it runs on any machine with Python and matplotlib.
"""

from __future__ import annotations

import argparse
import base64
from dataclasses import dataclass, field
import datetime
import html
import io
import math
import os
import sys
import time
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

from parachute_blackbox.analysis import (BANDS, Deployment, Event, FlightAnalysis,
                                         LANE_TITLES, LANES, SETTING_NAMES)
from parachute_blackbox.read import FileInfo, FlightFiles

ProgressArg = Union[None, bool, Callable[[int, int], None]]
DESIRED_PARAMETERS = ('attitude_threshold_deg', 'freefall_threshold_g', 'freefall_time_s',
                      'light_threshold_v', 'attitude_trigger', 'freefall_trigger')
"""The driver's parameters that say what the module should be set to (-1 / keep: leave it)."""
MAX_EVENT_ROWS = 600
"""Events listed in the HTML table; the counts above it are complete."""
MAX_ANNOTATIONS = 24
"""Trigger requests and deployments labelled on the timeline; the rest get markers only."""
MAX_LINES = 40
"""Deployments and reboots drawn as lines across the timeline; with more, markers only."""
PROGRESS_MIN_BYTES = 4 << 20
"""Below this the progress bar is not worth drawing, even on a terminal."""
LEVEL_COLORS = {'ok': '#2e7d32', 'info': '#607d8b', 'warn': '#ef6c00', 'bad': '#c62828',
                'unknown': '#7b1fa2'}
LANE_MARKERS = {'calls': 'o', 'request': 'D', 'deploy': '^', 'module': 's', 'settings': 'P',
                'link': 'X', 'blackbox': 'v', 'other': '*'}
BAND_COLORS = {'port': '#78909c', 'online': '#43a047', 'streaming': '#1e88e5',
               'armed': '#fb8c00', 'triggered': '#e53935', 'blackbox': '#8d6e63'}
BAND_OFF_COLORS = {'port': '#ef9a9a', 'online': '#ef9a9a', 'blackbox': '#ef9a9a'}
"""A closed port, an offline module and a black box that cannot write are problems: drawn in
red, not grey."""
BAND_TITLES = {'port': 'port open', 'online': 'online', 'streaming': 'streaming',
               'armed': 'armed', 'triggered': 'TRIGGERED', 'blackbox': 'black box writes'}


@dataclass
class DeploymentSummary:
    """One deployment as the report tells it."""

    number: int
    t: float
    seconds: float
    origin: str
    outcome: str
    source: str
    paragraph: str
    steps: List[Tuple[float, str]]


@dataclass
class ReportSummary:
    """What ``build_report`` wrote and the facts at the top of the report."""

    html_path: str
    png_path: str
    files: List[FileInfo]
    start: Optional[float]
    end: Optional[float]
    counts: Dict[str, int]
    deployments: List[DeploymentSummary]
    events: List[Tuple[float, str, str, str]]
    """``(seconds since start, lane, level, text)`` of the events kept, in time order."""
    reboots: List[float]
    unknown_kinds: Dict[str, int]
    unknown_fields: Dict[str, int]
    unknown_decisions: Dict[str, int] = field(default_factory=dict)
    """``decision.<what>`` of decisions whose ``what`` this version does not know."""
    facts: Dict[str, str] = field(default_factory=dict)
    warnings: List[str] = field(default_factory=list)
    elapsed_s: float = 0.0

    @property
    def duration_s(self) -> float:
        """Return the length of the flight's records in seconds."""
        if self.start is None or self.end is None:
            return 0.0
        return self.end - self.start

    @property
    def truncated(self) -> bool:
        """Whether any file ends in a partial or unreadable line."""
        return any(f.truncated for f in self.files)


# ---------------------------------------------------------------------------------------------
# Formatting
# ---------------------------------------------------------------------------------------------

def wall(t: Optional[float], ms: bool = True) -> str:
    """Format a time as UTC wall clock."""
    if t is None:
        return 'unknown'
    try:
        stamp = datetime.datetime.fromtimestamp(t, datetime.timezone.utc)
    except (OverflowError, OSError, ValueError):
        return f'{t:.3f} s since 1970'
    text = stamp.strftime('%Y-%m-%d %H:%M:%S')
    if ms:
        text += f'.{stamp.microsecond // 1000:03d}'
    return text + ' UTC'


def span(seconds: float) -> str:
    """Format a duration: '0.04 ms', '69.5 ms', '3.20 s', '12 min 5 s'."""
    if seconds < 0:
        return '-' + span(-seconds)
    if seconds < 0.001:
        return f'{seconds * 1000:.2f} ms'
    if seconds < 1:
        return f'{seconds * 1000:.1f} ms'
    if seconds < 120:
        return f'{seconds:.2f} s'
    if seconds < 7200:
        return f'{int(seconds // 60)} min {int(seconds % 60)} s'
    return f'{int(seconds // 3600)} h {int(seconds % 3600 // 60)} min'


def _e(text: Any) -> str:
    return html.escape(str(text), quote=True)


OUTCOME_PHRASES = {
    'deployed': 'the parachute DEPLOYED',
    'not deployed': 'it did NOT deploy',
    'refused': 'REFUSED: it did not deploy',
    'unknown': 'OUTCOME UNKNOWN',
    'failed': 'the deploy call FAILED before the module answered',
    'requested': 'no answer recorded: OUTCOME UNKNOWN',
}


def deployment_paragraph(dep: Deployment, t0: float) -> Tuple[str, List[Tuple[float, str]]]:
    """Tell one deployment in a short paragraph; return it and its steps (s since start)."""
    steps = sorted(dep.steps, key=lambda s: s.t)
    outcome = OUTCOME_PHRASES.get(dep.outcome, dep.outcome)
    if dep.outcome_text:
        outcome += f' ({dep.outcome_text})'
    text = [f'Deployment {dep.number} at +{dep.t - t0:.3f} s ({wall(dep.t)}): {outcome}.']
    trigger = dep.trigger or 'not recorded'
    if dep.source:
        trigger += f'; the module names the trigger source: {dep.source}'
    text.append(f'What triggered it: {trigger}.')
    text.append(f'Who decided: {dep.decided_by or "not recorded"}.')
    if len(steps) > 1:
        first = steps[0]
        chain = [_step_name(first.text)]
        previous = first
        for step in steps[1:]:
            chain.append(f'{_step_name(step.text)} {span(step.t - previous.t)} later')
            previous = step
        text.append('Step by step: ' + '; '.join(chain)
                    + f' (in all {span(steps[-1].t - first.t)} from the first step).')
    if dep.latency_ms is not None:
        text.append(f'The driver measured {dep.latency_ms:.2f} ms {dep.latency_what}'.rstrip()
                    + '.')
    if dep.tilt_deg is not None:
        age = f', {span(dep.status_age_s)} before' if dep.status_age_s is not None else ''
        text.append(f'Last status frame before it: tilt {dep.tilt_deg:.0f}°, acceleration '
                    f'{dep.accel_g:.1f} g{age}.')
    if dep.record:
        text.append(f'The module\'s trigger record: {dep.record}.')
    return ' '.join(text), [(s.t - t0, s.text) for s in steps]


def _step_name(text: str) -> str:
    return text.split(' (')[0].split(':')[0]


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
# Plots
# ---------------------------------------------------------------------------------------------

def _figure(width: float, height: float):
    # The object-oriented API with the Agg canvas: no pyplot, no global backend switch, so
    # importing this module never changes matplotlib for anyone else in the process.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(fig)
    return fig


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format='png', dpi=100)
    return buf.getvalue()


def _plot_series(ax, series, t0: float, color: str, label: str) -> bool:
    points = series.points()
    if not points:
        return False
    xs = [pt[0] - t0 for pt in points]
    lo = [pt[1] for pt in points]
    hi = [pt[2] for pt in points]
    mean = [pt[3] for pt in points]
    # Gaps (no sample for longer than a few buckets) break the line instead of bridging it.
    gap = series.width * 3 + 0.25
    xs2, lo2, hi2, mean2 = [], [], [], []
    for n, x in enumerate(xs):
        if n and x - xs[n - 1] > gap:
            xs2.append(float('nan'))
            lo2.append(float('nan'))
            hi2.append(float('nan'))
            mean2.append(float('nan'))
        xs2.append(x)
        lo2.append(lo[n])
        hi2.append(hi[n])
        mean2.append(mean[n])
    if any(h != low for h, low in zip(hi, lo)):
        ax.fill_between(xs2, lo2, hi2, color=color, alpha=0.3, linewidth=0, step='mid',
                        label=f'{label} min..max per {span(series.width)}')
    # Steps: a status frame's value holds until the next one; nothing is drawn between.
    ax.plot(xs2, mean2, color=color, linewidth=1.2, label=label, drawstyle='steps-mid')
    return True


def _plot_threshold(ax, history: List[Tuple[float, float]], t0: float, t_end: float,
                    color: str, label: str) -> None:
    if not history:
        return
    xs = [t - t0 for t, _ in history] + [t_end - t0]
    ys = [v for _, v in history] + [history[-1][1]]
    ax.step(xs, ys, where='post', color=color, linestyle='--', linewidth=1.3, label=label)


def _plot_bands(ax, a: FlightAnalysis, t0: float, t_end: float) -> None:
    from matplotlib.patches import Patch
    for row, name in enumerate(reversed(BANDS)):
        # One collection per state and band, however many spans (bounded by the buckets).
        ranges: Dict[Any, List[Tuple[float, float]]] = {
            True: [], False: [], 'mixed': [], None: []}
        for start, end, state in a.bands[name].spans(t_end):
            ranges[state].append((start - t0, max(end - start, 0.0)))
        y = (row + 0.15, 0.7)
        # Edges keep a state that lasted less than a pixel visible.
        if ranges[True]:
            ax.broken_barh(ranges[True], y, facecolors=BAND_COLORS[name],
                           edgecolor=BAND_COLORS[name], linewidth=0.5)
        if ranges[False]:
            off = BAND_OFF_COLORS.get(name, '#eceff1')
            ax.broken_barh(ranges[False], y, facecolors=off, edgecolor=off, linewidth=0.5)
        if ranges['mixed']:
            # Changing within a bucket: drawn in the colour of the state that matters (a
            # flapping link in the problem colour, a short TRIGGERED in its own).
            color = BAND_OFF_COLORS.get(name, BAND_COLORS[name])
            ax.broken_barh(ranges['mixed'], y, facecolors=color, alpha=0.7, hatch='////',
                           edgecolor=color, linewidth=0.5)
        if ranges[None]:
            ax.broken_barh(ranges[None], y, facecolors='white', hatch='..',
                           edgecolor='#cfd8dc', linewidth=0)
    ax.set_yticks([r + 0.5 for r in range(len(BANDS))])
    ax.set_yticklabels([BAND_TITLES[n] for n in reversed(BANDS)], fontsize=8)
    ax.set_ylim(0, len(BANDS))
    ax.legend(handles=[Patch(facecolor='#eceff1', label='no / locked / off'),
                       Patch(facecolor='#ef9a9a', label='port closed / offline /\n'
                             'black box not writing'),
                       Patch(facecolor='white', hatch='..', edgecolor='#cfd8dc',
                             label='unknown'),
                       Patch(facecolor='#b0bec5', hatch='////', label='changing faster\nthan '
                             'drawn')],
              loc='upper left', bbox_to_anchor=(1.002, 1.0), fontsize=7, frameon=False)


def _lane_y(lane: str) -> float:
    return len(LANES) - 1 - LANES.index(lane) + 0.5


def _plot_events(ax, a: FlightAnalysis, t0: float, t_end: float,
                 window: Optional[Tuple[float, float]] = None,
                 events: Optional[List[Event]] = None) -> None:
    from matplotlib.lines import Line2D
    for lane in LANES:
        log = a.lanes[lane]
        y = _lane_y(lane)
        kept = events if events is not None else log.kept()
        by_level: Dict[str, List[float]] = {}
        for ev in kept:
            if ev.lane != lane:
                continue
            if window is not None and not window[0] <= ev.t <= window[1]:
                continue
            by_level.setdefault(ev.level, []).append(ev.t - t0)
        for level, xs in by_level.items():
            ax.scatter(xs, [y] * len(xs), marker=LANE_MARKERS[lane], s=36,
                       color=LEVEL_COLORS[level], edgecolors='black', linewidths=0.3,
                       zorder=3)
        if events is None and log.dropped > 0:
            # More events than markers kept: draw how many fell into each bucket.
            # One artist for all buckets (a bar each would cost megabytes of patches).
            density = log.density
            counts = {i: b[0] for i, b in density.data.items()}
            first, last = min(counts), max(counts)
            peak = max(counts.values())
            edges = [density.time(i) - t0 for i in range(first, last + 2)]
            values = [y - 0.4 + 0.8 * counts.get(i, 0) / peak for i in range(first, last + 1)]
            ax.stairs(values, edges, baseline=y - 0.4, fill=True,
                      color=LEVEL_COLORS['info'], alpha=0.35, zorder=1)
            ax.text(1.0, (y + 0.1) / len(LANES), f' {log.total} (density)',
                    transform=ax.transAxes, fontsize=7, va='center', color='#455a64')
    ax.set_yticks([_lane_y(lane) for lane in LANES])
    ax.set_yticklabels([LANE_TITLES[lane] for lane in LANES], fontsize=8)
    ax.set_ylim(0, len(LANES))
    ax.grid(axis='y', color='#eceff1')
    ax.legend(handles=[Line2D([], [], marker='o', linestyle='', color=c, label=level)
                       for level, c in LEVEL_COLORS.items()],
              loc='upper left', bbox_to_anchor=(1.002, 1.0), fontsize=7, frameon=False)


def _label(ax, text: str, x: float, y: float, dy: int, **style: Any) -> None:
    """Write a label beside a marker, to its left near the right end of the axis."""
    lo, hi = ax.get_xlim()
    right = hi > lo and (x - lo) / (hi - lo) > 0.8
    ax.annotate(text, (x, y), xytext=(-4 if right else 4, dy), textcoords='offset points',
                ha='right' if right else 'left', fontsize=7, **style)


def _annotate(ax, a: FlightAnalysis, t0: float,
              window: Optional[Tuple[float, float]] = None) -> None:
    lo, hi = ax.get_xlim()
    # A 7-point character is at most about 6 pixels wide at 100 dpi: a label that would
    # overlap the last one drawn in its lane is left out (its marker stays).
    per_char = (hi - lo) * 6.0 / max(ax.bbox.width, 1.0)

    def thinned(items: List[Tuple[float, str]]) -> List[Tuple[float, str]]:
        out: List[Tuple[float, str]] = []
        last_end = -math.inf
        for t, text in items:
            if window is not None and not window[0] <= t <= window[1]:
                continue
            x, width = t - t0, (len(text) + 1) * per_char
            start = x - width if hi > lo and (x - lo) / (hi - lo) > 0.8 else x
            if start < last_end:
                continue
            last_end = start + width
            out.append((t, text))
            if len(out) >= MAX_ANNOTATIONS:
                break
        return out

    requests = []
    for req in a.requests:
        label = (req.decision or 'no decision recorded').upper()
        if req.latency_ms is not None:
            label += f' {req.latency_ms:.2f} ms'
        requests.append((req.t, label))
    for t, text in thinned(requests):
        _label(ax, text, t - t0, _lane_y('request'), 7, color='#4e342e')
    for t, text in thinned([(t, 'reboot') for t in a.reboots]):
        _label(ax, text, t - t0, _lane_y('module'), 7, color=LEVEL_COLORS['unknown'])
    deployments = []
    for dep in a.deployments:
        ack, frame = dep.first('ack'), dep.first('frame')
        label = f'#{dep.number} {dep.outcome}'
        if ack is not None and frame is not None:
            label += f', ack {span(ack.t - frame.t)} after the frame'
        deployments.append((dep.t, label))
    for t, text in thinned(deployments):
        _label(ax, text, t - t0, _lane_y('deploy'), 7, color=LEVEL_COLORS['bad'],
               fontweight='bold')


def _vertical_marks(axes, a: FlightAnalysis, t0: float, files: List[FileInfo],
                    window: Optional[Tuple[float, float]] = None) -> None:
    def inside(t: float) -> bool:
        return window is None or window[0] <= t <= window[1]

    # Lines across every panel while they stay few enough to read; else the markers alone.
    if window is not None or a.counts['deployments'] <= MAX_LINES:
        for dep in a.deployments:
            if inside(dep.t):
                for ax in axes:
                    ax.axvline(dep.t - t0, color=LEVEL_COLORS['bad'], linewidth=1.0, alpha=0.7)
    if window is not None or len(a.reboots) <= MAX_LINES:
        for t in a.reboots:
            if inside(t):
                for ax in axes:
                    ax.axvline(t - t0, color=LEVEL_COLORS['unknown'], linestyle=':',
                               linewidth=1.2)
    for info in files:
        if info.truncated and info.last_time is not None and inside(info.last_time):
            for ax in axes:
                ax.axvline(info.last_time - t0, color='black', linestyle='-.', linewidth=1.2)
            axes[0].annotate(f'{info.name} ends: TRUNCATED', (info.last_time - t0, 1.0),
                             xycoords=('data', 'axes fraction'), xytext=(-4, -12),
                             textcoords='offset points', ha='right', fontsize=7)
    if window is None:
        ordered = [f for f in files if f.first_time is not None and f.last_time is not None]
        for prev, nxt in zip(ordered, ordered[1:]):
            if nxt.first_time - prev.last_time > 0.5:
                for ax in axes:
                    ax.axvspan(prev.last_time - t0, nxt.first_time - t0, color='#9e9e9e',
                               alpha=0.25, linewidth=0)
                axes[0].annotate(f'no black box for {span(nxt.first_time - prev.last_time)}',
                                 ((prev.last_time + nxt.first_time) / 2 - t0, 0.5),
                                 xycoords=('data', 'axes fraction'), ha='center', fontsize=7)


def _wall_axis(ax, t0: float, duration: float) -> None:
    from matplotlib.ticker import FuncFormatter

    def label(x: float, _pos: Any) -> str:
        try:
            stamp = datetime.datetime.fromtimestamp(t0 + x, datetime.timezone.utc)
        except (OverflowError, OSError, ValueError):
            return ''
        if duration < 30:
            return stamp.strftime('%H:%M:%S.') + f'{stamp.microsecond // 1000:03d}'[:2]
        if duration < 2 * 86400:
            return stamp.strftime('%H:%M:%S')
        return stamp.strftime('%m-%d %H:%M')

    top = ax.secondary_xaxis('top')
    top.xaxis.set_major_formatter(FuncFormatter(label))
    top.set_xlabel('wall clock (UTC)', fontsize=8)
    top.tick_params(labelsize=8)


def timeline_png(a: FlightAnalysis, files: List[FileInfo], t0: float, t_end: float,
                 title: str) -> bytes:
    """Draw the main timeline; return it as PNG."""
    fig = _figure(16, 11)
    grid = fig.add_gridspec(4, 1, height_ratios=[3, 3, 2, 4.2], hspace=0.08,
                            left=0.08, right=0.86, top=0.91, bottom=0.06)
    ax_tilt = fig.add_subplot(grid[0])
    ax_acc = fig.add_subplot(grid[1], sharex=ax_tilt)
    ax_bands = fig.add_subplot(grid[2], sharex=ax_tilt)
    ax_ev = fig.add_subplot(grid[3], sharex=ax_tilt)
    duration = max(t_end - t0, 1e-3)
    ax_tilt.set_xlim(-0.01 * duration, duration * 1.01)
    _series_axes(ax_tilt, ax_acc, a, t0, t_end)
    _plot_bands(ax_bands, a, t0, t_end)
    _plot_events(ax_ev, a, t0, t_end)
    _annotate(ax_ev, a, t0)
    _vertical_marks([ax_tilt, ax_acc, ax_bands, ax_ev], a, t0, files)
    for ax in (ax_tilt, ax_acc, ax_bands):
        ax.tick_params(labelbottom=False)
    ax_tilt.set_xlim(-0.01 * duration, duration * 1.01)
    ax_ev.set_xlabel('seconds since the start of the black box', fontsize=9)
    _wall_axis(ax_tilt, t0, duration)
    fig.suptitle(title, fontsize=11)
    return _png(fig)


def _series_axes(ax_tilt, ax_acc, a: FlightAnalysis, t0: float, t_end: float) -> None:
    _series_axis(ax_tilt, a.tilt, '#1565c0', 'tilt', 'tilt [deg]', t0, t_end,
                 a.settings['attitude_threshold_deg'], 'attitude threshold')
    _series_axis(ax_acc, a.accel, '#00897b', 'acceleration', 'acceleration [g]', t0, t_end,
                 a.settings['freefall_threshold_g'], 'free-fall threshold')


def _series_axis(ax, series: Any, color: str, label: str, ylabel: str, t0: float, t_end: float,
                 threshold: List[Tuple[float, float]], threshold_label: str) -> None:
    if not _plot_series(ax, series, t0, color, label):
        ax.text(0.5, 0.5, 'no status frame in this black box', ha='center',
                transform=ax.transAxes, color='#78909c')
    _plot_threshold(ax, threshold, t0, t_end, '#c62828',
                    f'{threshold_label}\n(read from the module)')
    ax.set_ylabel(ylabel, fontsize=9)
    ax.grid(color='#eceff1')
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc='upper left', bbox_to_anchor=(1.002, 1.0), fontsize=7, frameon=False)
    ax.tick_params(labelsize=8)


def zoom_png(a: FlightAnalysis, zoom: Any, files: List[FileInfo], t_end: float) -> bytes:
    """Draw the full-resolution close-up of one deployment; return it as PNG."""
    dep = zoom.deployment
    # Not beyond the black box: a deployment near its start or end gets a narrower window.
    zoom.start, zoom.end = max(zoom.start, a.t0), min(zoom.end, max(t_end, dep.last_t))
    t_ref = dep.t
    fig = _figure(14, 6.5)
    grid = fig.add_gridspec(3, 1, height_ratios=[2, 2, 3.2], hspace=0.08,
                            left=0.1, right=0.85, top=0.9, bottom=0.09)
    ax_tilt = fig.add_subplot(grid[0])
    ax_acc = fig.add_subplot(grid[1], sharex=ax_tilt)
    ax_ev = fig.add_subplot(grid[2], sharex=ax_tilt)
    ax_tilt.set_xlim(zoom.start - t_ref, zoom.end - t_ref)
    xs = [s[0] - t_ref for s in zoom.samples]
    if xs:
        ax_tilt.plot(xs, [s[1] for s in zoom.samples], '.-', color='#1565c0', markersize=3,
                     linewidth=1, label='tilt (every status frame)', drawstyle='steps-post')
        ax_acc.plot(xs, [s[2] for s in zoom.samples], '.-', color='#00897b', markersize=3,
                    linewidth=1, label='acceleration (every status frame)',
                    drawstyle='steps-post')
        for ax in (ax_tilt, ax_acc):
            start = None
            for s in zoom.samples:
                if s[4] and start is None:
                    start = s[0]
                elif not s[4] and start is not None:
                    ax.axvspan(start - t_ref, s[0] - t_ref, color='#ffcdd2', alpha=0.6)
                    start = None
            if start is not None:
                ax.axvspan(start - t_ref, zoom.samples[-1][0] - t_ref, color='#ffcdd2',
                           alpha=0.6, label='status: TRIGGERED')
    for key, ax in (('attitude_threshold_deg', ax_tilt), ('freefall_threshold_g', ax_acc)):
        history = [(t, v) for t, v in a.settings[key] if t <= zoom.end]
        if history:
            start_value = [v for t, v in history if t <= zoom.start]
            points = ([(zoom.start, start_value[-1])] if start_value else []) + \
                [(t, v) for t, v in history if t > zoom.start]
            _plot_threshold(ax, points, t_ref, zoom.end, '#c62828', 'threshold')
    ax_tilt.set_ylabel('tilt [deg]', fontsize=9)
    ax_acc.set_ylabel('accel. [g]', fontsize=9)
    _plot_events(ax_ev, a, t_ref, zoom.end, (zoom.start, zoom.end), zoom.events)
    _annotate(ax_ev, a, t_ref, (zoom.start, zoom.end))
    for step in sorted(dep.steps, key=lambda s: s.t):
        if zoom.start <= step.t <= zoom.end:
            ax_ev.axvline(step.t - t_ref, color='#ffab91', linewidth=0.8, zorder=0)
    _vertical_marks([ax_tilt, ax_acc, ax_ev], a, t_ref, files, (zoom.start, zoom.end))
    for ax in (ax_tilt, ax_acc):
        ax.tick_params(labelbottom=False, labelsize=8)
        ax.grid(color='#eceff1')
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc='upper left', bbox_to_anchor=(1.002, 1.0), fontsize=7,
                      frameon=False)
    ax_tilt.set_xlim(zoom.start - t_ref, zoom.end - t_ref)
    ax_ev.set_xlabel(f'seconds from deployment {dep.number} (+{dep.t - a.t0:.3f} s, '
                     f'{wall(dep.t)})', fontsize=9)
    fig.suptitle(f'Deployment {dep.number}: the {span(zoom.end - zoom.start)} around it, '
                 'every frame', fontsize=11)
    return _png(fig)


# ---------------------------------------------------------------------------------------------
# Facts and HTML
# ---------------------------------------------------------------------------------------------

def _setting_fact(a: FlightAnalysis, key: str, unit: str) -> str:
    history = a.settings[key]
    if not history:
        return 'not read'
    values = [v for _, v in history]
    text = f'{values[-1]:g}{unit}'
    if len(values) > 1:
        text += ' (over the run: ' + ' → '.join(f'{v:g}' for v in values[-6:]) + ')'
    return text


def _facts(a: FlightAnalysis, files: List[FileInfo], start: Optional[float],
           end: Optional[float]) -> Dict[str, str]:
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
        out.append('<tr>' + ''.join(f'<th>{_e(h)}</th>' for h in header) + '</tr>')
    for row in rows:
        out.append('<tr>' + ''.join(f'<td>{cell if raw else _e(cell)}</td>' for cell in row)
                   + '</tr>')
    out.append('</table>')
    return '\n'.join(out)


def _img(png: bytes, alt: str) -> str:
    return (f'<img alt="{_e(alt)}" src="data:image/png;base64,'
            f'{base64.b64encode(png).decode("ascii")}">')


def _html(summary: ReportSummary, a: FlightAnalysis, timeline: bytes,
          zooms: List[Tuple[Deployment, bytes]]) -> str:
    t0 = a.t0
    title = summary.files[0].name if len(summary.files) == 1 else \
        f'{len(summary.files)} files of one flight'
    out = [f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
           f'<title>Black-box report: {_e(title)}</title><style>{_CSS}</style></head><body>',
           f'<h1>Parachute black-box report: {_e(title)}</h1>',
           f'<p class="lead">From {_e(wall(summary.start))} to {_e(wall(summary.end))} '
           f'({_e(span(summary.duration_s))}). Times below are seconds since the start '
           f'(+s) and UTC wall clock. Written by blackbox_report at '
           f'{_e(wall(time.time(), ms=False))}.</p>']
    for text in summary.warnings:
        cls = 'bad' if 'TRUNCATED' in text or 'UNKNOWN' in text else 'warn'
        out.append(f'<div class="{cls}">{_e(text)}</div>')
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
        out.append(f'<div class="dep" id="deployment-{dep.number}"><p>{_e(dep.paragraph)}</p>')
        out.append(_table([(f'+{s:.4f} s', wall(t0 + s), text) for s, text in dep.steps],
                          ('time', 'wall clock', 'step'), cls='times'))
        out.append('</div>')
    if a.counts['deployments'] > len(summary.deployments):
        out.append(f'<p>{a.counts["deployments"] - len(summary.deployments)} more deployments '
                   'are counted but not described one by one.</p>')
    out.append('<h2>Timeline</h2>')
    out.append(f'<p>Also written beside this file as <span class="mono">'
               f'{_e(os.path.basename(summary.png_path))}</span>. Tilt and acceleration are '
               f'drawn per {_e(span(a.tilt.width))} (line: mean, band: min..max). Red lines: '
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
        rows.append((f'+{ev.t - t0:.3f}', _e(wall(ev.t)), _e(LANE_TITLES[ev.lane]),
                     f'<span class="lvl-{ev.level}">{_e(ev.text)}</span>',
                     _e(ev.line if len(summary.files) == 1 else
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
        out.append('<p>From a newer (or a much older) driver. They are shown on the timeline '
                   'in the lane "unknown records" and counted here; nothing else depends on '
                   'them.</p>')
        rows = [('kind', k, v[0], f'{summary.files[v[1]].name}:{v[2]}', v[3])
                for k, v in a.unknown_kinds.items()]
        rows += [('field', _field_name(k), v[0], f'{summary.files[v[1]].name}:{v[2]}', v[3])
                 for k, v in a.unknown_fields.items()]
        rows += [('decision', _field_name(k), v[0], f'{summary.files[v[1]].name}:{v[2]}', v[3])
                 for k, v in a.unknown_whats.items()]
        out.append(_table(rows, ('what', 'name', 'count', 'first at', 'example')))
    out.append('<h2>All counts</h2>')
    out.append(_table(sorted((k, f'{v:,}') for k, v in a.counts.items()), ('count', 'value')))
    out.append(f'<p class="lead">Report made in {summary.elapsed_s:.1f} s from '
               f'{sum(f.size for f in summary.files):,} bytes.</p></body></html>')
    return '\n'.join(out)


def _field_name(key: Any) -> str:
    """Name an unknown field ``kind.field`` (or the catch-all past the listed ones)."""
    return '.'.join(map(str, key)) if isinstance(key, tuple) else str(key)


def _warnings(a: FlightAnalysis, files: List[FileInfo]) -> List[str]:
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
                            unknown_fields={_field_name(k): v[0]
                                            for k, v in a.unknown_fields.items()},
                            unknown_decisions={_field_name(k): v[0]
                                               for k, v in a.unknown_whats.items()})
    for dep in a.deployments:
        text, steps = deployment_paragraph(dep, t0)
        summary.deployments.append(DeploymentSummary(dep.number, dep.t, dep.t - t0, dep.origin,
                                                     dep.outcome, dep.source, text, steps))
    summary.events = [(ev.t - t0, ev.lane, ev.level, ev.text) for ev in sorted(
        (ev for lane in LANES for ev in a.lanes[lane].kept()), key=lambda e: e.t)]
    summary.facts = _facts(a, files, start, end)
    summary.warnings = _warnings(a, files)
    title = (f'{files[0].name if len(files) == 1 else f"{len(files)} black-box files"}: '
             f'{wall(start)} – {wall(end)} ({span(t_end - t0)})')
    timeline = timeline_png(a, files, t0, t_end, title)
    zooms = [(zoom.deployment, zoom_png(a, zoom, files, t_end)) for zoom in a.zooms]
    for directory in {os.path.dirname(os.path.abspath(x)) for x in (output_html, png_path)}:
        os.makedirs(directory, exist_ok=True)
    with open(png_path, 'wb') as handle:
        handle.write(timeline)
    summary.elapsed_s = time.monotonic() - started
    text = _html(summary, a, timeline, zooms)
    with open(output_html, 'w', encoding='utf-8') as handle:
        handle.write(text)
    return summary


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
    missing = [f for f in args.files if not os.path.isfile(f)]
    if missing:
        print(f'blackbox_report: no such file: {", ".join(missing)}', file=sys.stderr)
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
