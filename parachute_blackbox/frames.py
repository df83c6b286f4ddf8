"""What the frames on the wire mean: received messages and sent commands."""

from __future__ import annotations

from typing import Any, Callable, Dict, Optional, TYPE_CHECKING

from dps_parachute_ros import protocol as p
from parachute_blackbox.containers import Pending, TriggerRequestSeen
from parachute_blackbox.names import REQUEST_STALE_S, SETTING_NAMES, SETTING_REPLIES

if TYPE_CHECKING:
    from parachute_blackbox.analysis import FlightAnalysis


# ---------------------------------------------------------------------------------------------
# Received frames: typed message -> handler(analysis, message, t, answered request or None)
# ---------------------------------------------------------------------------------------------

def _rx_status(a: FlightAnalysis, msg: p.Status, t: float, req: Optional[Pending]) -> None:
    a.status_sample(t, float(msg.tilt_deg), float(msg.accel_g), msg.armed, msg.triggered)
    a.band('armed', t, msg.armed)
    if msg.triggered:
        a.module_triggered(t, 'status frame')
    else:
        a.band('triggered', t, False)


def _rx_heartbeat(a: FlightAnalysis, msg: p.Heartbeat, t: float,
                  req: Optional[Pending]) -> None:
    if req is not None:
        return  # the answer to our heartbeat
    # P5: a heartbeat nobody asked for is the module powering up (two, 50 ms apart).
    a.power_up_heartbeat(t)


def _rx_trigger_request(a: FlightAnalysis, msg: p.TriggerRequest, t: float,
                        req: Optional[Pending]) -> None:
    a.counts['trigger requests'] += 1
    seen = TriggerRequestSeen(t)
    a.requests.append(seen)
    a._undecided.append(seen)
    a.event(t, 'request', 'warn', 'the module asks to deploy (trigger request 0x39)')


def oldest_undecided(a: FlightAnalysis, t: float) -> Optional[TriggerRequestSeen]:
    """Return the trigger request the next decision is about.

    Decisions come in the order of the requests: a newer request supersedes a deferred one,
    which is then decided (timed out) after the newer one was received (D8).
    """
    while a._undecided and (a._undecided[0].decision or t - a._undecided[0].t > REQUEST_STALE_S):
        a._undecided.popleft()
    return a._undecided[0] if a._undecided else None


def _rx_deploy_ack(a: FlightAnalysis, msg: p.DeployAck, t: float,
                   req: Optional[Pending]) -> None:
    dep = a.current_deployment(t)
    if msg.success:
        a.counts['deploy acknowledgements'] += 1
        a.event(t, 'deploy', 'bad', 'module acknowledged the deploy (D4 01)')
        if dep is None:
            dep = a.open_deployment(t, 'ack', 'a deploy acknowledgement nobody was seen asking '
                                    'for (late, or the call was not recorded)')
        dep.step(t, 'ack', 'the module acknowledged: deploying (D4 01)')
        dep.outcome, dep.outcome_text = 'deployed', 'acknowledged by the module'
        a.band('armed', t, False)
    else:
        a.counts['deploys refused by the module'] += 1
        a.event(t, 'deploy', 'warn', 'module answered the deploy with D4 00: not deployed '
                '(locked, already triggered or in protection)')
        if dep is not None:
            dep.step(t, 'ack', 'the module answered D4 00: it did NOT deploy')
            dep.outcome, dep.outcome_text = 'refused', 'refused by the module (D4 00)'


def _rx_setting(a: FlightAnalysis, msg: Any, t: float, req: Optional[Pending]) -> None:
    code = SETTING_REPLIES[type(msg)]
    key, name, unit, step = SETTING_NAMES[code]
    if req is not None and req.control == p.CTRL_SET:
        sent = a._set_sent.get(code)
        if sent is not None and not p.is_set_ack(msg, sent[1]):
            a.event(t, 'settings', 'bad', f'{name}: the module did not acknowledge '
                    f'{sent[1] * step:g}{unit} (answered {msg.value})')
            a._set_sent.pop(code, None)
        return
    a.setting_value(t, code, msg.value)
    sent = a._set_sent.pop(code, None)
    if sent is None:
        return
    wrote, read = round(sent[1] * step, 3), round(msg.value * step, 3)
    if msg.value == sent[1]:
        a.counts['settings written and verified'] += 1
        a.event(t, 'settings', 'ok', f'{name} {wrote:g}{unit} written and verified')
    else:
        a.counts['settings not verified'] += 1
        a.event(t, 'settings', 'bad', f'{name}: wrote {wrote:g}{unit}, the module reads back '
                f'{read:g}{unit}')


