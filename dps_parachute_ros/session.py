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
from dps_parachute_ros.blackbox import BlackBox
from dps_parachute_ros.link import LinkBusy, LinkDown, LinkError, LinkTimeout, ParachuteLink
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
DEPLOY_FRAME = p.encode_deploy()
IDLE_WAKE_S = 0.2
"""The worker and the monitor sleep until their next deadline, and at most this long (they see
state changes nobody signals within it). Each wake-up costs CPU: they used to poll at 50 Hz."""


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
        self._initialized_at = 0.0
        self._init_retry_at = 0.0
        self._flags_query_answered = False
        self._throttle = Throttle()
        self._link_recorded: Tuple[int, ...] = (0,) * len(LINK_PROBLEM_COUNTERS)
        self._link_recorded_at = -1e9
        # -- guarded by _jobs_cond ----------------------------------------------------------
        self._jobs = _Jobs()
        self._jobs_cond = threading.Condition()
        # -- other ----------------------------------------------------------------------------
        self._actuation = threading.Lock()
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

    def _on_status(self, status: p.Status, via: str, epoch: Optional[int] = None) -> None:
        # A status frame tells armed and triggered as they are now: a re-read (D15).
        with self._lock:
            self._last_status_time = self.clock()
        before = self._set_triggered(status.triggered, via, epoch, tilt_deg=float(status.tilt_deg),
                                     accel_g=float(status.accel_g), armed=status.armed,
                                     fresh=True)
        if before is None:
            return  # a poll's answer from before a reboot
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
        elif snap.armed is False:
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
        if snap.armed:
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
        now = self.clock()
        with self._lock:
            if counters == self._link_recorded or \
                    (not final and now - self._link_recorded_at < LINK_RECORD_PERIOD_S):
                return
            self._link_recorded, self._link_recorded_at = counters, now
        self.blackbox.record('link', **info)

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
                    last_status = self._last_status_time
                    config = self._config
                if not snap.initialized:
                    if now >= retry_at:
                        self._schedule('init', force=True)
                    else:
                        wait = min(wait, retry_at - now)
                    continue
                stream_due = max(last_status, init_at) + config.offline_timeout_s
                if snap.streaming and snap.online and now > stream_due:
                    # The module answers but its stream stopped: it rebooted unnoticed (D3).
                    self._log('warn', 'the status stream stopped; re-initializing')
                    self._schedule('init', force=True)
                    continue
                if now >= next_aux:
                    next_aux = now + config.aux_poll_period_s
                    self._poll()
                if not snap.streaming and now >= next_heartbeat:
                    next_heartbeat = now + config.heartbeat_period_s
                    self._req(p.encode_heartbeat())
                due = [next_aux]
                if not snap.streaming:
                    due.append(next_heartbeat)
                elif snap.online:
                    due.append(stream_due + 0.001)  # judged with '>'
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
            self._set_streaming(self.config.stream_status)

    def _initialize(self) -> None:
        """Read the module afresh and bring it to the desired settings (D2)."""
        if not self.snapshot.port_open:
            return
        with self._lock:
            self._init_retry_at = self.clock() + 1.0
        try:
            epoch = self._note_boot_count(self._req(p.encode_boot_count_query(), retries=1).count,
                                          reinit=False)
            self._set_streaming(self.config.stream_status)
            armed = self._req(p.encode_armed_query(), retries=1).armed
            triggered = self._req(p.encode_triggered_query(), retries=1).triggered
            if self._set_triggered(triggered, 'query', epoch, armed=armed, fresh=True) is None:
                return  # it rebooted meanwhile: that schedules another initialization
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
        with self._lock:
            previous = self._snap.boot_count
            self._snap = replace(self._snap, boot_count=count)
            if None in self._reported_boots and previous is None:
                # A deployment reported before the first boot count read happened in this boot.
                self._reported_boots.discard(None)
                self._reported_boots.add(count)
            rebooted = previous is not None and previous != count
            if rebooted:
                self._epoch += 1
                # A new power-up clears the module's count of unsuccessful attempts (P19).
                self._snap = replace(self._snap, unacked_deploys=0, failed_deploys=0, fresh=False,
                                     armed=None)
            epoch = self._epoch
        if rebooted:
            self._log('warn', f'module boot count {previous} -> {count}: it rebooted')
            self._void_pending('the module rebooted while the request was pending')
            if reinit:
                self._schedule('init', force=True)
        return epoch

    def _set_streaming(self, enabled: bool) -> bool:
        reply = self._req(p.encode_streaming(enabled), retries=1)
        self._update(streaming=reply.enabled)
        return reply.enabled == enabled

    def _poll(self) -> None:
        epoch = self._current_epoch()
        light = self._req(p.encode_light_level_query()).volts
        charging = self._req(p.encode_charging_query()).charging
        voltage = self._req(p.encode_cell_voltage_query()).volts
        snap = self._update(light_v=light, charging=charging, voltage_v=voltage)
        if not snap.streaming:
            self._on_status(self._req(p.encode_status_query()), via='poll', epoch=epoch)
        else:
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
        # At most once per run while unknown (P14: a firmware ignoring D3 would take it as
        # "enable the attitude trigger"); a real module may stay silent: flags stay unknown.
        try:
            reply = self._req(p.encode_auto_trigger_query(), timeout=FLAGS_QUERY_TIMEOUT_S,
                              silence_ok=True)
        except LinkTimeout:
            return False
        self._set_flags(reply)
        with self._lock:
            self._flags_query_answered = True
        return True

    def _write_setting(self, name: str, value: float) -> Tuple[bool, str]:
        setting = SETTINGS[name]
        raw = setting.to_raw(value)
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

    def _write_flags(self, attitude: Optional[bool] = None,
                     freefall: Optional[bool] = None) -> Tuple[bool, str]:
        """Enable/disable auto triggers (None = leave); verified by the replies (P8, D5)."""
        if attitude is not None:
            self._set_flags(self._req(p.encode_attitude_trigger(attitude)))
        if freefall is not None:
            self._set_flags(self._req(p.encode_freefall_trigger(freefall)))
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

    def _apply_desired(self) -> None:
        """Write every desired setting that differs from the module's, then verify (D4)."""
        config = self.config
        for name, setting in SETTINGS.items():
            value = config.desired(name)
            if value != -1 and self.snapshot.raw(name) != setting.to_raw(value):
                ok, reason = self._write_setting(name, value)
                if not ok:
                    self._log('warn', f'desired setting not applied: {reason}')
        flags = {FLAG_SETTINGS[n]: config.desired(n) == 'enable' for n in FLAG_SETTINGS
                 if config.desired(n) != 'keep'}
        if flags:
            ok, reason = self._write_flags(**flags)
            if not ok:
                self._log('warn', f'desired auto triggers not applied: {reason}')
        self._update_mismatch()

    def _mismatch(self, snap: Snapshot, config: SessionConfig) -> List[str]:
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
        return mismatch

    def _update_mismatch(self, log: bool = True) -> None:
        with self._lock:
            mismatch = tuple(self._mismatch(self._snap, self._config))
            changed = mismatch != self._snap.mismatch
            self._snap = replace(self._snap, mismatch=mismatch)
            snap = self._snap
        if changed:
            self.listener.on_diagnostics()
            if mismatch and log:
                self._log('warn', 'settings do not match: ' + '; '.join(mismatch))
        self.listener.on_config(snap)

    def _would_deploy(self, changes: Dict[str, Any]) -> str:
        """Why the settings `changes` would deploy an armed module at once, or '' (D16).

        The module's rule (P21): attitude when the tilt is above the threshold, free fall when
        |a| stays below the threshold for the free-fall time, each only with its trigger
        enabled. Judged on a fresh status read, conservatively: tilt ≥ threshold, and a flag
        not known counts as enabled.
        """
        touched_att = {'attitude_threshold_deg', 'attitude'} & set(changes)
        touched_ff = {'freefall_threshold_g', 'freefall_time_s', 'freefall'} & set(changes)
        if not touched_att and not touched_ff:
            return ''
        epoch = self._current_epoch()
        status = self._req(p.encode_status_query(), retries=1)
        self._on_status(status, via='query', epoch=epoch)
        if not status.armed or status.triggered:
            return ''
        snap = self.snapshot
        reasons = []
        threshold = changes.get('attitude_threshold_deg', snap.attitude_threshold_raw)
        enabled = changes.get('attitude', snap.attitude_trigger_enabled)
        if touched_att and enabled is not False and threshold is not None and \
                status.tilt_deg >= threshold:
            reasons.append(f'tilt {status.tilt_deg}° ≥ attitude threshold {threshold:g}°')
        if 'freefall_threshold_g' in changes:
            ff_raw = p.freefall_threshold_to_raw(changes['freefall_threshold_g'])
        else:
            ff_raw = snap.freefall_threshold_raw
        enabled = changes.get('freefall', snap.freefall_trigger_enabled)
        if touched_ff and enabled is not False and ff_raw is not None and \
                round(status.accel_g * 10) < ff_raw:
            reasons.append(f'acceleration {status.accel_g:.1f} g < free-fall threshold '
                           f'{ff_raw / 10:.1f} g')
        if not reasons:
            return ''
        return 'would deploy now: ' + '; '.join(reasons) + '; lock first (~/arm false)'

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
        try:
            danger = self._would_deploy(values)
            if danger:
                return self._refused_setting(danger)
            for name, value in values.items():
                ok, message = self._write_setting(name, value)
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
            danger = self._would_deploy({'attitude': attitude, 'freefall': freefall})
            if danger:
                return self._refused_setting(danger)
            ok, message = self._write_flags(attitude, freefall)
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
        try:
            danger = self._would_deploy({FLAG_SETTINGS.get(n, n): (v == 'enable'
                                                                   if n in FLAG_SETTINGS else v)
                                         for n, v in wanted.items()})
            if danger:
                return self._param_refused(changes, f'refused, nothing written: {danger}')
            for name, value in wanted.items():
                if time.monotonic() > deadline:
                    raise LinkTimeout(f'no time left for {name} within '
                                      f'{PARAM_WRITE_BUDGET_S} s')
                if name in SETTINGS:
                    before = self.snapshot.raw(name)
                    if before is None:
                        before = self._req(SETTINGS[name].encode_query(), retries=1).value
                    ok, reason = self._write_setting(name, value)
                else:
                    which = FLAG_SETTINGS[name]
                    before = getattr(self.snapshot, f'{which}_trigger_enabled')
                    ok, reason = self._write_flags(**{which: value == 'enable'})
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
                    ok, reason = self._write_setting(name, SETTINGS[name].to_si(before))
                else:
                    ok, reason = self._write_flags(**{FLAG_SETTINGS[name]: before})
                if not ok:
                    raise LinkError(reason)
                back.append(name)
            except (LinkError, p.ProtocolError) as exc:
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
        self.blackbox.record('trigger_event', source=source_name(source), via=via,
                             record=None if record is None else record.raw.hex(' '))
        self.blackbox.sync(None)
        self.listener.on_deployment(Deployment(source, via, record))
        self._log('error', f'PARACHUTE DEPLOYED: source {source_name(source)}')
        return True

    def _fetch_records(self) -> List[p.TriggerRecord]:
        """Query the history; remember every record; return the non-empty ones."""
        records = [r for r in self.link.query_records() if not r.is_empty]
        with self._lock:
            self._known_records = (self._known_records or set()) | {r.raw for r in records}
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
            self._actuation.release()

    def _deploy(self, arm_if_locked: bool, t0: float) -> Result:
        snap = self.snapshot
        if snap.online and not snap.fresh:
            snap = self._wait_fresh()
        if not snap.online:
            return self._deploy_end('refused', f'deploy refused: {self._offline_text(snap)}; '
                                    'nothing sent')
        if snap.fresh and snap.triggered:
            return self._deploy_end('already deployed', 'already deployed: the module reports '
                                    'triggered; nothing sent', success=True)
        if not snap.fresh:
            return self._deploy_end(
                'refused', 'deploy refused: the module may have rebooted and has not been '
                f're-read within {REREAD_WAIT_S:.0f} s, so whether it is armed is not known; '
                'nothing sent. Try again in a moment.')
        if snap.armed is not True:
            if not arm_if_locked:
                return self._deploy_end(
                    'refused', 'deploy refused: the module is locked (a locked module cannot '
                    'deploy); arm it with ~/arm or set arm_if_locked; nothing sent')
            ok, message = self._arm(True)
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

    def _arm(self, want: bool) -> Tuple[bool, str]:
        word = 'arm' if want else 'lock'
        snap = self.snapshot
        if want and snap.online and not snap.fresh:
            snap = self._wait_fresh()
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
            reply = self._req(p.encode_arm(want), retries=1)
            if reply.armed != want:
                return False, (f'module answered {reply.raw.hex(" ")} to {word}: '
                               f'it stays {"armed" if reply.armed else "locked"}')
            state = self._req(p.encode_armed_query(), retries=1)
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
            ok = self._set_streaming(enabled)
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

    def preflight_check(self) -> Result:
        """`~/preflight_check`: go / no-go from the module read afresh, queries only (D17)."""
        checks: List[Tuple[bool, str, str]] = []
        config = self.config
        snap = self.snapshot
        names = ('armed', 'not triggered', 'not in protection', 'settings as desired',
                 'auto triggers as desired', 'battery')
        try:
            if not snap.port_open:
                raise LinkDown(self.link.serial.last_error or 'port not open')
            epoch = self._note_boot_count(self._req(p.encode_boot_count_query(), retries=1).count)
            checks.append((True, 'online', f'answers (boot count {self.snapshot.boot_count})'))
            armed = self._req(p.encode_armed_query(), retries=1).armed
            self._update_if(epoch, armed=armed)
            checks.append((armed, 'armed', 'armed' if armed else 'LOCKED: arm it with ~/arm'))
            triggered = self._query_triggered()
            if triggered is None:
                raise LinkTimeout('no reply to the triggered query')
            checks.append((not triggered, 'not triggered', 'not triggered' if not triggered
                           else 'TRIGGERED: the parachute has deployed'))
            checks.append(self._protection_check())
            for name, setting in SETTINGS.items():
                self._update(**{setting.field: self._req(setting.encode_query(),
                                                         retries=1).value})
            if self._flags_query_answered:
                self._query_flags()
            self._update_mismatch(log=False)
            checks += self._settings_checks(config)
            charging = self._req(p.encode_charging_query(), retries=1).charging
            volts = self._req(p.encode_cell_voltage_query(), retries=1).volts
            self._update(charging=charging, voltage_v=volts)
            low = not charging and volts < LOW_BATTERY_V
            checks.append((not low, 'battery', f'{volts:.2f} V '
                           f'{"charging" if charging else "on battery"}'
                           + (f', below {LOW_BATTERY_V} V' if low else '')))
        except LinkError as exc:
            done = {name for _, name, _ in checks}
            if 'online' not in done:
                checks.append((False, 'online', f'no answer: {exc}'))
            checks += [(False, name, 'not checked: the module did not answer')
                       for name in names if name not in done]
        checks.append(self._blackbox_check())
        ok = all(passed for passed, _, _ in checks)
        lines = [f'{"OK  " if passed else "FAIL"} {name}: {detail}'
                 for passed, name, detail in sorted(checks, key=lambda c: c[0])]
        self.blackbox.record('decision', what='preflight', ok=ok, checks=lines)
        return Result(ok, '\n'.join(lines))

    def _protection_check(self) -> Tuple[bool, str, str]:
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

    def _settings_checks(self, config: SessionConfig) -> List[Tuple[bool, str, str]]:
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

    def _blackbox_check(self) -> Tuple[bool, str, str]:
        synced = self.blackbox.sync(SAFETY_SYNC_S)
        status = self.blackbox.status()
        if synced and status.writing:
            return (True, 'black box writable', status.path)
        return (False, 'black box writable', self.blackbox_problem(status) or 'fsync failed')

    def blackbox_problem(self, status: Optional[Any] = None) -> str:
        """Why the black box does not record, naming the parameter; '' when it does."""
        status = status or self.blackbox.status()
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
