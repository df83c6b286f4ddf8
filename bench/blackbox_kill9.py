"""SIGKILL of ``parachute_node`` right after a deploy acknowledgement; the record must be on disk.

Each round starts the driver (black box in a fresh directory) against the virtual module, arms
the module, calls ``~/deploy`` and sends SIGKILL to the driver as soon as the service response
arrives (the user has been told "deployed"). Then the driver's black-box file (its name holds the
PID) must contain the decision it answered: ``deploy acknowledged``, or, when the module's
acknowledgement came too late and the driver found the module triggered instead, the ``deploy``
decision with ``success`` (both are synced before the answer). A round counts as ``ok`` only
then.

``wire_rounds`` more rounds kill the driver the moment the module's acknowledgement leaves the
module's port, before the driver can have handled it; those report whether the deploy
*request* was on disk (information: the contract syncs on safety events, and this shows how
early).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
from pathlib import Path
from typing import Dict, List

from bench.common import ParachuteRig, RosClient, wait_for, workdir


def _records(directory: Path, pid: int) -> List[dict]:
    out: List[dict] = []
    for path in directory.glob(f'*-{pid}*.jsonl'):
        for line in path.read_text(errors='replace').splitlines():
            try:
                out.append(json.loads(line))
            except ValueError:
                pass  # a torn last line after SIGKILL
    return out


def _has_deployed(records: List[dict]) -> bool:
    """Whether the decision behind a "deployed" answer is on disk."""
    return any(r.get('kind') == 'decision' and (
        r.get('what') == 'deploy acknowledged'
        or (r.get('what') == 'deploy' and r.get('success') is True)) for r in records)


def _has_request(records: List[dict]) -> bool:
    return any(r.get('kind') == 'request' and r.get('what') == 'deploy' for r in records)


def _arm(rig: ParachuteRig) -> None:
    with rig.runner.locked():
        rig.sim.triggered = False
        rig.sim.protection = False
        rig.sim.armed = True


def run(rounds: int = 20, wire_rounds: int = 5) -> Dict:
    """Run the kill rounds; return the figures."""
    from uav_serial_drivers.msg import ParachuteStatus
    from uav_serial_drivers.srv import Deploy
    ok = 0
    wire_request_on_disk = 0
    errors: List[str] = []
    kill = {'pid': None}

    def tap(direction: str, data: bytes, t: float) -> None:
        pid = kill['pid']
        if pid is not None and direction == 'tx' and data[:3] == b'\x41\x75\x11':
            kill['pid'] = None
            os.kill(pid, signal.SIGKILL)

    with workdir() as directory, ParachuteRig(directory) as rig:
        rig.runner.add_tap(tap)
        rig.node.stop()
        for i in range(rounds + wire_rounds):
            wire = i >= rounds
            node = rig.start_node()
            # A fresh participant per round: the killed driver's service lingers in the old
            # one's graph and would let a request go out before the new server is matched.
            client = RosClient(f'bench_kill9_{i}')
            armed = threading.Event()
            client.subscribe(ParachuteStatus, '/parachute/status',
                             lambda m, e=armed: e.set() if m.armed and not m.triggered else None)
            try:
                rig.wait_ready()
                _arm(rig)
                service = client.client(Deploy, '/parachute/deploy')
                # The driver sees the module armed (its status frames) before the deploy: a
                # fixed 0.5 s was not always enough for six test workers on two cores.
                wait_for(armed.is_set, 10.0, what='the driver seeing the module armed')
                kill['pid'] = node.pid if wire else None
                future = service.call_async(Deploy.Request(confirm='DEPLOY'))
                if not wire:
                    wait_for(future.done, 10.0, interval=0.0005, what='deploy response')
                    os.kill(node.pid, signal.SIGKILL)
                    response = future.result()
                    if not response.success:
                        errors.append(f'round {i}: deploy failed: {response.message}')
                else:
                    wait_for(lambda: future.done() or not node.alive(), 10.0, interval=0.001,
                             what='the kill at the acknowledgement')
                    if node.alive():
                        raise RuntimeError(f'no acknowledgement to kill at: the driver answered '
                                           f'{future.result().message!r}')
                node.popen.wait(10)
                records = _records(rig.blackbox_dir, node.pid)
                if wire:
                    wire_request_on_disk += _has_request(records)
                elif _has_deployed(records):
                    ok += 1
                else:
                    errors.append(f'round {i}: no record of the "deployed" decision '
                                  f'({len(records)} records on disk)')
            except (TimeoutError, RuntimeError, subprocess.TimeoutExpired) as exc:
                errors.append(f'round {i}: {exc}'[:300])
            finally:
                kill['pid'] = None
                node.stop(signal.SIGKILL, timeout=5.0)
                client.close()
    return {'kill9_rounds': rounds, 'kill9_record_on_disk': ok,
            'kill9_wire_rounds': wire_rounds,
            'kill9_wire_request_on_disk': wire_request_on_disk, 'errors': errors}


if __name__ == '__main__':
    import sys
    print(run(int(sys.argv[1]) if len(sys.argv) > 1 else 3, 2))
