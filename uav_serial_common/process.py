"""Process plumbing shared by the tests, the benchmarks and the demo (no rclpy import).

- `claim_domain_id()`: a ROS_DOMAIN_ID that no other test session or benchmark run on this machine
  holds, locked with a file until the process exits, so parallel runs never see each other.
- `die_with_parent()`: a ``preexec_fn`` that makes a child die with its parent, so a crashed run
  never leaves a driver behind to answer a later run that gets the same domain id.
- `wait_for()`: poll a predicate with a timeout; the timeout raises `WaitTimeout`, which is both
  an ``AssertionError`` (a failed test) and a ``TimeoutError`` (what the benchmarks catch).
- `executable_path()`: the installed path of one of the package's executables.
- `LaunchedProcesses`: start installed executables with parameters, wait for them to come up, stop
  them by signal (the tests' `launch` fixture).
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import random
import signal
import subprocess
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

PACKAGE = 'uav_serial_drivers'
DOMAIN_RANGE = range(20, 101)
_PR_SET_PDEATHSIG = 1
_locks: Dict[int, object] = {}


def claim_domain_id(exclude: Optional[int] = None) -> int:
    """Lock a free domain id (other than `exclude`) for the rest of this process's life."""
    for domain, _ in _locks.items():
        if domain != exclude:
            return domain
    ids = list(DOMAIN_RANGE)
    random.Random(os.getpid()).shuffle(ids)
    for domain in ids:
        if domain == exclude:
            continue
        handle = open(f'/tmp/uav_serial_drivers-ros-domain-{domain}.lock', 'w')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _locks[domain] = handle
        return domain
    raise RuntimeError(f'no free ROS_DOMAIN_ID in {DOMAIN_RANGE.start}..{DOMAIN_RANGE.stop - 1}')


def die_with_parent() -> None:
    """Ask the kernel to SIGKILL this child when its parent dies (use as ``preexec_fn``)."""
    ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)


def device_process() -> None:
    """``preexec_fn`` of a virtual device: it dies with its parent, at ``UAV_DEVICE_NICE``.

    A virtual device stands for hardware with a CPU of its own: starved by a busy host, it reads
    a driver's paced frames late and all at once, and its timing is no longer the device's. The
    test harness sets ``UAV_DEVICE_NICE`` (-10); where the priority cannot be raised (not root)
    the device runs at its parent's.
    """
    die_with_parent()
    nice = os.environ.get('UAV_DEVICE_NICE')
    if nice:
        try:
            os.setpriority(os.PRIO_PROCESS, 0, int(nice))
        except (OSError, ValueError):
            pass


class WaitTimeout(AssertionError, TimeoutError):
    """A `wait_for` that timed out: a failed assertion in a test, a TimeoutError elsewhere."""


def wait_scale() -> float:
    """Return the factor every test wait's timeout is stretched by (``UAV_WAIT_SCALE``).

    A timeout is a bound on a wait that ends as soon as its condition holds: stretching it costs
    nothing while things work, and keeps a test on a loaded machine (parallel test workers, a
    busy CI host) from failing on a condition that was merely late. The test harness sets it.
    """
    try:
        return max(1.0, float(os.environ.get('UAV_WAIT_SCALE', '1')))
    except ValueError:
        return 1.0


def wait_for(predicate: Callable[[], Any], timeout: float, interval: float = 0.01,
             what: str = 'condition') -> Any:
    """Poll `predicate` until truthy; raise `WaitTimeout` after `timeout` s (x `wait_scale()`)."""
    timeout *= wait_scale()
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise WaitTimeout(f'timed out after {timeout:.1f} s waiting for {what}')
        time.sleep(interval)


def executable_path(name: str) -> str:
    """Return the installed path of one of the package's executables."""
    from ament_index_python.packages import get_package_prefix
    path = Path(get_package_prefix(PACKAGE), 'lib', PACKAGE, name)
    if not path.exists():
        raise FileNotFoundError(f'{path} is not installed: run `make build`')
    return str(path)


