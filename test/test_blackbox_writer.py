"""The black-box writer shared by several driver instances: one folder, real files, real processes.

Every parachute driver defaults to the same ``blackbox_dir``; each prunes it to
``blackbox_max_mb``. A run being written is never removed by any of them (the writer's flock),
a run that holds a deployment goes only once no routine run is left (its ``.deployed`` marker),
and a file removed from under a writer anyway is noticed and replaced (issue 21, item 5).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import subprocess
import sys
import time

import pytest

from dps_parachute_ros.blackbox import BlackBox, DEPLOYED_SUFFIX
from dps_parachute_ros.session import ParachuteSession
from dps_parachute_ros.simulation import VirtualParachute
from dps_parachute_ros.state import Listener, SessionConfig
from dps_parachute_ros.virtual_node import create_runner
from parachute_blackbox.report import analyse
from support import FakeClock
from uav_serial_common.process import wait_for

ROOT = Path(__file__).resolve().parents[1]
BOUND = 100_000
# A writer in a process of its own: records until its stdin closes, then prints its status.
WRITER = '''
import json, sys, threading, time
from dps_parachute_ros.blackbox import BlackBox
box = BlackBox(sys.argv[1], max_bytes=int(sys.argv[2]))
box.record('start', port='/dev/other', baud=115200, config={})
assert box.sync(5.0)
print(box.path, flush=True)
done = threading.Event()
threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
i = 0
while not done.is_set():
    box.record('frame', dir='rx', hex='41 75 32 07 0a 00 01 44', i=i)
    i += 1
    if i % 50 == 0:
        box.sync(5.0)
    time.sleep(0.05)
box.sync(5.0)
status = box.status()
box.close()
print(json.dumps({'path': status.path, 'file_removed': status.file_removed, 'records': i}),
      flush=True)
'''


def _old_run(directory: Path, n: int, size: int = 40_000, deployed: bool = False) -> Path:
    """A finished run of an earlier day (mtime in 2001 + n s), with its marker if deployed."""
    path = directory / f'parachute-2020010{n}T000000Z-{100 + n}.jsonl'
    path.write_bytes(b'x' * size)
    os.utime(path, (1e9 + n, 1e9 + n))
    if deployed:
        Path(str(path) + DEPLOYED_SUFFIX).touch()
    return path


def _fill(box: BlackBox, count: int) -> None:
    for i in range(count):
        box.record('frame', dir='rx', hex='41 75 32 07 0a 00 01 44', i=i)
    assert box.sync(5.0)


@pytest.fixture
def other_process(tmp_path):
    directory = tmp_path / 'bb'
    directory.mkdir()
    proc = subprocess.Popen([sys.executable, '-c', WRITER, str(directory), str(BOUND)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            cwd=str(ROOT))
    try:
        yield directory, proc
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(10)


def test_round2_5_a_run_being_written_is_never_removed_and_deployments_go_last(other_process):
    directory, proc = other_process
    path_a = Path(proc.stdout.readline().strip())  # the other process's run, being written
    assert path_a.parent == directory
    deployed = _old_run(directory, 0, deployed=True)  # the oldest: an incident's evidence
    routine = [_old_run(directory, n) for n in (1, 2, 3)]
    # Two more writers of one process on the same folder, each pruning it to BOUND.
    box_b = BlackBox(str(directory), max_bytes=BOUND)
    box_c = BlackBox(str(directory), max_bytes=BOUND)
    try:
        box_b.record('start', port='/dev/b', baud=115200, config={})
        box_c.record('start', port='/dev/c', baud=115200, config={})
        assert box_b.sync(5.0) and box_c.sync(5.0)
        # Routine runs go first, oldest first, until the folder fits: the deployment stays.
        assert deployed.exists(), 'a run that holds a deployment went before routine runs'
        assert not routine[0].exists()
        assert Path(str(deployed) + DEPLOYED_SUFFIX).exists()
        # Both in-process runs and the other process's grow past the bound: every routine run
        # and then the deployment go; no run being written does, whoever prunes.
        _fill(box_b, 3000)
        _fill(box_c, 1500)
        for box in (box_b, box_c):
            box.set_max_bytes(BOUND)  # the bound is checked again now
        wait_for(lambda: not deployed.exists(), 10, what='the deployment removed at last')
        assert not any(p.exists() for p in routine)
        assert not deployed.exists() and not Path(str(deployed) + DEPLOYED_SUFFIX).exists()
        for path in (path_a, Path(box_b.path), Path(box_c.path)):
            assert path.exists(), f'{path.name} was removed while it was being written'
        assert box_b.status().file_removed == '' and box_c.status().file_removed == ''
        # The other process still writes into its file (not into a removed one).
        size = path_a.stat().st_size
        wait_for(lambda: path_a.stat().st_size > size, 10, what='the other run still growing')
    finally:
        box_b.close()
        box_c.close()
    # Its writer closes: now it is a finished run like any other, and the next pruner may go.
    out, _ = proc.communicate('', timeout=30)
    status = json.loads(out.strip().splitlines()[-1])
    assert status['path'] == str(path_a) and status['file_removed'] == ''
    lines = path_a.read_text().splitlines()
    assert json.loads(lines[0])['kind'] == 'start'
    assert sum(1 for line in lines if '"frame"' in line) == status['records']
    last = BlackBox(str(directory), max_bytes=1)
    try:
        assert not path_a.exists() and not Path(box_b.path).exists()
    finally:
        last.close()


class _Quiet(Listener):
    pass


def _blackbox_line(session: ParachuteSession) -> str:
    (line,) = [x for x in session.preflight_check().message.splitlines() if 'black box' in x]
    return line


def test_round2_5_a_file_removed_under_the_writer_is_noticed_and_replaced(tmp_path):
    sim = VirtualParachute(now=time.monotonic() - 1.0)
    sim.step(time.monotonic())
    runner = create_runner(sim, str(tmp_path / 'vpara'), baud=0).start()
    directory = tmp_path / 'bb'
    config = SessionConfig(port=runner.path, request_timeout_s=0.3,
                           blackbox_dir=str(directory), attitude_threshold_deg=70)
    session = ParachuteSession(config, _Quiet(), FakeClock())
    session.start()
    try:
        wait_for(lambda: session.snapshot.online and session.snapshot.initialized, 10,
                 what='the session initialized')
        first = session.blackbox.status().path
        assert _blackbox_line(session) == f'OK   black box writable: {first}'
        # A deployment: the run gets its marker (pruned only once no routine run is left).
        assert session.arm(True).ok
        deploy = session.deploy('DEPLOY')
        assert deploy.ok, deploy.message
        marker = Path(first + DEPLOYED_SUFFIX)
        wait_for(marker.exists, 5, what='the deployment marker')
        # Someone removes the run's file while the driver writes it.
        os.unlink(first)
        line = _blackbox_line(session)
        assert line.startswith('FAIL') and 'was removed while it was written' in line, line
        problem = session.blackbox_problem()  # what the diagnostics show, as ERROR
        assert first in problem and 'lost' in problem
        # A new file was started: it begins as the run did and says what became of the old.
        status = session.blackbox.status()
        assert status.path != first and os.path.exists(status.path)
        assert status.path in problem
        assert session.arm(False).ok
        assert session.blackbox.sync(5.0)
        records = [json.loads(x) for x in Path(status.path).read_text().splitlines()]
        assert records[0]['kind'] == 'start' and records[0]['config']['blackbox_dir'] == \
            str(directory)
        removed = [r for r in records if r['kind'] == 'blackbox']
        assert removed[0]['event'] == 'file removed' and removed[0]['path'] == first
        assert removed[0]['lost'] > 0
        assert any(r['kind'] == 'request' and r.get('what') == 'lock' for r in records)
        # The run still holds its deployment: the new file has the marker too.
        assert Path(status.path + DEPLOYED_SUFFIX).exists()
        # The report of the new file says what became of the old one.
        analysis, _ = analyse([status.path], progress=False)
        assert not analysis.unknown_fields and not analysis.unknown_kinds
        assert analysis.counts['black-box files removed under the driver'] == 1
    finally:
        session.stop()
        runner.stop()
