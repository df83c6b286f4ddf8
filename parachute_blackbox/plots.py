"""The report's pictures (matplotlib, Agg): the timeline and the close-ups of deployments."""

from __future__ import annotations

import datetime
import io
import math
from typing import Any, Dict, List, Optional, Tuple

from parachute_blackbox.analysis import FlightAnalysis
from parachute_blackbox.containers import Event
from parachute_blackbox.names import BANDS, LANE_TITLES, LANES
from parachute_blackbox.read import FileInfo
from parachute_blackbox.summary import (BAND_COLORS, BAND_OFF_COLORS, BAND_TITLES, LANE_MARKERS,
                                        LEVEL_COLORS, MAX_ANNOTATIONS, MAX_LINES, span, wall)


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
