"""The vocabulary of the autopilot link's core: MAVLink numbers, reason codes, events, actions.

No I/O and nothing heavy imported (not even pymavlink): `core.LinkCore` takes these `Event`s and
returns these `Action`s; the node, the port and the virtual autopilot build and carry them out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Tuple

from uav_serial_common.core_events import Log  # noqa: F401 (an action: every core's log line)

# MAVLink numbers (common.xml), here so the core imports nothing heavy.
MAV_TYPE_GCS = 6
MAV_TYPE_PARACHUTE = 37
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_UNINIT = 0
MAV_STATE_STANDBY = 3
MAV_STATE_ACTIVE = 4
MAV_STATE_CRITICAL = 5
MAV_STATE_EMERGENCY = 6
MAV_CMD_NAV_RETURN_TO_LAUNCH = 20
MAV_CMD_DO_FLIGHTTERMINATION = 185
MAV_CMD_DO_PARACHUTE = 208
MAV_CMD_COMPONENT_ARM_DISARM = 400
PARACHUTE_DISABLE = 0
PARACHUTE_ENABLE = 1
PARACHUTE_RELEASE = 2
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_TEMPORARILY_REJECTED = 1
MAV_RESULT_DENIED = 2
MAV_RESULT_UNSUPPORTED = 3
MAV_RESULT_FAILED = 4
MAV_RESULT_IN_PROGRESS = 5
RESULT_NAMES = {0: 'ACCEPTED', 1: 'TEMPORARILY_REJECTED', 2: 'DENIED', 3: 'UNSUPPORTED',
                4: 'FAILED', 5: 'IN_PROGRESS', 6: 'CANCELLED'}
SEVERITY = {'emergency': 0, 'alert': 1, 'critical': 2, 'error': 3, 'warning': 4,
            'notice': 5, 'info': 6, 'debug': 7}
FORCE_DISARM = 21196.0
"""MAV_CMD_COMPONENT_ARM_DISARM param2: disarm even in flight (PX4 and ArduPilot)."""
STATUSTEXT_LEN = 50
STATUS_NAMES = {MAV_STATE_UNINIT: 'UNINIT', MAV_STATE_STANDBY: 'STANDBY',
                MAV_STATE_ACTIVE: 'ACTIVE', MAV_STATE_CRITICAL: 'CRITICAL',
                MAV_STATE_EMERGENCY: 'EMERGENCY'}
STOP_MODES = ('off', 'disarm', 'terminate')

# COMMAND_ACK.result_param2 of a DO_PARACHUTE: why (README, "The autopilot link").
REASON_NONE = 0
REASON_OFFLINE = 1              # the module is offline: nothing sent
REASON_LOCKED = 2               # locked, and release_arms_if_locked is false: nothing sent
REASON_ALREADY_DEPLOYED = 3     # RELEASE: the module had already deployed (ACCEPTED)
REASON_NOT_DONE = 4             # the module answered and did not do it
REASON_OUTCOME_UNKNOWN = 5      # frames left, the outcome is not known (FAILED)
REASON_NO_PARACHUTE_NODE = 6    # the parachute node's service is not available: nothing sent
REASON_NO_ANSWER = 7            # the parachute node did not answer in time (FAILED, unknown)
REASON_BUSY = 8                 # another ENABLE/DISABLE or a RELEASE is running: nothing sent
REASON_PROTECTION = 9           # unsuccessful deploys: a third could lock the module (P11)
REASON_REFUSED = 10             # another refusal of the parachute node (its message is logged)
REASON_UNSUPPORTED_ACTION = 11  # param1 is not 0, 1 or 2
REASON_MOTOR_STOP_UNCONFIRMED = 12  # RELEASE done, but the autopilot did not confirm the stop
REASON_NAMES = {0: 'none', 1: 'offline', 2: 'locked', 3: 'already deployed', 4: 'not done',
                5: 'outcome unknown', 6: 'no parachute node', 7: 'no answer', 8: 'busy',
                9: 'protection', 10: 'refused', 11: 'unsupported action',
                12: 'motor stop unconfirmed'}


@dataclass(frozen=True)
class CoreConfig:
    """What the core needs of the node's parameters."""

    system_id: int = 1
    component_id: int = 161
    release_arms_if_locked: bool = False
    stop_motors_before_release: str = 'disarm'
    motor_stop_wait_s: float = 0.3
    handset_failsafe_to_autopilot: bool = False
    autopilot_timeout_s: float = 3.0
    progress_after_s: float = 0.1
    heartbeat_period_s: float = 1.0
    deploy_answer_s: float = 15.0
    arm_answer_s: float = 8.0
    preflight_period_s: float = 10.0
    resend_period_s: float = 0.1
    recent_s: float = 3.0


