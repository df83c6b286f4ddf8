"""The events a `DeployCore` takes and the actions it returns (``deploy_core``), and two texts."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional, Tuple, Type, Union

MAX_FAILED_DEPLOYS = 2
"""P11: three unsuccessful attempts in a row put the module into protection; we stop at two."""
REQUEST_TIMEOUT_S = 1.0
"""P12: a request unanswered this long makes the module offline."""


# -- events ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class DeployCall:
    """`~/deploy` asked: `token` must be DEPLOY; `gate`: a release gate is to be passed."""

    now: float
    token: str
    arm_if_locked: bool = False
    gate: bool = False


@dataclass(frozen=True)
class Reply:
    """A decoded frame from the module: the reply waited for, or one nobody asked for."""

    now: float
    message: Any


@dataclass(frozen=True)
class Timeout:
    """The reply the last `Send` expects did not come by its deadline (all its tries)."""

    now: float
    reason: str = ''


@dataclass(frozen=True)
class LinkDown:
    """The port closed (unplugged, a write failed). `frame_left`: the frame waited on left."""

    now: float
    reason: str = 'port closed'
    frame_left: bool = True
    shutting_down: bool = False


@dataclass(frozen=True)
class LinkUp:
    """The port (re)opened: nothing is known of the module until it answers."""

    now: float


@dataclass(frozen=True)
class Busy:
    """The link could not send the last `Send` now (another request of its kind): not sent."""

    now: float
    reason: str


@dataclass(frozen=True)
class Rebooted:
    """A reboot seen elsewhere (a boot count read by another path, None: a heartbeat)."""

    now: float
    boot_count: Optional[int] = None


@dataclass(frozen=True)
class GateDone:
    """The release gate asked for by `PassGate` was passed."""

    now: float


Event = Union[DeployCall, Reply, Timeout, LinkDown, LinkUp, Busy, Rebooted, GateDone]


# -- actions -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Send:
    """Send `frame` (with `retries`), then feed back its reply (one of `expect`) or Timeout."""

    frame: bytes
    expect: Tuple[Type, ...]
    deadline: float
    retries: int = 0
    silence_ok: bool = False


@dataclass(frozen=True)
class Record:
    """A black-box record; `sync`: on disk before the next action is carried out."""

    kind: str
    fields: Tuple[Tuple[str, Any], ...]
    sync: bool = False


@dataclass(frozen=True)
class SaveAttempts:
    """Keep this power-up's unsuccessful deploy frames for a restart (P11)."""

    boot_count: Optional[int]
    failed: int
    unacked: int
    since_read: int = 0
    """Of them, sent since the boot count was last read (they may have gone to a later boot)."""


@dataclass(frozen=True)
class PassGate:
    """Pass the release gate (feed `GateDone` back); every refusal was decided before it."""

    what: str = 'deploy'


@dataclass(frozen=True)
class Answer:
    """The one answer to the call.

    `outcome`: refused, deployed, already deployed, not deployed or unknown.
    """

    outcome: str
    ok: bool
    message: str
    latency_ms: Optional[float] = None
    counts: Optional[Tuple[int, int]] = None
    """(failed, unacked) when the answer set them (a deployment seen without its ack)."""


@dataclass(frozen=True)
class Log:
    """A log line."""

    level: str
    text: str


@dataclass(frozen=True)
class Report:
    """A deployment to publish on ``~/trigger_event`` (once per power-up, D7)."""

    via: str
    boot_count: Optional[int]


@dataclass(frozen=True)
class Stored:
    """The attempts an earlier run kept (``attempts.Attempts`` fits)."""

    boot_count: int
    failed: int
    unacked: int
    since_read: int = 0


Action = Union[Send, Record, SaveAttempts, PassGate, Answer, Log, Report]


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
