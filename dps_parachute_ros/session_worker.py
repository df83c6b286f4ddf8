"""The worker thread: its job queue, the poll, and the status stream with its fallback (D2).

Part of `ParachuteSession` (``dps_parachute_ros.session`` assembles it; the shared state and the
lock are described there). Threads:

- worker (``parachute-worker``): runs the queued jobs (``_run_job``: (re-)initialization, the
  trigger record of a deployment, a stream change, held settings) and otherwise polls light,
  charging and voltage (and the status while there is no stream), sends heartbeats, notices a
  stream that stopped and tries it again, and fetches trigger records still owed. Owns its
  schedule (``next_*`` locals of ``_work``).
- any thread may queue a job (``_schedule``, under ``_jobs_cond``).
- ``_on_status`` takes a status frame: a streamed one on the serial reader, an answered one on
  the thread that asked (the worker's poll, a caller's deploy, arm, settings write or
  preflight). A caller's ``set_streaming`` turns the stream on or off (``_set_streaming``).

Owns, guarded by ``_jobs_cond``: ``_jobs``. Guarded by ``_lock``: ``_last_status_time``,
``_last_stream_time``, ``_stream_on_at``, ``_stream_retry_at``, ``_stream_backoff``; the
``streaming`` and ``stream_problem`` fields of the snapshot.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import List, Optional

from dps_parachute_ros import protocol as p
from dps_parachute_ros.link import LinkError, LinkTimeout
from dps_parachute_ros.session_online import IDLE_WAKE_S


@dataclass
class _Jobs:
    queue: List[str] = field(default_factory=list)
    init_busy: bool = False


STREAM_GRACE = 0.5
"""Without a stream frame for this share of `offline_timeout_s` the driver asks the module: an
answer leaves time before the silence would make it offline, and means the stream stopped."""
STREAM_RETRY_S = (2.0, 60.0)
"""Back-off of the attempts to restore a stopped stream: first delay, longest delay."""


class Worker:
    """The worker thread of `ParachuteSession` (a mixin: it uses the session's state)."""

    def _schedule(self, job: str, force: bool = False) -> None:
        with self._jobs_cond:
            if job == 'init':
                if self._jobs.init_busy and not force:
                    return
                self._jobs.init_busy = True
            if job not in self._jobs.queue:
                self._jobs.queue.append(job)
            self._jobs_cond.notify()

    def _work(self) -> None:
        next_aux = -1e9
        next_heartbeat = -1e9
        wait = 0.0
        while not self._stopping.is_set():
            with self._jobs_cond:
                if not self._jobs.queue and wait > 0.0 and not self._stopping.is_set():
                    self._jobs_cond.wait(wait)
                job = self._jobs.queue.pop(0) if self._jobs.queue else None
            # Sleep until the next thing due, at most IDLE_WAKE_S; a job wakes it at once.
            wait = IDLE_WAKE_S
            try:
                if job is not None:
                    self._run_job(job)
                    wait = 0.0
                    continue
                snap = self.snapshot
                if not snap.port_open:
                    continue
                now = self.clock()
                with self._lock:
                    retry_at, init_at = self._init_retry_at, self._initialized_at
                    last_stream = max(self._last_stream_time, self._stream_on_at)
                    stream_retry_at = self._stream_retry_at
                    records_at = self._records_retry_at if self._source_owed else None
                    config = self._config
                if not snap.initialized:
                    if now >= retry_at:
                        self._schedule('init', force=True)
                    else:
                        wait = min(wait, retry_at - now)
                    continue
                stream_due = max(last_stream, init_at) + config.offline_timeout_s * STREAM_GRACE
                if snap.streaming and snap.online and now > stream_due:
                    self._stream_stopped()
                    continue
                stream_wanted = config.stream_status and not snap.streaming and snap.online
                if stream_wanted and now >= stream_retry_at:
                    self._start_stream()
                    continue
                if records_at is not None and snap.online and now >= records_at:
                    self._retry_records()
                    continue
                if now >= next_aux:
                    next_aux = now + config.aux_poll_period_s
                    self._poll()
                if not snap.streaming and now >= next_heartbeat:
                    next_heartbeat = now + config.heartbeat_period_s
                    # Its answer keeps nothing alive that the status poll does not: a module
                    # that ignores it but answers the status is online (the poll judges that).
                    self._req(p.encode_heartbeat(), silence_ok=True)
                due = [next_aux]
                if not snap.streaming:
                    due.append(next_heartbeat)
                elif snap.online:
                    due.append(stream_due + 0.001)  # judged with '>'
                if stream_wanted:
                    due.append(stream_retry_at)
                if records_at is not None:
                    due.append(records_at)
                wait = max(min(wait, min(due) - self.clock()), 0.001)
            except LinkError as exc:
                if not self._stopping.is_set():
                    self._log('warn', f'{exc}', key='worker-link')
            except Exception as exc:  # noqa: BLE001 - the worker must survive a bug
                self._log('error', f'worker failed: {exc!r}', key='worker')

    def _run_job(self, job: str) -> None:
        if job == 'init':
            try:
                self._initialize()
            finally:
                with self._jobs_cond:
                    self._jobs.init_busy = 'init' in self._jobs.queue
        elif job == 'trigger':
            self._trigger_job()
        elif job == 'records':
            self._fetch_records()
        elif job == 'stream' and self.snapshot.online:
            with self._lock:
                self._stream_backoff = STREAM_RETRY_S[0]
            self._start_stream()
        elif job == 'settings' and self.snapshot.online and self.snapshot.initialized:
            with self._lock:
                held = set(self._held)
            self._apply_desired(only=held)

    def _set_streaming(self, enabled: bool, silence_ok: bool = False) -> bool:
        reply = self._req(p.encode_streaming(enabled), retries=1, silence_ok=silence_ok)
        with self._lock:
            self._stream_on_at = self.clock()  # its first frame is due from now
            self._snap = replace(self._snap, streaming=reply.enabled,
                                 stream_problem=self._snap.stream_problem if enabled else '')
            self._lock.notify_all()
        return reply.enabled == enabled

    def _start_stream(self) -> None:
        """Turn the stream on or off as configured; a stream that does not come is polled."""
        want = self.config.stream_status
        try:
            # A module that ignores 0x13 but answers the rest is online (D2): no verdict here.
            acked = self._set_streaming(want, silence_ok=True)
        except LinkTimeout:
            if want:
                self._stream_fallback('the module did not answer stream on (0x13)')
            else:
                self._update(streaming=False, stream_problem='')
            return
        if want and not acked:
            self._stream_fallback('the module answered stream on (0x13) with "off"')

    def _stream_stopped(self) -> None:
        """No stream frame for a while: ask the module; an answer means the stream stopped."""
        with self._lock:
            silent = self.clock() - max(self._last_stream_time, self._stream_on_at)
        # A module that rebooted unnoticed has its stream off (D3): the boot count tells, and a
        # reboot re-initializes. The answer also keeps it online while its stream is silent.
        before = self._current_epoch()
        epoch = self._note_boot_count(self._req(p.encode_boot_count_query()).count)
        arms = self._arms_sent()
        status = self._req(p.encode_status_query())
        if epoch != before or epoch != self._current_epoch():
            return
        self._on_status(status, via='poll', epoch=epoch, arms=arms)
        self._stream_fallback(f'no status frame for {silent:.1f} s although the module answers')

    def _stream_fallback(self, why: str) -> None:
        """Poll the status instead of the stream, say so, and try the stream again later."""
        now = self.clock()
        with self._lock:
            delay = self._stream_backoff
            self._stream_backoff = min(delay * 2.0, STREAM_RETRY_S[1])
            self._stream_retry_at = now + delay
            period = self._config.aux_poll_period_s
            problem = (f'status stream dead ({why}): polling the status every {period:g} s; '
                       f'stream on again in {delay:.0f} s')
            self._snap = replace(self._snap, streaming=False, stream_problem=problem)
            self._lock.notify_all()
        self._log('warn', problem, key='stream', every_s=30.0)
        self.blackbox.record('state', event='status stream dead', reason=problem)
        self._emit_status()
        self.listener.on_diagnostics()

    def _poll(self) -> None:
        epoch, arms = self._asked()
        if not self.snapshot.streaming:
            # The status first: it is what the online judgement and a deploy need.
            self._on_status(self._req(p.encode_status_query()), via='poll', epoch=epoch,
                            arms=arms)
        values = {}
        for name, frame, field_ in (('light_v', p.encode_light_level_query(), 'volts'),
                                    ('charging', p.encode_charging_query(), 'charging'),
                                    ('voltage_v', p.encode_cell_voltage_query(), 'volts')):
            # A query the module leaves unanswered leaves its value as it was; it says
            # nothing of whether the module is online while other queries are answered.
            try:
                values[name] = getattr(self._req(frame, silence_ok=True), field_)
            except LinkTimeout:
                self._log('warn', f'no reply to the {name} query', key=f'poll-{name}',
                          every_s=30.0)
        snap = self._update(**values)
        if snap.streaming:
            self._emit_status()
        self.listener.on_battery(self.snapshot)
        self.listener.on_diagnostics()

    def _on_status(self, status: p.Status, via: str, epoch: Optional[int] = None,
                   arms: Optional[int] = None) -> None:
        # A status frame tells armed and triggered as they are now: a re-read (D15). One of
        # the stream is taken in the order of the wire; an answer, as of when it was asked.
        restored = False
        with self._lock:
            self._last_status_time = self.clock()
            if via == 'status':
                # Only the unsolicited frames are the stream; a poll's answer is not.
                self._last_stream_time = self._last_status_time
                if self._snap.stream_problem and self._config.stream_status:
                    restored = True
                    self._stream_backoff = STREAM_RETRY_S[0]
                    self._snap = replace(self._snap, streaming=True, stream_problem='')
        if restored:
            self._log('info', 'the status stream is back', key='stream-back', every_s=30.0)
            self.blackbox.record('state', event='status stream restored')
            self.listener.on_diagnostics()
        before = self._set_triggered(status.triggered, via, epoch, arms,
                                     tilt_deg=float(status.tilt_deg),
                                     accel_g=float(status.accel_g), armed=status.armed,
                                     fresh=True)
        if before is None:
            return  # a poll's answer from before a reboot
        self._recheck_held(status)
        if before.armed is not None and before.armed != status.armed:
            self.blackbox.record('state', armed=status.armed, via=via)
            self.blackbox.sync(None)
            self.listener.on_diagnostics()
        self._emit_status()
