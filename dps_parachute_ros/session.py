"""The DPS-S parachute module as a device: link, black box, state, rules and policies. No ROS.

`ParachuteSession` owns the `ParachuteLink`, the `BlackBox` and the module state (its types are
in `dps_parachute_ros.state`), and applies the rules of the README's "Safety model of deploy" and
the driver decisions (D..) of ``docs/protocols.md``. It reports through a `Listener`, takes its
clock (monotonic seconds, for every rule that judges time; waits are bounded in real time) from
the caller, and its services are calls that return a `Result`. The ROS node only translates.

Threads, what each owns, and the lock that guards what they share:

- serial reader (``SerialLink``): decodes frames and handles unsolicited ones at once: the status
  stream, reboot heartbeats, late deploy acknowledgements, and trigger requests, whose
  confirmation is written right there (why a confirm takes milliseconds). It never waits for a
  reply (only it delivers replies).
- worker (``parachute-worker``): (re-)initializes the module, polls light, charging and voltage,
  sends heartbeats, fetches trigger records. Owns its schedule (``next_*`` locals).
- monitor (``parachute-monitor``): judges online/offline and the defer deadline from the clock
  (``tick()``), and records the link's error counters in the black box when they change; no I/O.
  It sleeps until the next of those deadlines (at most ``IDLE_WAKE_S``); a deferred request
  wakes it.
- callers (the node's service threads): deploy, arm, settings, queries. ``_actuation``
  serializes deploy and arm (never taken on the reader thread or by a trigger-request answer).

All module state is one immutable `Snapshot` in ``_snap``; it and every other field marked
"guarded by _lock" below are read and replaced only under ``_lock`` (a Condition's lock, so a
deploy can wait for a re-read). Listener callbacks and link I/O never run under ``_lock``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
import threading
import time
from typing import Any, Callable, Dict, List, Optional, Set, Tuple

from dps_parachute_ros import protocol as p
from dps_parachute_ros.attempts import AttemptsFile
from dps_parachute_ros.blackbox import BlackBox
from dps_parachute_ros.link import LinkBusy, LinkDown, LinkError, LinkTimeout, ParachuteLink
from dps_parachute_ros.settings_rule import (conditions, JUDGED_STEPS, order, Step, Trigger,
                                             would_deploy)
from dps_parachute_ros.state import (config_problems, Deployment, FLAG_SETTINGS, Listener,
                                     MODULE_WINDOW_S, RequestDecision, Result, SessionConfig,
                                     SETTINGS, Snapshot, source_name)
from uav_serial_common.logs import Throttle

DEPLOY_TOKEN = 'DEPLOY'
SHUTDOWN_TOKEN = 'SHUTDOWN'
MAX_FAILED_DEPLOYS = 2
"""P11: three unsuccessful attempts in a row put the module into protection; we stop at two."""
LOW_BATTERY_V = 3.5
"""On battery, a cell below this is a warning (a 1S Li-ion cell is near empty there), D9."""
FLAGS_QUERY_TIMEOUT_S = 0.3
"""The auto-trigger flag query is our extension (P14): a real module may stay silent."""
PARAM_WRITE_BUDGET_S = 1.8
"""A runtime parameter change that writes to the module answers within this time (D4)."""
REREAD_WAIT_S = 1.0
"""A deploy or an arm waits this long for the module's state to be re-read (D15)."""
ACTUATION_WAIT_S = 10.0
"""A deploy or arm waits this long for one already running."""
POWER_UP_HEARTBEATS_S = 0.2
"""Unsolicited heartbeats closer together than this belong to one power-up (P5, D3)."""
SAFETY_SYNC_S = 0.5
"""Longest wait for the black box's fsync on a safety event; none while it is failing."""
LINK_RECORD_PERIOD_S = 1.0
"""The link's error counters go to the black box when they change, at most this often (D10)."""
LINK_PROBLEM_COUNTERS = ('checksum_errors', 'bytes_discarded', 'timeouts', 'reconnects')
LINK_QUIET_S = 10.0
"""Preflight: a link error (checksum, lost reply, reconnect) this recent fails."""
LINK_ERROR_COUNTERS = ('checksum_errors', 'timeouts', 'reconnects')
"""What preflight judges the link by. Not discarded bytes: they also come from the end of a
trigger-record answer cut at its quiet gap (P15); not the flag query's silence (P14)."""
DEPLOY_FRAME = p.encode_deploy()
STREAM_GRACE = 0.5
"""Without a stream frame for this share of `offline_timeout_s` the driver asks the module: an
answer leaves time before the silence would make it offline, and means the stream stopped."""
STREAM_RETRY_S = (2.0, 60.0)
"""Back-off of the attempts to restore a stopped stream: first delay, longest delay."""
RECORDS_RETRY_S = (1.0, 30.0)
"""Back-off of the trigger-record fetch owed to a deployment of unknown source, while online."""
Check = Tuple[bool, str, str]
"""A preflight line: passed, name, detail."""
HELD_RETRY_S = 1.0
"""A desired setting held back (it would deploy at once) is tried again at most this often."""
IDLE_WAKE_S = 0.2
"""The worker and the monitor sleep until their next deadline, and at most this long (they see
state changes nobody signals within it). Each wake-up costs CPU: they used to poll at 50 Hz."""


class Withheld(Exception):
    """A settings write the rule refused (D16): it would deploy the armed module at once."""

    def __init__(self, what: str, reason: str) -> None:
        super().__init__(f'{what} not written: {reason}')
        self.reason = reason


@dataclass
class _Pending:
    t_rx: float
    deadline: float


@dataclass
class _Jobs:
    queue: List[str] = field(default_factory=list)
    init_busy: bool = False


class _Guarded(Listener):
    """The caller's listener; an exception in it is logged, never raised into the session."""

    def __init__(self, inner: Listener, log: Callable[..., None]) -> None:
        self._inner = inner
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


