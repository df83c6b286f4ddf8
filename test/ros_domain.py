"""Process plumbing shared by the test harness and the benchmarks (no rclpy import here).

- `claim_domain_id()`: a ROS_DOMAIN_ID that no other test session or benchmark run on this machine
  holds, locked with a file until the process exits, so parallel runs never see each other.
- `die_with_parent()`: a ``preexec_fn`` that makes a child die with its parent, so a crashed run
  never leaves a driver behind to answer a later run that gets the same domain id.
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import random
import signal
from typing import Dict, Optional

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
