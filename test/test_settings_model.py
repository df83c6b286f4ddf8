"""The settings transaction's invariants, searched against the module model (issue 22 item 3).

A hypothesis state machine drives `SettingsCore` (``dps_parachute_ros.settings_core``) through
`SettingsRig` (test/settings_model_rig.py: the virtual parachute in virtual time, a wire with
faults on any frame) with random parameter sets, ``~/set_thresholds`` and ``~/set_auto_triggers``
calls, desired settings applied at connect and after a reboot, the module armed or locked, tilted
or falling (so the rule matters), reboots and unplugs in the middle of a set. After every step,
against the module model itself:

- D16: no write reaches an armed module that then asks or fires because of it, by any path, and
  no arm the rule let through makes the module ask or fire;
- an accepted call (DONE) left the module as asked;
- a refused parameter set left the module as it was, except what its refusal names as not put
  back; a REFUSED call sent no write at all;
- a write that reached the module is never reported as not written (nor held back);
- every call is answered once;
- what the core knows of a setting is the module's value, or not known.
"""

from __future__ import annotations

from typing import Any, Dict, List

from hypothesis import strategies as st
from hypothesis.stateful import invariant, rule, RuleBasedStateMachine

from model_runs import search
from settings_model_rig import FLAGS, raw_of, SettingsRig, WIRE_FAULTS, WORLD_FAULTS
from uav_serial_common.result import Outcome

NUMERIC = {
    'attitude_threshold_deg': st.sampled_from([10, 30, 45, 59, 60, 61, 75, 90]),
    'freefall_threshold_g': st.integers(1, 9).map(lambda raw: raw / 10),
    'freefall_time_s': st.integers(1, 255).map(lambda raw: raw / 100),
    'light_threshold_v': st.integers(0, 255).map(lambda raw: raw / 10),
}
thresholds = st.fixed_dictionaries({}, optional=NUMERIC).filter(bool)
parameter_sets = st.fixed_dictionaries({}, optional={
    **NUMERIC, 'attitude_trigger': st.booleans(), 'freefall_trigger': st.booleans()}).filter(bool)
faults = st.lists(st.sampled_from(WIRE_FAULTS + ('clean',) * 6 + WORLD_FAULTS), max_size=8)
TILTS = st.sampled_from([0.0, 15.0, 30.0, 44.6, 45.0, 59.0, 60.0, 60.4, 61.0, 75.0, 89.0])
ACCELS = st.sampled_from([1.0, 0.9, 0.6, 0.5, 0.46, 0.45, 0.44, 0.3, 0.15, 0.1, 0.0])


