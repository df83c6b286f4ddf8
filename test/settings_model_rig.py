"""A `SettingsCore` driven against the virtual parachute in virtual time, with wire faults.

`SettingsRig` plays the session's part (``session_settings``): it tells the core what is known of
the module before each event (``known``: the settings as read, kept from the core's `Learned`),
carries out the core's actions with ``uav_serial_common.core_runner.run_core`` (a `Request` goes to
the device model through a wire that applies the faults queued for it; the model's bytes come
back decoded as `Reply` events, or `Timeout` at the deadline, `LinkDown` when unplugged) and
keeps what the invariants need: every call with its answers, the write frames that reached the
module, and each write that made the armed module ask or fire (D16). No thread, no pty, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Set, Tuple

from dps_parachute_ros import protocol as p
from dps_parachute_ros.settings_core import (Drained, FLAGS, JudgeCall, Learned, SettingsCore,
                                             WriteCall)
from dps_parachute_ros.simulation import VirtualParachute
from dps_parachute_ros.state import SETTINGS
from parachute_model_rig import faulty_reply, REBOOT_S, REPLY_S
from uav_serial_common.core_events import (Answer, LinkDown, Log, Record, Reply, Request,
                                           Timeout)
from uav_serial_common.core_runner import run_core

START = 1000.0
WIRE_FAULTS = ('clean', 'drop_request', 'drop_reply', 'corrupt', 'delay', 'garbage',
               'unplug_before', 'unplug_after', 'reboot')
"""What can happen to one frame on the wire (or to the module just before it arrives)."""
WORLD_FAULTS = ('tilt', 'fall', 'level', 'arm_by_other', 'lock_by_other')
"""What the world does to the module meanwhile: before a query only, never between the status
read that judged a write and the write (no driver can close that race)."""
FIELDS = {
    # parameter: the module model's field, and the parameter value's raw value there
    'attitude_threshold_deg': 'attitude_threshold_deg',
    'freefall_threshold_g': 'freefall_threshold_raw',
    'freefall_time_s': 'freefall_time_raw',
    'light_threshold_v': 'light_threshold_raw',
    'attitude_trigger': 'attitude_trigger_enabled',
    'freefall_trigger': 'freefall_trigger_enabled',
}
WRITE_CODES = {p.CMD_ATTITUDE_THRESHOLD: 'attitude_threshold_deg',
               p.CMD_FREEFALL_THRESHOLD: 'freefall_threshold_g',
               p.CMD_FREEFALL_TIME: 'freefall_time_s', p.CMD_LIGHT_THRESHOLD: 'light_threshold_v',
               p.CMD_ATTITUDE_TRIGGER: 'attitude_trigger',
               p.CMD_FREEFALL_TRIGGER: 'freefall_trigger'}


def raw_of(name: str, value: Any) -> Any:
    """Return the module's raw value of a parameter value (a flag: its bool)."""
    return bool(value) if name in FLAGS else SETTINGS[name].to_raw(value)


def firing(model: VirtualParachute) -> Set[str]:
    """Return the trigger conditions the module meets now and would act on (P21)."""
    if not (model.powered and model.armed and not model.triggered and not model.protection):
        return set()
    met = set()
    if model.attitude_trigger_enabled and model.reported_tilt_deg > model.attitude_threshold_deg:
        met.add('attitude')
    if model.freefall_trigger_enabled and model.accel_g < model.freefall_threshold_raw / 10:
        met.add('freefall')
    return met


@dataclass
class Call:
    """One write call and what became of it."""

    event: Any
    before: Dict[str, Any]
    answers: List[Answer] = field(default_factory=list)
    reached: List[str] = field(default_factory=list)
    """Parameters whose write frame reached the module (in order)."""


