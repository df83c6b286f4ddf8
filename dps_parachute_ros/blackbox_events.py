"""What a black box says happened: records turned into a flight's events, series and states.

``FlightAnalysis.feed()`` takes the records of ``blackbox_read.FlightFiles`` one at a time and
keeps only bounded state, so a black box of any size fits in memory:

- time series (tilt, acceleration) as min/max per time bucket; state bands (port open, online,
  streaming, armed, triggered) as the states seen per bucket. Buckets double their width when
  there would be more than ``MAX_BUCKETS`` of them.
- events (one lane each: service calls, trigger requests, deployments, module, settings, link,
  black box, other) as the first and last few hundred per lane plus a count per bucket; every
  count is complete.
- deployments, each with its chain of steps and their times (request or call, decision, frame,
  acknowledgement or unknown outcome, the module's triggered flag, the trigger event).

What a record means is looked up in tables: ``RULES`` by the record's ``kind``, and below it
``DECISIONS`` by ``what``, ``DEPLOY_OUTCOMES`` by a deploy call's ``outcome``, ``STATE_FIELDS``
by field (``STATE_EVENTS`` by a state's ``event``), ``RX_MESSAGES`` by the type
``protocol.decode_module_frame`` gives a received frame and ``TX_COMMANDS`` by the command code
of a sent one. Adding a kind is one entry in ``RULES`` (``generic_rule`` covers a kind that only
needs showing). A kind or a field that no table knows is counted and listed, never fatal: the
black box of a newer driver still gives a report, and so does one of an older driver that lacks
fields or names them differently (the driver before the session core: ``start.parameters``,
``parameter.name/value``, ``deploy unacknowledged`` decisions, deploy calls ending in
``success`` false without an ``outcome``, numeric ``trigger_event.via``). The records of the
present driver are in ``docs/protocols.md`` (D10, D12, D17, D18). No ROS here.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field
import math
from typing import Any, Callable, Deque, Dict, List, Optional, Tuple

from dps_parachute_ros import protocol as p

MAX_BUCKETS = 2000
"""Time buckets per series or band at most; the timeline is a few thousand pixels wide."""
FIRST_BUCKET_S = 0.02
"""Bucket width to begin with: a short run keeps its 10-20 Hz status stream point by point."""
KEEP_EVENTS = 300
"""Events kept per lane at the start and again at the end of the flight."""
MAX_DEPLOYMENTS = 100
"""Deployments described one by one; more are counted."""
MAX_ZOOMS = 6
"""Deployments that get a full-resolution close-up of the seconds around them."""
ZOOM_BEFORE_S = 4.0
ZOOM_AFTER_S = 4.0
ZOOM_MAX_SAMPLES = 4000
REPLY_TIMEOUT_S = 1.0
"""P12: a reply later than this after its request is lost; the driver has given up by then.
The driver's ``request_timeout_s`` in its start record replaces it for that run."""
REPLY_MARGIN_S = 0.2
"""A request with no reply this long after the timeout since its last frame left is
unanswered: a margin for records of the reply that other threads' records overtook in the
queue."""
REQUEST_STALE_S = 2.0
"""A trigger request still undecided this long after it came gets no decision any more (the
module waits 1 s, P10; the driver decides within its defer timeout or at its stop)."""
DEPLOYMENT_WINDOW_S = 10.0
"""Triggered flags, acknowledgements and trigger events this close belong to one deployment."""
REBOOT_SAME_S = 0.2
"""Evidence of a reboot this close to the last one is the same reboot (two heartbeats 50 ms
apart, P5, and the driver's record of the first one)."""
RECORD_GAP_S = 2.0
"""No record at all for this long while online and streaming: the black box lost records."""
MAX_RECORDS_KEPT = 64
"""Distinct trigger records (module history) kept."""

LANES = ('calls', 'request', 'deploy', 'module', 'settings', 'link', 'blackbox', 'other')
LANE_TITLES = {
    'calls': 'service calls', 'request': 'trigger requests', 'deploy': 'deployment',
    'module': 'module (reboots)', 'settings': 'settings', 'link': 'link',
    'blackbox': 'black box', 'other': 'unknown records',
}
LEVELS = ('ok', 'info', 'warn', 'bad', 'unknown')
"""How an event is drawn: ok green, info grey-blue, warn orange, bad red, unknown purple."""
BANDS = ('port', 'online', 'streaming', 'armed', 'triggered', 'blackbox')
LINK_COUNTERS = ('checksum_errors', 'bytes_discarded', 'timeouts', 'reconnects', 'frames_in',
                 'frames_out')
"""The cumulative counters of a ``link`` record (the driver's decoder and serial link)."""
SETTING_NAMES = {
    p.CMD_ATTITUDE_THRESHOLD: ('attitude_threshold_deg', 'attitude threshold', '°', 1.0),
    p.CMD_FREEFALL_THRESHOLD: ('freefall_threshold_g', 'free-fall threshold', ' g', 0.1),
    p.CMD_FREEFALL_TIME: ('freefall_time_s', 'free-fall time', ' s', 0.01),
    p.CMD_LIGHT_THRESHOLD: ('light_threshold_v', 'light threshold', ' V', 0.1),
}
"""Setting command code -> (key, name, unit, raw step)."""
SETTING_REPLIES = {p.AttitudeThreshold: p.CMD_ATTITUDE_THRESHOLD,
                   p.FreefallThreshold: p.CMD_FREEFALL_THRESHOLD,
                   p.FreefallTime: p.CMD_FREEFALL_TIME,
                   p.LightThreshold: p.CMD_LIGHT_THRESHOLD}
COMMAND_NAMES = {
    p.CMD_HEARTBEAT: 'heartbeat', p.CMD_ARM: 'arm/lock', p.CMD_DEPLOY: 'deploy',
    p.CMD_SHUTDOWN: 'shutdown', p.CMD_STREAMING: 'streaming', p.CMD_LIGHT_LEVEL: 'light level',
    p.CMD_LIGHT_THRESHOLD: 'light threshold', p.CMD_ATTITUDE_TRIGGER: 'attitude trigger',
    p.CMD_FREEFALL_TRIGGER: 'free-fall trigger', p.CMD_ATTITUDE_THRESHOLD: 'attitude threshold',
    p.CMD_FREEFALL_THRESHOLD: 'free-fall threshold', p.CMD_FREEFALL_TIME: 'free-fall time',
    p.CMD_BOOT_COUNT: 'boot count', p.CMD_BAUD_RATE: 'baud rate', p.CMD_SENSOR_ZERO: 'zero sensor',
    p.CMD_ARMED: 'armed?', p.CMD_TRIGGERED: 'triggered?', p.CMD_STATUS: 'status',
    p.CMD_CHARGING: 'charging?', p.CMD_CELL_VOLTAGE: 'cell voltage',
    p.CMD_TRIGGER_RECORDS: 'trigger records', p.CMD_TRIGGER_REQUEST: 'trigger confirmation',
}
SOURCE_BITS = ((p.SOURCE_SERIAL, 'serial'), (p.SOURCE_ATTITUDE, 'attitude'),
               (p.SOURCE_PWM, 'PWM'), (p.SOURCE_FREEFALL, 'free fall'))
VIA_NAMES = {0: 'the deploy acknowledgement', 1: 'the status (triggered flag)',
             2: 'a new trigger record', 'deploy_ack': 'the deploy acknowledgement',
             'status': 'the status (triggered flag)', 'record': 'a new trigger record'}
"""``trigger_event.via``: a number in older black boxes, a name in the present driver's."""
COMMON_FIELDS = frozenset({'t', 'mono', 'kind'})


def source_text(source: int) -> str:
    """Name trigger-source bits: 'free fall', 'attitude+PWM', 'unknown'."""
    names = [name for bit, name in SOURCE_BITS if source & bit]
    return '+'.join(names) if names else 'unknown'


def short(value: Any, limit: int = 100) -> str:
    """Render a field value in one short line."""
    if isinstance(value, float):
        text = f'{value:.4g}'
    elif isinstance(value, (dict, list)):
        text = ', '.join(f'{k}={short(v, 30)}' for k, v in value.items()) \
            if isinstance(value, dict) else ', '.join(short(v, 30) for v in value)
    else:
        text = str(value)
    return text if len(text) <= limit else text[:limit - 1] + '…'


def describe_fields(record: Dict[str, Any], skip: frozenset = COMMON_FIELDS) -> str:
    """Return ``key=value, ...`` of a record's fields, bounded in length."""
    return short(', '.join(f'{k}={short(v, 40)}' for k, v in record.items() if k not in skip),
                 160)


