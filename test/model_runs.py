"""How the model-based tests search: how many sequences, counted, and said on one line.

The safety invariants of each device are checked by a hypothesis state machine against its model
(issue 22). The default run (`make test`) explores ``UAV_MODEL_EXAMPLES`` sequences (200); `make
bench` asks for many more (bench/models.py) and reads the ``model_sequences_<device>=N`` line
each run prints. ``UAV_MODEL_SHRINK=0`` reports a violation as found, without the search for a
shorter sequence.
"""

from __future__ import annotations

import os
from typing import Type

from hypothesis import HealthCheck, Phase, settings
from hypothesis.stateful import invariant, RuleBasedStateMachine, run_state_machine_as_test

EXAMPLES = int(os.environ.get('UAV_MODEL_EXAMPLES', '200'))
PHASES = [phase for phase in Phase
          if os.environ.get('UAV_MODEL_SHRINK', '1') != '0' or phase != Phase.shrink]


MIN_MEAN_STEPS = 30
"""Issue 22: sequences of at least 30 steps. Hypothesis ends some sequences early (a sequence
whose data ran out, one it chose to keep short), so each machine asks for more (`steps`) and the
run checks the mean."""


def search(machine: Type[RuleBasedStateMachine], device: str, steps: int) -> int:
    """Run `machine` over ``EXAMPLES`` sequences of up to `steps` steps; return how many ran."""

    class Counted(machine):  # type: ignore[valid-type, misc]
        sequences = 0
        steps_run = 0

        @invariant()
        def count_the_step(self) -> None:
            Counted.steps_run += 1

        def teardown(self) -> None:
            Counted.sequences += 1
            super().teardown()

    Counted.__name__ = machine.__name__
    run_state_machine_as_test(Counted, settings=settings(
        max_examples=EXAMPLES, stateful_step_count=steps, deadline=None, database=None,
        report_multiple_bugs=False, suppress_health_check=list(HealthCheck), phases=PHASES,
        print_blob=True))
    print(f'model_sequences_{device}={Counted.sequences} '
          f'model_steps_{device}={Counted.steps_run} model_violations=0')
    assert Counted.sequences >= EXAMPLES
    assert Counted.steps_run >= MIN_MEAN_STEPS * Counted.sequences, \
        f'{Counted.steps_run / Counted.sequences:.1f} steps per sequence on average'
    return Counted.sequences