def _rx_flags(a: FlightAnalysis, msg: p.AutoTriggerFlags, t: float,
              req: Optional[Pending]) -> None:
    before = dict(a.flags)
    a.flags = {'attitude': msg.attitude_enabled, 'freefall': msg.freefall_enabled}
    if req is not None and req.control == p.CTRL_SET:
        a.counts['settings written and verified'] += 1
        a.event(t, 'settings', 'ok', f'auto triggers set: attitude '
                f'{"on" if msg.attitude_enabled else "off"}, free fall '
                f'{"on" if msg.freefall_enabled else "off"}')
    elif before != a.flags and None not in before.values():
        a.event(t, 'settings', 'warn', f'auto triggers now: attitude '
                f'{"on" if msg.attitude_enabled else "off"}, free fall '
                f'{"on" if msg.freefall_enabled else "off"}')


def _rx_boot_count(a: FlightAnalysis, msg: p.BootCount, t: float,
                   req: Optional[Pending]) -> None:
    a.boot_count(t, msg.count)


def _rx_baud(a: FlightAnalysis, msg: p.BaudRate, t: float, req: Optional[Pending]) -> None:
    a.module_baud = msg.baud
    a.event(t, 'settings', 'warn', f'module baud rate set to {msg.baud or msg.code}')


def _rx_streaming(a: FlightAnalysis, msg: p.StreamingReply, t: float,
                  req: Optional[Pending]) -> None:
    a.band('streaming', t, msg.enabled)


def _rx_armed(a: FlightAnalysis, msg: Any, t: float, req: Optional[Pending]) -> None:
    a.band('armed', t, msg.armed)


def _rx_triggered(a: FlightAnalysis, msg: p.TriggeredState, t: float,
                  req: Optional[Pending]) -> None:
    if msg.triggered:
        a.module_triggered(t, 'query')
        return
    a.band('triggered', t, False)
    dep = a.current_deployment(t)
    call = a._call
    if req is not None and dep is not None and call is not None and call.get('dep') is dep \
            and dep.first('frame') is not None:
        # The driver asks before any retry whether the missing acknowledgement hid a
        # deployment (D6).
        dep.step(t, 'query', 'the module answers it is NOT triggered (asked after the missing '
                 'acknowledgement)')


def _rx_record(a: FlightAnalysis, msg: p.TriggerRecord, t: float,
               req: Optional[Pending]) -> None:
    a.trigger_record(t, msg)


def _rx_voltage(a: FlightAnalysis, msg: p.CellVoltage, t: float,
                req: Optional[Pending]) -> None:
    v = msg.volts
    lo, hi, _ = a.cell_voltage or (v, v, v)
    a.cell_voltage = (min(lo, v), max(hi, v), v)


def _rx_charging(a: FlightAnalysis, msg: p.Charging, t: float, req: Optional[Pending]) -> None:
    a.charging = msg.charging


def _rx_shutdown(a: FlightAnalysis, msg: p.ShutdownAck, t: float,
                 req: Optional[Pending]) -> None:
    a.event(t, 'module', 'warn', 'the module announced it is switching off (0x12)')


def _rx_unknown(a: FlightAnalysis, msg: p.UnknownFrame, t: float,
                req: Optional[Pending]) -> None:
    if msg.reason == 'trigger confirmation (host frame)' or msg.reason == 'host header':
        a.counts['echoes of host frames'] += 1
        return
    a.counts['frames of unknown meaning'] += 1
    a.event(t, 'link', 'info', f'frame of unknown meaning ({msg.reason}): '
            f'{msg.raw.hex(" ")}')