# ---------------------------------------------------------------------------------------------
# Bounded containers
# ---------------------------------------------------------------------------------------------

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

    def extent(self) -> Optional[Tuple[float, float]]:
        """Return the smallest and largest value, None if empty."""
        if not self.data:
            return None
        return (min(b[0] for b in self.data.values()), max(b[1] for b in self.data.values()))


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
class _Pending:
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


# ---------------------------------------------------------------------------------------------
# The rules
# ---------------------------------------------------------------------------------------------

Handler = Callable[['FlightAnalysis', Dict[str, Any], float], None]


@dataclass(frozen=True)
class Rule:
    """What one record kind means: its known fields and the handler that reads it."""

    kind: str
    fields: frozenset
    handler: Handler


def generic_rule(kind: str, lane: str, title: str, level: str = 'info',
                 fields: Tuple[str, ...] = ()) -> Rule:
    """Make the rule of a kind that only needs showing: '<title>: field=value, ...'."""
    def handler(a: 'FlightAnalysis', record: Dict[str, Any], t: float) -> None:
        a.event(t, lane, level, f'{title}: {describe_fields(record)}')
    return Rule(kind, frozenset(fields), handler)


class FlightAnalysis:
    """Everything the report needs from the records of one flight, in bounded memory."""

    def __init__(self, t0: float) -> None:
        self.t0 = t0
        self.t_last = t0
        self.file = 0
        self.line = 0
        self.counts: collections.Counter = collections.Counter()
        self.unknown_kinds: Dict[str, List[Any]] = {}
        self.unknown_fields: Dict[Tuple[str, str], List[Any]] = {}
        self.unknown_whats: Dict[Tuple[str, str], List[Any]] = {}
        self.tilt = Series(t0)
        self.accel = Series(t0)
        self.bands = {name: Track(t0) for name in BANDS}
        self.lanes = {name: EventLog(t0) for name in LANES}
        self.settings: Dict[str, List[Tuple[float, float]]] = {
            key: [] for key, _, _, _ in SETTING_NAMES.values()}
        self.flags: Dict[str, Optional[bool]] = {'attitude': None, 'freefall': None}
        self.boot_counts: List[Tuple[float, int]] = []
        self.module_baud: Optional[int] = None
        self.runs: List[Dict[str, Any]] = []
        self.policy_changes: List[Tuple[float, str]] = []
        self.preflight: Optional[Tuple[float, bool, List[str]]] = None
        self.deployments: List[Deployment] = []
        self.requests: Deque[TriggerRequestSeen] = collections.deque(maxlen=KEEP_EVENTS)
        self.reply_timeout_s = REPLY_TIMEOUT_S
        self.reboots: List[float] = []
        self.trigger_records: Dict[str, p.TriggerRecord] = {}
        self.cell_voltage: Optional[Tuple[float, float, float]] = None
        self.charging: Optional[bool] = None
        self.zooms: List[Zoom] = []
        self.last_status: Optional[Tuple[float, float, float]] = None
        self.last_mismatch: Optional[List[Any]] = None
        self._recent_samples: Deque[Tuple[float, float, float, bool, bool]] = \
            collections.deque(maxlen=ZOOM_MAX_SAMPLES)
        self._recent_events: Deque[Event] = collections.deque(maxlen=200)
        self._active_zooms: List[Zoom] = []
        self._pending: Dict[str, Deque[_Pending]] = {}
        self._pending_by_hex: Dict[str, _Pending] = {}
        self._pending_n = 0
        self._set_sent: Dict[int, Tuple[float, int]] = {}
        self._call: Optional[Dict[str, Any]] = None
        self._deployment: Optional[Deployment] = None
        self._unknown_dep: Optional[Deployment] = None   # outcome unknown, not resolved yet
        self._undecided: Deque[TriggerRequestSeen] = collections.deque(maxlen=16)
        self._link_counters: Dict[str, int] = {}          # the run's last link record
        self._bb_lost = 0                                 # the run's lost records so far
        self._reread_why = ''                             # why the next initialization reads
        self._decode_cache: Dict[str, Any] = {}
        self._prev_t: Optional[float] = None
        self._prev_file = -1
        self._port_seen = False
        self._reboots_unread = 0

    # -- input ------------------------------------------------------------------------------

    def feed(self, file: int, line: int, t: Optional[float], record: Dict[str, Any]) -> None:
        """Take one record (``t`` None: a record without time, placed at the last time)."""
        self.file, self.line = file, line
        if t is None:
            t = self.t_last
            self.counts['records without a time'] += 1
        else:
            self._check_gap(file, t)
            if t > self.t_last:
                self.t_last = t
        if self._pending_n:
            self._expire(t)
        kind = record.get('kind')
        if not isinstance(kind, str):
            kind = '(no kind)' if kind is None else f'({type(kind).__name__} kind)'
        rule = RULES.get(kind)
        self.counts['records'] += 1
        if rule is None:
            self._unknown(self.unknown_kinds, kind, record)
            self.event(t, 'other', 'unknown', f'record of unknown kind {kind!r}: '
                       f'{describe_fields(record)}')
            return
        for name in record:
            if name not in rule.fields and name not in COMMON_FIELDS:
                self._unknown(self.unknown_fields, (kind, name), record)
        try:
            rule.handler(self, record, t)
        except Exception as exc:  # noqa: BLE001 - one odd record must not cost the report
            # A field of a type this version does not expect: the record is listed, not fatal.
            self.counts['records not understood'] += 1
            self._unknown(self.unknown_kinds, f'{kind} (not understood: {type(exc).__name__})',
                          record)

    def _unknown(self, table: Dict[Any, List[Any]], key: Any, record: Dict[str, Any]) -> None:
        entry = table.get(key)
        if entry is None:
            if len(table) >= 200:
                key = '(more)'
                entry = table.get(key)
            if entry is None:
                entry = table[key] = [0, self.file, self.line, describe_fields(record)]
        entry[0] += 1

    def _check_gap(self, file: int, t: float) -> None:
        prev, self._prev_t = self._prev_t, t
        if file != self._prev_file:
            self._prev_file = file
            if prev is not None:
                self._expire(prev, reason='the end of the file')
            return
        if prev is None or t - prev < RECORD_GAP_S:
            return
        if self.bands['online'].value and self.bands['streaming'].value:
            self.counts['record gaps'] += 1
            self.event(prev, 'blackbox', 'warn',
                       f'no record for {t - prev:.1f} s while the module was online and '
                       'streaming: records lost, or the driver stalled')

    def event(self, t: float, lane: str, level: str, text: str) -> Event:
        """Add an event to a lane."""
        ev = Event(t, lane, level, text, self.file, self.line)
        self.lanes[lane].add(ev)
        self._recent_events.append(ev)
        for zoom in self._active_zooms:
            if len(zoom.events) < 400:
                zoom.events.append(ev)
        return ev

    # -- requests and replies ----------------------------------------------------------------

    def _expire(self, t: float, reason: str = '', expect: Optional[str] = None) -> None:
        """Settle requests with no reply: lost after the reply timeout and a margin.

        With a ``reason`` (the driver stopped, the port closed, the module rebooted), requests
        younger than the reply timeout were cut short rather than lost. With ``expect``, the
        requests waiting for that reply type are over now: the link sends one request per reply
        type at a time, so a new one means the one before it has given up.
        """
        timeout = self.reply_timeout_s
        queues = self._pending.values() if expect is None else [self._pending.get(expect, ())]
        for queue in queues:
            while queue and (reason or expect is not None
                             or t - queue[0].last_tx > timeout + REPLY_MARGIN_S):
                req = queue.popleft()
                self._pending_n -= 1
                if self._pending_by_hex.get(req.hex) is req:
                    del self._pending_by_hex[req.hex]
                name = COMMAND_NAMES.get(req.code, hex(req.code))
                sent = self._set_sent.pop(req.code, None) \
                    if req.control == p.CTRL_SET and req.code in SETTING_NAMES else None
                if reason and t - req.last_tx <= timeout:
                    # Its reply could still have come: not a lost frame.
                    self.counts['requests cut short'] += 1
                    continue
                if sent is not None:
                    # A later read-back would judge a write the module never confirmed.
                    _, setting, unit, step = SETTING_NAMES[req.code]
                    self.counts['settings writes not confirmed'] += 1
                    self.event(req.last_tx, 'settings', 'bad', f'{setting} {sent[1] * step:g}'
                               f'{unit}: the module did not confirm the write (no reply)')
                self.counts['unanswered requests'] += 1
                self.event(req.last_tx, 'link', 'warn', f'no reply to {name} ({req.hex}) within '
                           f'{timeout:.1f} s: request or reply lost')
                if req.code == p.CMD_DEPLOY:
                    self._deploy_unanswered(req, min(t, req.last_tx + timeout))

    def _deploy_unanswered(self, req: _Pending, t: float) -> None:
        """Note a deploy frame whose wait ended without an acknowledgement (P11, D6)."""
        self.counts['deploy frames unacknowledged'] += 1
        call = self._call
        dep = call['dep'] if call is not None and call.get('dep') is not None else \
            self.current_deployment(t)
        if dep is not None:
            dep.step(t, 'noack', f'no acknowledgement of the deploy frame (waited '
                     f'{self.reply_timeout_s:.1f} s)')
        self.event(t, 'deploy', 'warn', 'deploy frame not acknowledged')

    def finish(self) -> None:
        """Close the flight after its last record: requests still waiting were cut short."""
        self._expire(self.t_last, reason='the end of the black box')

    def request_sent(self, record: Dict[str, Any], t: float) -> None:
        """Note a request to the module (``request`` with ``hex`` and ``expect``)."""
        hex_text = str(record.get('hex', ''))
        try:
            raw = bytes.fromhex(hex_text)
        except ValueError:
            self.counts['requests with unreadable frames'] += 1
            return
        self.counts['requests to the module'] += 1
        expect = str(record.get('expect') or '')
        if not expect:
            # Nothing says which reply would answer it: it cannot be matched, nor called lost.
            self.counts['requests without an expected reply'] += 1
            return
        if self._pending.get(expect):
            self._expire(t, expect=expect)
        req = _Pending(t, hex_text, raw[2] if len(raw) > 2 else -1,
                       raw[3] if len(raw) > 3 else -1, expect, self.file, self.line)
        self._pending.setdefault(expect, collections.deque()).append(req)
        self._pending_by_hex[hex_text] = req
        self._pending_n += 1

    def _answered(self, msg: Any, t: float) -> Optional[_Pending]:
        queue = self._pending.get(type(msg).__name__)
        if not queue:
            return None
        req = queue.popleft()
        self._pending_n -= 1
        if self._pending_by_hex.get(req.hex) is req:
            del self._pending_by_hex[req.hex]
        self.counts['answered requests'] += 1
        if req.tx > 1:
            self.counts['requests answered after a retry'] += 1
            self.event(t, 'link', 'warn', f'{COMMAND_NAMES.get(req.code, hex(req.code))} '
                       f'answered only after {req.tx - 1} retry (a timeout)')
        return req

    # -- frames ------------------------------------------------------------------------------

    def frame(self, record: Dict[str, Any], t: float) -> None:
        """Read a frame on the wire (``frame`` record, ``dir`` rx or tx, ``hex``)."""
        direction = record.get('dir')
        hex_text = record.get('hex')
        if not isinstance(hex_text, str):
            self.counts['frames without bytes'] += 1
            return
        if direction == 'tx':
            self.counts['frames sent'] += 1
            self._tx(hex_text, t)
            return
        if direction != 'rx':
            self.counts[f'frames of direction {direction!r}'] += 1
            return
        self.counts['frames received'] += 1
        msg = self._decode_cache.get(hex_text)
        if msg is None:
            try:
                msg = p.decode_module_frame(p.parse_frame(bytes.fromhex(hex_text)))
            except p.ChecksumError:
                self.counts['checksum errors'] += 1
                self.event(t, 'link', 'warn', f'frame with a bad checksum: {hex_text}')
                return
            except (p.ProtocolError, ValueError, IndexError):
                self.counts['unreadable frames'] += 1
                self.event(t, 'link', 'warn', f'received bytes that are no DPS-S frame: '
                           f'{short(hex_text, 60)}')
                return
            if len(self._decode_cache) > 4096:
                self._decode_cache.clear()
            self._decode_cache[hex_text] = msg
        req = self._answered(msg, t) if self._pending_n else None
        handler = RX_MESSAGES.get(type(msg))
        if handler is not None:
            handler(self, msg, t, req)

    def _tx(self, hex_text: str, t: float) -> None:
        req = self._pending_by_hex.get(hex_text)
        if req is not None:
            req.tx += 1
            req.last_tx = t
        try:
            frame = p.parse_frame(bytes.fromhex(hex_text))
        except (p.ProtocolError, ValueError, IndexError):
            self.counts['unreadable frames sent'] += 1
            return
        handler = TX_COMMANDS.get(frame.code)
        if handler is not None:
            handler(self, frame, t)

    # -- state helpers -----------------------------------------------------------------------

    def band(self, name: str, t: float, value: Optional[bool]) -> bool:
        """Set a state band; return whether it changed."""
        return self.bands[name].set(t, value)

    def status_sample(self, t: float, tilt: float, accel: float, armed: bool,
                      triggered: bool) -> None:
        """One status frame's measurements."""
        self.counts['status frames'] += 1
        self.tilt.add(t, tilt)
        self.accel.add(t, accel)
        self.last_status = (t, tilt, accel)
        sample = (t, tilt, accel, armed, triggered)
        self._recent_samples.append(sample)
        if self._active_zooms:
            for zoom in list(self._active_zooms):
                if t > zoom.end:
                    self._active_zooms.remove(zoom)
                elif len(zoom.samples) < ZOOM_MAX_SAMPLES:
                    zoom.samples.append(sample)

    def note_reboot(self, t: float, evidence: str, level: str = 'warn') -> None:
        """Evidence of a module reboot; evidence close to the last reboot is the same reboot."""
        if self.reboots and abs(t - self.reboots[-1]) < REBOOT_SAME_S:
            return
        self._reboots_unread += 1
        self.reboots.append(t)
        if len(self.reboots) > 1000:
            del self.reboots[:500]
        self.counts['reboots'] += 1
        self._reread_why = 'the reboot'
        self.event(t, 'module', level, f'module rebooted ({evidence})')
        self.band('streaming', t, False)
        self.band('armed', t, False)
        self.band('triggered', t, False)
        if self._deployment is not None:
            self._deployment.closed = True
        self._expire(t, reason='before the module rebooted')

    def boot_count(self, t: float, count: int) -> None:
        """Note a boot count read from the module; a change is a reboot."""
        previous = self.boot_counts[-1][1] if self.boot_counts else None
        seen, self._reboots_unread = self._reboots_unread, 0
        if previous == count:
            return
        if len(self.boot_counts) < 1000:
            self.boot_counts.append((t, count))
        if previous is None:
            self.event(t, 'module', 'info', f'boot count {count}')
            return
        self.event(t, 'module', 'info', f'boot count {previous} → {count}')
        # Each power-up adds one (wrapping after 255); reboots nobody saw are added here.
        unseen = ((count - previous) & 0xFF) - seen
        if unseen > 0:
            self.note_reboot(t, f'{unseen} reboot(s) not seen as they happened: boot count '
                             f'{previous} → {count}')
            self.counts['reboots'] += unseen - 1

    def setting_value(self, t: float, code: int, raw: int) -> None:
        """Note a setting read back from the module (the thresholds drawn on the timeline)."""
        key, _, _, step = SETTING_NAMES[code]
        history = self.settings[key]
        value = round(raw * step, 3)
        if history and history[-1][1] == value:
            return
        if len(history) >= 500:
            del history[1:250]
        history.append((t, value))

    # -- deployments -------------------------------------------------------------------------

    def open_deployment(self, t: float, origin: str, trigger: str,
                        decided_by: str = '') -> Deployment:
        """Start describing a deployment (or an attempt at one)."""
        self.counts['deployments'] += 1
        dep = Deployment(self.counts['deployments'], t, origin, trigger, decided_by,
                         file=self.file, line=self.line)
        if self.last_status is not None:
            dep.tilt_deg, dep.accel_g = self.last_status[1], self.last_status[2]
            dep.status_age_s = max(0.0, t - self.last_status[0])
        self._deployment = dep
        if len(self.deployments) < MAX_DEPLOYMENTS:
            self.deployments.append(dep)
        if len(self.zooms) < MAX_ZOOMS:
            zoom = Zoom(dep, t - ZOOM_BEFORE_S, t + ZOOM_AFTER_S)
            zoom.samples = [s for s in self._recent_samples if s[0] >= zoom.start]
            zoom.events = [e for e in self._recent_events if e.t >= zoom.start]
            self.zooms.append(zoom)
            self._active_zooms.append(zoom)
        return dep

    def current_deployment(self, t: float) -> Optional[Deployment]:
        """Return the deployment that later evidence at ``t`` belongs to, if any."""
        dep = self._deployment
        if dep is None or dep.closed or t - dep.last_t > DEPLOYMENT_WINDOW_S:
            return None
        return dep

    def module_triggered(self, t: float, via: str) -> None:
        """Note that the module says it has triggered (status, query, the driver's record)."""
        before = self.bands['triggered'].value
        if not self.band('triggered', t, True):
            return
        dep = self.current_deployment(t)
        unknown = self._unknown_dep
        if dep is None and before is None and unknown is not None and not unknown.closed:
            # The driver could not tell whether its deploy went out, and nothing said "not
            # triggered" since: now the module says (D12).
            dep = unknown
        if dep is None and before is None:
            dep = self.open_deployment(t, 'module', 'the module was already TRIGGERED when the '
                                       'driver first saw it (deployed before this black box '
                                       'begins, or while nobody watched)', 'not seen')
            dep.outcome, dep.outcome_text = 'deployed', 'the module reports TRIGGERED'
        elif dep is None:
            dep = self.open_deployment(t, 'module', 'the module deployed on its own (no '
                                       'trigger request and no deploy call before it)',
                                       'the module (no host decision)')
            dep.outcome, dep.outcome_text = 'deployed', 'the module reports TRIGGERED'
        elif dep.outcome in ('unknown', 'requested'):
            dep.outcome, dep.outcome_text = 'deployed', 'the module reports TRIGGERED'
        dep.step(t, 'triggered', f'the module reports TRIGGERED ({via})')
        self.event(t, 'deploy', 'bad', f'module TRIGGERED ({via})')

    def trigger_record(self, t: float, record: p.TriggerRecord) -> None:
        """Note a trigger record from the module's history (16-byte 0x35 frame)."""
        if record.is_empty:
            return
        key = record.raw.hex(' ')
        if key in self.trigger_records:
            return
        if len(self.trigger_records) < MAX_RECORDS_KEPT:
            self.trigger_records[key] = record
        self.counts['trigger records read'] += 1
        dep = self._deployment  # a record read after a reboot still tells of the deployment
        if dep is not None and not dep.record and t - dep.last_t <= DEPLOYMENT_WINDOW_S:
            dep.record = record_text(record)
            dep.source = dep.source or source_text(record.source)
            dep.step(t, 'record', f'trigger record read: {dep.record}')


