"""Deployments as events: the triggered state, one ``~/trigger_event`` per deployment (D7).

Its source comes from the trigger records; when it is learnt later, the event is amended.

Part of `ParachuteSession` (``dps_parachute_ros.session`` assembles it; the shared state and the
lock are described there). Threads:

- every thread that reads the triggered state (the reader's status frames, the worker's
  initialization and poll, a deploy) takes it through ``_set_triggered``.
- worker: ``_trigger_job`` (``trigger`` job) reads the record of a deployment and reports it;
  ``_retry_records`` fetches records still owed; ``_report_at_init`` reports deployments that
  happened while nobody watched.
- callers: a deploy acknowledged reports its deployment (``_report``).

Owns, guarded by ``_lock``: ``_reported_boots``, ``_known_records``, ``_records_from_boot``,
``_triggered_seen``, ``_events``, ``_source_owed``, ``_records_retry_at``, ``_records_backoff``,
``_deployment_seq``; the ``triggered`` field of the snapshot.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, List, Optional

from dps_parachute_ros import protocol as p
from dps_parachute_ros.link import LinkDown, LinkError, LinkTimeout
from dps_parachute_ros.state import Deployment, Snapshot, source_name

RECORDS_RETRY_S = (1.0, 30.0)
"""Back-off of the trigger-record fetch owed to a deployment of unknown source, while online."""


class DeploymentEvents:
    """The deployment events of `ParachuteSession` (a mixin: it uses the session's state)."""

    def _set_triggered(self, triggered: Optional[bool], via: str, epoch: Optional[int] = None,
                       arms: Optional[int] = None, **also: Any) -> Optional[Snapshot]:
        """Take a triggered state read, with other fields, in one update.

        Returns the snapshot before it, or None when `epoch` shows that the module may have
        changed since it was read (nothing is taken then). `arms`: as `_update_if`'s.
        """
        with self._lock:
            if epoch is not None and epoch != self._epoch:
                return None
            also = self._newer_armed(arms, also)
            before = self._snap
            if triggered is not None:
                also['triggered'] = triggered
                if triggered and not before.triggered:
                    self._triggered_seen = (self.clock(), via)
            self._snap = before.evolve(**also)
            reported = self._snap.boot_count in self._reported_boots
            self._lock.notify_all()
        if triggered is None or before.triggered == triggered:
            return before
        self.blackbox.record('state', triggered=triggered, via=via)
        self.listener.on_triggered(triggered)
        self.listener.on_diagnostics()
        if triggered:
            self.blackbox.sync(None)
            self._log('error', f'the module reports TRIGGERED (via {via})')
            self._schedule('records' if reported else 'trigger')
        return before

    def _report(self, source: int, via: str, record: Optional[p.TriggerRecord],
                boot: Optional[int]) -> bool:
        """Publish a deployment unless this boot's deployment was reported (D7, one per boot).

        The module locks itself when it deploys and stays triggered until it is switched
        off (P11, P27): one deployment per power-up, so the boot count identifies it.
        """
        with self._lock:
            if boot in self._reported_boots:
                return False
            self._reported_boots.add(boot)
            self._deployment_seq += 1
            event = Deployment(source, via, record, self._deployment_seq)
            self._events[boot] = event
            if not source:
                # Owed: the record is fetched again until it comes (amend_sources).
                self._source_owed.add(boot)
                self._records_backoff = RECORDS_RETRY_S[0]
                self._records_retry_at = self.clock() + self._records_backoff
        self.blackbox.record('trigger_event', source=source_name(source), via=via,
                             record=None if record is None else record.raw.hex(' '))
        self.blackbox.sync(None)
        self.listener.on_deployment(event)
        self._log('error', f'PARACHUTE DEPLOYED: source {source_name(source)}'
                           + ('' if source else '; the trigger record is read again until it '
                              'tells, and ~/trigger_event amended then'))
        return True

    def _amend_sources(self, records: List[p.TriggerRecord]) -> None:
        """Amend the events published with an unknown source whose record is now read (D7).

        The amendment carries the deployment id of the event it corrects and `amends`: the
        same deployment, told better, never a second one.
        """
        with self._lock:
            owed = [(boot, self._events[boot]) for boot in self._source_owed
                    if boot in self._events]
        for boot, event in owed:
            mine = [r for r in records if r.boot_count == boot and r.source]
            if not mine:
                continue
            record = mine[-1]
            amended = replace(event, source=record.source, via='record', record=record,
                              amends=True)
            with self._lock:
                if boot not in self._source_owed:
                    continue
                self._source_owed.discard(boot)
                self._events[boot] = amended
            name = source_name(record.source)
            self.blackbox.record('state', event=f'trigger event {event.deployment_id} amended: '
                                 f'source {name}, from the trigger record of boot {boot}')
            self.blackbox.sync(None)
            self.listener.on_deployment(amended)
            self._log('warn', f'deployment {event.deployment_id} (reported with source '
                              f'unknown): source {name}, by its trigger record; ~/trigger_event '
                              'amended')

    def _retry_records(self) -> None:
        """Fetch the records owed to a deployment of unknown source again (backing off)."""
        with self._lock:
            delay = self._records_backoff
            self._records_backoff = min(delay * 2.0, RECORDS_RETRY_S[1])
            self._records_retry_at = self.clock() + delay
        try:
            self._fetch_records()
        except LinkError as exc:
            self._log('warn', f'trigger records not read ({exc}); trying again in {delay:.0f} s',
                      key='records-retry', every_s=30.0)

    def _fetch_records(self) -> p.TriggerRecords:
        """Query the history; remember every record; return the non-empty ones."""
        records = self.link.query_records().stored()
        with self._lock:
            self._known_records = (self._known_records or set()) | {r.raw for r in records}
        self._amend_sources(records)
        return records

    def _report_at_init(self, triggered: bool) -> None:
        """Report deployments found at (re)connect that nobody reported yet (D7)."""
        with self._lock:
            first = self._known_records is None
            known = set(self._known_records or ())
            boot = self._snap.boot_count
        try:
            records = self._fetch_records()
        except LinkTimeout:
            if triggered:
                self._schedule('trigger')  # try again for the record
            return  # a module without records may stay silent (P15)
        if triggered:
            mine = [r for r in records if r.boot_count == boot]
            record = mine[-1] if mine else None
            self._report(record.source if record else 0, 'status', record, boot)
        with self._lock:
            unknown_boot = self._unknown_boot if self._snap.deploy_outcome_unknown else None
        if unknown_boot is not None and unknown_boot != boot:
            self._settle_unknown_by_records(records, unknown_boot, boot)
        if first:
            with self._lock:
                self._records_from_boot = boot
            return
        # Deployments that happened while nobody watched (unplugged, rebooted). Only from the
        # power-up of the first records read on: an older record missing from that first answer
        # (cut short on a loaded host) was there before this run, not a deployment since.
        with self._lock:
            since = self._records_from_boot
        for record in records:
            if record.raw not in known and (since is None or boot is None or (
                    (record.boot_count - since) % 256 <= (boot - since) % 256)):  # (it wraps)
                self._report(record.source, 'record', record, record.boot_count)

    def _settle_unknown_by_records(self, records: p.TriggerRecords, unknown_boot: int,
                                   boot: Optional[int]) -> None:
        """Settle a deploy of unknown outcome in an earlier power-up by its trigger records.

        Only a record, or an answer with every slot's frame, tells (P15): an answer cut short
        is asked for again (twice), then the outcome stays unknown until the next reading.
        """
        for attempt in range(3):
            fired = any(r.boot_count == unknown_boot for r in records)
            if fired or records.complete:
                self._resolve_unknown_deploy(
                    fired, f'the module rebooted since (boot {unknown_boot} -> {boot}); its '
                    f'trigger records {"show" if fired else "show no"} deployment in boot '
                    f'{unknown_boot}')
                return
            if attempt == 2 or self._stopping.wait(0.2):
                break
            try:
                records = self._fetch_records()
            except LinkError:
                break
        self._log('warn', f'the trigger records came cut short (fewer than the {p.RECORD_SLOTS} '
                          'slots): the earlier deploy of unknown outcome stays unknown until they '
                          'are read whole')

    def _trigger_job(self) -> None:
        boot = self.snapshot.boot_count
        record = None
        for attempt in range(3):
            # A module may store the record a moment after raising the flag, and a loaded
            # host may cut a multi-frame answer short at the quiet gap: ask again, briefly.
            if attempt:
                self._stopping.wait(0.2)
            with self._lock:
                if boot in self._reported_boots:
                    return
            try:
                mine = [r for r in self._fetch_records() if r.boot_count == boot]
            except LinkDown as exc:
                # No use asking a module that is not there: say it now, read the record
                # when it is back (the initialization does; the event is amended then).
                self._log('warn', f'could not read the trigger record: {exc}')
                break
            except LinkError as exc:
                self._log('warn', f'could not read the trigger record: {exc}')
                continue
            if mine:
                record = mine[-1]
                break
        self._report(record.source if record else 0, 'status', record, boot)
