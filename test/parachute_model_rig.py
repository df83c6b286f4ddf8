"""A `DeployCore` driven against the virtual parachute in virtual time, with wire faults.

`ModelRig` carries out the core's actions with ``uav_serial_common.core_runner.run_core``: a
`Request` goes to the device model (``dps_parachute_ros.simulation``) through a wire that applies
the faults queued for it, the model's bytes are decoded by the protocol decoder and fed back as
`Reply` events (or `Timeout` at the deadline, `LinkDown` when unplugged). It keeps what the
invariants need: every action carried out, the deploy frames of each power-up without a
successful acknowledgement, what the core was told of the armed state since the last reboot it
could know of, and every call with its answers. No thread, no pty, no wall clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Set, Tuple

from dps_parachute_ros import protocol as p
from dps_parachute_ros.deploy_core import (
    ArmAnswer, ArmCall, ArmJudged, DEPLOY_FRAME, DeployAnswer, DeployCall, DeployCore, JudgeArm,
    POWER_UP_HEARTBEATS_S, Report, SaveAttempts, Stored)
from dps_parachute_ros.release_gate import GateDone, PassGate
from dps_parachute_ros.simulation import VirtualParachute
from uav_serial_common.core_events import (LinkDown, LinkUp, Log, Record, Reply, Request,
                                           SYNC_WAIT, Timeout)
from uav_serial_common.core_runner import run_core

START = 1000.0
REPLY_S = 0.004
"""Time from a request to its reply on a clean wire (a 6-byte frame each way at 115200)."""
REBOOT_S = 0.3
"""A module takes this long to switch off and boot again (longer than the 0.2 s that one
power-up's two heartbeats fit in, P5: two reboots never look like one)."""
LATE_HEARTBEAT_FAULTS = {'late_heartbeat': (0.6, None), 'late_heartbeat_slow': (1.5, None),
                         'late_heartbeat_reboot': (1.5, 1.2)}
"""The module reboots as the request comes, its first heartbeat is taken at once, then the
driver's reader stalls for the first figure (seconds): its second heartbeat (P5: 50 ms after the
first) and all the module sends meanwhile are taken then, more than 0.2 s after the first (D3:
a late heartbeat, handled as a possible reboot). ``_slow``: past the reply deadline.
``_reboot``: the module reboots again (the second figure: seconds after the first) before the
stall ends; that reboot's heartbeats are taken right after the late one."""
REBOOT_FAULTS = ('reboot', 'reboot_quiet', 'lost_heartbeat_reboot') + tuple(LATE_HEARTBEAT_FAULTS)
FAULTS = ('clean', 'drop_request', 'drop_reply', 'corrupt', 'delay', 'garbage', 'unplug_before',
          'unplug_after', 'lock_by_other', 'arm_by_other', 'trigger_by_other',
          'cut_records') + REBOOT_FAULTS
"""What can happen to one request on the wire (or to the module just before it arrives).
``cut_records``: a trigger-record answer loses its newest record's frame (cut short).
``lost_heartbeat_reboot``: the module reboots as the request comes, its first heartbeat is taken
with the reply, its second is lost, and it reboots again 0.3 s later (within the 2 s of a late
heartbeat: the second power-up's first heartbeat looks like the first's late second)."""
HEARTBEAT = p.encode_module_heartbeat()
ARM_FRAME, LOCK_FRAME = p.encode_arm(True), p.encode_arm(False)
JUDGEMENTS = ('safe', 'safe', 'would deploy', 'no answer')
"""What the settings core's check before an arm finds (D16): nothing, that arming would deploy
the module at once, or that the module did not answer what the check needs."""
REBOOT_KINDS = ('seen', 'quiet', 'late', 'lost_second_then_reboot')
"""How a generated reboot reaches the driver (D3): its heartbeats seen or lost, its second taken
late by a reader that stalled, or lost and another reboot following."""
REBOOT_AFTER_S = (0.3, 0.6, 1.5, 1.9)
"""When the late second heartbeat, or the second reboot, comes after the first heartbeat."""


def reboot_faults(kind: str, after: float) -> Dict[str, Any]:
    """Return a rig's reboot arguments (``quiet``, ``late_s``, ``again_s``) for `kind`."""
    return dict(quiet=kind == 'quiet', late_s=after if kind == 'late' else 0.0,
                again_s=after if kind == 'lost_second_then_reboot' else None)


GARBAGE = bytes([0x00, 0x13, 0x99, 0xFE, 0x37])  # no header byte: it completes no frame


def faulty_reply(fault: str, out: bytes) -> bytes:
    """Return what of the module's reply `out` reaches the driver under a wire `fault`."""
    if fault == 'drop_reply':
        return b''
    if fault == 'corrupt' and out:
        return out[:-1] + bytes([out[-1] ^ 0x40])
    if fault == 'garbage':
        return GARBAGE + out
    return out


def merged(parts: List[Tuple[bytes, int]]) -> List[Tuple[bytes, int]]:
    """Join the consecutive `parts` (bytes, boot count) of one power-up; drop empty ones."""
    out: List[Tuple[bytes, int]] = []
    for data, boot in parts:
        if out and out[-1][1] == boot:
            out[-1] = (out[-1][0] + data, boot)
        elif data:
            out.append((data, boot))
    return out


@dataclass
class Call:
    """One deploy call and what became of it."""

    token: str
    arm_if_locked: bool
    answers: List[DeployAnswer] = field(default_factory=list)
    deploy_frames: int = 0          # deploy frames that reached the module
    deploy_sends: int = 0           # deploy frames the core asked to send
    serial_deployments: int = 0     # deployments by this call's deploy frames
    deployments_before: int = 0
    deployments_after: int = 0
    triggered_before: bool = False


@dataclass
class ArmRun:
    """One arm (or lock) call and what became of it."""

    want: bool
    judgement: str
    boot_before: int
    answers: List[ArmAnswer] = field(default_factory=list)
    arm_sends: int = 0              # arm or lock frames that left for the module
    judged: int = 0                 # times the settings core's check was asked
    problems: List[str] = field(default_factory=list)


class ModelRig:
    """The core, the model and the wire between them; see the module docstring."""

    def __init__(self, boot_count: int = 7, armed: bool = True, mirror: bool = False) -> None:
        self.t = START
        # mirror: the core as the session runs it, told before each step what a keeper of the
        # knowledge (the session's threads; here a DeployCore never called) has taken in.
        self.mirror = mirror
        self.keeper: Optional[DeployCore] = None
        self.keeper_armed: Optional[tuple] = None  # (reboots, armed) of the last armed query
        self.model = VirtualParachute(now=self.t - 1.0, boot_count=boot_count)
        self.model.step(self.t)  # its power-up heartbeats went by before the driver started
        self.model.armed = armed
        self.plugged = True
        self.saved: Optional[SaveAttempts] = None
        self.faults: List[str] = []
        self.applied: List[str] = []           # the faults met by a request, in order
        self.actions: List[Any] = []
        self.calls: List[Call] = []
        self.call: Optional[Call] = None
        self.arm_calls: List[ArmRun] = []
        self.arm_call: Optional[ArmRun] = None
        self.triggered_read: Optional[bool] = None  # since the last known reboot or reconnect
        self.unacked: Dict[int, int] = {}      # model boot count -> deploy frames unacked
        self.armed_read = False                # an armed=True read since the last known reboot
        self.last_heartbeat = -1e9
        self.last_boot_told: Optional[int] = None
        self.unseen_reboot = False             # a reboot whose heartbeats were lost, not read
        self.unseen_change = False             # armed changed by another path, not read
        # The truth of a reader that stalls (a late heartbeat, D3): what the module sent
        # meanwhile, each part with its power-up (boot count), taken in order when it ends.
        self.held: List[Tuple[bytes, int]] = []
        self.hold_until = -1e9
        self.reboot_at: Optional[float] = None   # a reboot of the module due (in a stall)
        self.heard_boots: Set[int] = set()       # power-ups whose heartbeat the core took
        # A Reply not yet stepped (by id; kept alive so no other takes its id) and its boot.
        self.sent_by: Dict[int, Tuple[Reply, int]] = {}
        # A request's own end (Timeout, LinkDown) not yet stepped, and the request.
        self.end_of: Dict[int, Tuple[Any, Request]] = {}
        self.armed_boot: Optional[int] = None    # the power-up the last armed state read is of
        self.order_problems: List[str] = []
        self.decoder = p.StreamDecoder('from_module')
        self.core = self._new_core(None)

    def _new_core(self, stored: Optional[Stored]) -> DeployCore:
        if self.mirror:
            self.keeper = DeployCore(stored)
            core = DeployCore(mirror=True)
        else:
            core = DeployCore(stored)
        self.core = core
        self.armed_read = False
        self.triggered_read = None
        self.last_boot_told = None
        self._unhold()  # (a new process opens the port afresh)
        if self.plugged:
            self._run([LinkUp(self.t)])
        return core

    # -- what a test does ---------------------------------------------------------------------

    def deploy(self, token: str = 'DEPLOY', arm_if_locked: bool = False,
               faults: Optional[List[str]] = None, gate: bool = False) -> Call:
        """One `~/deploy`, with `faults` applied to its requests in turn; its Call."""
        self.faults = list(faults or [])
        call = Call(token, arm_if_locked, deployments_before=self.model.deployments,
                    triggered_before=self.model.triggered)
        self.calls.append(call)
        self.call = call
        self._run([DeployCall(self.t, token, arm_if_locked, gate)])
        call.deployments_after = self.model.deployments
        self.call = None
        self.faults = []
        return call

    def arm(self, want: bool = True, faults: Optional[List[str]] = None,
            judgement: str = 'safe') -> ArmRun:
        """One `~/arm` (or lock), `faults` applied to its requests in turn; its ArmRun."""
        self.faults = list(faults or [])
        call = ArmRun(want, judgement, self.model.boot_count)
        self.arm_calls.append(call)
        self.arm_call = call
        self._run([ArmCall(self.t, want)])
        self.arm_call = None
        self.faults = []
        return call

    def restart_driver(self) -> None:
        """Respawn the driver: a new core, with the attempts the old one kept."""
        saved = self.saved
        self._new_core(None if saved is None
                       else Stored(saved.boot_count, saved.failed, saved.unacked,
                                   saved.since_read))

    def unplug(self) -> None:
        if self.plugged:
            self.unplug_quietly()
            self._run([LinkDown(self.t, 'unplugged')])

    def replug(self) -> None:
        if not self.plugged:
            self.plugged = True
            self.armed_read = False
            self.triggered_read = None
            self._run([LinkUp(self.t)])

    def power_cycle(self, quiet: bool = False, late_s: float = 0.0,
                    again_s: Optional[float] = None) -> None:
        """Switch the module off and on (boot count +1, locked); `quiet`: heartbeats lost.

        `late_s`: its first heartbeat is taken at once, then the driver's reader stalls that
        long (its second heartbeat is taken late, D3). `again_s`: its first heartbeat is taken,
        its second is lost, and it reboots again that long after (within 2 s: that power-up's
        first heartbeat looks like a late second).
        """
        self.wait(REBOOT_S)
        self.model.power_cycle()
        if quiet or not self.plugged:
            self.unseen_reboot = True
        if quiet:
            self.model.step(self.t + 0.1)
        elif late_s or again_s is not None:
            self.wait(0.0)  # its first heartbeat
            if late_s and self.t >= self.hold_until:
                # (A stall going on is not made longer: no heartbeat is taken more than
                # LATE_HEARTBEAT_S after the one before, the rule's bound, D3.)
                self.hold_until = self.t + late_s
            if again_s is not None:
                self._lose_second_heartbeat()
                self.wait(again_s - 0.06)
                self.model.power_cycle()
                if not self.plugged:
                    self.unseen_reboot = True
        self.wait(0.1)

    def wait(self, seconds: float) -> None:
        """Time passes; what the module sends meanwhile reaches the core (when plugged)."""
        end = self.t + seconds
        if self.t < self.hold_until <= end:  # the reader takes what it held first
            self.t = self.hold_until
            self._run(self._deliver(self._module_to(self.t)))
        self.t = end
        self._run(self._deliver(self._module_to(self.t)))

    def status_frame(self) -> None:
        """Bring the module's status frame to the core (as the stream or a poll would)."""
        if self.plugged and self.model.powered:
            self._run(self._deliver([(self.model._status_frame(), self.model.boot_count)]))

    # -- the module's side of the wire, and a reader that stalls ------------------------------

    def _module_to(self, t: float) -> List[Tuple[bytes, int]]:
        """Return what the module sends up to `t`, each part with its boot count.

        A reboot due by then (``reboot_at``) comes first.
        """
        out = []
        if self.reboot_at is not None and self.reboot_at <= t:
            out.append((self.model.step(self.reboot_at), self.model.boot_count))
            self.model.power_cycle()
            self.unseen_reboot = True  # (until its boot count is read)
            self.reboot_at = None
        out.append((self.model.step(t), self.model.boot_count))
        return out

    def _deliver(self, parts: List[Tuple[bytes, int]]) -> List[Reply]:
        """Bring the module's `parts` to the core now, or hold them while the reader stalls."""
        if not self.plugged:
            return []
        if self.t < self.hold_until:
            self.held += parts
            return []
        parts, self.held = self.held + parts, []
        return [r for out, boot in parts for r in self._received(out, self.t, boot)]

    def _unhold(self) -> None:
        self.held, self.hold_until = [], -1e9

    def _lose_second_heartbeat(self) -> None:
        """50 ms on: the power-up's second heartbeat is lost on the wire, the rest arrives."""
        self.t += 0.06
        out = self.model.step(self.t)
        self._run(self._deliver([(out.replace(HEARTBEAT, b'', 1), self.model.boot_count)]))

    # -- carrying out the core's actions ------------------------------------------------------

    def _run(self, events: List[Any]) -> None:
        run_core(self, events, {
            Request: self._send, Record: self._keep, Log: self._keep, Report: self._keep,
            SaveAttempts: self._save, PassGate: self._gate, DeployAnswer: self._answer,
            JudgeArm: self._judge, ArmAnswer: self._arm_answer})

    def step(self, event: Any) -> List[Any]:
        """Step the core; a mirror core as the session does: its keeper takes the event first.

        What the invariants follow of the module's frames is taken here, as the core takes
        them: a batch the reader brings is stepped one frame at a time, and a request the core
        sends on one of them leaves before it takes the next (which it could not know of).
        """
        if isinstance(event, Reply):
            _, boot = self.sent_by.pop(id(event), (event, self.model.boot_count))
            self._told(event.message, event.now, boot)
        _, request = self.end_of.pop(id(event), (event, None))
        if request is not None and self.core._waiting is not request:
            # A frame the reader took before it (held by a stall) answered that request: a
            # runtime ends a request once, and the link's next request says it is down.
            return []
        if not self.mirror:
            return self.core.step(event)
        keeper = self.keeper
        assert keeper is not None
        if not isinstance(event, (DeployCall, ArmCall, GateDone, ArmJudged)):
            for action in keeper.step(event):
                if isinstance(action, SaveAttempts):
                    self.saved = action
            message = getattr(event, 'message', None)
            # The session's re-read: armed and triggered read with no reboot between (D15).
            if isinstance(message, p.ArmedState):
                self.keeper_armed = (keeper.reboots, message.armed)
            elif isinstance(message, p.TriggeredState) and self.keeper_armed and \
                    self.keeper_armed[0] == keeper.reboots:
                keeper.armed, keeper.fresh = self.keeper_armed[1], True
        self.core.know(port_open=keeper.port_open, online=keeper.online,
                       offline_reason=keeper.offline_reason, fresh=keeper.fresh,
                       armed=keeper.armed, triggered=keeper.triggered,
                       boot_count=keeper.boot_count, failed=keeper.failed,
                       unacked=keeper.unacked, outcome_unknown=keeper.outcome_unknown,
                       unknown_boot=keeper._unknown_boot, triggered_seen=keeper._triggered_seen,
                       frame_at=keeper._frame_at, reboots=keeper.reboots,
                       boot_current=keeper.boot_current, deployed_boots=set(keeper._reported))
        return self.core.step(event)

    def _keep(self, action: Any) -> None:
        self.actions.append(action)

    def _save(self, action: SaveAttempts) -> None:
        self.actions.append(action)
        self.saved = action

    def _gate(self, action: PassGate) -> List[Any]:
        self.actions.append(action)
        return [GateDone(self.t)]

    def _judge(self, action: JudgeArm) -> List[Any]:
        self.actions.append(action)
        call = self.arm_call
        assert call is not None
        call.judged += 1
        if call.judgement == 'would deploy':
            return [ArmJudged(self.t, danger='the attitude threshold is below the tilt now')]
        if call.judgement == 'no answer':
            return [ArmJudged(self.t, problem='no reply to the status query')]
        return [ArmJudged(self.t)]

    def _arm_answer(self, action: ArmAnswer) -> None:
        self.actions.append(action)
        call = self.arm_call
        if call is not None:
            call.answers.append(action)
        result = action.result
        keeper = self.keeper
        if keeper is not None and call is not None and call.arm_sends and \
                result.outcome.value == 'unknown' and result.cause == 'no_reply':
            keeper.armed, keeper.fresh = None, False  # what the session takes from it

    def _answer(self, action: DeployAnswer) -> None:
        self.actions.append(action)
        if self.call is not None:
            self.call.answers.append(action)
        keeper = self.keeper
        if keeper is not None:  # what the session takes from an answer
            if action.counts is not None:
                keeper.failed, keeper.unacked = action.counts
            if action.outcome == 'unknown':
                keeper.outcome_unknown, keeper._unknown_boot = True, keeper.boot_count
            self.saved = SaveAttempts(keeper.boot_count, keeper.failed, keeper.unacked,
                                      keeper._sent_since_read)

    def _send(self, send: Request) -> List[Any]:
        events = self._carry_out(send)
        for event in events:
            if isinstance(event, (Timeout, LinkDown)):
                self.end_of[id(event)] = (event, send)
        return events

    def _carry_out(self, send: Request) -> List[Any]:
        self.actions.append(send)
        if send.frame == DEPLOY_FRAME:
            self._check_before_deploy_frame()
        elif send.frame in (ARM_FRAME, LOCK_FRAME):
            self._check_before_arm_frame(send.frame == ARM_FRAME)
        if not self.plugged:
            return [LinkDown(self.t, 'unplugged', frame_left=False)]
        events: List[Any] = []
        for attempt in range(send.retries + 1):
            fault = self.faults.pop(0) if self.faults else 'clean'
            self.applied.append(fault)
            sent_at = self.t
            if fault == 'unplug_before':
                self.unplug_quietly()
                # (An attempt before this one left: the request's frame did.)
                return events + [LinkDown(self.t, 'unplugged', frame_left=attempt > 0)]
            out_parts: List[Tuple[bytes, int]] = []
            if fault in REBOOT_FAULTS:
                self.t += REBOOT_S
                out_parts = self._module_to(self.t)  # (what it sent before it went off)
            self._module_fault(fault)
            if fault in LATE_HEARTBEAT_FAULTS or fault == 'lost_heartbeat_reboot':
                # Its first heartbeat is taken at once (then the reader stalls, or the second
                # heartbeat is lost below).
                events += self._deliver(out_parts + self._module_to(self.t))
                out_parts = []
                if fault in LATE_HEARTBEAT_FAULTS:
                    stall, again = LATE_HEARTBEAT_FAULTS[fault]
                    if self.t >= self.hold_until:  # (a stall going on is not made longer)
                        self.hold_until = self.t + stall
                    if again is not None:
                        self.reboot_at = self.t + again
            if send.frame in (ARM_FRAME, LOCK_FRAME) and self.arm_call is not None:
                self.arm_call.arm_sends += 1
            if send.frame == DEPLOY_FRAME:
                self._count_deploy_frame()
                if self.keeper is not None:  # the session's _on_tx
                    self.keeper.failed += 1
                    self.keeper.unacked += 1
                    self.keeper._sent_since_read += 1
                    self.keeper._frame_at = self.t
            if fault != 'drop_request':
                before = self.model.deployments
                out_parts += self._module_to(self.t)
                out_parts.append((self.model.receive(send.frame, self.t),
                                  self.model.boot_count))
                if self.call is not None:
                    self.call.serial_deployments += self.model.deployments - before
                self.t += REPLY_S
                out_parts += self._module_to(self.t)
                if send.frame == DEPLOY_FRAME and self.call is not None:
                    self.call.deploy_frames += 1
            if fault == 'lost_heartbeat_reboot':
                self.t += 0.06
                out, boot = self._module_to(self.t)[-1]
                out_parts.append((out.replace(HEARTBEAT, b'', 1), boot))
                self.t += REBOOT_S - 0.06
                out_parts += self._module_to(self.t)
                self.model.power_cycle()  # its heartbeats come with what the wire carries next
            if fault == 'unplug_after':
                self.unplug_quietly()
                return events + [LinkDown(self.t, 'unplugged', frame_left=True)]
            out_parts = merged(out_parts)
            if out_parts and fault in ('drop_reply', 'corrupt', 'garbage'):
                out, boot = out_parts[-1]
                out_parts[-1] = (faulty_reply(fault, out), boot)
            late = fault == 'delay'
            ended = None if late else self._ends(send, fault, events, self._deliver(out_parts))
            if ended is not None:
                return ended
            if self.held and self.hold_until <= sent_at + self.core.timeout_s:
                # The reader takes what it held before the reply deadline.
                self.t = max(self.t, self.hold_until)
                ended = self._ends(send, fault, events, self._deliver(self._module_to(self.t)))
                if ended is not None:
                    return ended
            self.t = max(self.t, sent_at + self.core.timeout_s)
            if late:
                self.t += 0.05
                events.append(Timeout(self.t - 0.05))
                return events + self._deliver(out_parts)
        return events + [Timeout(self.t)]

    def _ends(self, send: Request, fault: str, events: List[Any],
              received: List[Reply]) -> Optional[List[Any]]:
        """Add `received` to `events`; return them if they end the request `send`, else None."""
        if p.TriggerRecord in send.expect:
            # The link collects a record query's answer into one reply (query_records).
            records = [e.message for e in received if isinstance(e.message, p.TriggerRecord)]
            received = [e for e in received if not isinstance(e.message, p.TriggerRecord)]
            stored = [i for i, r in enumerate(records) if not r.is_empty]
            if fault == 'cut_records' and records:
                del records[stored[-1] if stored else -1]
            if records:
                return events + received + [Reply(self.t, p.TriggerRecords(records))]
        events += received
        if any(isinstance(e.message, send.expect) for e in received):
            return events
        return None

    def unplug_quietly(self) -> None:
        self.plugged = False
        self.decoder.reset()
        self._unhold()  # (what the port held is lost with it)

    def _module_fault(self, fault: str) -> None:
        model = self.model
        if fault in REBOOT_FAULTS:
            model.power_cycle()
            self.unseen_reboot = True  # (its heartbeats may come late, or not at all)
            if fault == 'reboot_quiet':
                self.t += 0.06
                model.step(self.t)  # its two heartbeats are lost on the wire
        elif fault == 'lock_by_other' and model.armed:
            model.armed = False
            self.unseen_change = True
        elif fault == 'arm_by_other' and not model.triggered and not model.armed:
            model.armed = True
            self.unseen_change = True
        elif fault == 'trigger_by_other' and model._can_fire() and not model.igniter_fault:
            model._fire(p.SOURCE_PWM)

    def _received(self, out: bytes, now: float, boot: Optional[int] = None) -> List[Reply]:
        """Decode `out`, taken at `now`; `boot`: the power-up that sent it (default: now's)."""
        frames = self.decoder.feed(out) + self.decoder.flush()
        replies = [Reply(now, p.decode_module_frame(f)) for f in frames]
        for reply in replies:
            self.sent_by[id(reply)] = (reply, self.model.boot_count if boot is None else boot)
        return replies

    # -- what the invariants need -------------------------------------------------------------

    def _told(self, msg: Any, now: float, boot: int) -> None:
        """Follow what the core is told: reboots it can know of, armed states, acknowledgements.

        `boot`: the power-up that sent `msg`. Any heartbeat more than 0.2 s after the one
        before may tell a reboot (P5, D3: a late second heartbeat too): the armed state read
        before it is not known to hold after it.
        """
        if isinstance(msg, p.Heartbeat):
            self.heard_boots.add(boot)
            if now - self.last_heartbeat > POWER_UP_HEARTBEATS_S:
                self.armed_read, self.triggered_read = False, None
            self.last_heartbeat = now
        elif isinstance(msg, p.BootCount):
            if msg.count == self.model.boot_count:
                self.unseen_reboot = False
            if self.last_boot_told is not None and msg.count != self.last_boot_told:
                self.armed_read, self.triggered_read = False, None
            self.last_boot_told = msg.count
        elif isinstance(msg, (p.ArmedState, p.Status)):
            self.armed_read = msg.armed
            self.armed_boot = boot
            if msg.armed == self.model.armed:
                self.unseen_change = False
        if isinstance(msg, (p.Status, p.TriggeredState)):
            self.triggered_read = msg.triggered
        elif isinstance(msg, p.DeployAck) and msg.success:
            self.unacked[boot] = 0

    def _count_deploy_frame(self) -> None:
        boot = self.model.boot_count
        self.unacked[boot] = self.unacked.get(boot, 0) + 1
        if self.call is not None:
            self.call.deploy_sends += 1

    def _check_before_arm_frame(self, arm: bool) -> None:
        call = self.arm_call
        if call is None:
            return  # (a deploy's arm_if_locked: firing is the point, and its frame is judged)
        if not arm:
            return
        if self.triggered_read is not False:
            call.problems.append('an arm frame on a triggered state not read (as not '
                                 'triggered) since the last known reboot or reconnect')
        if not call.judged or call.judgement != 'safe':
            call.problems.append(f'an arm frame the check did not pass ({call.judgement}, '
                                 f'asked {call.judged} times)')

    def _check_before_deploy_frame(self) -> None:
        if not self.armed_read:
            self.order_problems.append('a deploy frame on an armed state not read since the '
                                       'last known reboot or reconnect')
        boot = self.model.boot_count
        if boot in self.heard_boots and self.armed_boot != boot:
            # (A reboot whose heartbeat the driver took, even one taken within 0.2 s of a
            # late heartbeat and so one with it, D3: its armed state must be read after.)
            self.order_problems.append(f'a deploy frame to power-up {boot}, whose heartbeat '
                                       f'the driver took, on an armed state read of power-up '
                                       f'{self.armed_boot}')
        before = [a for a in self.actions[:-1] if not isinstance(a, (Log, Report))]
        record = next((a for a in reversed(before) if isinstance(a, Record)), None)
        fields = dict(record.fields) if record else {}
        if record is None or fields.get('what') != 'deploy: sending the deploy frame' or \
                record.sync != SYNC_WAIT:
            self.order_problems.append(f'deploy frame without its synced decision: {record}')
        if not isinstance(before[-1], SaveAttempts) or before[-1].failed < 1:
            self.order_problems.append('deploy frame left before its attempt was kept')
