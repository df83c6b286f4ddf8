"""What each record kind means: ``RULES`` by kind, ``state`` records by field."""

from __future__ import annotations

from typing import Any, Callable, Dict, Optional, Tuple, TYPE_CHECKING

from dps_parachute_ros import protocol as p
from dps_parachute_ros.deploy_knowledge import LATE_HEARTBEAT_EVENT
from parachute_blackbox.decisions import decision_other, DECISIONS, finite
from parachute_blackbox.names import (BANDS, COMMON_FIELDS, DEPLOYMENT_WINDOW_S, describe_fields,
                                      LINK_COUNTERS, record_text, REPLY_TIMEOUT_S,
                                      Rule, short, VIA_NAMES)

if TYPE_CHECKING:
    from parachute_blackbox.analysis import FlightAnalysis


# ---------------------------------------------------------------------------------------------
# State records: field -> handler(analysis, record, t)
# ---------------------------------------------------------------------------------------------

def _state_port(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    up = bool(record['port_open'])
    reason = short(record.get('reason', ''), 120)
    seen_before, a._port_seen = a._port_seen, a._port_seen or up
    a.band('port', t, up)
    if up:
        a.counts['port opened'] += 1
        a._reread_why = a._reread_why or ('the reconnect' if seen_before else
                                          'the port opened')
        if seen_before:
            a.counts['reconnects'] += 1
            a.event(t, 'link', 'ok', f'port open again (reconnect): {reason}')
        else:
            a.event(t, 'link', 'info', f'port open: {reason}')
    else:
        a.counts['port closed'] += 1
        a._expire(t, reason='before the port closed')
        a.band('online', t, False)
        a.band('streaming', t, None)
        a.event(t, 'link', 'bad', f'port closed: {reason}')


def _state_online(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    online = bool(record['online'])
    was = a.bands['online'].value
    a.band('online', t, online)
    if not online:
        a.counts['offline'] += 1
        a.event(t, 'link', 'bad', f'module OFFLINE: {short(record.get("reason", ""), 140)}')
    else:
        if was is False:
            a._reread_why = a._reread_why or 'the module came back online'
        a.event(t, 'link', 'ok', 'module online')


def _state_armed(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    armed = bool(record['armed'])
    via = record.get('via', '')
    a.band('armed', t, armed)
    if via in ('arm', 'lock'):
        call = a._call
        for_deploy = via == 'arm' and call is not None and call.get('dep') is None
        if for_deploy:
            call['armed_at'] = t  # arm_if_locked: a step of the deployment that follows
        a.event(t, 'calls', 'ok' if armed == (via == 'arm') else 'bad',
                f'{"ARMED" if armed else "locked"} (verified by query after '
                f'{"~/deploy with arm_if_locked" if for_deploy else "~/arm"})')
    elif via in ('status', 'poll', 'query'):
        a.event(t, 'deploy', 'info', f'module now {"armed" if armed else "locked"} '
                f'({"status frame" if via == "status" else via})')


def _state_triggered(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    if record['triggered']:
        a.module_triggered(t, f'driver: via {record.get("via", "?")}')
    else:
        a.band('triggered', t, False)


def _state_event(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    text = str(record['event'])
    handler = STATE_EVENTS.get(text)
    if handler is not None:
        handler(a, record, t)
    else:
        a.event(t, 'module', 'info', f'{text}' + (
            f' ({describe_fields(record, COMMON_FIELDS | {"event"})})'
            if len(record) > 4 else ''))


def _state_initialized(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    count = record.get('boot_count')
    mismatch = record.get('mismatch') or []
    a.last_mismatch = list(mismatch) if isinstance(mismatch, list) else [mismatch]
    a.counts['initializations'] += 1
    why, a._reread_why = a._reread_why, ''
    # Armed and triggered are not trusted until read again after any of these (D15).
    head = f'module read afresh after {why}' if why else 'module read afresh'
    head += f' (boot #{count}): armed, triggered and settings read'
    if mismatch:
        a.event(t, 'module', 'bad', f'{head}; settings do NOT match: '
                f'{short("; ".join(map(str, a.last_mismatch)), 140)}')
    else:
        a.event(t, 'module', 'ok', f'{head}, settings as desired')


def _state_reboot(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    a.driver_saw_reboot(t)


def _state_late_heartbeat(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    a.driver_doubted_reboot(t)


def _state_zeroed(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    ok = record.get('success') is not False
    a.event(t, 'calls', 'ok' if ok else 'bad', 'attitude sensor zeroed at the present mounting '
            '(~/zero_sensor)' if ok else '~/zero_sensor: the module did not confirm the zeroing')


def _state_shut_down(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    a.counts['module shut down by request'] += 1
    a.event(t, 'module', 'warn', 'module switched off by ~/shutdown_module')


STATE_EVENTS: Dict[str, Callable[[FlightAnalysis, Dict[str, Any], float], None]] = {
    'initialized': _state_initialized,
    'module reboot (unsolicited heartbeat)': _state_reboot,
    LATE_HEARTBEAT_EVENT: _state_late_heartbeat,
    'sensor zeroed': _state_zeroed,
    'module shut down by request': _state_shut_down,
}
"""``state`` records with an ``event``, by its text; another text is shown as it is."""

STATE_FIELDS: Tuple[Tuple[str, Callable[[FlightAnalysis, Dict[str, Any], float], None]], ...] = (
    ('port_open', _state_port),
    ('online', _state_online),
    ('armed', _state_armed),
    ('triggered', _state_triggered),
    ('event', _state_event),
)
"""``state`` records by the fields they carry (one record may carry several)."""


# ---------------------------------------------------------------------------------------------
# Kinds
# ---------------------------------------------------------------------------------------------

def _kind_start(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    params = record.get('config')
    run = {'t': t, 'port': record.get('port'), 'baud': record.get('baud'),
           'parameters': dict(params) if isinstance(params, dict) else {},
           'file': a.file}
    if len(a.runs) < 100:
        a.runs.append(run)
    a.counts['driver starts'] += 1
    a._port_seen = False
    a._link_counters = {}  # a new driver's counters start at zero
    a._bb_lost = 0
    a._reread_why = ''
    a._undecided.clear()
    timeout = run['parameters'].get('request_timeout_s')
    a.reply_timeout_s = float(timeout) if isinstance(timeout, (int, float)) and \
        not isinstance(timeout, bool) and 0.0 < timeout <= 10.0 else REPLY_TIMEOUT_S
    policy = run['parameters'].get('trigger_request_policy')
    if policy and len(a.policy_changes) < 100:
        a.policy_changes.append((t, str(policy)))
    for name in BANDS:
        a.band(name, t, None)  # nothing is known until the driver has learned it
    a.band('blackbox', t, True)
    a.event(t, 'blackbox', 'info', f'driver started on {run["port"]} at {run["baud"]} baud'
            + (f', policy {policy}' if policy else ''))


def _kind_stop(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    a._expire(t, reason='before the driver stopped')
    a.event(t, 'blackbox', 'info', 'driver stopped (black box closed)')
    for name in BANDS:
        a.band(name, t, None)  # nobody watches until the next start


def _kind_frame(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    a.frame(record, t)


_CALL_TEXT = {
    'arm': '~/arm true', 'lock': '~/arm false', 'set_thresholds': '~/set_thresholds',
    'set_auto_triggers': '~/set_auto_triggers',
}


def _kind_request(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    if 'hex' in record:
        a.request_sent(record, t)
        return
    what = str(record.get('what', '?'))
    a.counts[f'service calls: {what}'] += 1
    if what == 'deploy':
        token_ok = record.get('token_ok')
        a._call = {'t': t, 'token_ok': token_ok, 'arm_if_locked': record.get('arm_if_locked'),
                   'dep': None}
        a.counts['deploy calls'] += 1
        a.event(t, 'calls', 'warn', '~/deploy called' + (
            '' if token_ok is not False else ' with a WRONG confirmation token')
            + (' (arm_if_locked)' if record.get('arm_if_locked') else ''))
        return
    detail = describe_fields(record, COMMON_FIELDS | {'what'})
    a.event(t, 'calls', 'info', f'{_CALL_TEXT.get(what, what)} called'
            + (f' ({detail})' if detail else ''))


def _kind_decision(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    handler = DECISIONS.get(str(record.get('what')), decision_other)
    handler(a, record, t)


def _kind_state(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    handled = False
    for name, handler in STATE_FIELDS:
        if name in record:
            handler(a, record, t)
            handled = True
    if not handled:
        a.event(t, 'other', 'unknown', f'state: {describe_fields(record)}')


def _kind_parameter(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    """Read a parameter set: all or nothing, module settings written and verified first (D4)."""
    accepted = record.get('accepted')
    reason = str(record.get('reason') or '')
    changes = record.get('changes')
    what = (', '.join(f'{k} := {short(v, 30)}' for k, v in changes.items()) or 'nothing'
            if isinstance(changes, dict) else '?')
    a.counts['parameter changes' if accepted else 'parameter changes refused'] += 1
    a.event(t, 'calls', 'ok' if accepted else 'bad',
            f'parameters {short(what, 100)}: {"accepted" if accepted else "REFUSED"}'
            + (f' ({short(reason, 140)})' if reason else ''))
    if '; put back ' in reason:
        names = reason.split('; put back ', 1)[1].split(';')[0]
        a.counts['settings put back'] += len(names.split(', '))
        a.event(t, 'settings', 'warn', f'put back after the refused set: {names}')
    if 'could NOT put back' in reason:
        a.counts['settings not put back'] += 1
        a.event(t, 'settings', 'bad', 'a refused parameter set left the module changed: could '
                f'NOT put back {short(reason.split("could NOT put back", 1)[1], 120)}')


def _kind_trigger_event(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    source = str(record.get('source', 'unknown'))
    via = record.get('via')
    via_text = (VIA_NAMES.get(via, str(via)) if isinstance(via, (int, str)) else
                'unknown' if via is None else short(via, 40))
    a.counts['trigger events'] += 1
    # The driver publishes one trigger event per deployment, possibly after fetching the record
    # for a while: it belongs to the last deployment even if the module rebooted meanwhile.
    dep = a._deployment
    if dep is not None and (t - dep.last_t > DEPLOYMENT_WINDOW_S or dep.first('event')):
        dep = None
    unknown = a._unknown_dep
    if dep is None and unknown is not None and not unknown.first('event'):
        dep = unknown  # a deploy of unknown outcome did go out (D12)
    if dep is None:
        dep = a.open_deployment(t, 'event', f'the driver learned of a deployment from '
                                f'{via_text}', 'the module (no host decision seen)')
        dep.outcome, dep.outcome_text = 'deployed', 'reported by the driver\'s trigger event'
    dep.source = source if source != 'unknown' or not dep.source else dep.source
    raw = record.get('record')
    if isinstance(raw, str) and raw:
        try:
            decoded = p.decode_module_frame(p.parse_frame(bytes.fromhex(raw)))
        except (p.ProtocolError, ValueError, IndexError):
            decoded = None
        if isinstance(decoded, p.TriggerRecord):
            a.trigger_record(t, decoded)
            dep.record = dep.record or record_text(decoded)
    dep.step(t, 'event', f'trigger event published: source {source}, learned from {via_text}')
    a.event(t, 'deploy', 'bad', f'PARACHUTE DEPLOYED: source {source} (learned from '
            f'{via_text})')


def _int_field(record: Dict[str, Any], names: Tuple[str, ...]) -> Optional[int]:
    values = [record[n] for n in names if isinstance(record.get(n), int)
              and not isinstance(record.get(n), bool)]
    return max(values) if values else None


def _kind_link(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    """Read the driver's link counters (cumulative for its run), recorded when one changed."""
    deltas: Dict[str, int] = {}
    for name in LINK_COUNTERS:
        value = _int_field(record, (name,))
        if value is None:
            continue
        before = a._link_counters.get(name, 0)
        deltas[name] = value - before if value >= before else value  # a new run's counters
        a._link_counters[name] = value
    checksum, noise = deltas.get('checksum_errors', 0), deltas.get('bytes_discarded', 0)
    a.counts['checksum errors'] += checksum
    a.counts['bytes of noise discarded'] += noise
    a.counts['request timeouts (as the driver counted)'] += deltas.get('timeouts', 0)
    if checksum or noise:
        # Such frames never reach the black box: the driver's decoder counted them.
        parts = ([f'{checksum} frame(s) with a bad checksum'] if checksum else []) + \
            ([f'{noise} byte(s) of noise'] if noise else [])
        a.event(t, 'link', 'warn', ' and '.join(parts) + ' discarded (the driver\'s decoder '
                'counted them)')


def _kind_blackbox(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    """Read the black box's own health: an outage it recovered from, the records it lost."""
    if record.get('event') == 'file removed':
        # The run's earlier file went under the writer (D14): its records are not in this one.
        gone = _int_field(record, ('lost',)) or 0
        a.counts['black-box files removed under the driver'] += 1
        a.counts['black-box records lost'] += gone
        a.event(t, 'blackbox', 'bad', f'the run\'s earlier black-box file was removed while it '
                f'was written: {short(record.get("path", "?"), 120)} ({gone} records lost '
                'with it); this file goes on from here')
        return
    lost = _int_field(record, ('lost',))
    if lost is not None and lost > a._bb_lost:
        a.counts['black-box records lost'] += lost - a._bb_lost
        a._bb_lost = lost
    error = short(record.get('error') or '', 120)
    a.counts['black-box write failures'] += 1
    if record.get('event') != 'writing again':
        a.event(t, 'blackbox', 'bad', f'black-box problem: {describe_fields(record)}')
        return
    since = finite(record.get('failed_at'))
    since = max(since, a.t0) if since is not None and since <= t else None
    if since is not None:
        a.band('blackbox', since, False)
        a.event(since, 'blackbox', 'bad', f'black box stopped writing: {error}')
    a.band('blackbox', t, True)
    outage = _int_field(record, ('lost_in_outage',))
    a.event(t, 'blackbox', 'warn', 'black box writing again'
            + (f' after {t - since:.1f} s' if since is not None else '')
            + (f': {outage} records lost' if outage is not None else '')
            + (f' ({lost} in this run)' if lost is not None else ''))


RULES: Dict[str, Rule] = {rule.kind: rule for rule in (
    Rule('start', frozenset({'port', 'baud', 'config'}), _kind_start),
    Rule('stop', frozenset(), _kind_stop),
    Rule('frame', frozenset({'dir', 'hex'}), _kind_frame),
    Rule('request', frozenset({'hex', 'expect', 'what', 'token_ok', 'arm_if_locked', 'values',
                               'attitude', 'freefall'}), _kind_request),
    Rule('decision', frozenset({'what', 'decision', 'policy', 'reason', 'latency_ms',
                                'attempt', 'attempts', 'hex', 'success', 'deadline_s',
                                'outcome', 'message', 'resolved', 'ack', 'ok', 'checks'}),
         _kind_decision),
    Rule('state', frozenset({'port_open', 'reason', 'online', 'armed', 'via', 'triggered',
                             'event', 'boot_count', 'mismatch', 'success'}), _kind_state),
    Rule('parameter', frozenset({'changes', 'accepted', 'reason'}), _kind_parameter),
    Rule('trigger_event', frozenset({'source', 'via', 'record'}), _kind_trigger_event),
    Rule('link', frozenset(LINK_COUNTERS), _kind_link),
    Rule('blackbox', frozenset({'event', 'error', 'failed_at', 'lost', 'lost_in_outage',
                                'path'}),
         _kind_blackbox),
)}
"""Record kind -> rule: the kinds the driver writes (a new kind is one entry here)."""
