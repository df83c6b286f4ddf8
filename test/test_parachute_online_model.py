"""The parachute's online judgement (D2), searched by a hypothesis state machine in virtual time.

Issue 22 items 1 and 3. ``dps_parachute_ros.online_rule.OnlineRule`` (no I/O, thread, lock or
clock) is told what the session tells it (requests counted by D2 leaving and ending, the port
opening) and judged when the session judges: after every frame, every request, every port
change, and at each deadline it names (the monitor's wake-ups). The test keeps the truth of the
line itself (every frame, request and port change with its time) and checks after every step:

- never online while the port is closed, nor before a valid frame came since it opened;
- offline once a request sent after the last frame has been unanswered for the timeout (in
  flight or given up), and once a streaming module has sent nothing for the timeout;
- online again with the first frame after going offline, and never offline without one of
  those silences (a module that answers is online);
- the next deadline it names is no later than the first moment a silence would make the module
  offline (the monitor sleeps until it), including after the timeout changes at run time.

``UAV_MODEL_EXAMPLES`` sets the number of sequences (default 200, of 40 steps); the run prints
``model_sequences_parachute_online=N model_violations=0``.
"""

from __future__ import annotations

from typing import Dict, List, Optional, Tuple

from hypothesis import strategies as st
from hypothesis.stateful import invariant, precondition, rule, RuleBasedStateMachine

from dps_parachute_ros.online_rule import NO_FRAME, OnlineRule
from model_runs import search

EPS = 1e-9


def test_issue22_found_the_rule_is_offline_at_the_deadline_it_names():
    # Campaign s12e run 8, the default search: a request judged at its own deadline (sent +
    # 1.0), where `now - sent` rounds to 0.9999999999999858: the module stayed online at the
    # time the monitor was woken for (which then wakes at once again).
    rule = OnlineRule(1.0)
    rule.port_opened(0)
    sent = 127.32256972129319
    assert (sent + 1.0) - sent < 1.0  # (such a time)
    assert rule.judge(sent - 5.0, True, 1, sent - 5.0, False).online
    rule.request_sent(1, sent, 1)
    due = rule.next_deadline(1, sent - 5.0, False)
    assert due == sent + 1.0
    assert not rule.judge(due, True, 1, sent - 5.0, False).online


