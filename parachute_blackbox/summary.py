"""What the report tells: its summary, its limits and colours, times and deployments as text."""

from __future__ import annotations

from dataclasses import dataclass, field
import datetime
import html
from typing import Any, Callable, Dict, List, Optional, Tuple, Union

from parachute_blackbox.containers import Deployment
from parachute_blackbox.read import FileInfo


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


def escape(text: Any) -> str:
    """Escape text for HTML (quotes too)."""
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