def record_text(record: p.TriggerRecord) -> str:
    """Describe a trigger record in one line."""
    return (f'source {source_text(record.source)}, boot #{record.boot_count}, '
            f'{record.uptime_s} s after power-up, thresholds {record.attitude_threshold_deg}° / '
            f'{record.freefall_threshold_g:.1f} g / {record.freefall_time_s:.2f} s, cell '
            f'{record.cell_voltage_v:.2f} V, {"charging" if record.charging else "on battery"}')


# ---------------------------------------------------------------------------------------------
# Received frames: typed message -> handler(analysis, message, t, answered request or None)
# ---------------------------------------------------------------------------------------------

def _rx_status(a: FlightAnalysis, msg: p.Status, t: float, req: Optional[_Pending]) -> None:
    a.status_sample(t, float(msg.tilt_deg), float(msg.accel_g), msg.armed, msg.triggered)
    a.band('armed', t, msg.armed)
    if msg.triggered:
        a.module_triggered(t, 'status frame')
    else:
        a.band('triggered', t, False)


def _rx_heartbeat(a: FlightAnalysis, msg: p.Heartbeat, t: float,
                  req: Optional[_Pending]) -> None:
    if req is not None:
        return  # the answer to our heartbeat
    # P5: a heartbeat nobody asked for is the module powering up (two, 50 ms apart).
    a.counts['unsolicited heartbeats'] += 1
    a.note_reboot(t, 'power-up heartbeat')


