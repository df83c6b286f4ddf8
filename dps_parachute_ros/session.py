"""The DPS-S parachute module as a device: link, black box, state, rules and policies. No ROS.

`ParachuteSession` owns the `ParachuteLink`, the `BlackBox` and the module state (its types are
in `dps_parachute_ros.state`), and applies the rules of the README's "Safety model of deploy" and
the driver decisions (D..) of ``docs/protocols.md``. It reports through a `Listener`, takes its
clock (monotonic seconds, for every rule that judges time; waits are bounded in real time) from
the caller, and its services are calls that return a `Result`. The ROS node only translates.

It is assembled here from one mixin class per responsibility, each in a module of its own whose
docstring says which threads run its code and which of the state below it owns:

- ``session_online``: online judgement (D2), the monitor thread, the link's counters;
- ``session_worker``: the worker thread, its jobs, the poll and the status stream;
- ``session_init``: (re-)initialization and reboots (D3, D15);
- ``session_triggers``: the trigger-request policy (D8), whose rules are ``trigger_core``'s;
- ``session_settings``: the settings rule every write passes (D16), the desired settings, the
  settings services and parameter sets (D4, D5);
- ``session_events``: deployments as events, one per deployment (D7);
- ``session_deploy``: the deploy procedure (D6), arming, the deploy frames counted (P11);
- ``session_preflight``: ``~/preflight_check`` (D17).

This module holds the shared state, the life cycle, the request bookkeeping every request passes
(``_req``), the dispatch of the frames the reader decodes, and the small services.

Threads, what each owns, and the lock that guards what they share:

- serial reader (``SerialLink``): decodes frames and handles unsolicited ones at once
  (``_on_message``): the status stream (``session_worker``), reboot heartbeats
  (``session_init``), late deploy acknowledgements (``session_deploy``), and trigger requests,
  whose confirmation is written right there (``session_triggers``: why a confirm takes
  milliseconds). It never waits for a reply (only it delivers replies).
- gate (``parachute-gate``, ``session_triggers``): with a release gate (``release_gate.py``), a
  short-lived thread per trigger request to confirm waits for the gate, then steps the
  trigger-request core, which judges again whether the confirmation may still leave.
- worker (``parachute-worker``, ``session_worker``): (re-)initializes the module, polls light,
  charging and voltage, sends heartbeats, fetches trigger records. Owns its schedule
  (``next_*`` locals).
- monitor (``parachute-monitor``, ``session_online``): judges online/offline and the defer
  deadline from the clock (``tick()``), and records the link's error counters in the black box
  when they change; no I/O. It sleeps until the next of those deadlines (at most
  ``IDLE_WAKE_S``); a deferred request wakes it by its deadline.
- callers (the node's service threads): deploy, arm, settings, queries. ``_actuation``
  serializes deploy and arm (never taken on the reader thread or by a trigger-request answer).

All module state is one immutable `Snapshot` in ``_snap``; it and every other field marked
"guarded by _lock" in ``__init__`` below (all are declared there; each module names those it
owns) are read and replaced only under ``_lock`` (a Condition's lock, so a deploy can wait for a
re-read). Listener callbacks and link I/O never run under ``_lock``.
"""

from __future__ import annotations

from dataclasses import asdict, replace
import threading
import time
from typing import Any, Callable, Dict, Optional, Set, Tuple

from dps_parachute_ros import protocol as p
from dps_parachute_ros.attempts import AttemptsFile
from dps_parachute_ros.blackbox import BlackBox
from dps_parachute_ros.deploy_knowledge import PowerUpHeartbeats
from dps_parachute_ros.link import LinkError, LinkTimeout, ParachuteLink
from dps_parachute_ros.online_rule import OnlineRule
from dps_parachute_ros.session_deploy import DeployProcedure
from dps_parachute_ros.session_events import DeploymentEvents, RECORDS_RETRY_S
from dps_parachute_ros.session_init import Initialization
from dps_parachute_ros.session_online import (IDLE_WAKE_S, LINK_ERROR_COUNTERS,
                                              LINK_PROBLEM_COUNTERS, OnlineJudgement)