RX_MESSAGES: Dict[type, Callable[..., None]] = {
    p.Status: _rx_status,
    p.Heartbeat: _rx_heartbeat,
    p.TriggerRequest: _rx_trigger_request,
    p.DeployAck: _rx_deploy_ack,
    p.AttitudeThreshold: _rx_setting,
    p.FreefallThreshold: _rx_setting,
    p.FreefallTime: _rx_setting,
    p.LightThreshold: _rx_setting,
    p.AutoTriggerFlags: _rx_flags,
    p.BootCount: _rx_boot_count,
    p.BaudRate: _rx_baud,
    p.StreamingReply: _rx_streaming,
    p.ArmReply: _rx_armed,
    p.ArmedState: _rx_armed,
    p.TriggeredState: _rx_triggered,
    p.TriggerRecord: _rx_record,
    p.CellVoltage: _rx_voltage,
    p.Charging: _rx_charging,
    p.ShutdownAck: _rx_shutdown,
    p.UnknownFrame: _rx_unknown,
}
"""Typed received message -> what it means for the report."""


# ---------------------------------------------------------------------------------------------
# Sent frames: command code -> handler(analysis, frame, t)
# ---------------------------------------------------------------------------------------------

def _tx_deploy(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    if frame.value != 1:
        return
    a.counts['deploy frames sent'] += 1
    dep = a.current_deployment(t)
    if dep is None or dep.origin != 'call':
        dep = a.open_deployment(t, 'frame', 'a deploy frame the black box shows no decision '
                                'for', 'unknown (no record of who decided)')
    dep.attempts = max(dep.attempts, 1)
    dep.step(t, 'frame', f'deploy frame on the wire ({frame.raw.hex(" ")})')
    a.event(t, 'deploy', 'warn', 'deploy frame sent (42 61 11 02 01)')


def _tx_confirm(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    if frame.data != p.CONFIRM_PAYLOAD:
        return
    a.counts['confirmations sent'] += 1
    req = oldest_undecided(a, t)
    if req is not None and req.t_confirm is None:
        req.t_confirm = t
        if req.deployment is not None:
            req.deployment.step(t, 'frame', 'confirmation frame on the wire (42 61 39 a5 01)')
    a.event(t, 'request', 'warn', 'confirmation sent (42 61 39 a5 01)')


def _tx_setting(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    if frame.data[0] != p.CTRL_SET:
        return
    code = frame.code
    key, name, unit, step = SETTING_NAMES[code]
    a._set_sent[code] = (t, frame.value)
    a.counts['settings written'] += 1


def _tx_auto_trigger(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    if frame.data[0] == p.CTRL_SET:
        a.counts['settings written'] += 1


def _tx_arm(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    a.counts['arm frames sent' if frame.value == 1 else 'lock frames sent'] += 1


def _tx_shutdown(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    a.event(t, 'calls', 'warn', 'shutdown frame sent to the module')


def _tx_baud(a: FlightAnalysis, frame: p.Frame, t: float) -> None:
    if frame.data[0] == p.CTRL_SET:
        a.event(t, 'settings', 'warn', f'baud rate change sent (code {frame.value})')


TX_COMMANDS: Dict[int, Callable[[FlightAnalysis, p.Frame, float], None]] = {
    p.CMD_DEPLOY: _tx_deploy,
    p.CMD_TRIGGER_REQUEST: _tx_confirm,
    p.CMD_ATTITUDE_THRESHOLD: _tx_setting,
    p.CMD_FREEFALL_THRESHOLD: _tx_setting,
    p.CMD_FREEFALL_TIME: _tx_setting,
    p.CMD_LIGHT_THRESHOLD: _tx_setting,
    p.CMD_ATTITUDE_TRIGGER: _tx_auto_trigger,
    p.CMD_FREEFALL_TRIGGER: _tx_auto_trigger,
    p.CMD_ARM: _tx_arm,
    p.CMD_SHUTDOWN: _tx_shutdown,
    p.CMD_BAUD_RATE: _tx_baud,
}
"""Command code of a sent frame -> what it means for the report."""
