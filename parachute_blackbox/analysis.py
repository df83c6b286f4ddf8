"""What a black box says happened: records turned into a flight's events, series and states.

``FlightAnalysis.feed()`` takes the records of ``read.FlightFiles`` one at a time and keeps only
bounded state (``containers``), so a black box of any size fits in memory:

- time series (tilt, acceleration) as min/max per time bucket; state bands (port open, online,
  streaming, armed, triggered) as the states seen per bucket. Buckets double their width when
  there would be more than ``MAX_BUCKETS`` of them.
- events (one lane each: service calls, trigger requests, deployments, module, settings, link,
  black box, other) as the first and last few hundred per lane plus a count per bucket; every
  count is complete.
- deployments, each with its chain of steps and their times (request or call, decision, frame,
  acknowledgement or unknown outcome, the module's triggered flag, the trigger event).

What a record means is looked up in tables: ``records.RULES`` by the record's ``kind``, and
below it ``decisions.DECISIONS`` by ``what``, ``records.STATE_FIELDS`` by field
(``STATE_EVENTS`` by a state's ``event``), ``frames.RX_MESSAGES`` by the type
``protocol.decode_module_frame`` gives a received frame and ``frames.TX_COMMANDS`` by the
command code of a sent one. Adding a kind is one entry in ``RULES``. A kind or a field that no
table knows is counted and listed, never fatal. The records are in ``docs/protocols.md`` (D10,
D12, D17, D18). No ROS here.
"""

from __future__ import annotations

import collections
from typing import Any, Deque, Dict, List, Optional, Tuple

from dps_parachute_ros import protocol as p
from parachute_blackbox.containers import (Deployment, Event, EventLog, Pending, Series, Track,
                                           TriggerRequestSeen, Zoom)
from parachute_blackbox.frames import RX_MESSAGES, TX_COMMANDS
from parachute_blackbox.names import (BANDS, COMMAND_NAMES, COMMON_FIELDS, DEPLOYMENT_WINDOW_S,
                                      describe_fields, KEEP_EVENTS, LANES, MAX_DEPLOYMENTS,
                                      MAX_RECORDS_KEPT, MAX_ZOOMS, REBOOT_RECORD_DELAY_S,
                                      REBOOT_SAME_S, RECORD_GAP_S, record_text, REPLY_MARGIN_S,
                                      REPLY_TIMEOUT_S, SETTING_NAMES, short, source_text,
                                      ZOOM_AFTER_S, ZOOM_BEFORE_S, ZOOM_MAX_SAMPLES)
from parachute_blackbox.records import RULES


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
        self._pending: Dict[str, Deque[Pending]] = {}
        self._pending_by_hex: Dict[str, Pending] = {}
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
        self._heartbeat_at: Optional[float] = None    # first power-up heartbeat not yet claimed
        # A boot count read between a power-up heartbeat and the driver's record of that reboot
        # (its reader can be slow to write it) already counts that reboot as seen.
        self._reboot_counted_early = False
        # Where that early count would leave a reboot unseen if the record says "late heartbeat,
        # not a reboot" instead: (when, previous, count) of the boot count read.
        self._early_doubt: Optional[Tuple[float, int, int]] = None
        self._last_heartbeat: Optional[float] = None  # the last unsolicited heartbeat frame

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

    def _deploy_unanswered(self, req: Pending, t: float) -> None:
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
        req = Pending(t, hex_text, raw[2] if len(raw) > 2 else -1,
                      raw[3] if len(raw) > 3 else -1, expect, self.file, self.line)
        self._pending.setdefault(expect, collections.deque()).append(req)
        self._pending_by_hex[hex_text] = req
        self._pending_n += 1

    def _answered(self, msg: Any, t: float) -> Optional[Pending]:
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

    def power_up_heartbeat(self, t: float) -> None:
        """Note an unsolicited heartbeat frame (P5): where the driver's reboot record points.

        It is not counted as a reboot here: the driver judges which heartbeats are one power-up
        (two, 50 ms apart) and records each reboot once, after handling the frame; how long
        after depends on the host's load. Its first frame only places that record in time.
        """
        self.counts['unsolicited heartbeats'] += 1
        previous, self._last_heartbeat = self._last_heartbeat, t
        if previous is None or t - previous >= REBOOT_SAME_S:
            self._heartbeat_at = t

    def driver_saw_reboot(self, t: float) -> None:
        """Take the driver's record of a reboot: one per reboot, at its heartbeat's time (D3)."""
        at, self._heartbeat_at = self._heartbeat_at, None
        if at is not None and not 0.0 <= t - at <= REBOOT_RECORD_DELAY_S:
            at = None  # no heartbeat frame just before it (a lost record): the record's time
        early, self._reboot_counted_early = self._reboot_counted_early, False
        self.note_reboot(t, 'the driver saw the power-up heartbeat', at=at)
        if early:
            self._reboots_unread -= 1  # the boot count read before this record took it in

    def driver_doubted_reboot(self, t: float) -> None:
        """Take the driver's record of a late power-up heartbeat (``MAYBE_REBOOT``).

        It is a reboot only if the boot count says so.
        """
        self._heartbeat_at = None
        early, self._reboot_counted_early = self._reboot_counted_early, False
        doubt, self._early_doubt = self._early_doubt, None
        self.event(t, 'module', 'info', 'unsolicited heartbeat late (the power-up\'s second, or '
                   'another reboot: the boot count tells); the module read afresh')
        if early and doubt is not None:
            # The boot count read before this record counted its heartbeat as a reboot seen.
            when, previous, count = doubt
            self.note_reboot(when, f'1 reboot(s) not seen as they happened: boot count '
                             f'{previous} → {count}')
            self._reboots_unread -= 1  # that boot count read took it in

    def note_reboot(self, t: float, evidence: str, level: str = 'warn',
                    at: Optional[float] = None) -> None:
        """Note a module reboot (the driver's record of one, or a boot count beyond those seen).

        ``at``: when it happened, if before the record at ``t`` that tells of it.
        """
        when = t if at is None else at
        self._reboots_unread += 1
        self.reboots.append(when)
        if len(self.reboots) > 1000:
            del self.reboots[:500]
        self.counts['reboots'] += 1
        self._reread_why = 'the reboot'
        self.event(when, 'module', level, f'module rebooted ({evidence})')
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
        pending = self._heartbeat_at
        if pending is not None and 0.0 <= t - pending <= REBOOT_RECORD_DELAY_S \
                and not self._reboot_counted_early:
            # A power-up heartbeat whose reboot record is still to come: that reboot is seen.
            seen += 1
            self._reboot_counted_early = True
        # Each power-up adds one (wrapping after 255); reboots nobody saw are added here.
        unseen = ((count - previous) & 0xFF) - seen
        self._early_doubt = (t, previous, count) if self._reboot_counted_early \
            and unseen >= 0 else None
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