class SettingsMachine(RuleBasedStateMachine):
    """Random calls, world changes and wire faults; the invariants after each step."""

    def __init__(self) -> None:
        super().__init__()
        self.rig = SettingsRig()

    # -- calls -------------------------------------------------------------------------------

    @rule(changes=parameter_sets, wire=faults)
    def parameter_set(self, changes: Dict[str, Any], wire: List[str]) -> None:
        call = self.rig.write(tuple(changes.items()), 'parameters', wire, all_or_nothing=True)
        self._check(call)

    @rule(values=thresholds, wire=faults)
    def set_thresholds(self, values: Dict[str, float], wire: List[str]) -> None:
        self._check(self.rig.write(tuple(values.items()), '~/set_thresholds', wire))

    @rule(attitude=st.booleans(), freefall=st.booleans(), wire=faults)
    def set_auto_triggers(self, attitude: bool, freefall: bool, wire: List[str]) -> None:
        steps = (('attitude_trigger', attitude), ('freefall_trigger', freefall))
        self._check(self.rig.write(steps, '~/set_auto_triggers', wire))

    @rule(desired=parameter_sets, reboot=st.booleans(), wire=faults)
    def desired_at_connect(self, desired: Dict[str, Any], reboot: bool, wire: List[str]) -> None:
        rig = self.rig
        if reboot:
            rig.power_cycle()
        rig.reconnect()  # the initialization reads every setting afresh
        differing = tuple((n, v) for n, v in desired.items() if rig.known[n] != raw_of(n, v))
        if differing:
            self._check(rig.write(differing, 'desired settings', wire, hold=True))

    # -- the world ---------------------------------------------------------------------------

    @rule(tilt=TILTS, accel=ACCELS)
    def move(self, tilt: float, accel: float) -> None:
        self.rig.model.set_tilt(tilt)
        self.rig.model.set_accel(accel)

    @rule(armed=st.booleans())
    def arm_or_lock(self, armed: bool) -> None:
        """Another path arms or locks the module (a PWM input, a ground station)."""
        self.rig.world('arm_by_other' if armed else 'lock_by_other')

    @rule(wire=faults)
    def arm_through_the_rule(self, wire: List[str]) -> None:
        """``~/arm true``: a step of the same rule (P21: arming beyond a threshold fires)."""
        call = self.rig.arm(wire)
        assert len(call.answers) == 1, call.answers

    @rule(seconds=st.sampled_from([0.1, 1.0, 3.0]))
    def wait(self, seconds: float) -> None:
        self.rig.wait(seconds)

    @rule()
    def reboot(self) -> None:
        self.rig.power_cycle()

    @rule()
    def unplug(self) -> None:
        self.rig.plugged = False

    @rule()
    def replug(self) -> None:
        if not self.rig.plugged:
            self.rig.reconnect()

    # -- the invariants ----------------------------------------------------------------------

    @invariant()
    def no_write_fired_the_module(self) -> None:
        assert not self.rig.violations, self.rig.violations

    @invariant()
    def known_settings_are_the_modules(self) -> None:
        truth = self.rig.truth()
        wrong = {n: (v, truth[n]) for n, v in self.rig.known.items()
                 if v is not None and v != truth[n]}
        assert not wrong, f'known (core, module): {wrong}'

    def _check(self, call: Any) -> None:
        assert len(call.answers) == 1, f'answered {len(call.answers)} times: {call.answers}'
        result = call.answers[0].result
        event = call.event
        after = self.rig.truth()
        changed = {n for n in after if after[n] != call.before[n]}
        written = result.value
        if result.outcome is Outcome.DONE:
            for name, value in event.steps:
                assert after[name] == raw_of(name, value), (name, result, after)
        if result.outcome is Outcome.REFUSED:
            assert not call.reached, (call.reached, result)
            assert not changed, (changed, result)
        if event.all_or_nothing and not result.ok:
            said = result.message.split('could NOT put back', 1)
            not_back = said[1] if len(said) > 1 else ''
            for name in changed:
                assert name in not_back, (name, call.before, after, result.message)
        for name in call.reached:
            value = dict(event.steps)[name]
            show = (f'{FLAGS[name]} trigger {"enable" if value else "disable"}'
                    if name in FLAGS else f'{name} = {value:g}')
            assert f'{show} not written' not in result.message, (name, result.message)
            if written is not None:
                assert name not in written.held, (name, result)


def test_round2_22_12_settings_invariants_hold_over_random_sequences() -> None:
    """Issue 22 item 3: the settings transaction's invariants, searched (bench: 20,000)."""
    search(SettingsMachine, 'parachute_settings_core', steps=50)


# -- what the search found, kept -----------------------------------------------------------------

def test_round2_22_12_a_rounded_acceleration_never_lets_a_threshold_write_fire():
    """The status gives |a| rounded to 0.1 g: 0.46 g reads 0.5 g, below a 0.5 g threshold.

    The search found it: the rule judged 'acceleration 0.5 g < 0.5 g' false and let the write
    of a 0.5 g free-fall threshold reach the armed module at 0.46 g, which then fired.
    """
    rig = SettingsRig()
    rig.write((('freefall_threshold_g', 0.1),), 'parameters', [], all_or_nothing=True)
    rig.world('arm_by_other')
    rig.model.set_accel(0.46)
    call = rig.write((('freefall_threshold_g', 0.5),), 'parameters', [], all_or_nothing=True)
    assert not rig.violations, rig.violations
    (answer,) = call.answers
    assert answer.result.outcome is Outcome.REFUSED and answer.result.cause == 'would_deploy'
    assert rig.model.freefall_threshold_raw == 1 and not call.reached