from dps_parachute_ros.session_preflight import (LOW_BATTERY_V,  # noqa: F401 (node.py imports it)
                                                 Preflight)
from dps_parachute_ros.session_settings import (HELD_RETRY_S,  # noqa: F401 (tests import it here)
                                                SettingsTransaction)
from dps_parachute_ros.session_triggers import TriggerRequests
from dps_parachute_ros.session_worker import _Jobs, STREAM_RETRY_S, Worker
from dps_parachute_ros.state import (config_problems, Deployment, FLAG_SETTINGS, Listener, Result,
                                     SessionConfig, SETTINGS, Snapshot)
from uav_serial_common.core_events import Log, Record, SYNC_ASK, SYNC_WAIT
from uav_serial_common.deadline_timer import DeadlineTimer
from uav_serial_common.logs import Throttle

SHUTDOWN_TOKEN = 'SHUTDOWN'
BLACKBOX_CLOSE_S = 4.0
"""Longest wait at stop for the black box's writer to put the last records on disk."""


class _Guarded(Listener):
    """The caller's listener; an exception in it is logged, never raised into the session."""

    def __init__(self, inner: Listener, log: Callable[..., None]) -> None:
        self._report = log
        # One wrapper per callback, made once: they run with every frame.
        for name in dir(inner):
            if name.startswith('on_') and callable(getattr(inner, name)):
                setattr(self, name, self._guard(name, getattr(inner, name)))

    def _guard(self, name: str, method: Callable[..., None]) -> Callable[..., None]:
        report = self._report

        def call(*args: Any) -> None:
            try:
                method(*args)
            except Exception as exc:  # noqa: BLE001 - a listener bug must not stop the session
                if name != 'on_log':
                    report('error', f'{name} failed: {exc!r}', key=name)
        return call


class _LinkLog:
    """The logger SerialLink expects, forwarded to the session's log."""

    def __init__(self, log: Callable[..., None]) -> None:
        self._log = log

    def debug(self, text: str, **_: Any) -> None:
        self._log('debug', text)

    def info(self, text: str, **_: Any) -> None:
        self._log('info', text)

    def warning(self, text: str, **_: Any) -> None:
        self._log('warn', text)

    warn = warning

    def error(self, text: str, **_: Any) -> None:
        self._log('error', text)