def _rx_trigger_request(a: FlightAnalysis, msg: p.TriggerRequest, t: float,
                        req: Optional[_Pending]) -> None:
    a.counts['trigger requests'] += 1
    seen = TriggerRequestSeen(t)
    a.requests.append(seen)
    a._undecided.append(seen)
    a.event(t, 'request', 'warn', 'the module asks to deploy (trigger request 0x39)')


def _oldest_undecided(a: FlightAnalysis, t: float) -> Optional[TriggerRequestSeen]:
    """Return the trigger request the next decision is about.

    Decisions come in the order of the requests: a newer request supersedes a deferred one,
    which is then decided (timed out) after the newer one was received (D8).
    """
    while a._undecided and (a._undecided[0].decision or t - a._undecided[0].t > REQUEST_STALE_S):
        a._undecided.popleft()
    return a._undecided[0] if a._undecided else None


def _rx_deploy_ack(a: FlightAnalysis, msg: p.DeployAck, t: float,
                   req: Optional[_Pending]) -> None:
    dep = a.current_deployment(t)
    if msg.success:
        a.counts['deploy acknowledgements'] += 1
        a.event(t, 'deploy', 'bad', 'module acknowledged the deploy (D4 01)')
        if dep is None:
            dep = a.open_deployment(t, 'ack', 'a deploy acknowledgement nobody was seen asking '
                                    'for (late, or the call was not recorded)')
        dep.step(t, 'ack', 'the module acknowledged: deploying (D4 01)')
        dep.outcome, dep.outcome_text = 'deployed', 'acknowledged by the module'
        a.band('armed', t, False)
    else:
        a.counts['deploys refused by the module'] += 1
        a.event(t, 'deploy', 'warn', 'module answered the deploy with D4 00: not deployed '
                '(locked, already triggered or in protection)')
        if dep is not None:
            dep.step(t, 'ack', 'the module answered D4 00: it did NOT deploy')
            dep.outcome, dep.outcome_text = 'refused', 'refused by the module (D4 00)'


def _rx_setting(a: FlightAnalysis, msg: Any, t: float, req: Optional[_Pending]) -> None:
    code = SETTING_REPLIES[type(msg)]
    key, name, unit, step = SETTING_NAMES[code]
    if req is not None and req.control == p.CTRL_SET:
        sent = a._set_sent.get(code)
        if sent is not None and not p.is_set_ack(msg, sent[1]):
            a.event(t, 'settings', 'bad', f'{name}: the module did not acknowledge '
                    f'{sent[1] * step:g}{unit} (answered {msg.value})')
            a._set_sent.pop(code, None)
        return
    a.setting_value(t, code, msg.value)
    sent = a._set_sent.pop(code, None)
    if sent is None:
        return
    wrote, read = round(sent[1] * step, 3), round(msg.value * step, 3)
    if msg.value == sent[1]:
        a.counts['settings written and verified'] += 1
        a.event(t, 'settings', 'ok', f'{name} {wrote:g}{unit} written and verified')
    else:
        a.counts['settings not verified'] += 1
        a.event(t, 'settings', 'bad', f'{name}: wrote {wrote:g}{unit}, the module reads back '
                f'{read:g}{unit}')


def _rx_flags(a: FlightAnalysis, msg: p.AutoTriggerFlags, t: float,
              req: Optional[_Pending]) -> None:
    before = dict(a.flags)
    a.flags = {'attitude': msg.attitude_enabled, 'freefall': msg.freefall_enabled}
    if req is not None and req.control == p.CTRL_SET:
        a.counts['settings written and verified'] += 1
        a.event(t, 'settings', 'ok', f'auto triggers set: attitude '
                f'{"on" if msg.attitude_enabled else "off"}, free fall '
                f'{"on" if msg.freefall_enabled else "off"}')
    elif before != a.flags and None not in before.values():
        a.event(t, 'settings', 'warn', f'auto triggers now: attitude '
                f'{"on" if msg.attitude_enabled else "off"}, free fall '
                f'{"on" if msg.freefall_enabled else "off"}')


def _rx_boot_count(a: FlightAnalysis, msg: p.BootCount, t: float,
                   req: Optional[_Pending]) -> None:
    a.boot_count(t, msg.count)


def _rx_baud(a: FlightAnalysis, msg: p.BaudRate, t: float, req: Optional[_Pending]) -> None:
    a.module_baud = msg.baud
    a.event(t, 'settings', 'warn', f'module baud rate set to {msg.baud or msg.code}')


def _rx_streaming(a: FlightAnalysis, msg: p.StreamingReply, t: float,
                  req: Optional[_Pending]) -> None:
    a.band('streaming', t, msg.enabled)


