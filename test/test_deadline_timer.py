"""The shared deadline timer (issue 22 item 2): deadlines, wakes, bugs and stops, on real threads.

Every wait ends on a condition; the bounds are generous (BOUND_S) and only a broken timer
reaches them: a lost wake or a missed deadline sleeps FAR_S, far beyond.
"""

import threading
import time
from typing import Callable, List, Optional

from uav_serial_common.deadline_timer import DeadlineTimer

BOUND_S = 20.0
FAR_S = 600.0


class Duty:
    """A duty whose runs the test sees; ``plan(run_index)`` returns the next deadline."""

    def __init__(self, plan: Callable[[int], Optional[float]]) -> None:
        self.plan = plan
        self.cond = threading.Condition()
        self.runs: List[float] = []
        self.errors: List[BaseException] = []

    def __call__(self) -> Optional[float]:
        now = time.monotonic()
        with self.cond:
            self.runs.append(now)
            index = len(self.runs) - 1
            self.cond.notify_all()
        return self.plan(index)

    def on_error(self, exc: BaseException) -> None:
        with self.cond:
            self.errors.append(exc)
            self.cond.notify_all()

    def wait_runs(self, count: int) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: len(self.runs) >= count, BOUND_S)


def make(duty: Duty, **kwargs) -> DeadlineTimer:
    kwargs.setdefault('idle_s', FAR_S)
    return DeadlineTimer(duty, name='test-timer', on_error=duty.on_error, **kwargs)


def test_round2_2_timer_runs_the_duty_at_its_deadline_not_before() -> None:
    dues: List[float] = []

    def plan(index: int) -> Optional[float]:
        if index == 0:
            dues.append(time.monotonic() + 0.2)
            return dues[0]
        return None

    duty = Duty(plan)
    timer = make(duty)
    timer.start()
    try:
        assert duty.wait_runs(2), 'the duty did not run at its deadline'
        assert duty.runs[1] >= dues[0] - 0.001, 'the duty ran before its deadline'
    finally:
        assert timer.stop(BOUND_S)


def test_round2_2_timer_wake_recomputes_a_deadline_moved_earlier() -> None:
    early = threading.Event()

    def plan(index: int) -> Optional[float]:
        return time.monotonic() if early.is_set() else time.monotonic() + FAR_S

    duty = Duty(plan)
    timer = make(duty)
    timer.start()
    try:
        assert duty.wait_runs(1)
        early.set()
        timer.wake()
        assert duty.wait_runs(2), 'a wake did not recompute the deadline'
    finally:
        assert timer.stop(BOUND_S)


def test_round2_2_timer_keeps_a_wake_that_comes_while_the_duty_runs() -> None:
    timer: Optional[DeadlineTimer] = None

    def plan(index: int) -> Optional[float]:
        if index == 0:
            timer.wake()  # as a reader thread would, while the duty runs
        return time.monotonic() + FAR_S

    duty = Duty(plan)
    timer = make(duty)
    timer.start()
    try:
        assert duty.wait_runs(2), 'the wake during the duty was lost'
    finally:
        assert timer.stop(BOUND_S)


def test_round2_2_timer_wake_by_a_deadline_runs_the_duty_then_not_at_once() -> None:
    duty = Duty(lambda index: None)  # nothing due: the timer sleeps FAR_S
    timer = make(duty)
    timer.start()
    try:
        assert duty.wait_runs(1)
        by = time.monotonic() + 0.2
        timer.wake(by=by)  # as a reader that read half a frame would
        assert duty.wait_runs(2), 'the deadline of the wake was not kept'
        assert duty.runs[1] >= by - 0.001, 'the duty ran before the deadline of the wake'
    finally:
        assert timer.stop(BOUND_S)


def test_round2_2_timer_wake_by_a_later_deadline_changes_nothing() -> None:
    dues: List[float] = []

    def plan(index: int) -> Optional[float]:
        dues.append(time.monotonic() + 0.2)
        return dues[-1]

    duty = Duty(plan)
    timer = make(duty)
    timer.start()
    try:
        assert duty.wait_runs(1)
        timer.wake(by=time.monotonic() + FAR_S)  # due later than the timer's own deadline
        assert duty.wait_runs(2)
        assert duty.runs[1] >= dues[0] - 0.001, 'a later deadline ran the duty at once'
    finally:
        assert timer.stop(BOUND_S)


def test_round2_2_timer_keeps_a_deadline_woken_while_the_duty_runs() -> None:
    timer: Optional[DeadlineTimer] = None
    bys: List[float] = []

    def plan(index: int) -> Optional[float]:
        if index == 0:
            bys.append(time.monotonic() + 0.1)
            timer.wake(by=bys[0])  # after the duty read the state the reader changed
        return time.monotonic() + FAR_S

    duty = Duty(plan)
    timer = make(duty)
    timer.start()
    try:
        assert duty.wait_runs(2), 'the deadline woken during the duty was lost'
        assert duty.runs[1] >= bys[0] - 0.001
    finally:
        assert timer.stop(BOUND_S)


def fail_first(index: int) -> Optional[float]:
    if index == 0:
        raise ValueError('a bug in the rules')
    return None


def test_round2_2_timer_logs_a_failing_duty_and_goes_on() -> None:
    duty = Duty(fail_first)
    timer = make(duty, retry_s=0.01)
    timer.start()
    try:
        assert duty.wait_runs(2), 'the timer did not go on after a failing duty'
        assert [str(e) for e in duty.errors] == ['a bug in the rules']
        assert timer.is_alive()
    finally:
        assert timer.stop(BOUND_S)


def test_round2_2_timer_outlives_a_failing_error_callback() -> None:
    def on_error(exc: BaseException) -> None:
        raise RuntimeError('a bug in the logger')

    duty = Duty(fail_first)
    timer = DeadlineTimer(duty, name='test-timer', on_error=on_error, idle_s=FAR_S)
    timer.start()
    try:
        assert duty.wait_runs(2)
    finally:
        assert timer.stop(BOUND_S)


def test_round2_2_timer_stop_joins_and_is_idempotent() -> None:
    duty = Duty(lambda index: None)
    timer = make(duty)
    timer.stop(BOUND_S)  # before start: nothing to stop
    timer.start()
    assert duty.wait_runs(1)
    assert timer.stop(BOUND_S)
    assert not timer.is_alive()
    assert not any(t.name == 'test-timer' for t in threading.enumerate())
    assert timer.stop(BOUND_S)
    timer.wake()  # after stop: runs nothing
    assert len(duty.runs) == 1
    timer.start()  # a stopped timer starts again
    assert duty.wait_runs(2)
    assert timer.stop(BOUND_S)


def test_round2_2_timer_stop_from_inside_the_duty_does_not_deadlock() -> None:
    timer: Optional[DeadlineTimer] = None
    returned = threading.Event()

    def plan(index: int) -> Optional[float]:
        timer.stop(BOUND_S)
        returned.set()
        return time.monotonic()  # due at once: only the stop keeps it from running again

    duty = Duty(plan)
    timer = make(duty)
    timer.start()
    assert duty.wait_runs(1)
    assert returned.wait(BOUND_S), 'stop from inside the duty deadlocked'
    thread = next((t for t in threading.enumerate() if t.name == 'test-timer'), None)
    if thread is not None:
        thread.join(BOUND_S)
        assert not thread.is_alive()
    assert len(duty.runs) == 1
