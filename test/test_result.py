"""The one result type of every driver (issue 22 item 5)."""

import ast
import dataclasses
import importlib
import inspect
import pathlib
import typing

import pytest

from uav_serial_common.result import Outcome, Result


def test_issue22_5_success_is_done_or_sent_and_every_other_outcome_is_not():
    assert {o for o in Outcome if o.ok} == {Outcome.DONE, Outcome.SENT}
    for outcome in Outcome:
        assert Result(outcome, 'x').ok is outcome.ok


def test_issue22_5_constructors_give_their_outcome_cause_and_value():
    assert Result.done('read', value=(1, 2), latency_ms=3.0) == \
        Result(Outcome.DONE, 'read', value=(1, 2), latency_ms=3.0)
    refused = Result.refused('offline', 'the board is offline; nothing sent')
    assert (refused.outcome, refused.cause, refused.ok) == (Outcome.REFUSED, 'offline', False)
    assert Result.sent('queued').outcome is Outcome.SENT
    assert Result.failed('no', value=[0]).value == [0]
    assert Result.unknown('sent, no reply').outcome is Outcome.UNKNOWN
    assert Result.checked(True, 'a').outcome is Outcome.DONE
    assert Result.checked(False, 'a').outcome is Outcome.FAILED
    renamed = refused.with_message('shorter')
    assert (renamed.outcome, renamed.cause, renamed.message) == \
        (Outcome.REFUSED, 'offline', 'shorter')


def test_issue22_5_a_result_is_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        Result.done('x').outcome = Outcome.FAILED


PACKAGES = ('dps_parachute_ros', 'desheng_servo_ros', 'originman_board_ros', 'handset_link_ros',
            'parachute_mavlink_ros', 'uav_serial_common')


def test_issue22_5_no_driver_defines_a_result_type_of_its_own():
    root = pathlib.Path(__file__).resolve().parents[1]
    own = []
    for package in PACKAGES:
        for path in sorted((root / package).glob('*.py')):
            if path == root / 'uav_serial_common' / 'result.py':
                continue
            for node in ast.walk(ast.parse(path.read_text())):
                names = [node.name] if isinstance(node, ast.ClassDef) else \
                    [t.id for t in getattr(node, 'targets', []) if isinstance(t, ast.Name)]
                own += [f'{path.name}: {n}' for n in names if n.endswith('Result')]
    assert own == []


@pytest.mark.parametrize('core, at_least', [
    ('dps_parachute_ros.session:ParachuteSession', 11),
    ('desheng_servo_ros.core:ServoBusCore', 10),
    ('originman_board_ros.core:OriginManCore', 16)])
def test_issue22_5_every_call_of_a_core_answers_the_one_result(core, at_least):
    module, name = core.split(':')
    cls = getattr(importlib.import_module(module), name)
    answers = {}
    for method, function in inspect.getmembers(cls, inspect.isfunction):
        returns = str(function.__annotations__.get('return', ''))
        if not method.startswith('_') and 'Result' in returns:
            hint = typing.get_type_hints(function)['return']
            answers[method] = typing.get_origin(hint) or hint
    assert len(answers) >= at_least, sorted(answers)
    assert {method: Result for method in answers} == answers