class SettingsRig:
    """The core, the model and the wire between them; see the module docstring."""

    def __init__(self, boot_count: int = 7) -> None:
        self.t = START
        self.model = VirtualParachute(now=self.t - 1.0, boot_count=boot_count)
        self.model.step(self.t)
        self.plugged = True
        self.known: Dict[str, Any] = self.truth()  # read at connect
        self.faults: List[str] = []
        self.calls: List[Call] = []
        self.call: Optional[Call] = None
        self.actions: List[Any] = []
        self.violations: List[str] = []
        self.decoder = p.StreamDecoder('from_module')
        self.core = SettingsCore()

    def truth(self) -> Dict[str, Any]:
        """Return the module's settings by parameter name (raw; flags as bools)."""
        return {name: getattr(self.model, attr) for name, attr in FIELDS.items()}

    # -- what a test does ---------------------------------------------------------------------

    def write(self, steps: Tuple[Tuple[str, Any], ...], origin: str, faults: List[str],
              all_or_nothing: bool = False, hold: bool = False) -> Call:
        """One write call with `faults` applied to its frames in turn; its Call."""
        return self._call(WriteCall(self.t, steps, origin, all_or_nothing, hold,
                                    1.8 if all_or_nothing else None), faults)

    def arm(self, faults: List[str]) -> Call:
        """``~/arm true``: judged by the core's rule (`JudgeCall`), then armed if it may."""
        call = self._call(JudgeCall(self.t, (('armed', True),), '~/arm'), faults)
        if call.answers and call.answers[0].result.ok and self.plugged:
            self._deliver(p.encode_arm(True), True, 'armed')
        return call

    def _call(self, event: Any, faults: List[str]) -> Call:
        self.faults = list(faults)
        call = Call(event, self.truth())
        self.calls.append(call)
        self.call = call
        self.core = SettingsCore()  # one per call, as the session makes it
        handlers = {Request: self._send, Learned: self._learned, Record: self.actions.append,
                    Log: self.actions.append, Answer: self._answer}
        run_core(self, [call.event], handlers)
        for _ in range(8):  # a reply it did not take: the session says Drained too
            if not self.core.busy:
                break
            run_core(self, [Drained(self.t)], handlers)
        self.call = None
        self.faults = []
        return call

    def step(self, event: Any) -> List[Any]:
        """Step the core as the session does: told what is known first."""
        self.core.know(self.plugged, '' if self.plugged else 'port closed (unplugged)',
                       values={n: v for n, v in self.known.items() if n not in FLAGS},
                       flags={n: v for n, v in self.known.items() if n in FLAGS})
        return self.core.step(event)

    def wait(self, seconds: float) -> None:
        """Time passes (what the module sends meanwhile is no reply to anything)."""
        self.t += seconds
        self.model.step(self.t)

    def power_cycle(self) -> None:
        """Switch the module off and on (it boots locked; its settings are kept, P17)."""
        self.wait(REBOOT_S)
        self.model.power_cycle()
        self.wait(0.1)

    def reconnect(self) -> None:
        """Plug in again; the initialization reads every setting afresh."""
        self.plugged = True
        self.decoder.reset()
        self.known = self.truth()

    def world(self, fault: str, tilt: float = 75.0, accel: float = 0.2) -> None:
        """Do to the module what the world does (a tilt, a fall, an arm by another path)."""
        model = self.model
        if fault == 'tilt':
            model.set_tilt(tilt)
        elif fault == 'fall':
            model.set_accel(accel)
        elif fault == 'level':
            model.set_tilt(0.0)
            model.set_accel(1.0)
        elif fault == 'arm_by_other' and not model.triggered:
            model.armed = True
        elif fault == 'lock_by_other':
            model.armed = False

    # -- carrying out the core's actions ------------------------------------------------------

    def _answer(self, action: Answer) -> None:
        self.actions.append(action)
        if self.call is not None:
            self.call.answers.append(action)

    def _learned(self, action: Learned) -> None:
        self.actions.append(action)
        self.known[action.name] = action.value

    def _send(self, send: Request) -> List[Any]:
        self.actions.append(send)
        if not self.plugged:
            return [LinkDown(self.t, 'unplugged', frame_left=False)]
        frame = p.StreamDecoder('from_host').feed(send.frame)[0]
        write = frame.code in WRITE_CODES and frame.raw[3] != p.CTRL_QUERY
        events: List[Any] = []
        for _ in range(send.retries + 1):
            fault = self.faults.pop(0) if self.faults else 'clean'
            sent_at = self.t
            if fault in WORLD_FAULTS:
                if not write:
                    self.world(fault)
                fault = 'clean'
            if fault == 'unplug_before':
                self._unplug()
                return events + [LinkDown(self.t, 'unplugged', frame_left=False)]
            if fault == 'reboot':
                self.t += REBOOT_S
                self.model.step(self.t)
                self.model.power_cycle()
            out = b''
            if fault != 'drop_request':
                out = self._deliver(send.frame, write, WRITE_CODES.get(frame.code, ''))
            if fault == 'unplug_after':
                self._unplug()
                return events + [LinkDown(self.t, 'unplugged', frame_left=True)]
            out = faulty_reply(fault, out)
            late = fault == 'delay'
            received = [] if late else self._received(out)
            events += received
            if any(isinstance(e.message, send.expect) for e in received):
                return events
            self.t = max(self.t, sent_at + self.core.timeout_s)
            if late:
                self.t += 0.05
                return events + [Timeout(self.t - 0.05)] + self._received(out)
        return events + [Timeout(self.t)]

    def _deliver(self, frame: bytes, write: bool, name: str) -> bytes:
        """Bring the frame to the module; check a write against D16 as it lands."""
        model = self.model
        out = model.step(self.t)  # (what time alone brings is not the write's doing)
        before = firing(model)
        asked = model.requests_sent + model.deployments
        out += model.receive(frame, self.t)
        now = firing(model) - before
        acted = model.requests_sent + model.deployments > asked
        self.t += REPLY_S
        out += model.step(self.t)
        if not write:
            return out
        if self.call is not None and model.powered:
            self.call.reached.append(name)
        # (Asking at once, or a condition newly met: it asks when its free-fall time is over.)
        if now or acted:
            self.violations.append(
                f'a write of {name} ({frame.hex(" ")}) made the armed module meet {now}: '
                f'tilt {model.reported_tilt_deg}, accel {model.accel_g}, settings '
                f'{self.truth()}')
        return out

    def _unplug(self) -> None:
        self.plugged = False
        self.decoder.reset()

    def _received(self, out: bytes) -> List[Reply]:
        frames = self.decoder.feed(out) + self.decoder.flush()
        return [Reply(self.t, p.decode_module_frame(f)) for f in frames]
