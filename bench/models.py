"""The model-based search of the safety invariants, at bench size (issue 22).

Each device's state machine (test/test_*_model.py, test/test_originman_plan.py, and the
parachute's settings rule) runs in a pytest process of its own with ``UAV_MODEL_EXAMPLES``
sequences; the process prints ``model_sequences_<device>=N``, read here. A run that fails is a
violation: its shrunk sequence is in the output, to be kept as an ``@example`` and fixed.
"""

from __future__ import annotations

import os
from pathlib import Path
import re
import subprocess
import sys
from typing import Dict

ROOT = Path(__file__).resolve().parents[1]

MODELS = {
    'handset': 'test/test_handset_model.py::'
               'test_round2_8_handset_failsafe_invariants_hold_over_random_sequences',
    'originman': 'test/test_originman_plan.py::'
                 'test_round2_6_7_11a_board_plan_invariants_hold_over_random_sequences',
    'servo': 'test/test_servo_model.py::'
             'test_round2_22_servo_bus_safety_invariants_hold_in_every_sequence',
    'servo_floods': 'test/test_servo_model.py::'
                    'test_floods_on_a_loaded_host_keep_the_newest_target_and_the_reads_share',
    'parachute': 'test/test_parachute_model.py::'
                 'test_round2_22_3_parachute_deploy_invariants_hold_over_random_sequences',
    'parachute_session': 'test/test_parachute_model.py::'
                         'test_round2_22_3_the_sessions_deploy_core_keeps_the_invariants_too',
    'parachute_online': 'test/test_parachute_online_model.py::'
                        'test_round2_22_11_parachute_online_judgement_holds_over_random_sequences',
    'parachute_settings': 'test/test_parachute_core.py::'
                          'test_round2_1_no_write_the_rule_lets_through_fires_the_module',
    'parachute_settings_core': 'test/test_settings_model.py::'
                               'test_round2_22_12_settings_invariants_hold_over_random_sequences',
    'parachute_trigger': 'test/test_trigger_model.py::'
                         'test_round2_22_7_trigger_request_invariants_hold_over_random_sequences',
}


def run(examples: int, timeout_s: float = 3600.0) -> Dict[str, object]:
    """Search every model with `examples` sequences; return the counts and the violations."""
    out: Dict[str, object] = {}
    violations = 0
    env = dict(os.environ, UAV_MODEL_EXAMPLES=str(examples))
    for device, test in MODELS.items():
        path = ROOT / test.split('::')[0]
        if not path.exists():
            out[f'model_sequences_{device}'] = 0
            continue
        command = [sys.executable, '-m', 'pytest', '-q', '-s', '-p', 'no:cacheprovider', test]
        proc = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True,
                              timeout=timeout_s)
        found = re.search(rf'model_sequences_{device}=(\d+)', proc.stdout)
        out[f'model_sequences_{device}'] = int(found.group(1)) if found else 0
        if proc.returncode != 0:
            violations += 1
            out[f'model_failure_{device}'] = _failure(proc.stdout)
    out['model_violations'] = violations
    return out


def _failure(output: str) -> str:
    """Return what a failed run says from its assertion on, and its reproduction blob.

    (The last lines alone are the end of a long sequence, without the assertion.)
    """
    start = output.find('\nE ')
    text = output[start + 1:start + 8001] if start >= 0 else output[-4000:]
    blob = [line for line in output.splitlines() if 'reproduce_failure' in line]
    return text + ('\n' + blob[0] if blob and blob[0] not in text else '')
