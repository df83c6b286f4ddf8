"""The events a `SettingsCore` takes and the actions it returns (``settings_core``).

A `Request`, its `Reply`, `Timeout` or `Busy`, the link down, a record, a log line and the one
`Answer` are ``uav_serial_common.core_events``'s: one vocabulary for the parachute's cores.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, Optional, Tuple, Union

from dps_parachute_ros import protocol as p
from dps_parachute_ros.deploy_events import REQUEST_TIMEOUT_S  # noqa: F401 (the core's)
from uav_serial_common.core_events import (  # noqa: F401 (the core's vocabulary)
    Answer, Busy, LinkDown, Log, Record, Reply, Request, Timeout)

FLAGS = {'attitude_trigger': 'attitude', 'freefall_trigger': 'freefall'}
"""The auto-trigger flags by parameter name, and the rule's step name of each (D5)."""
REPLIES = {'attitude_threshold_deg': p.AttitudeThreshold,
           'freefall_threshold_g': p.FreefallThreshold, 'freefall_time_s': p.FreefallTime,
           'light_threshold_v': p.LightThreshold,
           'attitude_trigger': p.AutoTriggerFlags, 'freefall_trigger': p.AutoTriggerFlags}
"""What the module answers to a write or a query of each setting."""


# -- events ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class WriteCall:
    """Write `steps` ((parameter name, value): an SI value, or a bool for a trigger flag).

    `all_or_nothing`: a parameter set (D4): within `budget_s`, and what was written is put
    back when one write fails. `hold`: the desired settings (at connect, after a reboot, held
    ones): a step the rule refuses is held back, the others are written. `changes`: the whole
    parameter set, for its black-box record.
    """

    now: float
    steps: Tuple[Tuple[str, Any], ...]
    origin: str
    all_or_nothing: bool = False
    hold: bool = False
    budget_s: Optional[float] = None
    changes: Optional[Tuple[Tuple[str, Any], ...]] = None


@dataclass(frozen=True)
class JudgeCall:
    """Judge rule `steps` (``('armed', True)``, ``('attitude', True)`` ...) by the rule (D16).

    For what is not a settings write and must pass the same check: an arm, the auto-trigger
    flag query (P14). Answered DONE (it may go), REFUSED ``would_deploy`` (why not) or FAILED
    ``no_reply`` (the module did not answer: it may not go).
    """

    now: float
    steps: Tuple[Tuple[str, Any], ...]
    origin: str


@dataclass(frozen=True)
class Drained:
    """No other reply is coming for the `Send` waited on (its runtime handed over all it had).

    A reply the core did not take (it may be an earlier request's, late) leaves it waiting; the
    runtime says so, and the core sends the frame again.
    """

    now: float


Event = Union[WriteCall, JudgeCall, Reply, Timeout, LinkDown, Busy, Drained]


# -- actions -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Learned:
    """What the module has now: a setting's raw value or a flag (None: not known any more)."""

    name: str
    value: Any


@dataclass
class Written:
    """What a write did, step by step (the value of the answer)."""

    verified: Dict[str, str] = field(default_factory=dict)
    """Parameter name -> message, for each write read back as asked."""
    failed: Dict[str, str] = field(default_factory=dict)
    """Parameter name -> why, for each write that was sent and not verified."""
    held: Dict[str, Tuple[Any, str]] = field(default_factory=dict)
    """Parameter name -> (value, why): withheld by the rule, nothing sent (``hold``)."""
    sent: Tuple[str, ...] = ()
    """The parameter names whose write frame left (in order)."""


Action = Union[Request, Record, Log, Learned, Answer]
"""The `Answer` to a `WriteCall` has a `Written` as its result's ``value``."""