def test_round2_22_12_a_lost_acknowledgement_makes_the_setting_unknown_to_the_rule():
    """The core side of the pty test of the same name: judged on the threshold read again."""
    rig = SettingsRig()
    rig.write((('attitude_trigger', False),), '~/set_auto_triggers', [])
    rig.model.set_tilt(30)
    rig.world('arm_by_other')
    call = rig.write((('attitude_threshold_deg', 10),), '~/set_thresholds',
                     ['clean', 'drop_reply'])
    (answer,) = call.answers
    assert answer.result.outcome is Outcome.UNKNOWN and rig.model.attitude_threshold_deg == 10
    assert rig.known['attitude_threshold_deg'] is None
    call = rig.write((('attitude_trigger', True),), '~/set_auto_triggers', [])
    (answer,) = call.answers
    assert answer.result.cause == 'would_deploy' and not call.reached, answer
    assert not rig.violations and not rig.model.attitude_trigger_enabled


def test_round2_22_12_a_late_status_is_never_taken_for_the_one_that_judges_a_write():
    """The search found it (bench size): the rule judged a put-back on a late status.

    A parameter set's status query timed out; its reply came late, after the put-back of the
    attitude trigger had asked for the status again, and the module had been armed (another
    path) in between: the late 'locked' status was taken for the fresh one and the enable of
    the attitude trigger reached the armed module at 75° of tilt over a 10° threshold.
    """
    rig = SettingsRig()
    rig.write((('attitude_threshold_deg', 10),), 'parameters', ['tilt'], all_or_nothing=True)
    call = rig.write((('attitude_threshold_deg', 10), ('attitude_trigger', False),
                      ('freefall_trigger', False)), 'parameters',
                     ['clean', 'clean', 'delay', 'arm_by_other'], all_or_nothing=True)
    assert not rig.violations, rig.violations
    (answer,) = call.answers
    assert not answer.result.ok and 'could NOT put back attitude_trigger' in \
        answer.result.message, answer.result
    assert rig.model.armed and not rig.model.attitude_trigger_enabled


def test_round2_22_12_the_status_that_judges_a_write_is_the_last_frame_before_it():
    """A parameter set reads a value it does not know (to put it back) before the judgement.

    Found reading the core's first version beside the search (the session before the core
    judged each write again, just before it): the value was read after the status, so a module
    armed (another path) in between was judged locked, and a 20° threshold reached it at 30° of
    tilt. The status is read last now, as it is for a put-back.
    """
    rig = SettingsRig()
    rig.model.set_tilt(30)
    call = rig.write((('attitude_threshold_deg', 80),), '~/set_thresholds',
                     ['clean', 'drop_reply'])
    assert call.answers[0].result.outcome is Outcome.UNKNOWN
    assert rig.known['attitude_threshold_deg'] is None and rig.model.attitude_threshold_deg == 80
    call = rig.write((('attitude_threshold_deg', 20),), 'parameters',
                     ['clean', 'arm_by_other'], all_or_nothing=True)
    assert not rig.violations, rig.violations
    (answer,) = call.answers
    assert answer.result.cause == 'would_deploy' and not call.reached, answer.result
    assert rig.model.armed and rig.model.attitude_threshold_deg == 80


def test_round2_22_12_a_reply_sent_for_again_is_the_one_that_judges():
    """The search found it (bench size) in the first fix of the late status (above).

    That fix sent the status query again for each reply it did not take and took the next
    reply: the reply to the query before the last, from before the module was tilted to 75°,
    judged the put-back of the attitude trigger, which reached the armed module over a 10°
    threshold. A reply not taken now waits for the reply to the same frame; only when none is
    coming (`Drained`) does the frame go again.
    """
    rig = SettingsRig()
    rig.arm([])
    assert rig.model.armed
    call = rig.write((('attitude_threshold_deg', 10), ('attitude_trigger', False)), 'parameters',
                     ['clean', 'clean', 'delay', 'clean', 'clean', 'tilt'], all_or_nothing=True)
    assert not rig.violations, rig.violations
    (answer,) = call.answers
    assert not answer.result.ok and 'put back attitude_trigger' in answer.result.message, \
        answer.result
    assert rig.model.attitude_trigger_enabled and rig.model.attitude_threshold_deg == 60
