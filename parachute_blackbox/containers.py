"""Bounded containers of the analysis: time buckets, event lanes, deployments, requests."""

from __future__ import annotations

import collections
from dataclasses import dataclass, field
from typing import Any, Deque, Dict, List, Optional, Tuple

from parachute_blackbox.names import FIRST_BUCKET_S, KEEP_EVENTS, MAX_BUCKETS


class _Buckets:
    """Fixed-count time buckets whose width doubles when time runs past the last one."""

    def __init__(self, t0: float, width: float = FIRST_BUCKET_S,
                 max_buckets: int = MAX_BUCKETS) -> None:
        self.t0 = t0
        self.width = width
        self.max_buckets = max_buckets
        self.data: Dict[int, list] = {}

    def index(self, t: float) -> int:
        i = int((t - self.t0) / self.width)
        if i < 0:
            return 0  # a record a little out of order before the first one
        while i >= self.max_buckets:
            self._halve()
            i = int((t - self.t0) / self.width)
        return i

    def _halve(self) -> None:
        merged: Dict[int, list] = {}
        for i in sorted(self.data):
            j = i // 2
            if j in merged:
                self.merge(merged[j], self.data[i])
            else:
                merged[j] = self.data[i]
        self.data = merged
        self.width *= 2

    def merge(self, into: list, other: list) -> None:
        raise NotImplementedError

    def time(self, i: int) -> float:
        """Return the start of bucket ``i``."""
        return self.t0 + i * self.width


class Series(_Buckets):
    """A measurement over time: min, max, sum and count per bucket."""

    def add(self, t: float, value: float) -> None:
        """Add one sample."""
        i = self.index(t)
        b = self.data.get(i)
        if b is None:
            self.data[i] = [value, value, value, 1]
        else:
            if value < b[0]:
                b[0] = value
            if value > b[1]:
                b[1] = value
            b[2] += value
            b[3] += 1

    def merge(self, into: list, other: list) -> None:
        """Combine two buckets' min, max, sum and count."""
        into[0] = min(into[0], other[0])
        into[1] = max(into[1], other[1])
        into[2] += other[2]
        into[3] += other[3]

    def points(self) -> List[Tuple[float, float, float, float]]:
        """Return ``(bucket middle, min, max, mean)`` in time order."""
        half = self.width / 2
        return [(self.time(i) + half, b[0], b[1], b[2] / b[3])
                for i, b in sorted(self.data.items())]

    @property
    def count(self) -> int:
        """Return the number of samples added."""
        return sum(b[3] for b in self.data.values())


class Density(_Buckets):
    """How many events fell into each bucket."""

    def add(self, t: float) -> None:
        """Count one event at ``t``."""
        i = self.index(t)
        b = self.data.get(i)
        if b is None:
            self.data[i] = [1]
        else:
            b[0] += 1

    def merge(self, into: list, other: list) -> None:
        """Add two buckets' counts."""
        into[0] += other[0]

    def points(self) -> List[Tuple[float, float, int]]:
        """Return ``(bucket start, width, count)`` in time order."""
        return [(self.time(i), self.width, b[0]) for i, b in sorted(self.data.items())]


class Track(_Buckets):
    """A state over time (True, False or None = unknown), kept per bucket.

    A bucket holds its number of changes, the time of its first and last change, the state
    before the first and after the last: one change is drawn where it happened, several
    (flapping faster than a bucket) as 'mixed' between the first and the last.
    """

    def __init__(self, t0: float, **kwargs: Any) -> None:
        super().__init__(t0, **kwargs)
        self.value: Optional[bool] = None
        self.changes = 0

    def set(self, t: float, value: Optional[bool]) -> bool:
        """Set the state at ``t``; return whether it changed."""
        if value == self.value:
            return False
        i = self.index(t)
        b = self.data.get(i)
        if b is None:
            self.data[i] = [1, t, self.value, value, t]
        else:
            b[0] += 1
            b[3] = value
            b[4] = max(b[4], t)
        self.changes += 1
        self.value = value
        return True

    def merge(self, into: list, other: list) -> None:
        """Combine an earlier bucket with a later one: changes add up, the later state wins."""
        into[0] += other[0]
        into[3] = other[3]
        into[4] = max(into[4], other[4])

    def spans(self, t_end: float) -> List[Tuple[float, float, Any]]:
        """Return ``(start, end, state)`` runs; state is True, False, None or 'mixed'."""
        runs: List[List[Any]] = []

        def push(t: float, state: Any) -> None:
            if runs and runs[-1][2] == state:
                return
            if runs:
                runs[-1][1] = max(runs[-1][0], t)
            runs.append([t, t, state])

        for _, (n, t_first, before, after, t_last) in sorted(self.data.items()):
            if not runs:
                push(t_first, before)
            if n == 1:
                push(t_first, after)
            else:
                push(t_first, 'mixed')
                push(t_last, after)
        if runs:
            runs[-1][1] = max(runs[-1][0], t_end)
        return [(a, b, s) for a, b, s in runs if b > a]