class LaunchedProcess:
    """One executable started by the `launch` fixture."""

    def __init__(self, name: str, popen: subprocess.Popen, stderr_path: Path,
                 stdout_path: Path) -> None:
        self.name = name
        self.popen = popen
        self.stderr_path = stderr_path
        self.stdout_path = stdout_path

    @property
    def pid(self) -> int:
        """Return the process id."""
        return self.popen.pid

    def output(self) -> str:
        """Return what the process wrote to stdout and stderr so far."""
        text = ''
        for path in (self.stdout_path, self.stderr_path):
            try:
                text += path.read_text(errors='replace')
            except FileNotFoundError:
                pass
        return text

    def alive(self) -> bool:
        """Return whether the process still runs."""
        return self.popen.poll() is None

    def stop(self, sig: int = signal.SIGINT, timeout: float = 10.0) -> Optional[int]:
        """Send `sig`, wait `timeout` s (x `wait_scale()`), then kill; return the exit code."""
        if self.popen.poll() is None:
            try:
                os.kill(self.popen.pid, sig)
            except ProcessLookupError:
                pass
            try:
                self.popen.wait(timeout * wait_scale())
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(5)
        return self.popen.returncode


def ros_args(params_path: Path, parameters: Optional[Dict[str, Any]] = None,
             node_name: Optional[str] = None, namespace: Optional[str] = None) -> List[str]:
    """Return the ``--ros-args`` of a node: remaps, and `parameters` in a file at `params_path`.

    The file is what ``--params-file`` takes, so rcl types the values as for ``ros2 run``
    (a process, or a node in the test's process, ``test/inproc.py``).
    """
    import yaml  # only here: the drivers themselves never need it
    args = ['--ros-args']
    if node_name:
        args += ['-r', f'__node:={node_name}']
    if namespace:
        args += ['-r', f'__ns:={namespace}']
    if parameters:
        params_path.write_text(yaml.safe_dump({'/**': {'ros__parameters': parameters}}))
        args += ['--params-file', str(params_path)]
    return args


class LaunchedProcesses:
    """Starts installed executables for one test and stops them all afterwards."""

    def __init__(self, tmp_path: Path, test_name: str) -> None:
        self.tmp_path = tmp_path
        self.test_name = test_name
        self.processes: List[LaunchedProcess] = []

    def start(self, executable: str, parameters: Optional[Dict[str, Any]] = None,
              node_name: Optional[str] = None, namespace: Optional[str] = None,
              wait_service: Optional[str] = None, wait_topic: Optional[str] = None,
              ros: Optional[Any] = None, timeout: float = 20.0,
              extra_env: Optional[Dict[str, str]] = None) -> LaunchedProcess:
        """Start `executable` with `parameters`; wait for a service or topic via `ros`.

        `ros` is anything with an rclpy ``node`` (a `uav_serial_common.ros_client.RosHarness`).
        """
        index = len(self.processes)
        args = [executable_path(executable)] + ros_args(
            self.tmp_path / f'{executable}-{index}.params.yaml', parameters, node_name, namespace)
        stdout_path = self.tmp_path / f'{executable}-{index}.stdout'
        stderr_path = self.tmp_path / f'{executable}-{index}.stderr'
        env = dict(os.environ)
        env.update(extra_env or {})
        with open(stdout_path, 'wb') as out, open(stderr_path, 'wb') as err:
            device = executable.startswith('virtual_')
            popen = subprocess.Popen(args, stdout=out, stderr=err, env=env,
                                     start_new_session=True,
                                     preexec_fn=device_process if device else die_with_parent)
        proc = LaunchedProcess(executable, popen, stderr_path, stdout_path)
        self.processes.append(proc)
        try:
            if ros is not None and wait_service:
                wait_for(lambda: not proc.alive() or any(
                    n == wait_service for n, _ in ros.node.get_service_names_and_types()),
                    timeout, interval=0.05, what=f'service {wait_service} of {executable}')
            if ros is not None and wait_topic:
                wait_for(lambda: not proc.alive() or ros.node.count_publishers(wait_topic) > 0,
                         timeout, interval=0.05, what=f'topic {wait_topic} of {executable}')
        except AssertionError as exc:
            raise AssertionError(f'{exc}\n--- output of {executable} ---\n{proc.output()}') \
                from None
        if not proc.alive():
            raise AssertionError(f'{executable} exited with {proc.popen.returncode}\n'
                                 f'--- output ---\n{proc.output()}')
        return proc

    def stop_all(self) -> None:
        """Stop every process this test started (SIGINT, then SIGKILL)."""
        for proc in reversed(self.processes):
            proc.stop()
