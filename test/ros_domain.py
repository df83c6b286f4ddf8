"""Process plumbing shared by the test harness, the benchmarks and the demo (no rclpy import).

- `claim_domain_id()`: a ROS_DOMAIN_ID that no other test session or benchmark run on this machine
  holds, locked with a file until the process exits, so parallel runs never see each other.
- `die_with_parent()`: a ``preexec_fn`` that makes a child die with its parent, so a crashed run
  never leaves a driver behind to answer a later run that gets the same domain id.
- `wait_for()`: poll a predicate with a timeout; the timeout raises `WaitTimeout`, which is both
  an ``AssertionError`` (a failed test) and a ``TimeoutError`` (what the benchmarks catch).
- `executable_path()`: the installed path of one of the package's executables.
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import random
import signal
import time
from pathlib import Path
from typing import Any, Callable, Dict, Optional

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


class WaitTimeout(AssertionError, TimeoutError):
    """A `wait_for` that timed out: a failed assertion in a test, a TimeoutError elsewhere."""


def wait_for(predicate: Callable[[], Any], timeout: float, interval: float = 0.01,
             what: str = 'condition') -> Any:
    """Poll `predicate` until truthy; raise `WaitTimeout` after `timeout` s."""
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