class ParachuteSession(TriggerRequests, OnlineJudgement, Worker, Initialization,
                       SettingsTransaction, DeploymentEvents, DeployProcedure, Preflight):
    """One DPS-S module behind one serial port: state, rules, policies, worker threads."""

    def __init__(self, config: SessionConfig, listener: Optional[Listener] = None,
                 clock: Callable[[], float] = time.monotonic,
                 blackbox: Optional[BlackBox] = None) -> None:
        """Check `config` (ValueError) and set up; `start()` opens the port."""
        problems = config_problems(config)
        if problems:
            raise ValueError('; '.join(problems))
        self.clock = clock
        self.listener: Listener = _Guarded(listener or Listener(), self._log)
        self._lock = threading.Condition(threading.RLock())
        # -- guarded by _lock ---------------------------------------------------------------
        self._config = config
        self._snap = Snapshot(policy=config.trigger_request_policy)
        self._epoch = 0                     # +1 whenever the module may have changed unseen
        self._arms = 0                      # arm and lock frames sent (a read before is older)
        self._reboots = 0                   # reboots seen (a deploy's core compares them)
        self._boot_read_reboots = -1        # _reboots when the boot count was last read
        self._sent_since_boot_read = 0      # deploy frames since then (P11)
        self._online = OnlineRule(config.offline_timeout_s)
        self._in_flight_seq = 0
        self._reported_boots: Set[Optional[int]] = set()   # boots whose deployment was reported
        self._known_records: Optional[Set[bytes]] = None
        self._records_from_boot: Optional[int] = None  # boot count of the first records read
        self._deploy_frame_left = False
        self._unknown_boot: Optional[int] = None  # boot count when a deploy became unknown
        self._power_ups = PowerUpHeartbeats()  # which heartbeats tell a reboot
        self._last_status_time = -1e9
        self._last_stream_time = -1e9       # last unsolicited status frame (the stream's)
        self._stream_on_at = -1e9           # when the module last acknowledged stream on/off
        self._stream_retry_at = 0.0
        self._stream_backoff = STREAM_RETRY_S[0]
        self._deploy_frame_at: Optional[float] = None
        self._triggered_seen: Optional[Tuple[float, str]] = None  # (when, via) it rose
        self._events: Dict[Optional[int], Deployment] = {}  # boot -> the event published
        self._source_owed: Set[Optional[int]] = set()  # boots whose event said source unknown
        self._records_retry_at = 0.0
        self._deployment_seq = 0
        self._records_backoff = RECORDS_RETRY_S[0]
        self._initialized_at = 0.0
        self._init_retry_at = 0.0
        self._flags_query_answered = False
        self._flags_query_sent = False
        self._held: Dict[str, Tuple[Any, str]] = {}  # desired setting -> (value, why not written)
        self._held_retry_at = -1e9
        self._settings_lock = threading.RLock()  # one settings write at a time
        self._throttle = Throttle()
        self._link_recorded: Tuple[int, ...] = (0,) * len(LINK_PROBLEM_COUNTERS)
        self._link_recorded_at = -1e9
        self._link_seen: Tuple[int, ...] = (0,) * len(LINK_ERROR_COUNTERS)
        self._silent_flag_queries = 0       # flag queries unanswered (P14): no link error
        self._link_changed_at = -1e9        # when one of the problem counters last grew
        self._init_triggers()               # the trigger-request core (_trigger_lock)
        # -- guarded by _jobs_cond ----------------------------------------------------------
        self._jobs = _Jobs()
        self._jobs_cond = threading.Condition()
        # -- other ----------------------------------------------------------------------------
        self._actuation = threading.Lock()
        self._attempts = AttemptsFile(config.blackbox_dir, config.port)
        self.release_gate: Optional[Any] = None  # a ReleaseGate (release_gate.py), or None
        self._stopping = threading.Event()
        max_bytes = int(config.blackbox_max_mb * 1e6) if config.blackbox_max_mb > 0 else None
        self.blackbox = blackbox or BlackBox(config.blackbox_dir, max_bytes=max_bytes,
                                             on_problem=self._on_blackbox_problem)
        if blackbox is not None:
            blackbox.on_problem = self._on_blackbox_problem
        self.blackbox.record('start', port=config.port, baud=config.baud, config=asdict(config))
        self.link = ParachuteLink(
            config.port, config.baud, on_message=self._on_message,
            on_connection=self._on_connection, blackbox=self.blackbox,
            logger=_LinkLog(self._log), layout=config.auto_trigger_flag_layout, clock=clock,
            on_tx=self._on_tx)
        self._worker = threading.Thread(target=self._work, name='parachute-worker', daemon=True)
        self._monitor = DeadlineTimer(
            self._monitor_duty, name='parachute-monitor', clock=self.clock, idle_s=IDLE_WAKE_S,
            retry_s=IDLE_WAKE_S, on_error=self._monitor_failed)

    # -- life cycle ----------------------------------------------------------------------------

    def start(self) -> 'ParachuteSession':
        """Start the worker, the monitor and the link (which opens the port, with retries)."""
        status = self.blackbox.status()
        if not status.writing:
            self._log('error', f'black box: {status.error}; the driver runs without it')
        self._worker.start()
        self._monitor.start()
        self.link.start()
        return self

    def stop(self) -> None:
        """Stop everything and close the black box; bounded (< 4 s). The module is left as is."""
        self._stopping.set()
        self._monitor.stop(timeout=1.0)
        with self._jobs_cond:
            self._jobs_cond.notify_all()
        self._trigger_stop()
        self.link.stop(timeout=1.0)
        if self._worker.is_alive():
            self._worker.join(1.0)
        # A deploy or arm in flight has just lost its link: let it record its outcome.
        if self._actuation.acquire(timeout=1.0):
            self._actuation.release()
        self._record_link(final=True)
        self.blackbox.record('stop')
        # The writer normally ends in milliseconds; a starved CPU can hold it for seconds, and
        # the process ending first would lose every record still queued (a run's first second
        # is not on disk yet). Bounded below ros2 launch's SIGTERM escalation (5 s).
        self.blackbox.close(timeout=BLACKBOX_CLOSE_S)

    @property
    def config(self) -> SessionConfig:
        """The configuration in force."""
        with self._lock:
            return self._config

    @property
    def snapshot(self) -> Snapshot:
        """The module state now."""
        with self._lock:
            return self._snap

    def reconfigure(self, config: SessionConfig) -> None:
        """Apply local settings of an accepted parameter set (module settings: `commit`)."""
        problems = config_problems(config)
        if problems:
            raise ValueError('; '.join(problems))
        with self._lock:
            old, self._config = self._config, config
            if config.trigger_request_policy != old.trigger_request_policy:
                self._update(policy=config.trigger_request_policy)
        self.link.layout = config.auto_trigger_flag_layout
        if config.blackbox_max_mb != old.blackbox_max_mb:
            self.blackbox.set_max_bytes(int(config.blackbox_max_mb * 1e6)
                                        if config.blackbox_max_mb > 0 else None)
        if (config.trigger_request_policy, config.defer_timeout_s) != \
                (old.trigger_request_policy, old.defer_timeout_s):
            # (Recorded, and a request still open settled under the new policy, by the core.)
            self._policy_changed(config.trigger_request_policy, config.defer_timeout_s)
        if config.stream_status != old.stream_status:
            self._schedule('stream')
        if any(getattr(config, n) != getattr(old, n) for n in (*SETTINGS, *FLAG_SETTINGS)):
            self._update_mismatch()
        self.listener.on_diagnostics()

    # -- small helpers ---------------------------------------------------------------------------

    def _log(self, level: str, text: str, key: Optional[str] = None,
             every_s: float = 5.0) -> None:
        if key is not None:
            now = self.clock()
            with self._lock:
                note = self._throttle.admit(key, now, every_s)
            if note is None:
                return
            text += note
        self.listener.on_log(level, text)

    def _carry_log(self, action: Log) -> None:
        """Carry out a core's `Log` (every core's: one handler)."""
        self._log(action.level, action.text)

    def _carry_record(self, action: Record) -> None:
        """Carry out a core's `Record`, synced as it asks (``core_events``: two guarantees).

        `SYNC_WAIT`: on disk before the next action (a bounded wait, `_safety_sync`);
        `SYNC_ASK`: an fsync asked for, not waited on.
        """
        self.blackbox.record(action.kind, **dict(action.fields))
        if action.sync == SYNC_WAIT:
            self._safety_sync()
        elif action.sync == SYNC_ASK:
            self.blackbox.sync(None)

    def _update(self, **changes: Any) -> Snapshot:
        """Replace fields of the snapshot (caller holds _lock or takes it here)."""
        with self._lock:
            self._snap = self._snap.evolve(**changes)
            self._lock.notify_all()
            return self._snap

    def _update_if(self, epoch: int, arms: Optional[int] = None, **changes: Any) -> bool:
        """Apply a read result only if the module cannot have changed since it was asked.

        `arms`: the arm and lock frames sent when it was asked (`_arms_sent`); an armed state
        read before one is not taken (`_newer_armed`).
        """
        with self._lock:
            if epoch != self._epoch:
                return False
            self._snap = self._snap.evolve(**self._newer_armed(arms, changes))
            self._lock.notify_all()
            return True

    def _newer_armed(self, arms: Optional[int], changes: Dict[str, Any]) -> Dict[str, Any]:
        """Return `changes` without an armed state older than the last arm or lock frame.

        A read's result is taken by the thread that asked, maybe after an arm frame that
        another thread sent and read back since: the older answer must not undo the newer one
        (an armed module taken for locked refuses a deploy). Caller holds _lock.
        """
        if arms is None or arms == self._arms or 'armed' not in changes:
            return changes
        changes = dict(changes)
        del changes['armed']
        if self._snap.armed is None:
            changes.pop('fresh', None)  # not re-read: armed is still unknown
        return changes

    def _current_epoch(self) -> int:
        with self._lock:
            return self._epoch

    def _asked(self) -> Tuple[int, int]:
        """Return (epoch, arm and lock frames sent) at once: what a read is taken against."""
        with self._lock:
            return self._epoch, self._arms

    def _arms_sent(self) -> int:
        """Return the count of arm and lock frames that left (for `_update_if`'s `arms`)."""
        with self._lock:
            return self._arms

    def _offline_text(self, snap: Snapshot) -> str:
        return f'module offline ({snap.offline_reason})'

    def _emit_status(self) -> None:
        self.listener.on_status(self.snapshot)

    def _on_blackbox_problem(self, text: str, ok: bool) -> None:
        if ok:
            self._log('info', f'black box: {text}')
        else:
            self._log('error', f'black box: {text}', key='blackbox', every_s=30.0)
        self.listener.on_diagnostics()

    # -- module I/O ------------------------------------------------------------------------------

    def _req(self, frame: bytes, retries: int = 0, timeout: Optional[float] = None,
             silence_ok: bool = False) -> Any:
        """Request with the D2 bookkeeping: an unanswered request makes the module offline."""
        token = None
        if not silence_ok:
            with self._lock:
                self._in_flight_seq += 1
                token = self._in_flight_seq
                self._online.request_sent(token, self.clock(), self.link.last_frame[0])
        unanswered = False
        try:
            return self.link.request(frame, timeout=timeout or self.config.request_timeout_s,
                                     retries=retries)
        except LinkTimeout:
            unanswered = True
            raise
        finally:
            if token is not None:
                with self._lock:
                    self._online.request_ended(token, unanswered)
            self._judge_online()

    # -- reader thread ---------------------------------------------------------------------------

    def _on_message(self, msg: Any) -> None:
        if self._stopping.is_set():
            return
        if isinstance(msg, p.TriggerRequest):
            self._on_trigger_request()
        elif isinstance(msg, p.Status):
            self._on_status(msg, via='status')
        elif isinstance(msg, p.Heartbeat):
            self._on_heartbeat()
        elif isinstance(msg, p.DeployAck):
            self._on_deploy_reply(msg, late=True)
        elif isinstance(msg, p.AutoTriggerFlags):
            self._set_flags(msg)
        elif isinstance(msg, p.ShutdownAck):
            self._log('warn', 'the module announced that it is switching off')
            self._update(shutdown_expected=True)
        self._judge_online()

    def _set_flags(self, reply: p.AutoTriggerFlags) -> None:
        self._update(attitude_trigger_enabled=reply.attitude_enabled,
                     freefall_trigger_enabled=reply.freefall_enabled)

    # -- other services --------------------------------------------------------------------------

    def get_config(self) -> Result:
        """`~/get_config`: read every setting afresh."""
        snap = self.snapshot
        if not snap.online:
            return Result.refused('offline', f'{self._offline_text(snap)}; showing the last '
                                  'read-back')
        try:
            self._read_config()
        except LinkError as exc:
            return Result.failed(f'could not read the settings: {exc}', cause='no_reply')
        return Result.done('read afresh from the module')

    def get_trigger_records(self) -> Result[Tuple[p.TriggerRecord, ...]]:
        """`~/get_trigger_records`: the module's non-empty trigger records (the value)."""
        snap = self.snapshot
        if not snap.online:
            return Result.refused('offline', self._offline_text(snap))
        try:
            records = self._fetch_records()
        except LinkError as exc:
            return Result.failed(f'no trigger records: {exc}', cause='no_reply')
        if not records.complete:
            return Result.done(f'{len(records)} record(s) in an answer cut short (a slot\'s frame '
                               'lost or corrupted): there may be more; ask again',
                               value=tuple(records))
        return Result.done(f'{len(records)} record(s)', value=tuple(records))

    def set_streaming(self, enabled: bool) -> Result:
        """`~/set_streaming`: turn the status stream on or off (kept across reconnects)."""
        snap = self.snapshot
        if not snap.online:
            return Result.refused('offline', f'{self._offline_text(snap)}; nothing sent')
        try:
            ok = self._set_streaming(enabled, silence_ok=True)
        except LinkError as exc:
            return Result.unknown(f'streaming not confirmed: {exc}', cause='no_reply')
        with self._lock:
            self._config = replace(self._config, stream_status=enabled)
        self._emit_status()
        return Result.checked(ok, f'status stream {"on" if self.snapshot.streaming else "off"}')

    def zero_sensor(self) -> Result:
        """`~/zero_sensor`: take the present attitude as level (P26)."""
        snap = self.snapshot
        if not snap.online:
            return Result.refused('offline', f'{self._offline_text(snap)}; nothing sent')
        try:
            ack = self._req(p.encode_sensor_zero(), retries=1)
        except LinkError as exc:
            return Result.unknown(f'zeroing not confirmed: {exc}', cause='no_reply')
        self.blackbox.record('state', event='sensor zeroed', success=ack.success)
        return Result.checked(ack.success, 'attitude sensor zeroed at the present mounting'
                              if ack.success else f'module answered {ack.raw.hex(" ")}')

    def shutdown_module(self, confirm: str) -> Result:
        """`~/shutdown_module`: switch the module off (token SHUTDOWN)."""
        if confirm != SHUTDOWN_TOKEN:
            return Result.refused('bad_token', f"refused: confirm must be exactly "
                                  f"'{SHUTDOWN_TOKEN}' (got {confirm!r}); nothing sent")
        snap = self.snapshot
        if not snap.online:
            return Result.refused('offline', f'{self._offline_text(snap)}; nothing sent')
        self._update(shutdown_expected=True)
        try:
            self._req(p.encode_shutdown(), retries=1)
        except LinkError as exc:
            self._update(shutdown_expected=False)
            return Result.unknown(f'shutdown not acknowledged: {exc}', cause='no_reply')
        self.blackbox.record('state', event='module shut down by request')
        self._safety_sync()
        return Result.done('module acknowledged and is switching off; switch it on with its '
                           'button (2 s) or external power')

    # -- diagnostics helpers -----------------------------------------------------------------

    def blackbox_problem(self, status: Optional[Any] = None) -> str:
        """Why the black box does not record, naming the parameter; '' when it does."""
        status = status or self.blackbox.status()
        if status.file_removed:
            # Part of this run's record is gone for good: said until the driver restarts.
            return f'{status.file_removed}; writing on in {status.path}'
        if status.writing:
            return ''
        where = f'blackbox_dir {self.config.blackbox_dir!r}: ' if status.open_failed else ''
        return f'cannot write: {where}{status.error}; {status.lost} records lost'

    def link_info(self) -> Dict[str, Any]:
        """Counters of the link for the diagnostics."""
        stats = self.link.serial.stats
        decoder = self.link.decoder
        return dict(frames_in=stats.frames_in, frames_out=stats.frames_out,
                    checksum_errors=decoder.checksum_errors,
                    bytes_discarded=decoder.bytes_discarded, timeouts=self.link.timeouts,
                    reconnects=stats.reconnects)

    def link_problem(self) -> str:
        """Explain why the module is offline, with what to do about it (D11)."""
        snap = self.snapshot
        config = self.config
        if not snap.port_open:
            return self.link.serial.last_error or f'{config.port} is not open'
        decoder = self.link.decoder
        bytes_in = self.link.serial.stats.bytes_in
        if self.link.last_frame_time is None and bytes_in > 0:
            return (f'{config.port} is open but none of the {bytes_in} bytes received form a '
                    f'valid DPS-S frame ({decoder.checksum_errors} checksum errors): wrong baud '
                    f'rate? Check the `baud` parameter ({config.baud}; the module default is '
                    '115200)')
        if snap.shutdown_expected:
            return 'the module was shut down by request; switch it on again'
        return (f'{snap.offline_reason}: is the module powered and connected, and is the '
                f'`baud` parameter ({config.baud}) right?')
