"""The events a `DeployCore` takes and the actions it returns (``deploy_core``), and two texts.

Those shared with other cores are ``uav_serial_common.core_events``'s (a request, its reply or
why none came, the link, a reboot, a record, a log line) and ``release_gate``'s (`PassGate`,
`GateDone`); they are imported here for the deploy core's modules.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple, Union

from dps_parachute_ros.release_gate import GateDone, PassGate
from uav_serial_common.core_events import (Busy, LinkDown, LinkUp, Log, Rebooted, Record,
                                           Reply, Request, SYNC_WAIT, Timeout)
from uav_serial_common.result import Result

__all__ = ['ArmAnswer', 'ArmCall', 'ArmJudged', 'Busy', 'DeployAnswer', 'DeployCall',
           'GateDone', 'JudgeArm', 'LinkDown', 'LinkUp', 'Log', 'PassGate', 'Rebooted', 'Record',
           'Reply', 'Report', 'Request', 'SaveAttempts', 'Stored', 'SYNC_WAIT', 'Timeout',
           'guard_text', 'why', 'MAX_FAILED_DEPLOYS', 'REQUEST_TIMEOUT_S', 'Event', 'Action']

MAX_FAILED_DEPLOYS = 2
"""P11: three unsuccessful attempts in a row put the module into protection; we stop at two."""
REQUEST_TIMEOUT_S = 1.0
"""P12: a request unanswered this long makes the module offline."""


# -- events (and those of ``uav_serial_common.core_events``) ------------------------------------

@dataclass(frozen=True)
class DeployCall:
    """`~/deploy` asked: `token` must be DEPLOY; `gate`: a release gate is to be passed."""

    now: float
    token: str
    arm_if_locked: bool = False
    gate: bool = False


@dataclass(frozen=True)
class ArmCall:
    """`~/arm` asked: arm the module (`want` True) or lock it (P7)."""

    now: float
    want: bool


@dataclass(frozen=True)
class ArmJudged:
    """What `JudgeArm` found.

    `danger`: why arming now would deploy the module at once (D16, P21); `problem`: the module
    did not answer what the check needs (nothing was sent then).
    """

    now: float
    danger: str = ''
    problem: str = ''


Event = Union[DeployCall, ArmCall, Reply, Timeout, LinkDown, LinkUp, Busy, Rebooted, GateDone,
              ArmJudged]


# -- actions (and those of ``uav_serial_common.core_events``) -----------------------------------

@dataclass(frozen=True)
class SaveAttempts:
    """Keep this power-up's unsuccessful deploy frames for a restart (P11)."""

    boot_count: Optional[int]
    failed: int
    unacked: int
    since_read: int = 0
    """Of them, sent since the boot count was last read (they may have gone to a later boot)."""


@dataclass(frozen=True)
class DeployAnswer:
    """The one answer to a `DeployCall`.

    `outcome`: refused, deployed, already deployed, not deployed or unknown.
    """

    outcome: str
    ok: bool
    message: str
    latency_ms: Optional[float] = None
    counts: Optional[Tuple[int, int]] = None
    """(failed, unacked) when the answer set them (a deployment seen without its ack)."""


@dataclass(frozen=True)
class Report:
    """A deployment to publish on ``~/trigger_event`` (once per power-up, D7)."""

    via: str
    boot_count: Optional[int]


@dataclass(frozen=True)
class Stored:
    """The attempts an earlier run kept (``attempts.Attempts`` fits).

    Boot count None: that run never read it (its frames count, as sent since the last read).
    """

    boot_count: Optional[int]
    failed: int
    unacked: int
    since_read: int = 0


@dataclass(frozen=True)
class JudgeArm:
    """Ask whether arming now would deploy the module at once (D16).

    The settings core's one check; the caller answers with `ArmJudged`.
    """

    origin: str = '~/arm'


@dataclass(frozen=True)
class ArmAnswer:
    """The one answer to an `ArmCall`: DONE only when the reply and a query agree (P7)."""

    result: Result


Action = Union[Request, Record, SaveAttempts, PassGate, JudgeArm, DeployAnswer, ArmAnswer, Log,
               Report]


def guard_text(failed: int, unacked: int) -> str:
    """Refuse a deploy frame that could be the third unsuccessful one (P11): the text."""
    if unacked >= MAX_FAILED_DEPLOYS:
        what = f'{unacked} deploy frames in a row went unacknowledged'
    else:
        what = f'{failed} deploy frames in a row were refused or went unacknowledged'
    return (f'deploy refused: {what}; a third could put the module into protection (P11). '
            'Check the link; a module reboot clears this. Nothing sent')


def why(event: Event) -> str:
    """Tell what ended a wait that brought no reply."""
    if isinstance(event, Timeout):
        return event.reason or f'no reply within {REQUEST_TIMEOUT_S * 1000:.0f} ms'
    if isinstance(event, (LinkDown, Busy)):
        return event.reason
    return 'no reply'