def _rx_armed(a: FlightAnalysis, msg: Any, t: float, req: Optional[_Pending]) -> None:
    a.band('armed', t, msg.armed)


def _rx_triggered(a: FlightAnalysis, msg: p.TriggeredState, t: float,
                  req: Optional[_Pending]) -> None:
    if msg.triggered:
        a.module_triggered(t, 'query')
        return
    a.band('triggered', t, False)
    dep = a.current_deployment(t)
    call = a._call
    if req is not None and dep is not None and call is not None and call.get('dep') is dep \
            and dep.first('frame') is not None:
        # The driver asks before any retry whether the missing acknowledgement hid a
        # deployment (D6).
        dep.step(t, 'query', 'the module answers it is NOT triggered (asked after the missing '
                 'acknowledgement)')


def _rx_record(a: FlightAnalysis, msg: p.TriggerRecord, t: float,
               req: Optional[_Pending]) -> None:
    a.trigger_record(t, msg)


def _rx_voltage(a: FlightAnalysis, msg: p.CellVoltage, t: float,
                req: Optional[_Pending]) -> None:
    v = msg.volts
    lo, hi, _ = a.cell_voltage or (v, v, v)
    a.cell_voltage = (min(lo, v), max(hi, v), v)


def _rx_charging(a: FlightAnalysis, msg: p.Charging, t: float, req: Optional[_Pending]) -> None:
    a.charging = msg.charging


def _rx_shutdown(a: FlightAnalysis, msg: p.ShutdownAck, t: float,
                 req: Optional[_Pending]) -> None:
    a.event(t, 'module', 'warn', 'the module announced it is switching off (0x12)')


def _rx_unknown(a: FlightAnalysis, msg: p.UnknownFrame, t: float,
                req: Optional[_Pending]) -> None:
    if msg.reason == 'trigger confirmation (host frame)' or msg.reason == 'host header':
        a.counts['echoes of host frames'] += 1
        return
    a.counts['frames of unknown meaning'] += 1
    a.event(t, 'link', 'info', f'frame of unknown meaning ({msg.reason}): '
            f'{msg.raw.hex(" ")}')


RX_MESSAGES: Dict[type, Callable[..., None]] = {
    p.Status: _rx_status,
    p.Heartbeat: _rx_heartbeat,
    p.TriggerRequest: _rx_trigger_request,
    p.DeployAck: _rx_deploy_ack,
    p.AttitudeThreshold: _rx_setting,
    p.FreefallThreshold: _rx_setting,
    p.FreefallTime: _rx_setting,
    p.LightThreshold: _rx_setting,
    p.AutoTriggerFlags: _rx_flags,
    p.BootCount: _rx_boot_count,
    p.BaudRate: _rx_baud,
    p.StreamingReply: _rx_streaming,
    p.ArmReply: _rx_armed,
    p.ArmedState: _rx_armed,
    p.TriggeredState: _rx_triggered,
    p.TriggerRecord: _rx_record,
    p.CellVoltage: _rx_voltage,
    p.Charging: _rx_charging,
    p.ShutdownAck: _rx_shutdown,
    p.UnknownFrame: _rx_unknown,
}
"""Typed received message -> what it means for the report."""


# ---------------------------------------------------------------------------------------------
# Sent frames: command code -> handler(analysis, frame, t)
# ---------------------------------------------------------------------------------------------