# -- events ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Heartbeat:
    """A HEARTBEAT heard on the link."""

    sysid: int
    compid: int
    mav_type: int
    autopilot: int
    base_mode: int = 0


@dataclass(frozen=True)
class Command:
    """A COMMAND_LONG or COMMAND_INT heard on the link."""

    sysid: int
    compid: int
    target_system: int
    target_component: int
    command: int
    params: Tuple[float, ...]
    confirmation: int = 0
    kind: str = 'COMMAND_LONG'


@dataclass(frozen=True)
class Ack:
    """A COMMAND_ACK heard on the link."""

    sysid: int
    compid: int
    command: int
    result: int
    target_system: int = 0
    target_component: int = 0


@dataclass(frozen=True)
class BadData:
    """Bytes that were no MAVLink message (garbage, a bad CRC)."""

    what: str


@dataclass(frozen=True)
class LinkState:
    """The MAVLink port opened or failed to open / closed."""

    open: bool
    error: str = ''


@dataclass(frozen=True)
class ParachuteState:
    """One ``~/status`` of the parachute node."""

    online: bool
    armed: bool
    triggered: bool


@dataclass(frozen=True)
class Answer:
    """The answer to a `Call`; ``success`` None: no answer (unavailable or timed out)."""

    call_id: int
    success: Optional[bool]
    message: str


@dataclass(frozen=True)
class Deployed:
    """A ``~/trigger_event`` of the parachute node: a deployment and its source."""

    source: str


@dataclass(frozen=True)
class RequestDecided:
    """A ``~/trigger_request`` of the parachute node: the module asked, the policy answered."""

    decision: str
    reason: str


@dataclass(frozen=True)
class GateRequest:
    """The parachute node is about to release: stop the motors (``~/release_gate``)."""

    gate_id: int


@dataclass(frozen=True)
class Failsafe:
    """A ``~/failsafe`` of the handset link."""

    action: str
    reason: str = ''


@dataclass(frozen=True)
class Tick:
    """Time passed (the node sends one at `next_deadline()`)."""


Event = Any

# -- actions ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Send:
    """Send one MAVLink message: ``kind`` is its name, ``fields`` pymavlink's arguments."""

    kind: str
    fields: Dict[str, Any]


@dataclass(frozen=True)
class Call:
    """Call a service of the parachute node: ``deploy``, ``arm`` or ``preflight_check``."""

    call_id: int
    service: str
    args: Dict[str, Any]
    timeout_s: float


@dataclass(frozen=True)
class AnswerGate:
    """Answer a `GateRequest`: whether the autopilot confirmed the motor stop, and how."""

    gate_id: int
    stopped: bool
    message: str


Action = Any


def split_text(text: str) -> List[str]:
    """Cut a text into STATUSTEXT-sized pieces."""
    return [text[i:i + STATUSTEXT_LEN] for i in range(0, len(text), STATUSTEXT_LEN)] or ['']


def classify(service: str, action: int, success: Optional[bool],
             message: str) -> Tuple[int, int]:
    """Return (MAV_RESULT, reason code) for the parachute node's answer to a DO_PARACHUTE."""
    text = message.lower()
    if success is None:
        if 'not available' in text:
            return MAV_RESULT_DENIED, REASON_NO_PARACHUTE_NODE
        return MAV_RESULT_FAILED, REASON_NO_ANSWER
    if success:
        if action == PARACHUTE_RELEASE and 'already deployed' in text:
            return MAV_RESULT_ACCEPTED, REASON_ALREADY_DEPLOYED
        return MAV_RESULT_ACCEPTED, REASON_NONE
    if 'unknown' in text:
        return MAV_RESULT_FAILED, REASON_OUTCOME_UNKNOWN
    if 'nothing sent' in text:
        if 'offline' in text:
            return MAV_RESULT_DENIED, REASON_OFFLINE
        if 'protection' in text:
            return MAV_RESULT_DENIED, REASON_PROTECTION
        if 'locked' in text:
            return MAV_RESULT_DENIED, REASON_LOCKED
        if 'deployed' in text or 'triggered' in text:
            return MAV_RESULT_DENIED, REASON_ALREADY_DEPLOYED
        if 'another deploy or arm' in text:
            return MAV_RESULT_DENIED, REASON_BUSY
        return MAV_RESULT_DENIED, REASON_REFUSED
    return MAV_RESULT_FAILED, REASON_NOT_DONE
