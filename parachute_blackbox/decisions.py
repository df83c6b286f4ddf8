"""What the driver's ``decision`` records mean: deploys, trigger requests, policy, preflight."""

from __future__ import annotations

import math
from typing import Any, Callable, Dict, Optional, Tuple, TYPE_CHECKING

from parachute_blackbox.containers import Deployment, TriggerRequestSeen
from parachute_blackbox.frames import oldest_undecided
from parachute_blackbox.names import describe_fields, short


if TYPE_CHECKING:
    from parachute_blackbox.analysis import FlightAnalysis


# ---------------------------------------------------------------------------------------------
# Decisions: ``what`` -> handler(analysis, record, t)
# ---------------------------------------------------------------------------------------------

def finite(value: Any) -> Optional[float]:
    """Return a finite number as a float, anything else as None."""
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        return float(value)
    return None


def _call_deployment(a: FlightAnalysis, t: float) -> Deployment:
    """Return the running ~/deploy call's deployment, opened at its first decision to send."""
    call = a._call
    if call is not None and call.get('dep') is not None:
        return call['dep']
    if call is None:
        # No record of the call (the file begins during it): the call deployment going on.
        dep = a.current_deployment(t)
        if dep is not None and dep.origin == 'call':
            return dep
    t_call = call['t'] if call else t
    who = 'a ~/deploy service call'
    if call and call.get('arm_if_locked'):
        who += ' (arm_if_locked: arm first if locked)'
    dep = a.open_deployment(t_call, 'call', 'a ~/deploy service call (a person or the flight '
                            'software asked for it)', who)
    dep.outcome = 'requested'
    if call is not None:
        call['dep'] = dep
        dep.step(t_call, 'call', '~/deploy called with the confirmation token')
        if call.get('armed_at') is not None:
            dep.step(call['armed_at'], 'arm', 'armed first (arm_if_locked), verified by query')
    return dep