def _tx_deploy(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    if frame.value != 1:
        return
    a.counts['deploy frames sent'] += 1
    dep = a.current_deployment(t)
    if dep is None or dep.origin != 'call':
        dep = a.open_deployment(t, 'frame', 'a deploy frame the black box shows no decision '
                                'for', 'unknown (no record of who decided)')
    dep.attempts = max(dep.attempts, 1)
    dep.step(t, 'frame', f'deploy frame on the wire ({frame.raw.hex(" ")})')
    a.event(t, 'deploy', 'warn', 'deploy frame sent (42 61 11 02 01)')


def _tx_confirm(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    if frame.data != p.CONFIRM_PAYLOAD:
        return
    a.counts['confirmations sent'] += 1
    req = _oldest_undecided(a, t)
    if req is not None and req.t_confirm is None:
        req.t_confirm = t
        if req.deployment is not None:
            req.deployment.step(t, 'frame', 'confirmation frame on the wire (42 61 39 a5 01)')
    a.event(t, 'request', 'warn', 'confirmation sent (42 61 39 a5 01)')


def _tx_setting(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    if frame.data[0] != p.CTRL_SET:
        return
    code = frame.code
    key, name, unit, step = SETTING_NAMES[code]
    a._set_sent[code] = (t, frame.value)
    a.counts['settings written'] += 1


def _tx_auto_trigger(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    if frame.data[0] == p.CTRL_SET:
        a.counts['settings written'] += 1


def _tx_arm(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    a.counts['arm frames sent' if frame.value == 1 else 'lock frames sent'] += 1


def _tx_shutdown(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    a.event(t, 'calls', 'warn', 'shutdown frame sent to the module')


def _tx_baud(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    if frame.data[0] == p.CTRL_SET:
        a.event(t, 'settings', 'warn', f'baud rate change sent (code {frame.value})')


TX_COMMANDS: Dict[int, Callable[[FlightAnalysis, p.Frame, float], None]] = {
    p.CMD_DEPLOY: _tx_deploy,
    p.CMD_TRIGGER_REQUEST: _tx_confirm,
    p.CMD_ATTITUDE_THRESHOLD: _tx_setting,
    p.CMD_FREEFALL_THRESHOLD: _tx_setting,
    p.CMD_FREEFALL_TIME: _tx_setting,
    p.CMD_LIGHT_THRESHOLD: _tx_setting,
    p.CMD_ATTITUDE_TRIGGER: _tx_auto_trigger,
    p.CMD_FREEFALL_TRIGGER: _tx_auto_trigger,
    p.CMD_ARM: _tx_arm,
    p.CMD_SHUTDOWN: _tx_shutdown,
    p.CMD_BAUD_RATE: _tx_baud,
}
"""Command code of a sent frame -> what it means for the report."""


# ---------------------------------------------------------------------------------------------
# Decisions: ``what`` -> handler(analysis, record, t)
# ---------------------------------------------------------------------------------------------

def _ms(value: Any) -> Optional[float]:
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        return float(value)
    return None


def _call_deployment(a: FlightAnalysis, t: float) -> Deployment:
    """Return the running ~/deploy call's deployment, opened at its first decision to send."""
    call = a._call
    if call is not None and call.get('dep') is not None:
        return call['dep']
    if call is None:
        # No record of the call (the file begins during it): the call deployment going on.
        dep = a.current_deployment(t)
        if dep is not None and dep.origin == 'call':
            return dep
    t_call = call['t'] if call else t
    who = 'a ~/deploy service call'
    if call and call.get('arm_if_locked'):
        who += ' (arm_if_locked: arm first if locked)'
    dep = a.open_deployment(t_call, 'call', 'a ~/deploy service call (a person or the flight '
                            'software asked for it)', who)
    dep.outcome = 'requested'
    if call is not None:
        call['dep'] = dep
        dep.step(t_call, 'call', '~/deploy called with the confirmation token')
        if call.get('armed_at') is not None:
            dep.step(call['armed_at'], 'arm', 'armed first (arm_if_locked), verified by query')
    return dep


def _decision_send(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    dep = _call_deployment(a, t)
    attempt = record.get('attempt')
    dep.attempts = max(dep.attempts, attempt if isinstance(attempt, int) else 1)
    dep.step(t, 'decision', f'the driver decided to send the deploy frame (attempt '
             f'{attempt if attempt is not None else "?"}, on disk before the frame)')


def _decision_unacked(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    # An older driver said so itself. Its frame's request is over (lost) however soon it stops.
    dep = _call_deployment(a, t)
    before = a.counts['deploy frames unacknowledged']
    a._expire(t, expect='DeployAck')
    if a.counts['deploy frames unacknowledged'] == before:  # no request record of the frame
        a.counts['deploy frames unacknowledged'] += 1
        dep.step(t, 'noack', f'no acknowledgement of attempt {record.get("attempt", "?")}')
        a.event(t, 'deploy', 'warn', f'deploy attempt {record.get("attempt", "?")} not '
                'acknowledged')
    if dep.outcome in ('requested', 'unknown'):
        dep.outcome, dep.outcome_text = 'unknown', 'no acknowledgement: outcome not known'


def _decision_acked(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    dep = _call_deployment(a, t)
    dep.latency_ms = _ms(record.get('latency_ms'))
    dep.latency_what = 'from the ~/deploy call to the acknowledgement'
    if isinstance(record.get('attempts'), int):
        dep.attempts = record['attempts']
    dep.outcome, dep.outcome_text = 'deployed', 'acknowledged by the module'
    dep.step(t, 'decided', 'the driver recorded the acknowledgement'
             + (f' ({dep.latency_ms:.1f} ms after the call, by the driver\'s clock)'
                if dep.latency_ms is not None else ''))
    a.counts['deploy calls acknowledged'] += 1


def _decision_module_refused(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    dep = _call_deployment(a, t)
    dep.outcome, dep.outcome_text = 'refused', 'refused by the module (D4 00)'


DEPLOY_OUTCOMES: Dict[str, Tuple[str, str]] = {
    'deployed': ('deployed', 'bad'),
    'not deployed': ('not deployed', 'warn'),
    'unknown': ('unknown', 'unknown'),
    'refused': ('refused', 'warn'),
    'already deployed': ('already deployed', 'info'),
    'failed': ('failed', 'bad'),
    'acknowledged': ('deployed', 'bad'),
    'success': ('deployed', 'bad'),
}
"""A deploy call's ``outcome`` (D10) -> (the deployment's outcome, how its event is drawn)."""
_REASON_PREFIXES = ('deploy refused: ', 'deployed: ', 'already deployed: ',
                    'deploy outcome UNKNOWN: ')
"""Words the driver's reasons begin with that only repeat the outcome."""


def _reason(record: Dict[str, Any]) -> str:
    text = str(record.get('reason') or record.get('message') or '')
    for prefix in _REASON_PREFIXES:
        if text.startswith(prefix):
            return text[len(prefix):]
    return text


def _decision_deploy(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    """Read ``what: deploy``: how a ~/deploy call ended (D10), or an unknown one later (D12)."""
    if 'resolved' in record:
        _deploy_resolved(a, record, t)
        return
    call, a._call = a._call, None
    dep = call.get('dep') if call else None
    if call is None:
        current = a.current_deployment(t)
        if current is not None and current.origin == 'call' and not current.first('outcome'):
            dep = current
    reason = _reason(record)
    outcome = record.get('outcome')
    if outcome is None:
        # An older driver: a call that did not succeed, its outcome not named.
        if record.get('success') is not False:
            a.event(t, 'deploy', 'info', f'deploy decision: {describe_fields(record)}')
            return
        if dep is None:
            outcome = 'refused'
        elif dep.outcome == 'refused':
            outcome = 'refused'  # the module answered D4 00
        elif dep.first('noack') is not None or dep.first('frame') is not None:
            outcome = 'unknown'  # frames left, nothing came back, and it never asked
        else:
            outcome = 'failed'
    known, level = DEPLOY_OUTCOMES.get(str(outcome), (str(outcome), 'unknown'))
    if dep is None and known in ('refused', 'already deployed', 'failed'):
        # Nothing went out: a call answered, not a deployment.
        if known == 'already deployed':
            a.counts['deploy calls answered already deployed'] += 1
            a.event(t, 'calls', 'info', f'~/deploy: already deployed ({short(reason, 120)})')
        else:
            a.counts['deploy calls refused'] += 1
            a.event(t, 'calls', 'warn', f'~/deploy refused: {short(reason, 140)}')
        return
    if dep is None:
        dep = _call_deployment(a, t)
    # The call is over: a deploy frame still waiting was not acknowledged (cut short when the
    # call ended on a dropped link or a stop, whose outcome is unknown).
    a._expire(t, reason='when the deploy call ended' if known == 'unknown' else '',
              expect='DeployAck')
    if dep.outcome == 'refused' and known == 'not deployed':
        text = f'the module refused the deploy frame; {reason}'
    else:
        text = reason or f'outcome {known}'
    dep.outcome, dep.outcome_text = known, text
    if record.get('ack') == 'lost':
        a.counts['deploy acknowledgements lost'] += 1
    dep.step(t, 'outcome', f'the call ended: {known}')
    if known == 'unknown':
        a.counts['deploys with unknown outcome'] += 1
        a._unknown_dep = dep
        a.band('triggered', t, None)  # not known until the module is heard again
    a.event(t, 'deploy', level, f'deploy call ended: {known}: {short(reason, 120)}')


def _deploy_resolved(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    """Read what became of a deploy whose outcome was unknown, as the driver learned it (D12)."""
    known, level = DEPLOY_OUTCOMES.get(str(record.get('outcome')),
                                       (str(record.get('outcome')), 'unknown'))
    how = short(record.get('resolved', ''), 80)
    dep, a._unknown_dep = a._unknown_dep, None
    a.counts['unknown deploy outcomes resolved'] += 1
    if dep is not None:
        ended = dep.first('outcome')
        later = f', {t - ended.t:.2f} s after the call ended' if ended is not None else ''
        dep.outcome_text = (f'unknown when the call ended ({dep.outcome_text}); then read: '
                            f'{known} ({how}{later})')
        dep.outcome = known
        dep.step(t, 'resolved', f'the driver read the outcome: {known} ({how})')
    a.event(t, 'deploy', level, f'the earlier deploy of unknown outcome: {known} ({how})')


def _decision_trigger_request(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    decision = str(record.get('decision', '?'))
    req = _oldest_undecided(a, t)
    if req is None:
        # A decision with no request frame before it (an older black box without frames).
        req = TriggerRequestSeen(t)
        a.requests.append(req)
        a.counts['trigger requests'] += 1
    req.decision, req.policy = decision, str(record.get('policy', ''))
    req.reason = str(record.get('reason', ''))
    req.latency_ms = _ms(record.get('latency_ms'))
    req.t_decision = t
    a.counts[f'trigger requests {decision}'] += 1
    latency = f', {req.latency_ms:.2f} ms' if req.latency_ms is not None else ''
    level = 'bad' if decision == 'confirmed' else 'warn'
    by = f' by policy {req.policy}' if req.policy else ''
    a.event(t, 'request', level, f'trigger request {decision.upper()}{by}{latency}: '
            f'{short(req.reason, 100)}')
    if decision == 'confirmed':
        if req.reason.startswith('policy changed'):
            who = (f'the change of trigger_request_policy to {req.policy!r} while the request '
                   'was held (D8)')
        elif req.reason.startswith('answered'):
            who = ('a person or program answering ~/answer_trigger_request (policy '
                   f'{req.policy})')
        else:
            who = f'policy {req.policy!r} (the driver, at once)'
        dep = a.open_deployment(req.t, 'request', 'the module asked to deploy (trigger request '
                                '0x39: its crash detection fired on external power)', who)
        dep.outcome = 'requested'
        dep.latency_ms = req.latency_ms
        dep.latency_what = 'from the trigger request to the confirmation written'
        dep.step(req.t, 'request', 'trigger request received from the module')
        if req.deferred:
            dep.step(req.t, 'defer', 'deferred to ~/answer_trigger_request')
        dep.step(t, 'decision', f'confirmed ({req.reason})')
        if req.t_confirm is not None:
            dep.step(req.t_confirm, 'frame', 'confirmation frame on the wire')
        req.deployment = dep


def _decision_deferred(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    req = a._undecided[-1] if a._undecided else None  # the request just received
    if req is not None and not req.decision:
        req.deferred = True
    a.event(t, 'request', 'info', 'trigger request deferred: waiting up to '
            f'{record.get("deadline_s", "?")} s for ~/answer_trigger_request')


def _decision_policy(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    policy = str(record.get('policy', '?'))
    if len(a.policy_changes) < 100:
        a.policy_changes.append((t, policy))
    a.event(t, 'settings', 'warn', f'trigger_request_policy changed to {policy}')


def _decision_settings_refused(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    a.counts['settings changes refused (would deploy)'] += 1
    a.event(t, 'settings', 'warn', 'settings change refused, nothing written (D16): '
            f'{short(record.get("reason", ""), 140)}')


def _decision_preflight(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    ok = record.get('ok') is True
    checks = record.get('checks')
    lines = [str(c) for c in checks[:40]] if isinstance(checks, list) else []
    failed = [line[4:].strip() for line in lines if line.startswith('FAIL')]
    a.counts['preflight checks'] += 1
    if not ok:
        a.counts['preflight checks NO-GO'] += 1
    a.preflight = (t, ok, lines)
    if ok:
        text = f'~/preflight_check: GO ({len(lines)} checks OK)'
    else:
        text = '~/preflight_check: NO-GO: ' + '; '.join(failed)
    a.event(t, 'calls', 'ok' if ok else 'bad', short(text, 200))


def _decision_release_gate(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    route = record.get('route', '?')
    if record.get('called') is False:
        text = f'release gate not called for the {route}: {record.get("reason", "")}'
    elif record.get('success') is True:
        text = f'release gate for the {route}: {record.get("message", "")}'
    else:
        text = (f'release gate for the {route} gave no go ({record.get("message", "")}): '
                'released anyway')
    a.event(t, 'deploy', 'ok' if record.get('success') is True else 'warn', short(text, 200))


def _decision_other(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    what = str(record.get('what'))
    a._unknown(a.unknown_whats, ('decision', what), record)
    level = 'unknown'
    if 'deploy' in what:
        a.event(t, 'deploy', level, f'deploy decision {what!r}: {describe_fields(record)}')
    else:
        a.event(t, 'other', level, f'decision {what!r}: {describe_fields(record)}')


DECISIONS: Dict[str, Callable[[FlightAnalysis, Dict[str, Any], float], None]] = {
    'deploy: sending the deploy frame': _decision_send,
    'deploy unacknowledged': _decision_unacked,
    'deploy acknowledged': _decision_acked,
    'deploy refused by module': _decision_module_refused,
    'deploy': _decision_deploy,
    'trigger request': _decision_trigger_request,
    'trigger request deferred': _decision_deferred,
    'policy': _decision_policy,
    'settings refused': _decision_settings_refused,
    'preflight': _decision_preflight,
    'release gate': _decision_release_gate,
}
"""``decision`` records by their ``what``; any other ``what`` is shown as it is."""


# ---------------------------------------------------------------------------------------------
# State records: field -> handler(analysis, record, t)
# ---------------------------------------------------------------------------------------------

def _state_port(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    up = bool(record['port_open'])
    reason = short(record.get('reason', ''), 120)
    seen_before, a._port_seen = a._port_seen, a._port_seen or up
    a.band('port', t, up)
    if up:
        a.counts['port opened'] += 1
        a._reread_why = a._reread_why or ('the reconnect' if seen_before else
                                          'the port opened')
        if seen_before:
            a.counts['reconnects'] += 1
            a.event(t, 'link', 'ok', f'port open again (reconnect): {reason}')
        else:
            a.event(t, 'link', 'info', f'port open: {reason}')
    else:
        a.counts['port closed'] += 1
        a._expire(t, reason='before the port closed')
        a.band('online', t, False)
        a.band('streaming', t, None)
        a.event(t, 'link', 'bad', f'port closed: {reason}')


def _state_online(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    online = bool(record['online'])
    was = a.bands['online'].value
    a.band('online', t, online)
    if not online:
        a.counts['offline'] += 1
        a.event(t, 'link', 'bad', f'module OFFLINE: {short(record.get("reason", ""), 140)}')
    else:
        if was is False:
            a._reread_why = a._reread_why or 'the module came back online'
        a.event(t, 'link', 'ok', 'module online')


def _state_armed(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    armed = bool(record['armed'])
    via = record.get('via', '')
    a.band('armed', t, armed)
    if via in ('arm', 'lock'):
        call = a._call
        for_deploy = via == 'arm' and call is not None and call.get('dep') is None
        if for_deploy:
            call['armed_at'] = t  # arm_if_locked: a step of the deployment that follows
        a.event(t, 'calls', 'ok' if armed == (via == 'arm') else 'bad',
                f'{"ARMED" if armed else "locked"} (verified by query after '
                f'{"~/deploy with arm_if_locked" if for_deploy else "~/arm"})')
    elif via in ('status', 'poll', 'query'):
        a.event(t, 'deploy', 'info', f'module now {"armed" if armed else "locked"} '
                f'({"status frame" if via == "status" else via})')


def _state_triggered(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    if record['triggered']:
        a.module_triggered(t, f'driver: via {record.get("via", "?")}')
    else:
        a.band('triggered', t, False)


def _state_event(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    text = str(record['event'])
    handler = STATE_EVENTS.get(text)
    if handler is not None:
        handler(a, record, t)
    elif 'reboot' in text:
        a.note_reboot(t, text)
    else:
        a.event(t, 'module', 'info', f'{text}' + (
            f' ({describe_fields(record, COMMON_FIELDS | {"event"})})'
            if len(record) > 4 else ''))


def _state_initialized(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    count = record.get('boot_count')
    mismatch = record.get('mismatch') or []
    a.last_mismatch = list(mismatch) if isinstance(mismatch, list) else [mismatch]
    a.counts['initializations'] += 1
    why, a._reread_why = a._reread_why, ''
    # Armed and triggered are not trusted until read again after any of these (D15).
    head = f'module read afresh after {why}' if why else 'module read afresh'
    head += f' (boot #{count}): armed, triggered and settings read'
    if mismatch:
        a.event(t, 'module', 'bad', f'{head}; settings do NOT match: '
                f'{short("; ".join(map(str, a.last_mismatch)), 140)}')
    else:
        a.event(t, 'module', 'ok', f'{head}, settings as desired')


def _state_reboot(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    a.note_reboot(t, 'the driver saw the power-up heartbeat')


def _state_zeroed(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    ok = record.get('success') is not False
    a.event(t, 'calls', 'ok' if ok else 'bad', 'attitude sensor zeroed at the present mounting '
            '(~/zero_sensor)' if ok else '~/zero_sensor: the module did not confirm the zeroing')


def _state_shut_down(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    a.counts['module shut down by request'] += 1
    a.event(t, 'module', 'warn', 'module switched off by ~/shutdown_module')


STATE_EVENTS: Dict[str, Callable[[FlightAnalysis, Dict[str, Any], float], None]] = {
    'initialized': _state_initialized,
    'module reboot (unsolicited heartbeat)': _state_reboot,
    'sensor zeroed': _state_zeroed,
    'module shut down by request': _state_shut_down,
}
"""``state`` records with an ``event``, by its text; another text is shown as it is."""

STATE_FIELDS: Tuple[Tuple[str, Callable[[FlightAnalysis, Dict[str, Any], float], None]], ...] = (
    ('port_open', _state_port),
    ('online', _state_online),
    ('armed', _state_armed),
    ('triggered', _state_triggered),
    ('event', _state_event),
)
"""``state`` records by the fields they carry (one record may carry several)."""


# ---------------------------------------------------------------------------------------------
# Kinds
# ---------------------------------------------------------------------------------------------

def _kind_start(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    params = record.get('config')
    if not isinstance(params, dict):
        params = record.get('parameters')  # older drivers
    run = {'t': t, 'port': record.get('port'), 'baud': record.get('baud'),
           'parameters': dict(params) if isinstance(params, dict) else {},
           'file': a.file}
    if len(a.runs) < 100:
        a.runs.append(run)
    a.counts['driver starts'] += 1
    a._port_seen = False
    a._link_counters = {}  # a new driver's counters start at zero
    a._bb_lost = 0
    a._reread_why = ''
    a._undecided.clear()
    timeout = run['parameters'].get('request_timeout_s')
    a.reply_timeout_s = float(timeout) if isinstance(timeout, (int, float)) and \
        not isinstance(timeout, bool) and 0.0 < timeout <= 10.0 else REPLY_TIMEOUT_S
    policy = run['parameters'].get('trigger_request_policy')
    if policy and len(a.policy_changes) < 100:
        a.policy_changes.append((t, str(policy)))
    for name in BANDS:
        a.band(name, t, None)  # nothing is known until the driver has learned it
    a.band('blackbox', t, True)
    a.event(t, 'blackbox', 'info', f'driver started on {run["port"]} at {run["baud"]} baud'
            + (f', policy {policy}' if policy else ''))


def _kind_stop(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    a._expire(t, reason='before the driver stopped')
    a.event(t, 'blackbox', 'info', 'driver stopped (black box closed)')
    for name in BANDS:
        a.band(name, t, None)  # nobody watches until the next start


def _kind_frame(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    a.frame(record, t)


_CALL_TEXT = {
    'arm': '~/arm true', 'lock': '~/arm false', 'set_thresholds': '~/set_thresholds',
    'set_auto_triggers': '~/set_auto_triggers',
}


def _kind_request(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    if 'hex' in record:
        a.request_sent(record, t)
        return
    what = str(record.get('what', '?'))
    a.counts[f'service calls: {what}'] += 1
    if what == 'deploy':
        token_ok = record.get('token_ok')
        a._call = {'t': t, 'token_ok': token_ok, 'arm_if_locked': record.get('arm_if_locked'),
                   'dep': None}
        a.counts['deploy calls'] += 1
        a.event(t, 'calls', 'warn', '~/deploy called' + (
            '' if token_ok is not False else ' with a WRONG confirmation token')
            + (' (arm_if_locked)' if record.get('arm_if_locked') else ''))
        return
    detail = describe_fields(record, COMMON_FIELDS | {'what'})
    a.event(t, 'calls', 'info', f'{_CALL_TEXT.get(what, what)} called'
            + (f' ({detail})' if detail else ''))


def _kind_decision(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    handler = DECISIONS.get(str(record.get('what')), _decision_other)
    handler(a, record, t)


def _kind_state(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    handled = False
    for name, handler in STATE_FIELDS:
        if name in record:
            handler(a, record, t)
            handled = True
    if not handled:
        a.event(t, 'other', 'unknown', f'state: {describe_fields(record)}')


def _kind_parameter(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    """Read a parameter set: all or nothing, module settings written and verified first (D4)."""
    accepted = record.get('accepted')
    reason = str(record.get('reason') or '')
    changes = record.get('changes')
    if isinstance(changes, dict):
        what = ', '.join(f'{k} := {short(v, 30)}' for k, v in changes.items()) or 'nothing'
    else:  # an older driver: one record per parameter
        what = f'{record.get("name", "?")} := {short(record.get("value", "?"), 30)}'
    a.counts['parameter changes' if accepted else 'parameter changes refused'] += 1
    a.event(t, 'calls', 'ok' if accepted else 'bad',
            f'parameters {short(what, 100)}: {"accepted" if accepted else "REFUSED"}'
            + (f' ({short(reason, 140)})' if reason else ''))
    if '; put back ' in reason:
        names = reason.split('; put back ', 1)[1].split(';')[0]
        a.counts['settings put back'] += len(names.split(', '))
        a.event(t, 'settings', 'warn', f'put back after the refused set: {names}')
    if 'could NOT put back' in reason:
        a.counts['settings not put back'] += 1
        a.event(t, 'settings', 'bad', 'a refused parameter set left the module changed: could '
                f'NOT put back {short(reason.split("could NOT put back", 1)[1], 120)}')


def _kind_trigger_event(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    source = str(record.get('source', 'unknown'))
    via = record.get('via')
    via_text = (VIA_NAMES.get(via, str(via)) if isinstance(via, (int, str)) else
                'unknown' if via is None else short(via, 40))
    a.counts['trigger events'] += 1
    # The driver publishes one trigger event per deployment, possibly after fetching the record
    # for a while: it belongs to the last deployment even if the module rebooted meanwhile.
    dep = a._deployment
    if dep is not None and (t - dep.last_t > DEPLOYMENT_WINDOW_S or dep.first('event')):
        dep = None
    unknown = a._unknown_dep
    if dep is None and unknown is not None and not unknown.first('event'):
        dep = unknown  # a deploy of unknown outcome did go out (D12)
    if dep is None:
        dep = a.open_deployment(t, 'event', f'the driver learned of a deployment from '
                                f'{via_text}', 'the module (no host decision seen)')
        dep.outcome, dep.outcome_text = 'deployed', 'reported by the driver\'s trigger event'
    dep.source = source if source != 'unknown' or not dep.source else dep.source
    raw = record.get('record')
    if isinstance(raw, str) and raw:
        try:
            decoded = p.decode_module_frame(p.parse_frame(bytes.fromhex(raw)))
        except (p.ProtocolError, ValueError, IndexError):
            decoded = None
        if isinstance(decoded, p.TriggerRecord):
            a.trigger_record(t, decoded)
            dep.record = dep.record or record_text(decoded)
    dep.step(t, 'event', f'trigger event published: source {source}, learned from {via_text}')
    a.event(t, 'deploy', 'bad', f'PARACHUTE DEPLOYED: source {source} (learned from '
            f'{via_text})')


def _int_field(record: Dict[str, Any], names: Tuple[str, ...]) -> Optional[int]:
    values = [record[n] for n in names if isinstance(record.get(n), int)
              and not isinstance(record.get(n), bool)]
    return max(values) if values else None


def _kind_link(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    """Read the driver's link counters (cumulative for its run), recorded when one changed."""
    deltas: Dict[str, int] = {}
    for name in LINK_COUNTERS:
        value = _int_field(record, (name,))
        if value is None:
            continue
        before = a._link_counters.get(name, 0)
        deltas[name] = value - before if value >= before else value  # a new run's counters
        a._link_counters[name] = value
    checksum, noise = deltas.get('checksum_errors', 0), deltas.get('bytes_discarded', 0)
    a.counts['checksum errors'] += checksum
    a.counts['bytes of noise discarded'] += noise
    a.counts['request timeouts (as the driver counted)'] += deltas.get('timeouts', 0)
    if checksum or noise:
        # Such frames never reach the black box: the driver's decoder counted them.
        parts = ([f'{checksum} frame(s) with a bad checksum'] if checksum else []) + \
            ([f'{noise} byte(s) of noise'] if noise else [])
        a.event(t, 'link', 'warn', ' and '.join(parts) + ' discarded (the driver\'s decoder '
                'counted them)')


def _kind_blackbox(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    """Read the black box's own health: an outage it recovered from, the records it lost."""
    lost = _int_field(record, ('lost', 'lost_records', 'records_lost', 'dropped',
                               'dropped_records', 'errors'))
    if lost is not None and lost > a._bb_lost:
        a.counts['black-box records lost'] += lost - a._bb_lost
        a._bb_lost = lost
    error = short(record.get('error') or record.get('reason') or '', 120)
    a.counts['black-box write failures'] += 1
    if record.get('event') != 'writing again':
        a.event(t, 'blackbox', 'bad', f'black-box problem: {describe_fields(record)}')
        return
    since = _ms(record.get('failed_at'))
    since = max(since, a.t0) if since is not None and since <= t else None
    if since is not None:
        a.band('blackbox', since, False)
        a.event(since, 'blackbox', 'bad', f'black box stopped writing: {error}')
    a.band('blackbox', t, True)
    outage = _int_field(record, ('lost_in_outage',))
    a.event(t, 'blackbox', 'warn', 'black box writing again'
            + (f' after {t - since:.1f} s' if since is not None else '')
            + (f': {outage} records lost' if outage is not None else '')
            + (f' ({lost} in this run)' if lost is not None else ''))


RULES: Dict[str, Rule] = {rule.kind: rule for rule in (
    Rule('start', frozenset({'port', 'baud', 'config', 'parameters'}), _kind_start),
    Rule('stop', frozenset(), _kind_stop),
    Rule('frame', frozenset({'dir', 'hex'}), _kind_frame),
    Rule('request', frozenset({'hex', 'expect', 'what', 'token_ok', 'arm_if_locked', 'values',
                               'attitude', 'freefall'}), _kind_request),
    Rule('decision', frozenset({'what', 'decision', 'policy', 'reason', 'latency_ms',
                                'attempt', 'attempts', 'hex', 'success', 'deadline_s',
                                'outcome', 'message', 'resolved', 'ack', 'ok', 'checks'}),
         _kind_decision),
    Rule('state', frozenset({'port_open', 'reason', 'online', 'armed', 'via', 'triggered',
                             'event', 'boot_count', 'mismatch', 'success'}), _kind_state),
    Rule('parameter', frozenset({'changes', 'accepted', 'reason', 'name', 'value'}),
         _kind_parameter),
    Rule('trigger_event', frozenset({'source', 'via', 'record'}), _kind_trigger_event),
    Rule('link', frozenset(LINK_COUNTERS), _kind_link),
    Rule('blackbox', frozenset({'event', 'error', 'failed_at', 'lost', 'lost_in_outage',
                                'errors', 'lost_records', 'what', 'reason'}), _kind_blackbox),
    # Kinds no driver wrote yet, with the names a newer one would likely use.
    Rule('blackbox_error', frozenset({'error', 'errors', 'lost', 'lost_records'}),
         _kind_blackbox),
    generic_rule('preflight', 'calls', 'preflight check',
                 fields=('check', 'ok', 'result', 'message', 'checks')),
    generic_rule('settings', 'settings', 'settings', fields=('written', 'verified', 'values')),
    generic_rule('policy', 'settings', 'policy', 'warn', fields=('policy', 'reason', 'by')),
    generic_rule('note', 'other', 'note', fields=('text', 'message')),
)}
"""Record kind -> rule. Add a kind here (``generic_rule`` when it only needs showing)."""
