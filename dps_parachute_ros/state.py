"""The parachute's data, shared by the device core and the ROS adapter. No ROS, no I/O.

- `SessionConfig`: what the driver is told (the node's parameters, same names), and its checks;
- `Snapshot`: everything known about the module at one moment, immutable;
- `Deployment`, `RequestDecision`: what the core reports; `Result` (from
  `uav_serial_common.result`): what it answers;
- `Listener`: the callbacks the core reports through;
- `SETTINGS`: the module's numeric settings as data (parameter name, codecs, SI conversion).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Callable, Dict, List, Optional, Tuple

from dps_parachute_ros import protocol as p
from uav_serial_common.records import evolve
# The drivers' one result type; the session's modules import it from here.
from uav_serial_common.result import Outcome, Result  # noqa: F401

MODULE_WINDOW_S = 1.0
"""The module deploys on a confirmation only within 1 s of its request (P10)."""

POLICIES = ('confirm', 'deny', 'defer')
TRIGGER_MODES = ('keep', 'enable', 'disable')
LAYOUTS = ('table', 'prose')


@dataclass(frozen=True)
class Setting:
    """One numeric module setting: parameter name, snapshot field, codecs, SI conversion."""

    name: str
    field: str
    to_raw: Callable[[float], int]
    encode_set: Callable[[float], bytes]
    encode_query: Callable[[], bytes]
    to_si: Callable[[int], float]
    unit: str


SETTINGS: Dict[str, Setting] = {s.name: s for s in (
    Setting('attitude_threshold_deg', 'attitude_threshold_raw', p.attitude_threshold_to_raw,
            p.encode_attitude_threshold_set, p.encode_attitude_threshold_query,
            lambda raw: raw, '°'),
    Setting('freefall_threshold_g', 'freefall_threshold_raw', p.freefall_threshold_to_raw,
            p.encode_freefall_threshold_set, p.encode_freefall_threshold_query,
            lambda raw: raw / 10, ' g'),
    Setting('freefall_time_s', 'freefall_time_raw', p.freefall_time_to_raw,
            p.encode_freefall_time_set, p.encode_freefall_time_query,
            lambda raw: raw / 100, ' s'),
    Setting('light_threshold_v', 'light_threshold_raw', p.light_threshold_to_raw,
            p.encode_light_threshold_set, p.encode_light_threshold_query,
            lambda raw: raw / 10, ' V'),
)}
FLAG_SETTINGS = {'attitude_trigger': 'attitude', 'freefall_trigger': 'freefall'}
SOURCE_NAMES = ((p.SOURCE_SERIAL, 'serial'), (p.SOURCE_ATTITUDE, 'attitude'),
                (p.SOURCE_PWM, 'pwm'), (p.SOURCE_FREEFALL, 'freefall'))


def source_name(source: int) -> str:
    """Name the trigger-source bits: 'serial', 'attitude+freefall', 'unknown' ..."""
    names = [name for bit, name in SOURCE_NAMES if source & bit]
    return '+'.join(names) if names else 'unknown'


@dataclass(frozen=True)
class SessionConfig:
    """What the driver is told: the node's parameters (same names) and a few fixed values."""

    port: str = '/dev/ttyUSB0'
    baud: int = 115200
    offline_timeout_s: float = 1.0
    heartbeat_period_s: float = 10.0
    stream_status: bool = True
    aux_poll_period_s: float = 1.0
    trigger_request_policy: str = 'confirm'
    defer_timeout_s: float = 0.8
    auto_trigger_flag_layout: str = 'table'
    blackbox_dir: str = '~/.ros/uav_serial_drivers/blackbox'
    blackbox_max_mb: float = 200.0
    attitude_threshold_deg: int = -1
    freefall_threshold_g: float = -1.0
    freefall_time_s: float = -1.0
    light_threshold_v: float = -1.0
    attitude_trigger: str = 'keep'
    freefall_trigger: str = 'keep'
    request_timeout_s: float = 1.0
    """Per attempt (P12); not a parameter (the fast tests shorten it)."""

    @classmethod
    def from_values(cls, values: Dict[str, Any]) -> 'SessionConfig':
        """Build from a name -> value dict, ignoring names that are not fields."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in values.items() if k in names})

    def desired(self, name: str) -> Any:
        """Return the desired value of a module setting (-1 / 'keep' = leave the module's)."""
        return getattr(self, name)


def value_problem(name: str, value: Any) -> str:
    """Return why `value` is not acceptable for parameter `name`, or '' when it is."""
    if name == 'defer_timeout_s' and not 0.0 < value < MODULE_WINDOW_S:
        return 'defer_timeout_s must be below 1 s: the module waits only 1 s for an answer'
    if name in SETTINGS and value != -1:
        try:
            SETTINGS[name].to_raw(value)
        except p.ProtocolError as exc:
            return f'{name}: {exc} (or -1 to leave the module as it is)'
    return ''


def config_problems(config: SessionConfig) -> List[str]:
    """Every problem of a configuration, one line each (empty: usable)."""
    problems = []
    for name, choices in (('trigger_request_policy', POLICIES),
                          ('auto_trigger_flag_layout', LAYOUTS),
                          ('attitude_trigger', TRIGGER_MODES),
                          ('freefall_trigger', TRIGGER_MODES)):
        value = getattr(config, name)
        if value not in choices:
            problems.append(f"{name} must be one of {', '.join(choices)}, got {value!r}")
    for name in ('defer_timeout_s', *SETTINGS):
        problem = value_problem(name, getattr(config, name))
        if problem:
            problems.append(problem)
    return problems


@dataclass(frozen=True)
class Snapshot:
    """Everything known about the module at one moment (None = not known)."""

    port_open: bool = False
    online: bool = False
    offline_reason: str = 'not connected yet'
    initialized: bool = False
    fresh: bool = False
    """Armed and triggered were read since the module last could have changed unseen (D15)."""
    armed: Optional[bool] = None
    triggered: Optional[bool] = None
    tilt_deg: Optional[float] = None
    accel_g: Optional[float] = None
    streaming: bool = False
    """The stream is on and its frames arrive (false while the driver polls instead)."""
    stream_problem: str = ''
    """Why the stream is wanted (`stream_status`) but not used: the driver polls the status."""
    light_v: Optional[float] = None
    charging: Optional[bool] = None
    voltage_v: Optional[float] = None
    attitude_trigger_enabled: Optional[bool] = None
    freefall_trigger_enabled: Optional[bool] = None
    attitude_threshold_raw: Optional[int] = None
    freefall_threshold_raw: Optional[int] = None
    freefall_time_raw: Optional[int] = None
    light_threshold_raw: Optional[int] = None
    boot_count: Optional[int] = None
    config_reads: int = 0
    """Incremented at every read-back of the settings (the node stamps ~/config by it)."""
    mismatch: Tuple[str, ...] = ()
    held: Tuple[str, ...] = ()
    """Desired settings not written because they would deploy the armed module at once (D16)."""
    unacked_deploys: int = 0
    """Deploy frames sent since the last deploy reply (P11)."""
    failed_deploys: int = 0
    """Deploy frames sent since the last successful one or power-up: refused or unanswered."""
    deploy_outcome_unknown: bool = False
    pending_request: bool = False
    policy: str = 'confirm'
    shutdown_expected: bool = False

    def evolve(self, **changes: Any) -> 'Snapshot':
        """Return a copy with `changes` (every status frame makes one: `records.evolve`)."""
        return evolve(self, **changes)

    def raw(self, name: str) -> Optional[int]:
        """Return the raw value of a numeric setting as last read back."""
        return getattr(self, SETTINGS[name].field)

    @property
    def settings_valid(self) -> bool:
        """Every setting and the boot count have been read back once."""
        return None not in [self.raw(n) for n in SETTINGS] and self.boot_count is not None

    @property
    def bay_open(self) -> bool:
        """The light level is above the light threshold read back (D9)."""
        threshold = self.light_threshold_raw
        return self.light_v is not None and threshold is not None and \
            self.light_v > threshold / 10


@dataclass(frozen=True)
class Deployment:
    """A deployment the driver learned of (D7): one per deployment."""

    source: int
    via: str                              # 'deploy_ack', 'status' or 'record'
    record: Optional[p.TriggerRecord] = None
    deployment_id: int = 0
    """1, 2, ... per driver run; an amendment carries the id of the event it corrects."""
    amends: bool = False
    """This corrects the source of the event with the same id (published as unknown): it is no
    new deployment."""


@dataclass(frozen=True)
class RequestDecision:
    """The driver's answer to one trigger request from the module (D8)."""

    decision: str                         # 'confirmed', 'denied' or 'timed_out'
    policy: str
    reason: str
    latency_ms: Optional[float] = None


class Listener:
    """What the session reports; override what you need. Called from the session's threads."""

    def on_status(self, snap: Snapshot) -> None:
        """Take a new status: stream frame, poll, or a change of online/armed/triggered."""

    def on_battery(self, snap: Snapshot) -> None:
        """Take new battery values (read, or online changed)."""

    def on_config(self, snap: Snapshot) -> None:
        """Take the settings read back, or a change of whether they match the desired ones."""

    def on_triggered(self, triggered: bool) -> None:
        """Take a change of the trigger state."""

    def on_deployment(self, event: Deployment) -> None:
        """Take a deployment of the module (once per deployment)."""

    def on_trigger_request(self, decision: RequestDecision) -> None:
        """Take the answer given (or not) to a trigger request of the module."""

    def on_log(self, level: str, text: str) -> None:
        """Write a line to the log: level 'debug', 'info', 'warn' or 'error'."""

    def on_diagnostics(self) -> None:
        """Take note that something the diagnostics show has changed."""
