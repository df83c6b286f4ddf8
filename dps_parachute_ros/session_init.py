"""(Re-)initialization of the module and what a reboot changes (D2, D3, D15).

Part of `ParachuteSession` (``dps_parachute_ros.session`` assembles it; the shared state and the
lock are described there). Threads:

- worker: ``_initialize`` (the ``init`` job) reads the module afresh after the port opens, the
  module comes back online, or it rebooted.
- serial reader: ``_on_heartbeat``: an unsolicited heartbeat is a reboot (P5; which ones:
  ``deploy_knowledge.PowerUpHeartbeats``).
- any thread that reads the boot count (the worker, a deploy or arm, preflight):
  ``_note_boot_count``: a changed count is a reboot.

Owns, guarded by ``_lock``: ``_epoch`` (+1 whenever the module may have changed unseen: here on
a reboot, and by ``_on_connection``; every thread reads it), ``_reboots`` (reboots seen),
``_boot_read_reboots`` and ``_sent_since_boot_read`` (``_on_tx`` counts up: P11 after a reboot
found late), ``_power_ups``, ``_initialized_at``, ``_init_retry_at``; the
``boot_count`` and ``initialized`` fields of the snapshot.
"""

from __future__ import annotations

from dataclasses import replace

from dps_parachute_ros import protocol as p
from dps_parachute_ros.deploy_knowledge import heartbeat_actions, SAME_POWER_UP
from dps_parachute_ros.link import LinkError
from uav_serial_common.core_events import Log