class OnlineModel(RuleBasedStateMachine):
    """The D2 rule against the truth of a line the test drives."""

    def __init__(self) -> None:
        super().__init__()
        self.rule = OnlineRule(1.0)
        self.t = 100.0
        self.port_open = False
        self.frames = 0
        self.last_frame: Optional[float] = None
        self.frames_at_open = 0
        self.streaming = False
        self.seq = 0
        self.open_requests: Dict[int, Tuple[float, int]] = {}   # token -> (sent, frames then)
        self.given_up: List[Tuple[float, int]] = []             # unanswered, ended
        self.offline_at_frames: Optional[int] = None   # frame count when judged offline
        self.was_online = False
        self.last_event = ''

    # -- what the session does ------------------------------------------------------------------

    def judge(self) -> None:
        verdict = self.rule.judge(self.t, self.port_open, self.frames, self.last_frame,
                                  self.streaming, 'port closed (test)')
        if self.was_online and not verdict.online:
            self.offline_at_frames = self.frames
        self.was_online = verdict.online

    def silences(self) -> List[float]:
        """The times at which each silence of the line reaches the timeout (truth)."""
        timeout = self.rule.timeout_s
        due = [sent + timeout for sent, n in list(self.open_requests.values()) + self.given_up
               if n == self.frames]
        if self.streaming and self.last_frame is not None and self.port_open:
            due.append(self.last_frame + timeout)
        return due

    # -- steps ----------------------------------------------------------------------------------

    @rule(dt=st.floats(0.0, 3.0))
    def time_passes(self, dt: float) -> None:
        end = self.t + dt
        # The monitor wakes at each deadline the rule names (and the rule is judged then).
        for _ in range(100):
            due = self.rule.next_deadline(self.frames, self.last_frame, self.streaming)
            if due is None or due > end:
                break
            self.t = max(self.t, due)
            self.judge()
            self.a_silence_past_the_timeout_is_offline()  # checked at each wake-up too
        self.t = end
        self.judge()
        self.last_event = 'time'

    @precondition(lambda self: self.port_open)
    @rule()
    def a_frame_comes(self) -> None:
        self.frames += 1
        self.last_frame = self.t
        self.judge()
        self.last_event = 'frame'

    @precondition(lambda self: self.port_open)
    @rule()
    def a_request_leaves(self) -> None:
        self.seq += 1
        self.open_requests[self.seq] = (self.t, self.frames)
        self.rule.request_sent(self.seq, self.t, self.frames)
        self.last_event = 'request'

    @precondition(lambda self: self.open_requests)
    @rule(answered=st.booleans(), which=st.integers(0, 10))
    def a_request_ends(self, answered: bool, which: int) -> None:
        tokens = sorted(self.open_requests)
        token = tokens[which % len(tokens)]
        sent = self.open_requests.pop(token)
        if answered and self.port_open:
            self.frames += 1            # its reply, a frame like any other
            self.last_frame = self.t
        elif not answered:
            self.given_up.append(sent)
        self.rule.request_ended(token, unanswered=not answered)
        self.judge()
        self.last_event = 'answer' if answered and self.port_open else 'given up'

    @rule(on=st.booleans())
    def streaming_changes(self, on: bool) -> None:
        self.streaming = on
        self.judge()
        self.last_event = 'streaming'

    @rule(timeout=st.sampled_from([0.2, 0.5, 1.0, 2.5]))
    def the_timeout_changes(self, timeout: float) -> None:
        self.rule.timeout_s = timeout
        self.judge()
        self.last_event = 'timeout'

    @precondition(lambda self: self.port_open)
    @rule()
    def the_port_closes(self) -> None:
        self.port_open = False
        for token in list(self.open_requests):  # they fail: the link is down
            self.rule.request_ended(token, unanswered=False)
        self.open_requests.clear()
        self.judge()
        self.last_event = 'closed'

    @precondition(lambda self: not self.port_open)
    @rule()
    def the_port_opens(self) -> None:
        self.port_open = True
        self.frames_at_open = self.frames
        self.rule.port_opened(self.frames)
        self.judge()
        self.last_event = 'opened'

    # -- invariants -----------------------------------------------------------------------------

    @invariant()
    def never_online_without_a_port_and_a_frame(self) -> None:
        online = self.rule.verdict.online
        assert not (online and not self.port_open)
        assert not (online and self.frames <= self.frames_at_open)
        if self.port_open and self.frames <= self.frames_at_open:
            assert self.rule.verdict.reason == NO_FRAME

    @invariant()
    def a_silence_past_the_timeout_is_offline(self) -> None:
        if self.rule.verdict.online:
            late = [due for due in self.silences() if due <= self.t + EPS]
            assert not late, (self.t, late)

    @invariant()
    def a_module_that_answers_is_online(self) -> None:
        if self.last_event in ('frame', 'answer'):
            assert self.rule.verdict.online, self.rule.verdict
        if self.rule.verdict.online and self.offline_at_frames is not None:
            assert self.frames > self.offline_at_frames  # back only with a new frame
        if not self.rule.verdict.online and self.port_open and \
                self.frames > self.frames_at_open:
            # Offline with frames since the port opened: no frame since going offline, or a
            # silence past the timeout right now.
            assert self.frames == self.offline_at_frames or \
                any(due <= self.t + EPS for due in self.silences()), self.rule.verdict

    @invariant()
    def the_monitor_wakes_in_time(self) -> None:
        if not self.rule.verdict.online:
            return
        due = self.rule.next_deadline(self.frames, self.last_frame, self.streaming)
        truth = self.silences()
        if truth:
            assert due is not None and due <= min(truth) + EPS, (due, truth)


def test_round2_22_11_parachute_online_judgement_holds_over_random_sequences():
    search(OnlineModel, 'parachute_online', steps=50)


def test_round2_22_11_a_request_that_gave_up_still_counts_until_a_frame():
    # The finding of the pty test test_round2_22_10 (a request popped when it gave up left the
    # module "online" however long it stayed silent), kept at the level of the rule.
    machine = OnlineModel()
    machine.the_port_opens()
    machine.a_frame_comes()
    machine.a_request_leaves()
    machine.time_passes(0.5)
    machine.a_request_ends(answered=False, which=0)
    assert machine.rule.verdict.online
    machine.time_passes(0.6)
    assert not machine.rule.verdict.online
    machine.a_frame_comes()
    assert machine.rule.verdict.online
    machine.teardown()