class ParachuteSession:
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
        self._port_open_count = 0           # link.last_frame count when the port opened
        self._offline_count = 0             # ... when the module went offline
        self._in_flight: Dict[int, Tuple[float, int]] = {}  # request -> (sent, frame count)
        self._in_flight_seq = 0
        self._pending: Optional[_Pending] = None
        self._reported_boots: Set[Optional[int]] = set()   # boots whose deployment was reported
        self._known_records: Optional[Set[bytes]] = None
        self._deploy_frame_left = False
        self._unknown_boot: Optional[int] = None  # boot count when a deploy became unknown
        self._last_boot_heartbeat = -1e9
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
        self._throttle = Throttle()
        self._link_recorded: Tuple[int, ...] = (0,) * len(LINK_PROBLEM_COUNTERS)
        self._link_recorded_at = -1e9
        self._link_seen: Tuple[int, ...] = (0,) * len(LINK_ERROR_COUNTERS)
        self._silent_flag_queries = 0       # flag queries unanswered (P14): no link error
        self._link_changed_at = -1e9        # when one of the problem counters last grew
        # -- guarded by _jobs_cond ----------------------------------------------------------
        self._jobs = _Jobs()
        self._jobs_cond = threading.Condition()
        # -- other ----------------------------------------------------------------------------
        self._actuation = threading.Lock()
        self._attempts = AttemptsFile(config.blackbox_dir, config.port)
        self.release_gate: Optional[Any] = None  # a ReleaseGate (release_gate.py), or None
        self._stopping = threading.Event()
        self._monitor_wake = threading.Event()
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
        self._monitor = threading.Thread(target=self._monitor_loop, name='parachute-monitor',
                                         daemon=True)

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
        self._monitor_wake.set()
        with self._jobs_cond:
            self._jobs_cond.notify_all()
        with self._lock:
            pending, self._pending = self._pending, None
        if pending is not None:
            self.blackbox.record('decision', what='trigger request', decision='not answered',
                                 reason='driver stopped while the request was deferred')
        self.link.stop(timeout=1.0)
        for thread in (self._worker, self._monitor):
            if thread.is_alive():
                thread.join(1.0)
        # A deploy or arm in flight has just lost its link: let it record its outcome.
        if self._actuation.acquire(timeout=1.0):
            self._actuation.release()
        self._record_link(final=True)
        self.blackbox.record('stop')
        self.blackbox.close(timeout=1.0)

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
            pending = None
            if config.trigger_request_policy != old.trigger_request_policy:
                self._update(policy=config.trigger_request_policy)
                pending, self._pending = self._pending, None
        self.link.layout = config.auto_trigger_flag_layout
        if config.blackbox_max_mb != old.blackbox_max_mb:
            self.blackbox.set_max_bytes(int(config.blackbox_max_mb * 1e6)
                                        if config.blackbox_max_mb > 0 else None)
        if config.trigger_request_policy != old.trigger_request_policy:
            policy = config.trigger_request_policy
            self.blackbox.record('decision', what='policy', policy=policy)
            self.blackbox.sync(None)
            self._log('info', f'trigger requests: {policy}')
            if pending is not None:
                # A policy change settles a waiting request at once, under the new policy (D8).
                why = f'policy changed to {policy} while the request was pending'
                if policy == 'confirm':
                    self._answer_pending(pending, True, policy, why)
                else:
                    self._decide('denied', policy, why, pending.t_rx, None)
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

    def _update(self, **changes: Any) -> Snapshot:
        """Replace fields of the snapshot (caller holds _lock or takes it here)."""
        with self._lock:
            self._snap = self._snap.evolve(**changes)
            self._lock.notify_all()
            return self._snap

    def _update_if(self, epoch: int, **changes: Any) -> bool:
        """Apply a read result only if the module cannot have changed since it was asked."""
        with self._lock:
            if epoch != self._epoch:
                return False
            self._snap = self._snap.evolve(**changes)
            self._lock.notify_all()
            return True

    def _current_epoch(self) -> int:
        with self._lock:
            return self._epoch

    def _safety_sync(self) -> bool:
        """Fsync the black box on a safety event: bounded, and no wait while it is failing."""
        return self.blackbox.sync(SAFETY_SYNC_S if self.blackbox.status().writing else 0.0)

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
                self._in_flight[token] = (self.clock(), self.link.last_frame[0])
        try:
            return self.link.request(frame, timeout=timeout or self.config.request_timeout_s,
                                     retries=retries)
        finally:
            if token is not None:
                with self._lock:
                    self._in_flight.pop(token, None)
            self._judge_online()

    def _on_tx(self, data: bytes) -> None:
        # Every deploy frame that leaves counts until the module answers one, whatever ends
        # the wait (P11, D6): a timeout, a dropped link, a shutdown.
        if data == DEPLOY_FRAME:
            with self._lock:
                self._deploy_frame_left = True
                self._deploy_frame_at = self.clock()
                self._snap = replace(self._snap, unacked_deploys=self._snap.unacked_deploys + 1,
                                     failed_deploys=self._snap.failed_deploys + 1)

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

    def _on_heartbeat(self) -> None:
        # P5: nobody asked, so the module has just (re)booted. It sends two, 50 ms apart: one
        # reboot (D3). Until it is re-read its armed state is unknown (D15).
        now = self.clock()
        with self._lock:
            first = now - self._last_boot_heartbeat > POWER_UP_HEARTBEATS_S
            self._last_boot_heartbeat = now
            if first:
                self._epoch += 1
                self._snap = replace(self._snap, streaming=False, armed=None, triggered=None,
                                     fresh=False, initialized=False)
        if not first:
            return
        self._log('warn', 'unsolicited heartbeat: the module has (re)booted')
        self.blackbox.record('state', event='module reboot (unsolicited heartbeat)')
        self._void_pending('the module rebooted while the request was pending')
        self._schedule('init', force=True)
        self._emit_status()
        self.listener.on_diagnostics()
        with self._lock:
            # The second heartbeat of this power-up may have waited (in the port) for all of
            # this to finish, long on a loaded host: the 0.2 s run from here, not from before.
            self._last_boot_heartbeat = max(self._last_boot_heartbeat, self.clock())

    def _on_status(self, status: p.Status, via: str, epoch: Optional[int] = None) -> None:
        # A status frame tells armed and triggered as they are now: a re-read (D15).
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
        before = self._set_triggered(status.triggered, via, epoch, tilt_deg=float(status.tilt_deg),
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

    def _on_connection(self, up: bool, reason: str) -> None:
        if self._stopping.is_set():
            return
        with self._lock:
            self._epoch += 1
            if up:
                self._port_open_count = self.link.last_frame[0]
            self._snap = replace(self._snap, port_open=up, initialized=False, fresh=False)
        self.blackbox.record('state', port_open=up, reason=reason)
        if up:
            self._schedule('init', force=True)
        self._judge_online()

    def _set_flags(self, reply: p.AutoTriggerFlags) -> None:
        self._update(attitude_trigger_enabled=reply.attitude_enabled,
                     freefall_trigger_enabled=reply.freefall_enabled)

    # -- trigger requests (D8) ---------------------------------------------------------------

    def _on_trigger_request(self) -> None:
        t_rx = self.clock()
        with self._lock:
            policy = self._config.trigger_request_policy
            defer_s = self._config.defer_timeout_s
        if policy == 'confirm' and self.release_gate is not None and \
                self.release_gate.available('trigger request'):
            # The gate (the motor stop) waits: never on the reader thread, which delivers replies.
            threading.Thread(target=self._confirm_after_gate, args=(t_rx, policy),
                             name='parachute-gate', daemon=True).start()
        elif policy == 'confirm':
            try:
                self.link.write(p.encode_trigger_confirm())  # first, before anything else
            except LinkDown as exc:
                self._decide('denied', policy, f'could not send the confirmation: {exc}', t_rx,
                             None)
                return
            self._decide('confirmed', policy, 'policy confirm: confirmed at once', t_rx,
                         self.clock())
        elif policy == 'deny':
            self._decide('denied', policy, 'policy deny: no confirmation sent', t_rx, None)
        else:
            with self._lock:
                old = self._pending
                self._pending = _Pending(t_rx, t_rx + defer_s)
                self._snap = replace(self._snap, pending_request=True)
            self._monitor_wake.set()  # its deadline
            if old is not None:
                self._decide('timed_out', policy, 'superseded by a newer trigger request',
                             old.t_rx, None)
            self.blackbox.record('decision', what='trigger request deferred', deadline_s=defer_s)
            self.blackbox.sync(None)
            self._log('warn', f'trigger request from the module: answer ~/answer_trigger_request '
                              f'within {defer_s:.2f} s (else denied)')
            self.listener.on_diagnostics()

    def _confirm_after_gate(self, t_rx: float, policy: str) -> None:
        self.release_gate.before_release('trigger request', t_rx)
        try:
            self.link.write(p.encode_trigger_confirm())
        except LinkDown as exc:
            self._decide('denied', policy, f'could not send the confirmation: {exc}', t_rx, None)
            return
        self._decide('confirmed', policy, 'policy confirm: confirmed after the release gate',
                     t_rx, self.clock())

    def _decide(self, decision: str, policy: str, reason: str, t_rx: float,
                t_tx: Optional[float]) -> None:
        latency = None if t_tx is None else (t_tx - t_rx) * 1000.0
        with self._lock:
            if self._pending is None:
                self._snap = replace(self._snap, pending_request=False)
        self.blackbox.record('decision', what='trigger request', decision=decision,
                             policy=policy, reason=reason, latency_ms=latency)
        self.blackbox.sync(None)
        self.listener.on_trigger_request(RequestDecision(decision, policy, reason, latency))
        if decision == 'confirmed':
            self._log('error', f'trigger request confirmed: {reason}')
        else:
            self._log('warn', f'trigger request {decision}: {reason}')
        self.listener.on_diagnostics()

    def _answer_pending(self, pending: _Pending, confirm: bool, policy: str,
                        why: str) -> Result:
        """Answer a deferred request; say what is true about what the module does (D8)."""
        if not confirm:
            self._decide('denied', policy, f'{why}: no confirmation sent', pending.t_rx, None)
            return Result(True, 'denied: nothing sent')
        age = self.clock() - pending.t_rx
        snap = self.snapshot
        problem = ''
        if age >= MODULE_WINDOW_S:
            problem = (f"{age:.2f} s after the request: the module's 1 s window has passed "
                       '(P10); no confirmation sent')
        elif not snap.online:
            problem = f'{self._offline_text(snap)}: no confirmation sent'
        elif snap.triggered:
            problem = 'the module has already deployed: no confirmation sent'
        elif snap.armed is False and snap.fresh:
            problem = ('the module is locked, and a locked module cannot deploy (P12, P20): '
                       'no confirmation sent')
        if problem:
            decision = 'timed_out' if age >= MODULE_WINDOW_S else 'denied'
            self._decide(decision, policy, f'{why}, but {problem}', pending.t_rx, None)
            return Result(False, f'not confirmed: {problem}')
        if self.release_gate is not None:
            self.release_gate.before_release('trigger request', pending.t_rx)
        try:
            self.link.write(p.encode_trigger_confirm())
        except LinkDown as exc:
            self._decide('denied', policy, f'{why}, but the link is down: {exc}', pending.t_rx,
                         None)
            return Result(False, f'confirmation not sent: {exc}')
        t_tx = self.clock()
        # Armed only as read since the module last could have changed unseen (D15).
        if snap.armed and snap.fresh:
            outcome = 'the module was armed: it deploys on it (~/trigger_event reports it)'
        else:
            outcome = ("the module's armed state is not known: ~/triggered shows whether it "
                       'deploys')
        self._decide('confirmed', policy, f'{why}; {outcome}', pending.t_rx, t_tx)
        return Result(True, f'confirmation sent {(t_tx - pending.t_rx) * 1000:.0f} ms after the '
                            f'request; {outcome}')

    def _void_pending(self, why: str) -> None:
        """Settle a waiting request the module no longer makes (it rebooted): nothing sent."""
        with self._lock:
            pending, self._pending = self._pending, None
            policy = self._config.trigger_request_policy
        if pending is not None:
            # A rebooted module boots locked and has forgotten its question (D15): a confirm now
            # would answer nobody, and the armed state behind "it deploys" is from before.
            self._decide('denied', policy, f'{why}: its request is gone; no confirmation sent',
                         pending.t_rx, None)

    def answer_trigger_request(self, confirm: bool) -> Result:
        """`~/answer_trigger_request`: answer the deferred request, if one is pending."""
        with self._lock:
            pending, self._pending = self._pending, None
            policy = self._config.trigger_request_policy
        if pending is None:
            return Result(False, 'no trigger request is pending')
        return self._answer_pending(pending, confirm, policy,
                                    f'answered {str(confirm).lower()} via '
                                    '~/answer_trigger_request')

    # -- monitor thread: online/offline (D2) and the defer deadline -------------------------------

    def _monitor_loop(self) -> None:
        wake = self._monitor_wake
        wait = IDLE_WAKE_S
        while not self._stopping.is_set():
            wake.wait(wait)
            wake.clear()
            if self._stopping.is_set():
                return
            try:
                self.tick()
                self._record_link()
                wait = self._monitor_wait()
            except Exception as exc:  # noqa: BLE001 - the monitor must survive a bug
                self._log('error', f'monitor failed: {exc!r}', key='monitor')
                wait = IDLE_WAKE_S

    def _monitor_wait(self) -> float:
        """Return how long the monitor may sleep: until the next deadline ``tick()`` judges."""
        now = self.clock()
        count, last = self.link.last_frame
        due = now + IDLE_WAKE_S
        with self._lock:
            timeout = self._config.offline_timeout_s
            if self._pending is not None:
                due = min(due, self._pending.deadline)
            snap = self._snap
            if snap.online:
                sent = [t for t, c in self._in_flight.values() if c == count]
                if sent:
                    due = min(due, min(sent) + timeout)
                if snap.streaming and last is not None:
                    due = min(due, last + timeout)
        return max(due - now, 0.001)

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
        now = self.clock()
        with self._lock:
            pending = self._pending
            if pending is None or now < pending.deadline:
                return
            self._pending = None
            policy = self._config.trigger_request_policy
            defer_s = self._config.defer_timeout_s
        self._decide('timed_out', policy,
                     f'nobody answered within defer_timeout_s = {defer_s:.2f} s: denied',
                     pending.t_rx, None)

    def _judge_online(self) -> None:
        now = self.clock()
        count, last = self.link.last_frame
        with self._lock:
            snap = self._snap
            timeout = self._config.offline_timeout_s
            if not snap.port_open:
                online, reason = False, self.link.serial.last_error or 'port closed'
            elif last is None or count <= self._port_open_count:
                online, reason = False, 'no valid frame from the module since the port opened'
            elif not snap.online and count <= self._offline_count:
                online, reason = False, snap.offline_reason  # back only with a new frame
            else:
                online, reason = True, ''
                stale = [t for t, c in self._in_flight.values() if c == count]
                if stale and now - min(stale) >= timeout:
                    online = False
                    reason = f'no reply within {timeout:.1f} s of a request'
                elif snap.streaming and now - last >= timeout:
                    online = False
                    reason = f'no status frame for {timeout:.1f} s while streaming'
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
                self._offline_count = count
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

    # -- worker thread -----------------------------------------------------------------------

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
            armed = self._req(p.encode_armed_query(), retries=1).armed
            triggered = self._req(p.encode_triggered_query(), retries=1).triggered
            if self._set_triggered(triggered, 'query', epoch, armed=armed, fresh=True) is None:
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
                # A new power-up clears the module's count of unsuccessful attempts (P19).
                self._snap = replace(self._snap, unacked_deploys=0, failed_deploys=0, fresh=False,
                                     armed=None)
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
            self._void_pending('the module rebooted while the request was pending')
            if reinit:
                self._schedule('init', force=True)
        return epoch

    def _save_attempts(self, leaving: int = 0) -> None:
        """Keep the unsuccessful deploy frames of this power-up for a later run (P11)."""
        snap = self.snapshot
        problem = self._attempts.save(snap.boot_count, snap.failed_deploys + leaving,
                                      snap.unacked_deploys + leaving)
        if problem:
            self._log('warn', f'deploy attempts not kept for a restart: {problem}',
                      key='attempts', every_s=60.0)

    def _set_streaming(self, enabled: bool, silence_ok: bool = False) -> bool:
        reply = self._req(p.encode_streaming(enabled), retries=1, silence_ok=silence_ok)
        with self._lock:
            self._stream_on_at = self.clock()  # its first frame is due from now
            self._snap = replace(self._snap, streaming=reply.enabled,
                                 stream_problem=self._snap.stream_problem if enabled else '')
            self._lock.notify_all()
        return reply.enabled == enabled

    # -- the status stream, and polling when it is gone (D2) -------------------------------------

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
        status = self._req(p.encode_status_query())
        if epoch != before or epoch != self._current_epoch():
            return
        self._on_status(status, via='poll', epoch=epoch)
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
        epoch = self._current_epoch()
        if not self.snapshot.streaming:
            # The status first: it is what the online judgement and a deploy need.
            self._on_status(self._req(p.encode_status_query()), via='poll', epoch=epoch)
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

    # -- settings (D4, D5) -----------------------------------------------------------------------

    def _read_config(self, reinit: bool = True) -> None:
        """Read every setting afresh (raises LinkError)."""
        for setting in SETTINGS.values():
            reply = self._req(setting.encode_query(), retries=1)
            self._update(**{setting.field: reply.value})
        self._note_boot_count(self._req(p.encode_boot_count_query(), retries=1).count, reinit)
        snap = self.snapshot
        if snap.attitude_trigger_enabled is None or snap.freefall_trigger_enabled is None:
            self._query_flags()
        with self._lock:
            self._snap = replace(self._snap, config_reads=self._snap.config_reads + 1)
        self._update_mismatch(log=False)

    def _query_flags(self) -> bool:
        # P14: a firmware ignoring D3 would take the query as "enable the attitude trigger", so
        # it is a possible settings write: sent at most once per run while unanswered (D5), and
        # only when enabling the attitude trigger would not deploy the module at once (D16).
        with self._lock:
            if self._flags_query_sent and not self._flags_query_answered:
                return False
        danger = self._gate([('attitude', True)], 'auto-trigger flag query (P14)')
        if danger:
            self._log('warn', 'auto-trigger flag query not sent (a firmware may take it as '
                              f'"enable the attitude trigger", P14): {danger}', key='flag-query')
            return False
        with self._lock:
            self._flags_query_sent = True
        try:
            reply = self._req(p.encode_auto_trigger_query(), timeout=FLAGS_QUERY_TIMEOUT_S,
                              silence_ok=True)
        except LinkTimeout:
            with self._lock:
                self._silent_flag_queries += 1
            return False
        self._set_flags(reply)
        with self._lock:
            self._flags_query_answered = True
        return True

    # -- the settings rule: every write to the module passes here (D16) -------------------------

    @staticmethod
    def _trigger_settings(snap: Snapshot) -> Trigger:
        return Trigger(snap.attitude_threshold_raw, snap.freefall_threshold_raw,
                       snap.attitude_trigger_enabled, snap.freefall_trigger_enabled)

    def _gate(self, steps: List[Step], origin: str) -> str:
        """Why writing `steps` (in order) would deploy the module at once, or '' to write.

        The one check of every settings write, whoever asks (D16): the status is read afresh
        (raises LinkError when it is not answered: nothing is written then) and judged by
        `settings_rule.would_deploy`. A refusal is recorded in the black box.
        """
        if not any(name in JUDGED_STEPS for name, _ in steps):
            return ''
        epoch = self._current_epoch()
        status = self._req(p.encode_status_query(), retries=1)
        self._on_status(status, via='query', epoch=epoch)
        danger = would_deploy(self._trigger_settings(self.snapshot), status.armed,
                              status.triggered, float(status.tilt_deg), float(status.accel_g),
                              steps)
        if danger:
            self.blackbox.record('decision', what='settings write withheld', origin=origin,
                                 steps=[list(step) for step in steps], reason=danger)
        return danger

    def _write_setting(self, name: str, value: float, origin: str) -> Tuple[bool, str]:
        """Write one numeric setting, verified; raises Withheld when the rule forbids it."""
        setting = SETTINGS[name]
        raw = setting.to_raw(value)
        danger = self._gate([(name, value)], origin)
        if danger:
            raise Withheld(f'{name} = {value:g}', danger)
        reply = self._req(setting.encode_set(value))
        if not p.is_set_ack(reply, raw):
            return False, (f'module answered {reply.raw.hex(" ")} to setting {name} = {value}: '
                           'not an acknowledgement')
        back = self._req(setting.encode_query()).value
        with self._lock:
            self._snap = replace(self._snap, **{setting.field: back},
                                 config_reads=self._snap.config_reads + 1)
            snap = self._snap
        self.listener.on_config(snap)
        if back != raw:
            return False, (f'{name}: wrote {setting.to_si(raw)}, module reads back '
                           f'{setting.to_si(back)}')
        return True, f'{name} = {setting.to_si(raw)} verified'

    def _write_flags(self, attitude: Optional[bool] = None, freefall: Optional[bool] = None,
                     origin: str = '') -> Tuple[bool, str]:
        """Enable/disable auto triggers (None = leave); verified by the replies (P8, D5).

        Each frame is judged by the rule first (raises Withheld); a disable goes first.
        """
        encode = {'attitude': p.encode_attitude_trigger, 'freefall': p.encode_freefall_trigger}
        asked = (('attitude', attitude), ('freefall', freefall))
        for which, value in order([(w, v) for w, v in asked if v is not None]):
            danger = self._gate([(which, value)], origin)
            if danger:
                raise Withheld(f'{which} trigger {"enable" if value else "disable"}', danger)
            self._set_flags(self._req(encode[which](value)))
        snap = self.snapshot
        self.listener.on_config(snap)
        wrong = []
        if attitude is not None and snap.attitude_trigger_enabled != attitude:
            wrong.append('attitude trigger reads '
                         f'{"enabled" if snap.attitude_trigger_enabled else "disabled"}')
        if freefall is not None and snap.freefall_trigger_enabled != freefall:
            wrong.append('free-fall trigger reads '
                         f'{"enabled" if snap.freefall_trigger_enabled else "disabled"}')
        if wrong:
            return False, ('module did not confirm: ' + ', '.join(wrong)
                           + f' (flag layout {self.link.layout})')
        return True, 'auto triggers verified'

    def _write_step(self, param: str, value: Any, origin: str) -> Tuple[bool, str]:
        """Write one desired setting by its parameter name (flags: 'enable' / 'disable')."""
        if param in SETTINGS:
            return self._write_setting(param, value, origin)
        return self._write_flags(**{FLAG_SETTINGS[param]: value == 'enable'}, origin=origin)

    @staticmethod
    def _step(param: str, value: Any) -> Step:
        """Return the rule's step for a desired setting given by parameter name and value."""
        if param in FLAG_SETTINGS:
            return FLAG_SETTINGS[param], value == 'enable'
        return param, value

    def _ordered(self, wanted: Dict[str, Any]) -> List[Tuple[str, Any]]:
        """Parameter name -> value pairs in the rule's safest order (a disable first)."""
        steps = {self._step(n, v): n for n, v in wanted.items()}
        return [(steps[step], wanted[steps[step]]) for step in order(steps)]

    def _desired_differing(self) -> Dict[str, Any]:
        """Return the desired settings (parameter name -> value) the module does not have."""
        config = self.config
        snap = self.snapshot
        wanted: Dict[str, Any] = {}
        for name, setting in SETTINGS.items():
            value = config.desired(name)
            if value != -1 and snap.raw(name) != setting.to_raw(value):
                wanted[name] = value
        for name, which in FLAG_SETTINGS.items():
            value = config.desired(name)
            if value != 'keep' and \
                    getattr(snap, f'{which}_trigger_enabled') != (value == 'enable'):
                wanted[name] = value
        return wanted

    def _apply_desired(self, only: Optional[Set[str]] = None) -> None:
        """Write every desired setting that differs from the module's, then verify (D4).

        One that would deploy the armed module at once is held back (D16): logged, named in
        the settings diagnostics, and written once it no longer would (``_recheck_held``, which
        passes `only` the held ones: a value set by a service meanwhile stays until the next
        re-initialization, as before).
        """
        with self._lock:
            self._held_retry_at = self.clock() + HELD_RETRY_S
            before = dict(self._held)
        wanted = self._desired_differing()
        if only is not None:
            wanted = {n: v for n, v in wanted.items() if n in only}
        held = {n: h for n, h in before.items() if only is not None and n not in only}
        for name, value in self._ordered(wanted):
            try:
                ok, reason = self._write_step(name, value, 'desired settings')
            except Withheld as exc:
                held[name] = (value, exc.reason)
                if before.get(name, (None, ''))[0] != value:
                    self._log('warn', f'desired setting {name} = {value} not written: '
                                      f'{exc.reason}; it is written once it no longer would '
                                      '(judged on every status)')
                continue
            if not ok:
                self._log('warn', f'desired setting not applied: {reason}')
            elif name in before:
                self._log('info', f'desired setting held back is written now: {reason}')
        with self._lock:
            self._held = held
        self._update_mismatch()

    def _recheck_held(self, status: p.Status) -> None:
        """On a status: retry held-back settings the rule would let through now (reader)."""
        now = self.clock()
        with self._lock:
            if not self._held or not self._snap.initialized or now < self._held_retry_at:
                return
            steps = [self._step(n, v) for n, (v, _) in self._held.items()]
            trigger = self._trigger_settings(self._snap)
        if all(would_deploy(trigger, status.armed, status.triggered, float(status.tilt_deg),
                            float(status.accel_g), [step]) for step in steps):
            return
        with self._lock:
            self._held_retry_at = now + HELD_RETRY_S
        self._schedule('settings')

    def _mismatch(self, snap: Snapshot, config: SessionConfig,
                  held: Dict[str, Tuple[Any, str]]) -> List[str]:
        mismatch = []
        for name, setting in SETTINGS.items():
            value = config.desired(name)
            have = snap.raw(name)
            if value != -1 and have != setting.to_raw(value):
                mismatch.append(f'{name}: want {value}, module '
                                f'{"unknown" if have is None else setting.to_si(have)}')
        for name, which in FLAG_SETTINGS.items():
            value = config.desired(name)
            have = getattr(snap, f'{which}_trigger_enabled')
            if value != 'keep' and (have is None or have != (value == 'enable')):
                mismatch.append(f'{name}: want {value}, module '
                                f'{"unknown" if have is None else have}')
        return [f'{line} (not written: {held[line.split(":")[0]][1]})'
                if line.split(':')[0] in held else line for line in mismatch]

    def _update_mismatch(self, log: bool = True) -> None:
        with self._lock:
            # A held setting the module has now, or no longer desired, is no longer held.
            differing = self._desired_names()
            self._held = {n: (v, why) for n, (v, why) in self._held.items()
                          if self._config.desired(n) == v and n in differing}
            mismatch = tuple(self._mismatch(self._snap, self._config, self._held))
            held = tuple(f'{n} = {v} not written: {why}' for n, (v, why) in self._held.items())
            changed = mismatch != self._snap.mismatch or held != self._snap.held
            self._snap = replace(self._snap, mismatch=mismatch, held=held)
            snap = self._snap
        if changed:
            self.listener.on_diagnostics()
            if mismatch and log:
                self._log('warn', 'settings do not match: ' + '; '.join(mismatch))
        self.listener.on_config(snap)

    def _desired_names(self) -> Set[str]:
        """Desired settings the module does not have (caller holds _lock)."""
        return {line.split(':')[0] for line in self._mismatch(self._snap, self._config, {})}

    def set_thresholds(self, values: Dict[str, float]) -> Result:
        """`~/set_thresholds`: write the given settings (name -> SI value), each verified."""
        for name, value in values.items():
            try:
                SETTINGS[name].to_raw(value)
            except p.ProtocolError as exc:
                return Result(False, f'refused, nothing sent: {exc}')
        self.blackbox.record('request', what='set_thresholds', values=values)
        snap = self.snapshot
        if not snap.online:
            return Result(False, f'{self._offline_text(snap)}; nothing sent')
        results = []
        ok_all = True
        steps = order(values.items())
        try:
            danger = self._gate(steps, '~/set_thresholds')
            if danger:
                return self._refused_setting(danger)
            for name, value in steps:
                try:
                    ok, message = self._write_setting(name, value, '~/set_thresholds')
                except Withheld as exc:
                    ok, message = False, str(exc)
                ok_all &= ok
                results.append(message)
        except LinkError as exc:
            ok_all = False
            results.append(f'no reply: {exc}')
        self._update_mismatch()
        return Result(ok_all, '; '.join(results) or 'nothing to change')

    def _refused_setting(self, danger: str) -> Result:
        self.blackbox.record('decision', what='settings refused', reason=danger)
        self._log('warn', f'settings change refused: {danger}')
        return Result(False, f'refused, nothing written: {danger}')

    def set_auto_triggers(self, attitude: bool, freefall: bool) -> Result:
        """`~/set_auto_triggers`: enable/disable both auto triggers, verified (D5)."""
        self.blackbox.record('request', what='set_auto_triggers', attitude=attitude,
                             freefall=freefall)
        snap = self.snapshot
        if not snap.online:
            return Result(False, f'{self._offline_text(snap)}; nothing sent')
        try:
            danger = self._gate(order([('attitude', attitude), ('freefall', freefall)]),
                                '~/set_auto_triggers')
            if danger:
                return self._refused_setting(danger)
            ok, message = self._write_flags(attitude, freefall, '~/set_auto_triggers')
        except Withheld as exc:
            ok, message = False, str(exc)
        except LinkError as exc:
            ok, message = False, f'no reply: {exc}'
        self._update_mismatch()
        return Result(ok, message)

    def commit_desired(self, changes: Dict[str, Any]) -> Tuple[bool, str]:
        """Write desired settings of a parameter set to the module: all or nothing (D4).

        Every write is verified; when one fails, those already written are put back. Local
        settings are not touched here: `reconfigure` applies them once the set is accepted.
        """
        wanted = {n: v for n, v in changes.items()
                  if (n in SETTINGS or n in FLAG_SETTINGS) and v not in (-1, 'keep')}
        if not wanted:
            return True, ''
        names = ', '.join(wanted)
        snap = self.snapshot
        if not snap.online:
            return self._param_refused(changes, f'{self._offline_text(snap)}; {names} not '
                                                'written')
        deadline = time.monotonic() + PARAM_WRITE_BUDGET_S
        written: List[Tuple[str, Any]] = []
        steps = self._ordered(wanted)
        try:
            danger = self._gate([self._step(n, v) for n, v in steps], 'parameters')
            if danger:
                return self._param_refused(changes, f'refused, nothing written: {danger}')
            for name, value in steps:
                if time.monotonic() > deadline:
                    raise LinkTimeout(f'no time left for {name} within '
                                      f'{PARAM_WRITE_BUDGET_S} s')
                if name in SETTINGS:
                    before = self.snapshot.raw(name)
                    if before is None:
                        before = self._req(SETTINGS[name].encode_query(), retries=1).value
                else:
                    before = getattr(self.snapshot, f'{FLAG_SETTINGS[name]}_trigger_enabled')
                try:
                    ok, reason = self._write_step(name, value, 'parameters')
                except Withheld as exc:
                    raise LinkError(str(exc)) from None
                written.append((name, before))
                if not ok:
                    raise LinkError(reason)
        except LinkError as exc:
            undone = self._undo(written)
            return self._param_refused(changes, f'module did not confirm {names}: {exc}'
                                                f'{undone}')
        self.blackbox.record('parameter', changes=changes, accepted=True)
        return True, ''

    def _undo(self, written: List[Tuple[str, Any]]) -> str:
        """Put back settings written by a refused parameter set; say how that went."""
        if not written:
            return ''
        back, failed = [], []
        for name, before in reversed(written):
            try:
                if before is None:
                    raise LinkError('its previous value is not known')
                if name in SETTINGS:
                    ok, reason = self._write_setting(name, SETTINGS[name].to_si(before),
                                                     'putting back a refused parameter set')
                else:
                    ok, reason = self._write_flags(**{FLAG_SETTINGS[name]: before},
                                                   origin='putting back a refused parameter '
                                                   'set')
                if not ok:
                    raise LinkError(reason)
                back.append(name)
            except (LinkError, Withheld, p.ProtocolError) as exc:
                failed.append(f'{name} ({exc})')
        self._update_mismatch()
        text = f'; put back {", ".join(back)}' if back else ''
        if failed:
            text += f'; could NOT put back {"; ".join(failed)}'
            self._log('error', f'a refused parameter set left the module changed: {text}')
        return text

    def _param_refused(self, changes: Dict[str, Any], reason: str) -> Tuple[bool, str]:
        self.blackbox.record('parameter', changes=changes, accepted=False, reason=reason)
        self._log('warn', f'parameter set refused: {reason}')
        return False, reason

    # -- deployments (D6, D7) ------------------------------------------------------------------

    def _set_triggered(self, triggered: Optional[bool], via: str, epoch: Optional[int] = None,
                       **also: Any) -> Optional[Snapshot]:
        """Take a triggered state read, with other fields, in one update.

        Returns the snapshot before it, or None when `epoch` shows that the module may have
        changed since it was read (nothing is taken then).
        """
        with self._lock:
            if epoch is not None and epoch != self._epoch:
                return None
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

    def _fetch_records(self) -> List[p.TriggerRecord]:
        """Query the history; remember every record; return the non-empty ones."""
        records = [r for r in self.link.query_records() if not r.is_empty]
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
            fired = [r for r in records if r.boot_count == unknown_boot]
            self._resolve_unknown_deploy(
                bool(fired), f'the module rebooted since (boot {unknown_boot} -> {boot}); its '
                f'trigger records {"show" if fired else "show no"} deployment in boot '
                f'{unknown_boot}')
        if not first:
            # Deployments that happened while nobody watched (unplugged, rebooted).
            for record in records:
                if record.raw not in known:
                    self._report(record.source, 'record', record, record.boot_count)

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

    def _on_deploy_reply(self, ack: p.DeployAck, late: bool) -> None:
        with self._lock:
            failed = 0 if ack.success else self._snap.failed_deploys
            self._snap = replace(self._snap, unacked_deploys=0, failed_deploys=failed)
        if not late:
            self._save_attempts()  # (a late one is saved by the deploy call it ends)
        if not ack.success:
            return
        if late:
            self._log('warn', 'late deploy acknowledgement: the module deployed')
        self._deployed_by_ack()
        self._resolve_unknown_deploy(True, 'late acknowledgement')

    def _deployed_by_ack(self) -> None:
        with self._lock:
            self._snap = replace(self._snap, armed=False)
            boot = self._snap.boot_count
        self._report(p.SOURCE_SERIAL, 'deploy_ack', None, boot)
        self._set_triggered(True, via='deploy ack')
        self._schedule('records')

    def _resolve_unknown_deploy(self, triggered: bool, how: str) -> None:
        with self._lock:
            if not self._snap.deploy_outcome_unknown:
                return
            self._snap = replace(self._snap, deploy_outcome_unknown=False)
        outcome = 'deployed' if triggered else 'not deployed'
        self.blackbox.record('decision', what='deploy', outcome=outcome, resolved=how)
        self.blackbox.sync(None)
        self._log('error' if triggered else 'warn',
                  f'the earlier deploy whose outcome was unknown: {outcome} ({how})')
        self.listener.on_diagnostics()

    def _wait_fresh(self) -> Snapshot:
        """Wait (bounded) until armed and triggered have been re-read (D15)."""
        deadline = time.monotonic() + REREAD_WAIT_S
        with self._lock:
            while not self._snap.fresh and self._snap.online:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._stopping.is_set():
                    break
                self._lock.wait(min(remaining, 0.05))
            return self._snap

    def _query_triggered(self) -> Optional[bool]:
        """Ask the module whether it is triggered; None when it does not answer."""
        epoch = self._current_epoch()
        try:
            triggered = self._req(p.encode_triggered_query()).triggered
        except LinkError:
            return None
        if epoch == self._current_epoch():
            self._set_triggered(triggered, via='query')
        return triggered

    def deploy(self, confirm: str, arm_if_locked: bool = False) -> Result:
        """`~/deploy`: the rules of the README's "Safety model of deploy" (D6)."""
        t0 = self.clock()
        self.blackbox.record('request', what='deploy', token_ok=confirm == DEPLOY_TOKEN,
                             arm_if_locked=arm_if_locked)
        if confirm != DEPLOY_TOKEN:
            return self._deploy_end('refused', f"deploy refused: confirm must be exactly "
                                    f"'{DEPLOY_TOKEN}' (got {confirm!r}); nothing sent")
        if not self._actuation.acquire(timeout=ACTUATION_WAIT_S):
            return self._deploy_end('refused', 'deploy refused: another deploy or arm did not '
                                    f'finish within {ACTUATION_WAIT_S:.0f} s; nothing sent')
        try:
            if self._stopping.is_set():
                return self._deploy_end('refused', 'deploy refused: the driver is shutting '
                                        'down; nothing sent')
            return self._deploy(arm_if_locked, t0)
        finally:
            self._save_attempts()
            self._actuation.release()

    def _reread(self, snap: Snapshot) -> Snapshot:
        """Ask the module what a deploy or an arm needs, when the driver's knowledge is old.

        A module that answers is online (its answer is a frame), however it was judged before:
        an offline verdict or a re-read still to come never refuses a module that answers.
        """
        if not snap.port_open:
            return snap
        epoch = self._current_epoch()
        try:
            # A reboot first (D15); a module silent to this one query is judged by the next.
            epoch = self._note_boot_count(
                self._req(p.encode_boot_count_query(), silence_ok=snap.online).count)
        except LinkTimeout:
            if not snap.online:
                return self.snapshot  # silent: offline it is
        except LinkError:
            return self.snapshot
        try:
            # Armed and triggered in one frame; the two queries if it does not answer that.
            self._on_status(self._req(p.encode_status_query(), retries=1), 'query', epoch)
        except LinkTimeout:
            try:
                armed = self._req(p.encode_armed_query(), retries=1).armed
                triggered = self._req(p.encode_triggered_query(), retries=1).triggered
            except LinkError:
                return self.snapshot
            self._set_triggered(triggered, 'query', epoch, armed=armed, fresh=True)
        except LinkError:
            pass
        return self.snapshot

    def _seen_triggered(self) -> str:
        """How the driver knows the module deployed, or '' (triggered not seen)."""
        with self._lock:
            if not self._snap.triggered or self._triggered_seen is None:
                return ''
            at, via = self._triggered_seen
            sent = self._deploy_frame_at
        text = f'the module reported TRIGGERED (via {via}'
        if sent is not None and at >= sent:
            text += f', {(at - sent) * 1000:.0f} ms after the deploy frame left'
        return text + ')'

    def _deploy(self, arm_if_locked: bool, t0: float) -> Result:
        snap = self.snapshot
        if snap.online and not snap.fresh:
            snap = self._wait_fresh()
        if not snap.online or not snap.fresh:
            snap = self._reread(snap)
        if not snap.online:
            seen = self._seen_triggered()
            if seen:
                # A deployment stays one: the module stays triggered until switched off.
                return self._deploy_end('already deployed', f'already deployed: {seen}; it '
                                        f'is offline now ({snap.offline_reason}); nothing '
                                        'sent', success=True)
            return self._deploy_end('refused', f'deploy refused: {self._offline_text(snap)}; '
                                    'nothing sent')
        if snap.fresh and snap.triggered:
            return self._deploy_end('already deployed', 'already deployed: the module reports '
                                    'triggered; nothing sent', success=True)
        if not snap.fresh:
            return self._deploy_end(
                'refused', 'deploy refused: the module may have rebooted and has not been '
                're-read (it did not answer the status, armed or triggered query), so whether it '
                'is armed is not known; nothing sent. Try again in a moment.')
        if snap.armed is not True:
            if not arm_if_locked:
                return self._deploy_end(
                    'refused', 'deploy refused: the module is locked (a locked module cannot '
                    'deploy); arm it with ~/arm or set arm_if_locked; nothing sent')
            ok, message = self._arm(True, judge=False)  # deploying is what was asked
            if not ok:
                return self._deploy_end('refused', f'deploy refused: arming failed: {message}')
        attempts = 0
        while True:
            snap = self.snapshot
            if attempts and not (snap.fresh and snap.armed):
                # It rebooted (or was locked) during the wait: a retry would go out on old
                # knowledge (D15). The triggered query just said it did not deploy.
                snap = self._wait_fresh()
                if not snap.fresh or not snap.armed:
                    state = 'is locked now' if snap.fresh else 'rebooted and was not re-read'
                    return self._deploy_end(
                        'not deployed', f'deploy NOT acknowledged after {attempts} attempt(s), '
                        f'the module reports it is not triggered: it did NOT deploy, and it '
                        f'{state}; not retrying', t0=t0)
            if snap.failed_deploys >= MAX_FAILED_DEPLOYS:
                if attempts:
                    return self._deploy_end(
                        'not deployed', f'deploy NOT acknowledged after {attempts} attempts, '
                        'and the module reports it is not triggered: it did NOT deploy. Not '
                        'retrying (P11: three unsuccessful attempts put the module into '
                        'protection)', t0=t0)
                return self._deploy_end('refused', self._guard_text(snap))
            if not attempts and self.release_gate is not None:
                self.release_gate.before_release('deploy')  # every refusal is decided above
            attempts += 1
            # The decision is on disk before the frame leaves: a crash between the two must
            # not leave a deployment the black box never heard of.
            self.blackbox.record('decision', what='deploy: sending the deploy frame',
                                 attempt=attempts)
            self._safety_sync()
            self._save_attempts(leaving=1)  # a respawned driver counts it too (P11)
            with self._lock:
                self._deploy_frame_left = False
            try:
                ack = self._req(DEPLOY_FRAME)
            except LinkTimeout:
                ack = None
            except LinkBusy as exc:
                return self._deploy_end('refused', f'deploy refused: {exc}')
            except LinkDown as exc:
                with self._lock:
                    left = self._deploy_frame_left
                if not left and attempts == 1:
                    return self._deploy_end('refused', f'deploy failed before the frame left: '
                                            f'{exc}; nothing sent')
                why = ('the driver is shutting down' if self._stopping.is_set()
                       else f'the link dropped ({exc})')
                sent = attempts if left else attempts - 1
                return self._deploy_unknown(
                    f'{sent} deploy frame(s) sent, but {why} before any acknowledgement', t0)
            if ack is not None:
                self._on_deploy_reply(ack, late=False)
                return self._deploy_answered(ack, attempts, t0)
            # No acknowledgement: lost on either way, or corrupted. Before any retry, ask
            # whether it deployed (D6): a triggered module refuses a retry and counts it.
            triggered = self._query_triggered()
            if triggered or self.snapshot.triggered:
                return self._deploy_end(
                    'deployed', f'deployed: the module reports triggered; its acknowledgement '
                    f'was lost ({attempts} attempt(s))', success=True, t0=t0, ack='lost')
            if triggered is None and self.snapshot.failed_deploys >= MAX_FAILED_DEPLOYS:
                return self._deploy_unknown(
                    f'{attempts} deploy frame(s) sent, none acknowledged, and the module did '
                    'not answer whether it is triggered', t0)

    def _deploy_answered(self, ack: p.DeployAck, attempts: int, t0: float) -> Result:
        latency = (self.clock() - t0) * 1000.0
        if ack.success:
            # The acknowledgement is on disk before anyone hears of it (SIGKILL-safe).
            self.blackbox.record('decision', what='deploy acknowledged', hex=ack.raw.hex(' '),
                                 latency_ms=latency, attempts=attempts)
            self._safety_sync()
            return self._deploy_end('deployed', f'deployed: acknowledged after {attempts} '
                                    f'attempt(s), {latency:.1f} ms', success=True, t0=t0,
                                    log=False)
        self.blackbox.record('decision', what='deploy refused by module', hex=ack.raw.hex(' '))
        # Never "did not deploy" while the module says it is triggered (D6).
        triggered = self._query_triggered()
        if triggered:
            return self._deploy_end(
                'deployed', f'deployed: the module refused this frame ({ack.raw.hex(" ")}) '
                'because it is already triggered: an earlier frame deployed it and its '
                'acknowledgement was lost', success=True, t0=t0, ack='lost')
        if triggered is None:
            return self._deploy_unknown(f'the module refused the deploy frame '
                                        f'({ack.raw.hex(" ")}) and did not answer whether it '
                                        'is triggered', t0)
        return self._deploy_end(
            'not deployed', f'the module answered {ack.raw.hex(" ")} and reports it is not '
            'triggered: it did NOT deploy (locked, or in protection after unsuccessful '
            'attempts)', t0=t0)

    def _guard_text(self, snap: Snapshot) -> str:
        if snap.unacked_deploys >= MAX_FAILED_DEPLOYS:
            what = f'{snap.unacked_deploys} deploy frames in a row went unacknowledged'
        else:
            what = (f'{snap.failed_deploys} deploy frames in a row were refused or went '
                    'unacknowledged')
        return (f'deploy refused: {what}; a third could put the module into protection (P11). '
                'Check the link; a module reboot clears this. Nothing sent')

    def _deploy_unknown(self, what: str, t0: float) -> Result:
        seen = self._seen_triggered()
        if seen:
            # Seen triggered after the frame left: a deployment, whatever became of the reply.
            with self._lock:
                self._snap = replace(self._snap, unacked_deploys=0, failed_deploys=0)
            return self._deploy_end('deployed', f'deployed: {seen}; its acknowledgement did '
                                    f'not come ({what})', success=True, t0=t0, ack='lost')
        with self._lock:
            self._unknown_boot = self._snap.boot_count
        self._update(deploy_outcome_unknown=True)
        message = (f'deploy outcome UNKNOWN: {what}. The driver reads the triggered state as '
                   'soon as the module answers again and reports a deployment on '
                   '~/trigger_event')
        self.blackbox.record('decision', what='deploy', outcome='unknown', reason=message)
        self._safety_sync()
        self._log('error', message)
        self.listener.on_diagnostics()
        return Result(False, message, latency_ms=None)

    def _deploy_end(self, outcome: str, message: str, success: bool = False,
                    t0: Optional[float] = None, log: bool = True, **extra: Any) -> Result:
        latency = None if t0 is None else (self.clock() - t0) * 1000.0
        if outcome == 'refused' and self.snapshot.deploy_outcome_unknown:
            # True of this call, and not the whole truth: a caller must never read "refused"
            # as "the parachute did not deploy" while an earlier frame's fate is not known.
            message += ('; an earlier deploy frame left without an acknowledgement: its outcome '
                        'is UNKNOWN (the parachute may have deployed) until the module answers')
        self.blackbox.record('decision', what='deploy', outcome=outcome, success=success,
                             reason=message, **extra)
        self._safety_sync()
        if log:
            self._log('info' if success else 'warn', message)
        if success:
            self._emit_status()
        return Result(success, message, latency_ms=latency if success else None)

    # -- arm -------------------------------------------------------------------------------------

    def arm(self, want: bool) -> Result:
        """`~/arm`: arm or lock; success only when the reply and a query agree (P7)."""
        self.blackbox.record('request', what='arm' if want else 'lock')
        if not self._actuation.acquire(timeout=ACTUATION_WAIT_S):
            return Result(False, 'another deploy or arm is still running; nothing sent')
        try:
            ok, message = self._arm(want)
        finally:
            self._actuation.release()
        self._log('info' if ok else 'warn', message)
        return Result(ok, message)

    def _arm(self, want: bool, judge: bool = True) -> Tuple[bool, str]:
        """Arm or lock, verified; an arm that would fire at once is refused (D16, P21).

        `judge` False: arming for a deploy (``arm_if_locked``), where firing is the point.
        """
        word = 'arm' if want else 'lock'
        snap = self.snapshot
        if want and snap.online and not snap.fresh:
            snap = self._wait_fresh()
        if not snap.online or (want and not snap.fresh):
            snap = self._reread(snap)
        if not snap.online:
            return False, f'cannot {word}: {self._offline_text(snap)}; nothing sent'
        if want and not snap.fresh:
            return False, ('cannot arm: the module may have rebooted and has not been re-read, '
                           'so whether it has deployed is not known; nothing sent')
        if want and snap.triggered:
            return False, ('cannot arm: the module has deployed (triggered); a triggered module '
                           'is never re-armed. Re-pack it and switch it off and on; nothing sent')
        epoch = self._current_epoch()
        try:
            danger = self._gate([('armed', True)], '~/arm') if want and judge else ''
            if danger:
                return False, f'cannot arm, nothing sent: {danger}'
            reply = self._req(p.encode_arm(want), retries=1)
            if reply.armed != want:
                return False, (f'module answered {reply.raw.hex(" ")} to {word}: '
                               f'it stays {"armed" if reply.armed else "locked"}')
            try:
                state = self._req(p.encode_armed_query(), retries=1)
            except LinkTimeout:
                # The status frame tells armed too: a module silent to the armed query alone
                # is still verified (and can be armed for a deploy).
                state = self._req(p.encode_status_query(), retries=1)
        except LinkError as exc:
            return False, f'{word} not confirmed: {exc}'
        self._update_if(epoch, armed=state.armed)
        self.blackbox.record('state', armed=state.armed, via=word)
        self._safety_sync()
        self._emit_status()
        self.listener.on_diagnostics()
        if state.armed != want:
            return False, (f'module acknowledged {word} but the query says '
                           f'{"armed" if state.armed else "locked"}')
        return True, 'armed (verified by query)' if want else 'locked (verified by query)'

    # -- other services --------------------------------------------------------------------------

    def get_config(self) -> Result:
        """`~/get_config`: read every setting afresh."""
        snap = self.snapshot
        if not snap.online:
            return Result(False, f'{self._offline_text(snap)}; showing the last read-back')
        try:
            self._read_config()
        except LinkError as exc:
            return Result(False, f'could not read the settings: {exc}')
        return Result(True, 'read afresh from the module')

    def get_trigger_records(self) -> Result:
        """`~/get_trigger_records`: the module's non-empty trigger records."""
        snap = self.snapshot
        if not snap.online:
            return Result(False, self._offline_text(snap))
        try:
            records = self._fetch_records()
        except LinkError as exc:
            return Result(False, f'no trigger records: {exc}')
        return Result(True, f'{len(records)} record(s)', records=tuple(records))

    def set_streaming(self, enabled: bool) -> Result:
        """`~/set_streaming`: turn the status stream on or off (kept across reconnects)."""
        snap = self.snapshot
        if not snap.online:
            return Result(False, f'{self._offline_text(snap)}; nothing sent')
        try:
            ok = self._set_streaming(enabled, silence_ok=True)
        except LinkError as exc:
            return Result(False, f'streaming not confirmed: {exc}')
        with self._lock:
            self._config = replace(self._config, stream_status=enabled)
        self._emit_status()
        return Result(ok, f'status stream {"on" if self.snapshot.streaming else "off"}')

    def zero_sensor(self) -> Result:
        """`~/zero_sensor`: take the present attitude as level (P26)."""
        snap = self.snapshot
        if not snap.online:
            return Result(False, f'{self._offline_text(snap)}; nothing sent')
        try:
            ack = self._req(p.encode_sensor_zero(), retries=1)
        except LinkError as exc:
            return Result(False, f'zeroing not confirmed: {exc}')
        self.blackbox.record('state', event='sensor zeroed', success=ack.success)
        return Result(ack.success, 'attitude sensor zeroed at the present mounting'
                      if ack.success else f'module answered {ack.raw.hex(" ")}')

    def shutdown_module(self, confirm: str) -> Result:
        """`~/shutdown_module`: switch the module off (token SHUTDOWN)."""
        if confirm != SHUTDOWN_TOKEN:
            return Result(False, f"refused: confirm must be exactly '{SHUTDOWN_TOKEN}' "
                                 f'(got {confirm!r}); nothing sent')
        snap = self.snapshot
        if not snap.online:
            return Result(False, f'{self._offline_text(snap)}; nothing sent')
        self._update(shutdown_expected=True)
        try:
            self._req(p.encode_shutdown(), retries=1)
        except LinkError as exc:
            self._update(shutdown_expected=False)
            return Result(False, f'shutdown not acknowledged: {exc}')
        self.blackbox.record('state', event='module shut down by request')
        self._safety_sync()
        return Result(True, 'module acknowledged and is switching off; switch it on with its '
                            'button (2 s) or external power')

    # -- preflight (D17) -------------------------------------------------------------------------

    def _preflight_steps(self) -> List[Tuple[Tuple[str, ...], bool, Callable[[], List[Check]]]]:
        """Return the checks of ``~/preflight_check`` in the order of its lines.

        Each is (the names of its lines, whether it queries the module, the check). A check that
        queries raises LinkError when the module does not answer: its lines and those of every
        later querying check say "not checked"; the others are judged from what the driver
        knows. One more check is one more entry here.
        """
        return [
            (('online',), True, self._pf_online),
            (('armed',), True, self._pf_armed),
            (('not triggered',), True, self._pf_triggered),
            (('not in protection',), False, lambda: [self._protection_check()]),
            (('settings as desired', 'auto triggers as desired'), True, self._pf_settings),
            (('auto triggers on',), False, self._pf_auto_triggers_on),
            (('trigger requests confirmed',), False, self._pf_policy),
            (('no trigger condition met',), True, self._pf_conditions),
            (('bay closed',), True, self._pf_bay),
            (('battery',), True, self._pf_battery),
            (('link clean',), False, self._pf_link),
            (('status stream',), False, lambda: [self._stream_check(self.config)]),
            (('black box writable',), False, lambda: [self._blackbox_check()]),
        ]

    def preflight_check(self) -> Result:
        """`~/preflight_check`: go / no-go from the module read afresh, queries only (D17)."""
        checks: List[Check] = []
        silent: Optional[LinkError] = None
        if not self.snapshot.port_open:
            silent = LinkDown(self.link.serial.last_error or 'port not open')
        for names, queries, check in self._preflight_steps():
            if queries and silent is not None:
                checks += [(False, name, f'no answer: {silent}' if name == 'online' else
                            'not checked: the module did not answer') for name in names]
                continue
            try:
                checks += check()
            except LinkError as exc:
                silent = exc
                checks += [(False, name, f'no answer: {exc}' if name == 'online' else
                            'not checked: the module did not answer') for name in names]
        ok = all(passed for passed, _, _ in checks)
        lines = [f'{"OK  " if passed else "FAIL"} {name}: {detail}'
                 for passed, name, detail in sorted(checks, key=lambda c: c[0])]
        self.blackbox.record('decision', what='preflight', ok=ok, checks=lines)
        return Result(ok, '\n'.join(lines))

    def _pf_online(self) -> List[Check]:
        self._note_boot_count(self._req(p.encode_boot_count_query(), retries=1).count)
        return [(True, 'online', f'answers (boot count {self.snapshot.boot_count})')]

    def _pf_armed(self) -> List[Check]:
        epoch = self._current_epoch()
        armed = self._req(p.encode_armed_query(), retries=1).armed
        self._update_if(epoch, armed=armed)
        return [(armed, 'armed', 'armed' if armed else 'LOCKED: arm it with ~/arm')]

    def _pf_triggered(self) -> List[Check]:
        triggered = self._query_triggered()
        if triggered is None:
            raise LinkTimeout('no reply to the triggered query')
        return [(not triggered, 'not triggered', 'not triggered' if not triggered
                 else 'TRIGGERED: the parachute has deployed')]

    def _pf_settings(self) -> List[Check]:
        for setting in SETTINGS.values():
            self._update(**{setting.field: self._req(setting.encode_query(), retries=1).value})
        if self._flags_query_answered:
            self._query_flags()
        self._update_mismatch(log=False)
        return self._settings_checks(self.config)

    def _pf_auto_triggers_on(self) -> List[Check]:
        # Both off: the module never deploys on its own detection, only on ~/deploy.
        snap = self.snapshot
        flags = (snap.attitude_trigger_enabled, snap.freefall_trigger_enabled)
        if None in flags:
            return [(True, 'auto triggers on', 'not known (the module never reported them, '
                     'P14)')]
        text = (f'attitude {"on" if flags[0] else "OFF"}, free fall '
                f'{"on" if flags[1] else "OFF"}')
        if not any(flags):
            return [(False, 'auto triggers on', f'{text}: the module never deploys on its own '
                     'crash detection, only on ~/deploy')]
        return [(True, 'auto triggers on', text)]

    def _pf_policy(self) -> List[Check]:
        config = self.config
        policy = config.trigger_request_policy
        if policy == 'deny':
            return [(False, 'trigger requests confirmed', 'trigger_request_policy deny: a '
                     "request of the module (its own crash detection, on external power) is "
                     'never confirmed, so it does not deploy on its own')]
        if policy == 'defer':
            return [(True, 'trigger requests confirmed', 'trigger_request_policy defer: '
                     'confirmed only if ~/answer_trigger_request answers true within '
                     f'{config.defer_timeout_s:.2f} s, else denied')]
        return [(True, 'trigger requests confirmed', 'trigger_request_policy confirm')]

    def _pf_conditions(self) -> List[Check]:
        epoch = self._current_epoch()
        status = self._req(p.encode_status_query(), retries=1)
        self._on_status(status, via='query', epoch=epoch)
        snap = self.snapshot
        tilt, accel = float(status.tilt_deg), float(status.accel_g)
        met = conditions(self._trigger_settings(snap), tilt, accel)
        if snap.pending_request:
            return [(False, 'no trigger condition met', 'a trigger request of the module is '
                     'waiting for an answer')]
        if met:
            what = ('the module is deploying or asking to' if status.armed else
                    'arming now fires the parachute at once')
            return [(False, 'no trigger condition met', f'{"; ".join(met)}: {what} (P21)')]
        return [(True, 'no trigger condition met', f'tilt {tilt:g}°, |a| {accel:.1f} g')]

    def _pf_bay(self) -> List[Check]:
        light = self._req(p.encode_light_level_query(), retries=1).volts
        snap = self._update(light_v=light)
        threshold = snap.light_threshold_raw / 10
        if snap.bay_open:
            return [(False, 'bay closed', f'BAY OPEN: light {light:.1f} V > light threshold '
                     f'{threshold:.1f} V (lid open or the parachute out?)')]
        return [(True, 'bay closed', f'light {light:.1f} V ≤ light threshold {threshold:.1f} V')]

    def _pf_battery(self) -> List[Check]:
        charging = self._req(p.encode_charging_query(), retries=1).charging
        volts = self._req(p.encode_cell_voltage_query(), retries=1).volts
        self._update(charging=charging, voltage_v=volts)
        low = not charging and volts < LOW_BATTERY_V
        return [(not low, 'battery', f'{volts:.2f} V {"charging" if charging else "on battery"}'
                 + (f', below {LOW_BATTERY_V} V' if low else ''))]

    def _pf_link(self) -> List[Check]:
        # The counters are for the whole run: one burst long ago is no reason for a no-go, a
        # recent one is (a deploy frame would meet the same link).
        counters, changed_at = self._note_link()
        totals = ', '.join(f'{n} {c}' for n, c in zip(LINK_ERROR_COUNTERS, counters))
        ago = self.clock() - changed_at
        if ago < LINK_QUIET_S:
            return [(False, 'link clean', f'link errors {ago:.1f} s ago (run: {totals}); a '
                     f'clean link for {LINK_QUIET_S:.0f} s is a go')]
        return [(True, 'link clean', f'no link error in the last {LINK_QUIET_S:.0f} s (run: '
                 f'{totals})')]

    def _protection_check(self) -> Check:
        # The module has no query for its protection state (P19): judged from the deploy
        # frames this driver sent since the module's last power-up.
        snap = self.snapshot
        if snap.failed_deploys >= MAX_FAILED_DEPLOYS:
            return (False, 'not in protection', self._guard_text(snap).split(': ', 1)[1])
        if snap.deploy_outcome_unknown:
            return (False, 'not in protection', 'a deploy whose outcome is unknown')
        detail = 'no unsuccessful deploy attempt since power-up' if not snap.failed_deploys \
            else f'{snap.failed_deploys} unsuccessful deploy attempt since power-up'
        return (True, 'not in protection', detail + ' (judged by the driver: the module has '
                'no query for it)')

    def _settings_checks(self, config: SessionConfig) -> List[Check]:
        snap = self.snapshot
        numeric = [m for m in snap.mismatch if m.split(':')[0] in SETTINGS]
        flags = [m for m in snap.mismatch if m.split(':')[0] in FLAG_SETTINGS]
        desired = [n for n in SETTINGS if config.desired(n) != -1]
        wanted_flags = [n for n in FLAG_SETTINGS if config.desired(n) != 'keep']
        with self._lock:
            flags_read = self._flags_query_answered
        how = 'read afresh' if flags_read else 'as last reported by the module (P14)'
        return [
            (not numeric, 'settings as desired', '; '.join(numeric) if numeric else
             (f'{", ".join(desired)} verified' if desired else 'none desired (all -1)')),
            (not flags, 'auto triggers as desired', '; '.join(flags) if flags else
             (f'{", ".join(wanted_flags)} verified, {how}' if wanted_flags else
              'none desired (keep)')),
        ]

    def _stream_check(self, config: SessionConfig) -> Tuple[bool, str, str]:
        # The queries above are answered whether the stream flows or not: judged from it.
        if not config.stream_status:
            return (True, 'status stream', 'off (stream_status false): the status is polled')
        snap = self.snapshot
        with self._lock:
            silent = self.clock() - max(self._last_stream_time, self._stream_on_at)
        if snap.stream_problem:
            return (False, 'status stream', snap.stream_problem)
        if not snap.streaming or silent > config.offline_timeout_s * STREAM_GRACE:
            return (False, 'status stream', f'no status frame for {silent:.1f} s')
        return (True, 'status stream', 'flowing')

    def _blackbox_check(self) -> Tuple[bool, str, str]:
        synced = self.blackbox.sync(SAFETY_SYNC_S)  # also notices a file removed under it
        status = self.blackbox.status()
        problem = self.blackbox_problem(status)
        if synced and not problem:
            return (True, 'black box writable', status.path)
        return (False, 'black box writable', problem or 'fsync failed')

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

    # -- diagnostics helpers -----------------------------------------------------------------

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
