"""Online judgement (D2), the monitor thread, and the link's counters in the black box (D10).

Part of `ParachuteSession` (``dps_parachute_ros.session`` assembles it; the shared state and the
lock are described there). Threads:

- monitor (``parachute-monitor``, a ``DeadlineTimer`` running ``_monitor_duty``) judges
  online/offline and the defer deadline from the clock (``tick()``), and records the link's
  error counters in the black box when they change; no I/O. It sleeps until the next of those
  deadlines (``_monitor_due``, at most ``IDLE_WAKE_S``); a deferred request wakes it by its
  deadline (``_monitor.wake(by=...)``).
- every thread that sees a frame or ends a request (``_req``) calls ``_judge_online``; the
  serial reader also reports the port opening or closing (``_on_connection``).

The rule itself is ``online_rule.OnlineRule`` (no I/O, no clock): ``_req`` tells it of each
request it counts, ``_on_connection`` of each port opening, and ``_judge_online`` asks it for the
verdict and carries a change out (black box, log, re-initialization, listeners).

Owns, guarded by ``_lock``: ``_online`` (the rule), ``_link_recorded``, ``_link_recorded_at``,
``_link_seen``, ``_link_changed_at``; the ``online`` and ``offline_reason`` fields of the
snapshot.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Dict, Optional, Tuple

LINK_RECORD_PERIOD_S = 1.0
"""The link's error counters go to the black box when they change, at most this often (D10)."""
LINK_PROBLEM_COUNTERS = ('checksum_errors', 'bytes_discarded', 'timeouts', 'reconnects')
LINK_ERROR_COUNTERS = ('checksum_errors', 'timeouts', 'reconnects')
"""What preflight judges the link by. Not discarded bytes: they also come from the end of a
trigger-record answer cut at its quiet gap (P15); not the flag query's silence (P14)."""
IDLE_WAKE_S = 0.2
"""The worker and the monitor sleep until their next deadline, and at most this long (they see
state changes nobody signals within it). Each wake-up costs CPU: they used to poll at 50 Hz."""


class OnlineJudgement:
    """Online judgement of `ParachuteSession` (a mixin: it uses the session's state)."""

    def _monitor_duty(self) -> Optional[float]:
        """Judge the time-based rules now; return when next due (the monitor's duty)."""
        if self._stopping.is_set():
            return None
        self.tick()
        self._record_link()
        return self._monitor_due()

    def _monitor_failed(self, exc: BaseException) -> None:
        self._log('error', f'monitor failed: {exc!r}', key='monitor')

    def _monitor_due(self) -> Optional[float]:
        """Return the next deadline ``tick()`` judges (clock time), None if none."""
        count, last = self.link.last_frame
        due = self._trigger_deadline()
        with self._lock:
            self._online.timeout_s = self._config.offline_timeout_s
            judged = self._online.next_deadline(count, last, self._snap.streaming)
        return min((t for t in (due, judged) if t is not None), default=None)

    def _record_link(self, final: bool = False) -> None:
        """Record the link's error counters when they changed (throttled; `final`: now)."""
        # Checksum errors and noise never become frames, so without this the black box would
        # not know of them; the counters are cumulative for the run (D10).
        info = self.link_info()
        counters = tuple(info[name] for name in LINK_PROBLEM_COUNTERS)
        self._note_link(info)
        now = self.clock()
        with self._lock:
            if counters == self._link_recorded or \
                    (not final and now - self._link_recorded_at < LINK_RECORD_PERIOD_S):
                return
            self._link_recorded, self._link_recorded_at = counters, now
        self.blackbox.record('link', **info)

    def _note_link(self, info: Optional[Dict[str, Any]] = None
                   ) -> Tuple[Tuple[int, ...], float]:
        """Note when a link error counter last grew; return the counters and that time."""
        info = info or self.link_info()
        with self._lock:
            info = dict(info, timeouts=info['timeouts'] - self._silent_flag_queries)
            counters = tuple(info[name] for name in LINK_ERROR_COUNTERS)
            if counters != self._link_seen:
                self._link_seen = counters
                self._link_changed_at = self.clock()
            return counters, self._link_changed_at

    def tick(self) -> None:
        """Judge the time-based rules now (the monitor does at each deadline, or IDLE_WAKE_S)."""
        self._judge_online()
        self._trigger_tick(self.clock())  # the defer deadline, the module's window

    def _judge_online(self) -> None:
        now = self.clock()
        count, last = self.link.last_frame
        with self._lock:
            snap = self._snap
            self._online.timeout_s = self._config.offline_timeout_s
            verdict = self._online.judge(now, snap.port_open, count, last, snap.streaming,
                                         self.link.serial.last_error)
            online, reason = verdict.online, verdict.reason
            if online == snap.online:
                return
            reread = online and snap.initialized
            if reread:
                # It may have changed while silent: re-read before acting on it (D15).
                self._snap = replace(snap, online=True, offline_reason='', fresh=False,
                                     initialized=False)
            elif online:
                self._snap = replace(snap, online=True, offline_reason='')
            else:
                self._snap = replace(snap, online=False, offline_reason=reason)
            self._lock.notify_all()
        with self._jobs_cond:
            schedule_init = online and (reread or not self._jobs.init_busy)
        self._log('info' if online else 'error',
                  'module online' if online else f'module offline: {reason}')
        self.blackbox.record('state', online=online, reason=reason)
        if schedule_init:
            self._schedule('init', force=True)
        self.listener.on_diagnostics()
        snap = self.snapshot
        self.listener.on_status(snap)
        self.listener.on_battery(snap)

    def _on_connection(self, up: bool, reason: str) -> None:
        if self._stopping.is_set():
            return
        with self._lock:
            self._epoch += 1
            if up:
                self._online.port_opened(self.link.last_frame[0])
            self._snap = replace(self._snap, port_open=up, initialized=False, fresh=False)
        self.blackbox.record('state', port_open=up, reason=reason)
        if up:
            self._schedule('init', force=True)
        self._judge_online()
