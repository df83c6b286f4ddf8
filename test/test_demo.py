"""`make demo` keeps working: the scripted mission runs to its end and cleans up after itself."""

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_demo_mission_succeeds_and_leaves_no_process_behind():
    result = subprocess.run([sys.executable, str(ROOT / 'tools' / 'demo.py'), '--no-tty'],
                            capture_output=True, text=True, timeout=120, env=dict(os.environ))
    assert result.returncode == 0, result.stdout + result.stderr
    last = result.stdout.strip().splitlines()[-1]
    assert last.startswith('demo: OK'), last
    for step in ['trigger event: source freefall', 'settings re-applied', 'refused:',
                 'failsafe → RETURN_TO_HOME', 'link regained → failsafe NONE',
                 'key 1: pressed → release_from_short_press → click',
                 'raw [800, 200, 650] reached', 'motors stopped by the motor timeout']:
        assert step in result.stdout, f'{step!r} missing from the demo output'
    # It ends with the black-box report of its own run.
    report = Path(re.search(r'report (\S+\.html)$', last).group(1))
    assert report.is_file() and report.with_suffix('.png').is_file()
    assert 'Deployment 1 at +' in report.read_text(encoding='utf-8')
    leftovers = subprocess.run(['pgrep', '-f', 'uav-demo-'], capture_output=True, text=True)
    assert leftovers.stdout == '', f'demo processes left behind: {leftovers.stdout}'