@dataclass
class Event:
    """One thing that happened, as drawn on the timeline and listed in the report."""

    t: float
    lane: str
    level: str
    text: str
    file: int = 0
    line: int = 0


class EventLog:
    """One lane's events: the first and the last ``keep`` of them and a complete count."""

    def __init__(self, t0: float, keep: int = KEEP_EVENTS) -> None:
        self.first: List[Event] = []
        self.last: Deque[Event] = collections.deque(maxlen=keep)
        self.keep = keep
        self.total = 0
        self.levels: collections.Counter = collections.Counter()
        self.density = Density(t0)

    def add(self, event: Event) -> None:
        """Keep or count one event."""
        self.total += 1
        self.levels[event.level] += 1
        self.density.add(event.t)
        if len(self.first) < self.keep:
            self.first.append(event)
        else:
            self.last.append(event)

    def kept(self) -> List[Event]:
        """Return the events kept, in time order."""
        return self.first + list(self.last)

    @property
    def dropped(self) -> int:
        """Return how many events were counted but not kept."""
        return self.total - len(self.first) - len(self.last)


# ---------------------------------------------------------------------------------------------
# Deployments, trigger requests, reboots
# ---------------------------------------------------------------------------------------------

@dataclass
class Step:
    """One step of a deployment: its time, its kind and what happened."""

    t: float
    key: str
    text: str


@dataclass
class Deployment:
    """A deployment or an attempt at one, with every step the black box shows."""

    number: int
    t: float
    origin: str
    trigger: str
    decided_by: str = ''
    outcome: str = 'unknown'
    outcome_text: str = ''
    source: str = ''
    record: str = ''
    latency_ms: Optional[float] = None
    latency_what: str = ''
    attempts: int = 0
    tilt_deg: Optional[float] = None
    accel_g: Optional[float] = None
    status_age_s: Optional[float] = None
    steps: List[Step] = field(default_factory=list)
    closed: bool = False
    file: int = 0
    line: int = 0

    def step(self, t: float, key: str, text: str) -> None:
        """Append to the steps (bounded: a deployment has a handful)."""
        if len(self.steps) < 40:
            self.steps.append(Step(t, key, text))

    def first(self, key: str) -> Optional[Step]:
        """Return the first step of a kind."""
        return next((s for s in self.steps if s.key == key), None)

    @property
    def last_t(self) -> float:
        """Return the time of the last step."""
        return self.steps[-1].t if self.steps else self.t


@dataclass
class TriggerRequestSeen:
    """A trigger request (0x39) from the module and what the driver answered."""

    t: float
    decision: str = ''
    policy: str = ''
    reason: str = ''
    latency_ms: Optional[float] = None
    t_decision: Optional[float] = None
    t_confirm: Optional[float] = None
    deployment: Optional[Deployment] = None
    deferred: bool = False


@dataclass
class Zoom:
    """Full-resolution status samples and events around one deployment."""

    deployment: Deployment
    start: float
    end: float
    samples: List[Tuple[float, float, float, bool, bool]] = field(default_factory=list)
    events: List[Event] = field(default_factory=list)


@dataclass
class Pending:
    """A request to the module that waits for its reply."""

    t: float
    hex: str
    code: int
    control: int
    expect: str
    file: int
    line: int
    tx: int = 0
    last_tx: float = 0.0

    def __post_init__(self) -> None:
        self.last_tx = self.t