def _decision_send(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    dep = _call_deployment(a, t)
    attempt = record.get('attempt')
    dep.attempts = max(dep.attempts, attempt if isinstance(attempt, int) else 1)
    dep.step(t, 'decision', f'the driver decided to send the deploy frame (attempt '
             f'{attempt if attempt is not None else "?"}, on disk before the frame)')


def _decision_acked(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    dep = _call_deployment(a, t)
    dep.latency_ms = finite(record.get('latency_ms'))
    dep.latency_what = 'from the ~/deploy call to the acknowledgement'
    if isinstance(record.get('attempts'), int):
        dep.attempts = record['attempts']
    dep.outcome, dep.outcome_text = 'deployed', 'acknowledged by the module'
    dep.step(t, 'decided', 'the driver recorded the acknowledgement'
             + (f' ({dep.latency_ms:.1f} ms after the call, by the driver\'s clock)'
                if dep.latency_ms is not None else ''))
    a.counts['deploy calls acknowledged'] += 1


def _decision_module_refused(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    dep = _call_deployment(a, t)
    dep.outcome, dep.outcome_text = 'refused', 'refused by the module (D4 00)'


DEPLOY_OUTCOMES: Dict[str, Tuple[str, str]] = {
    'deployed': ('deployed', 'bad'),
    'not deployed': ('not deployed', 'warn'),
    'unknown': ('unknown', 'unknown'),
    'refused': ('refused', 'warn'),
    'already deployed': ('already deployed', 'info'),
    'failed': ('failed', 'bad'),
    'acknowledged': ('deployed', 'bad'),
    'success': ('deployed', 'bad'),
}
"""A deploy call's ``outcome`` (D10) -> (the deployment's outcome, how its event is drawn)."""
_REASON_PREFIXES = ('deploy refused: ', 'deployed: ', 'already deployed: ',
                    'deploy outcome UNKNOWN: ')
"""Words the driver's reasons begin with that only repeat the outcome."""


def _reason(record: Dict[str, Any]) -> str:
    text = str(record.get('reason') or record.get('message') or '')
    for prefix in _REASON_PREFIXES:
        if text.startswith(prefix):
            return text[len(prefix):]
    return text


def _decision_deploy(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    """Read ``what: deploy``: how a ~/deploy call ended (D10), or an unknown one later (D12)."""
    if 'resolved' in record:
        _deploy_resolved(a, record, t)
        return
    call, a._call = a._call, None
    dep = call.get('dep') if call else None
    if call is None:
        current = a.current_deployment(t)
        if current is not None and current.origin == 'call' and not current.first('outcome'):
            dep = current
    reason = _reason(record)
    outcome = record.get('outcome')
    known, level = DEPLOY_OUTCOMES.get(str(outcome), (str(outcome), 'unknown'))
    if dep is None and known in ('refused', 'already deployed', 'failed'):
        # Nothing went out: a call answered, not a deployment.
        if known == 'already deployed':
            a.counts['deploy calls answered already deployed'] += 1
            a.event(t, 'calls', 'info', f'~/deploy: already deployed ({short(reason, 120)})')
        else:
            a.counts['deploy calls refused'] += 1
            a.event(t, 'calls', 'warn', f'~/deploy refused: {short(reason, 140)}')
        return
    if dep is None:
        dep = _call_deployment(a, t)
    # The call is over: a deploy frame still waiting was not acknowledged (cut short when the
    # call ended on a dropped link or a stop, whose outcome is unknown).
    a._expire(t, reason='when the deploy call ended' if known == 'unknown' else '',
              expect='DeployAck')
    if dep.outcome == 'refused' and known == 'not deployed':
        text = f'the module refused the deploy frame; {reason}'
    else:
        text = reason or f'outcome {known}'
    dep.outcome, dep.outcome_text = known, text
    if record.get('ack') == 'lost':
        a.counts['deploy acknowledgements lost'] += 1
    dep.step(t, 'outcome', f'the call ended: {known}')
    if known == 'unknown':
        a.counts['deploys with unknown outcome'] += 1
        a._unknown_dep = dep
        a.band('triggered', t, None)  # not known until the module is heard again
    a.event(t, 'deploy', level, f'deploy call ended: {known}: {short(reason, 120)}')


def _deploy_resolved(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    """Read what became of a deploy whose outcome was unknown, as the driver learned it (D12)."""
    known, level = DEPLOY_OUTCOMES.get(str(record.get('outcome')),
                                       (str(record.get('outcome')), 'unknown'))
    how = short(record.get('resolved', ''), 80)
    dep, a._unknown_dep = a._unknown_dep, None
    a.counts['unknown deploy outcomes resolved'] += 1
    if dep is not None:
        ended = dep.first('outcome')
        later = f', {t - ended.t:.2f} s after the call ended' if ended is not None else ''
        dep.outcome_text = (f'unknown when the call ended ({dep.outcome_text}); then read: '
                            f'{known} ({how}{later})')
        dep.outcome = known
        dep.step(t, 'resolved', f'the driver read the outcome: {known} ({how})')
    a.event(t, 'deploy', level, f'the earlier deploy of unknown outcome: {known} ({how})')


def _decision_trigger_request(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    decision = str(record.get('decision', '?'))
    req = oldest_undecided(a, t)
    if req is None:
        # A decision with no request frame before it (its record was lost, D18).
        req = TriggerRequestSeen(t)
        a.requests.append(req)
        a.counts['trigger requests'] += 1
    req.decision, req.policy = decision, str(record.get('policy', ''))
    req.reason = str(record.get('reason', ''))
    req.latency_ms = finite(record.get('latency_ms'))
    req.t_decision = t
    a.counts[f'trigger requests {decision}'] += 1
    latency = f', {req.latency_ms:.2f} ms' if req.latency_ms is not None else ''
    level = 'bad' if decision == 'confirmed' else 'warn'
    by = f' by policy {req.policy}' if req.policy else ''
    a.event(t, 'request', level, f'trigger request {decision.upper()}{by}{latency}: '
            f'{short(req.reason, 100)}')
    if decision == 'confirmed':
        if req.reason.startswith('policy changed'):
            who = (f'the change of trigger_request_policy to {req.policy!r} while the request '
                   'was held (D8)')
        elif req.reason.startswith('answered'):
            who = ('a person or program answering ~/answer_trigger_request (policy '
                   f'{req.policy})')
        else:
            who = f'policy {req.policy!r} (the driver, at once)'
        dep = a.open_deployment(req.t, 'request', 'the module asked to deploy (trigger request '
                                '0x39: its crash detection fired on external power)', who)
        dep.outcome = 'requested'
        dep.latency_ms = req.latency_ms
        dep.latency_what = 'from the trigger request to the confirmation written'
        dep.step(req.t, 'request', 'trigger request received from the module')
        if req.deferred:
            dep.step(req.t, 'defer', 'deferred to ~/answer_trigger_request')
        dep.step(t, 'decision', f'confirmed ({req.reason})')
        if req.t_confirm is not None:
            dep.step(req.t_confirm, 'frame', 'confirmation frame on the wire')
        req.deployment = dep


def _decision_deferred(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    req = a._undecided[-1] if a._undecided else None  # the request just received
    if req is not None and not req.decision:
        req.deferred = True
    a.event(t, 'request', 'info', 'trigger request deferred: waiting up to '
            f'{record.get("deadline_s", "?")} s for ~/answer_trigger_request')


def _decision_policy(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    policy = str(record.get('policy', '?'))
    if len(a.policy_changes) < 100:
        a.policy_changes.append((t, policy))
    a.event(t, 'settings', 'warn', f'trigger_request_policy changed to {policy}')


def _decision_settings_refused(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    a.counts['settings changes refused (would deploy)'] += 1
    a.event(t, 'settings', 'warn', 'settings change refused, nothing written (D16): '
            f'{short(record.get("reason", ""), 140)}')


def _decision_withheld(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    # Every write the rule stopped (a refused service call also has its 'settings refused').
    a.event(t, 'settings', 'warn', f'{record.get("origin", "?")}: not written, it would deploy '
            f'the armed module at once (D16): {short(record.get("reason", ""), 140)}')


def _decision_preflight(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    ok = record.get('ok') is True
    checks = record.get('checks')
    lines = [str(c) for c in checks[:40]] if isinstance(checks, list) else []
    failed = [line[4:].strip() for line in lines if line.startswith('FAIL')]
    a.counts['preflight checks'] += 1
    if not ok:
        a.counts['preflight checks NO-GO'] += 1
    a.preflight = (t, ok, lines)
    if ok:
        text = f'~/preflight_check: GO ({len(lines)} checks OK)'
    else:
        text = '~/preflight_check: NO-GO: ' + '; '.join(failed)
    a.event(t, 'calls', 'ok' if ok else 'bad', short(text, 200))


def _decision_release_gate(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    route = record.get('route', '?')
    if record.get('called') is False:
        text = f'release gate not called for the {route}: {record.get("reason", "")}'
    elif record.get('success') is True:
        text = f'release gate for the {route}: {record.get("message", "")}'
    else:
        text = (f'release gate for the {route} gave no go ({record.get("message", "")}): '
                'released anyway')
    a.event(t, 'deploy', 'ok' if record.get('success') is True else 'warn', short(text, 200))


def decision_other(a: FlightAnalysis, record: Dict[str, Any], t: float) -> None:
    """Show a decision whose ``what`` this version does not know, and count it."""
    what = str(record.get('what'))
    a._unknown(a.unknown_whats, ('decision', what), record)
    level = 'unknown'
    if 'deploy' in what:
        a.event(t, 'deploy', level, f'deploy decision {what!r}: {describe_fields(record)}')
    else:
        a.event(t, 'other', level, f'decision {what!r}: {describe_fields(record)}')


DECISIONS: Dict[str, Callable[[FlightAnalysis, Dict[str, Any], float], None]] = {
    'deploy: sending the deploy frame': _decision_send,
    'deploy acknowledged': _decision_acked,
    'deploy refused by module': _decision_module_refused,
    'deploy': _decision_deploy,
    'trigger request': _decision_trigger_request,
    'trigger request deferred': _decision_deferred,
    'policy': _decision_policy,
    'settings refused': _decision_settings_refused,
    'settings write withheld': _decision_withheld,
    'preflight': _decision_preflight,
    'release gate': _decision_release_gate,
}
"""``decision`` records by their ``what``; any other ``what`` is shown as it is."""