class Initialization:
    """Initialization and reboots of `ParachuteSession` (a mixin: it uses the session's state)."""

    def _on_heartbeat(self) -> None:
        # P5: nobody asked, so the module has just (re)booted. It sends two, 50 ms apart: one
        # reboot (D3). Until it is re-read its armed state is unknown (D15).
        now = self.clock()
        with self._lock:
            verdict = self._power_ups.take(now)
            if verdict != SAME_POWER_UP:
                self._epoch += 1
                self._reboots += 1
                self._snap = replace(self._snap, streaming=False, armed=None, triggered=None,
                                     fresh=False, initialized=False)
        if verdict == SAME_POWER_UP:
            return
        for action in heartbeat_actions(verdict):
            if isinstance(action, Log):
                self._carry_log(action)
            else:
                self._carry_record(action)
        self._rebooted_voids()
        self._schedule('init', force=True)
        self._emit_status()
        self.listener.on_diagnostics()
        with self._lock:
            # The second heartbeat of this power-up may have waited (in the port) for all of
            # this to finish, long on a loaded host: the 0.2 s run from here, not from before.
            self._power_ups.handled(self.clock())

    def _rebooted_voids(self) -> None:
        """Void what a reboot ends, whoever found it (a power-up heartbeat, a new boot count).

        The module's pending trigger request, and the rest of a records answer in flight: a
        power-up goes on with neither.
        """
        self.link.void_answers()
        self._void_pending('the module rebooted while the request was pending')

    def _initialize(self) -> None:
        """Read the module afresh and bring it to the desired settings (D2)."""
        if not self.snapshot.port_open:
            return
        with self._lock:
            self._init_retry_at = self.clock() + 1.0
        try:
            epoch = self._note_boot_count(self._req(p.encode_boot_count_query(), retries=1).count,
                                          reinit=False)
            # Armed and triggered first: a deploy waiting for them never waits behind a stream
            # the module does not turn on.
            arms = self._arms_sent()
            armed = self._req(p.encode_armed_query(), retries=1).armed
            triggered = self._req(p.encode_triggered_query(), retries=1).triggered
            if self._set_triggered(triggered, 'query', epoch, arms, armed=armed,
                                   fresh=True) is None:
                return  # it rebooted meanwhile: that schedules another initialization
            self._start_stream()
            with self._lock:
                same_boot = self._unknown_boot in (None, self._snap.boot_count)
            if same_boot:
                # After a reboot the flag is clear whatever happened before it: the trigger
                # records settle that deploy (_report_at_init).
                self._resolve_unknown_deploy(triggered, 'read after reconnecting')
            self._read_config(reinit=False)
            self._apply_desired()
            self._report_at_init(triggered)
        except LinkError as exc:
            self._log('warn', f'initialization failed ({exc}); retrying', key='init')
            return
        now = self.clock()
        with self._lock:
            if epoch != self._epoch:
                return
            self._initialized_at = now
            self._snap = replace(self._snap, initialized=True)
            snap = self._snap
        self.blackbox.record('state', event='initialized', boot_count=snap.boot_count,
                             mismatch=list(snap.mismatch))
        self._log('info', f'module initialized: boot count {snap.boot_count}, streaming '
                          f'{snap.streaming}, settings '
                          f'{"verified" if not snap.mismatch else "MISMATCH"}')
        self.listener.on_config(snap)
        self._emit_status()
        self.listener.on_diagnostics()

    def _note_boot_count(self, count: int, reinit: bool = True) -> int:
        """Take a boot count read; return the epoch after it.

        A change is a reboot (D3): the module is read afresh (unless `reinit` is False: the
        initialization in progress does that).
        """
        stored = self._attempts.load() if self.snapshot.boot_count is None else None
        with self._lock:
            previous = self._snap.boot_count
            self._snap = replace(self._snap, boot_count=count)
            restored = previous is None and stored is not None and \
                stored.boot_count == count and stored.failed > self._snap.failed_deploys
            if restored:
                # The same power-up as an earlier run's unsuccessful deploy frames (P11).
                self._snap = replace(self._snap, failed_deploys=stored.failed,
                                     unacked_deploys=max(stored.unacked,
                                                         self._snap.unacked_deploys))
            elif previous is None and stored is not None and stored.since_read:
                # Another power-up; the frames that run sent after its last boot count read
                # may have gone to this one (a reboot it never saw): they count.
                self._snap = replace(
                    self._snap,
                    failed_deploys=max(self._snap.failed_deploys,
                                       min(stored.failed, stored.since_read)),
                    unacked_deploys=max(self._snap.unacked_deploys,
                                        min(stored.unacked, stored.since_read)))
            if None in self._reported_boots and previous is None:
                # A deployment reported before the first boot count read happened in this boot.
                self._reported_boots.discard(None)
                self._reported_boots.add(count)
                if None in self._events:
                    self._events[count] = self._events.pop(None)
                if None in self._source_owed:
                    self._source_owed.discard(None)
                    self._source_owed.add(count)
            rebooted = previous is not None and previous != count
            if rebooted:
                self._epoch += 1
                self._reboots += 1
                # A new power-up clears the module's count of unsuccessful attempts (P19); the
                # frames since the last read may have come after the reboot: they stay.
                sent = self._sent_since_boot_read
                self._snap = replace(self._snap, fresh=False, armed=None,
                                     unacked_deploys=min(self._snap.unacked_deploys, sent),
                                     failed_deploys=min(self._snap.failed_deploys, sent))
            self._sent_since_boot_read = 0
            self._boot_read_reboots = self._reboots
            epoch = self._epoch
        if restored:
            self._log('warn', f'{stored.failed} deploy frame(s) without a successful '
                              f'acknowledgement in this power-up (boot {count}), sent by an '
                              'earlier run of the driver: they count (P11)')
            self.blackbox.record('state', event='deploy attempts of an earlier run',
                                 boot_count=count, failed_deploys=stored.failed,
                                 unacked_deploys=stored.unacked)
            self.listener.on_diagnostics()
        if rebooted:
            self._log('warn', f'module boot count {previous} -> {count}: it rebooted')
            self._rebooted_voids()
            if reinit:
                self._schedule('init', force=True)
        return epoch
