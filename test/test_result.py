"""The one result type of every driver (issue 22 item 5)."""

import dataclasses

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
