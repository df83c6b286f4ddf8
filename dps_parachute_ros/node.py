"""``parachute_node``: ROS 2 driver of the DPS-S drone parachute module.

Threads, and what may block where:

- the serial reader (``SerialLink``) decodes frames and handles unsolicited ones at once: the
  status stream, reboot heartbeats and trigger requests, whose confirmation is written from
  right there. It never waits for a reply (that would deadlock: only it delivers replies).
- one worker thread (re-)initializes the module, polls light, charging and voltage, sends
  heartbeats, and fetches trigger records after a deployment.
- services that talk to the module run on the executor's threads, each safety service in a
  callback group of its own, so a deploy never waits behind a slow query.
- a 20 Hz timer (no serial I/O) judges online/offline and publishes diagnostics.

Decisions where the contract and the vendor document are silent are in ``docs/protocols.md``
(DPS-S, "Driver decisions").
"""

from __future__ import annotations

import collections
import math
import threading
import time
from typing import Any, Callable, Dict, List, Optional, Tuple

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import BatteryState
from std_msgs.msg import Bool
from std_srvs.srv import SetBool, Trigger

from dps_parachute_ros import protocol as p
from dps_parachute_ros.blackbox import BlackBox
from dps_parachute_ros.link import LinkDown, LinkError, LinkTimeout, ParachuteLink
from uav_serial_common.node_main import run_node
from uav_serial_drivers.msg import (ParachuteConfig, ParachuteStatus, TriggerEvent,
                                    TriggerRecord, TriggerRequest)
from uav_serial_drivers.srv import (Confirmed, Deploy, GetParachuteConfig, GetTriggerRecords,
                                    SetAutoTriggers, SetThresholds)

NAN = float('nan')
DEPLOY_TOKEN = 'DEPLOY'
SHUTDOWN_TOKEN = 'SHUTDOWN'
MAX_UNACKED_DEPLOYS = 2
"""P11: three unsuccessful attempts in a row put the module into protection; we stop at two."""
LOW_BATTERY_V = 3.5
"""On battery, a cell below this is reported as WARN (a 1S LiPo/Li-ion is near empty there)."""
FLAGS_QUERY_TIMEOUT_S = 0.3
"""The auto-trigger flag query is our extension (P14): a real module may stay silent."""
PARAM_WRITE_BUDGET_S = 1.8
"""A runtime parameter change that writes to the module answers within this time."""
POLICIES = ('confirm', 'deny', 'defer')
TRIGGER_MODES = ('keep', 'enable', 'disable')
LAYOUTS = ('table', 'prose')
POWER_UP_HEARTBEATS_S = 0.2
"""Unsolicited heartbeats closer together than this belong to one power-up (P5)."""

# Desired-setting parameter -> (raw converter, set encoder, query encoder, raw -> SI).
SETTINGS: Dict[str, Tuple[Callable, Callable, Callable, Callable[[int], float]]] = {
    'attitude_threshold_deg': (p.attitude_threshold_to_raw, p.encode_attitude_threshold_set,
                               p.encode_attitude_threshold_query, lambda raw: raw),
    'freefall_threshold_g': (p.freefall_threshold_to_raw, p.encode_freefall_threshold_set,
                             p.encode_freefall_threshold_query, lambda raw: raw / 10),
    'freefall_time_s': (p.freefall_time_to_raw, p.encode_freefall_time_set,
                        p.encode_freefall_time_query, lambda raw: raw / 100),
    'light_threshold_v': (p.light_threshold_to_raw, p.encode_light_threshold_set,
                          p.encode_light_threshold_query, lambda raw: raw / 10),
}
FLAG_PARAMS = {'attitude_trigger': 'attitude', 'freefall_trigger': 'freefall'}
SOURCE_NAMES = ((p.SOURCE_SERIAL, 'serial'), (p.SOURCE_ATTITUDE, 'attitude'),
                (p.SOURCE_PWM, 'pwm'), (p.SOURCE_FREEFALL, 'freefall'))


def source_name(source: int) -> str:
    """Name the trigger-source bits: 'serial', 'attitude+freefall', 'unknown' ..."""
    names = [name for bit, name in SOURCE_NAMES if source & bit]
    return '+'.join(names) if names else 'unknown'


def record_msg(record: p.TriggerRecord) -> TriggerRecord:
    """Convert a decoded 16-byte trigger record to its message, SI units."""
    return TriggerRecord(
        boot_count=record.boot_count, uptime_s=float(record.uptime_s), source=record.source,
        source_name=source_name(record.source),
        attitude_threshold_deg=record.attitude_threshold_deg,
        freefall_threshold_g=float(record.freefall_threshold_g),
        freefall_time_s=float(record.freefall_time_s), serial_connected=record.serial_link,
        charging=record.charging, light_threshold_v=float(record.light_threshold_v),
        cell_voltage_v=float(record.cell_voltage_v), raw=list(record.raw))


def _nan_if_none(value: Optional[float]) -> float:
    return NAN if value is None else float(value)


class ParachuteNode(Node):
    """The DPS-S parachute driver."""

    def __init__(self) -> None:
        super().__init__('parachute')
        self._declare_parameters()
        gp = self.get_parameter
        self.port: str = gp('port').value
        self.baud: int = gp('baud').value
        self.frame_id: str = gp('frame_id').value
        self.offline_timeout_s: float = gp('offline_timeout_s').value
        self.heartbeat_period_s: float = gp('heartbeat_period_s').value
        self.aux_poll_period_s: float = gp('aux_poll_period_s').value
        self.policy: str = gp('trigger_request_policy').value
        self.defer_timeout_s: float = gp('defer_timeout_s').value
        self.desired: Dict[str, Any] = {name: gp(name).value
                                        for name in list(SETTINGS) + list(FLAG_PARAMS)}
        self._stream_wanted: bool = gp('stream_status').value
        self._validate_startup()

        self.blackbox = BlackBox(gp('blackbox_dir').value)
        self.blackbox.record('start', port=self.port, baud=self.baud,
                             parameters={n: prm.value for n, prm in self._parameters.items()})

        # Module state as last learned (None = not known).
        self._state_lock = threading.RLock()
        self._port_open = False
        self._port_open_time = 0.0
        self._online = False
        self._offline_reason = 'not connected yet'
        self._armed: Optional[bool] = None
        self._triggered: Optional[bool] = None
        self._tilt: Optional[float] = None
        self._accel: Optional[float] = None
        self._light: Optional[float] = None
        self._charging: Optional[bool] = None
        self._voltage: Optional[float] = None
        self._streaming = False
        self._flags: Tuple[Optional[bool], Optional[bool]] = (None, None)
        self._cfg_raw: Dict[str, Optional[int]] = {name: None for name in SETTINGS}
        self._boot_count: Optional[int] = None
        self._mismatch: List[str] = []
        self._config_stamp = None
        self._in_flight: Dict[int, float] = {}
        self._in_flight_seq = 0
        self._trigger_reported = False
        self._known_records: Optional[set] = None
        self._unacked_deploys = 0
        self._pending_request: Optional[dict] = None
        self._request_lock = threading.Lock()
        self._arm_lock = threading.Lock()
        self._deploy_lock = threading.Lock()
        self._initialized = False
        self._init_queued_or_running = False
        self._init_retry_at = 0.0
        self._last_diag = 0.0
        self._diag_dirty = True
        self._shutdown_expected = False
        self._last_boot_heartbeat = 0.0
        self._last_status_time = 0.0

        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
        events_qos = QoSProfile(depth=8, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                reliability=ReliabilityPolicy.RELIABLE)
        self.status_pub = self.create_publisher(ParachuteStatus, '~/status', 10)
        self.config_pub = self.create_publisher(ParachuteConfig, '~/config', latched)
        self.triggered_pub = self.create_publisher(Bool, '~/triggered', latched)
        self.event_pub = self.create_publisher(TriggerEvent, '~/trigger_event', events_qos)
        self.request_pub = self.create_publisher(TriggerRequest, '~/trigger_request', 10)
        self.battery_pub = self.create_publisher(BatteryState, '~/battery', 10)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)

        deploy_group = MutuallyExclusiveCallbackGroup()
        arm_group = MutuallyExclusiveCallbackGroup()
        answer_group = MutuallyExclusiveCallbackGroup()
        other_group = ReentrantCallbackGroup()
        self.create_service(Deploy, '~/deploy', self._srv_deploy, callback_group=deploy_group)
        self.create_service(SetBool, '~/arm', self._srv_arm, callback_group=arm_group)
        self.create_service(SetBool, '~/answer_trigger_request', self._srv_answer,
                            callback_group=answer_group)
        for srv_type, name, handler in (
                (SetThresholds, '~/set_thresholds', self._srv_set_thresholds),
                (SetAutoTriggers, '~/set_auto_triggers', self._srv_set_auto_triggers),
                (GetParachuteConfig, '~/get_config', self._srv_get_config),
                (GetTriggerRecords, '~/get_trigger_records', self._srv_get_records),
                (SetBool, '~/set_streaming', self._srv_set_streaming),
                (Trigger, '~/zero_sensor', self._srv_zero_sensor),
                (Confirmed, '~/shutdown_module', self._srv_shutdown_module)):
            self.create_service(srv_type, name, handler, callback_group=other_group)
        self.create_timer(0.05, self._monitor, callback_group=MutuallyExclusiveCallbackGroup())

        self._publish_triggered_value: Optional[bool] = None
        self._publish_config()
        self._jobs: collections.deque = collections.deque()
        self._jobs_cond = threading.Condition()
        self._stop = threading.Event()
        self.link = ParachuteLink(
            self.port, self.baud, on_message=self._on_message,
            on_connection=self._on_connection, blackbox=self.blackbox,
            logger=self.get_logger(), layout=gp('auto_trigger_flag_layout').value)
        self._worker = threading.Thread(target=self._work, name='parachute-worker',
                                        daemon=True)
        self._worker.start()
        self.link.start()
        # A threshold parameter is accepted only once the module has confirmed it, so the
        # callback waits on the module (bounded by PARAM_WRITE_BUDGET_S). It runs in the
        # parameter services' callback group, the node's default one, which nothing else uses:
        # deploy, arm, the answer service and the monitor have groups of their own.
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.get_logger().info(
            f'DPS-S parachute driver on {self.port} at {self.baud} baud; trigger requests: '
            f'{self.policy}; black box: {self.blackbox.path}')

    # -- parameters -------------------------------------------------------------------------

    def _declare_parameters(self) -> None:
        def d(name, default, description, read_only=False, int_range=None, float_range=None,
              constraints=''):
            desc = ParameterDescriptor(description=description, read_only=read_only,
                                       additional_constraints=constraints)
            if int_range:
                desc.integer_range = [IntegerRange(from_value=int_range[0],
                                                   to_value=int_range[1], step=1)]
            if float_range:
                desc.floating_point_range = [FloatingPointRange(
                    from_value=float_range[0], to_value=float_range[1], step=0.0)]
            self.declare_parameter(name, default, desc)

        d('port', '/dev/ttyUSB0', 'serial device or pyserial URL', read_only=True)
        d('baud', 115200, 'serial rate [bit/s] (module default 115200)', read_only=True,
          int_range=(300, 4000000))
        d('frame_id', 'parachute', 'header frame_id of published messages')
        d('offline_timeout_s', 1.0, 'no reply / no stream frame for this long = offline [s]',
          float_range=(0.1, 30.0))
        d('heartbeat_period_s', 10.0, 'host heartbeat period while the stream is off [s]',
          float_range=(0.5, 60.0))
        d('stream_status', True, 'turn the module status stream on at connect')
        d('aux_poll_period_s', 1.0, 'poll period of light level, charging, cell voltage [s]',
          float_range=(0.05, 60.0))
        d('trigger_request_policy', 'confirm', 'answer to the module trigger requests',
          constraints='one of: confirm, deny, defer')
        d('defer_timeout_s', 0.8, 'under defer: answer deadline, then deny (< 1 s window) [s]',
          float_range=(0.05, 0.95))
        d('auto_trigger_flag_layout', 'table', 'reading of the 0x16 reply nibbles (P8)',
          constraints='one of: table, prose')
        d('blackbox_dir', '~/.ros/uav_serial_drivers/blackbox',
          'directory of the black-box files (one JSON-lines file per run)')
        d('attitude_threshold_deg', -1, 'desired attitude threshold [deg], 10..90; -1 = leave',
          int_range=(-1, 90))
        d('freefall_threshold_g', -1.0, 'desired free-fall threshold [g], 0.1..0.9; -1 = leave',
          float_range=(-1.0, 0.9))
        d('freefall_time_s', -1.0, 'desired free-fall time [s], 0.01..2.55; -1 = leave',
          float_range=(-1.0, 2.55))
        d('light_threshold_v', -1.0, 'desired light threshold [V], 0..25.5; -1 = leave',
          float_range=(-1.0, 25.5))
        d('attitude_trigger', 'keep', 'desired attitude auto-trigger',
          constraints='one of: keep, enable, disable')
        d('freefall_trigger', 'keep', 'desired free-fall auto-trigger',
          constraints='one of: keep, enable, disable')

    def _validate_startup(self) -> None:
        problems = [self._check_param(name, self.get_parameter(name).value)
                    for name in ('trigger_request_policy', 'auto_trigger_flag_layout',
                                 *SETTINGS, *FLAG_PARAMS)]
        problems = [x for x in problems if x]
        if problems:
            raise ValueError('; '.join(problems))

    @staticmethod
    def _check_param(name: str, value: Any) -> str:
        """Return why ``value`` is not acceptable for ``name``, or '' when it is."""
        if name == 'trigger_request_policy' and value not in POLICIES:
            return f"trigger_request_policy must be one of {', '.join(POLICIES)}, got {value!r}"
        if name == 'auto_trigger_flag_layout' and value not in LAYOUTS:
            return f"auto_trigger_flag_layout must be 'table' or 'prose', got {value!r}"
        if name in FLAG_PARAMS and value not in TRIGGER_MODES:
            return f"{name} must be one of {', '.join(TRIGGER_MODES)}, got {value!r}"
        if name == 'defer_timeout_s' and not 0.0 < value < 1.0:
            return 'defer_timeout_s must be below 1 s: the module waits only 1 s for an answer'
        if name in SETTINGS and value != -1:
            try:
                SETTINGS[name][0](value)
            except p.ProtocolError as exc:
                return f'{name}: {exc} (or -1 to leave the module as it is)'
        return ''

    def _on_set_parameters(self, params) -> SetParametersResult:
        deadline = time.monotonic() + PARAM_WRITE_BUDGET_S
        for param in params:
            problem = self._check_param(param.name, param.value)
            if problem:
                return SetParametersResult(successful=False, reason=problem)
        for param in params:
            name, value = param.name, param.value
            if name in SETTINGS or name in FLAG_PARAMS:
                ok, reason = self._write_desired(name, value, deadline)
                self.blackbox.record('parameter', name=name, value=value, accepted=ok,
                                     reason=reason)
                if not ok:
                    self.get_logger().warning(f'refused {name} := {value!r}: {reason}')
                    return SetParametersResult(successful=False, reason=reason)
                self.desired[name] = value
                self._update_mismatch()
            elif name == 'trigger_request_policy':
                self.policy = value
                self.blackbox.record('decision', what='policy', policy=value)
                self.blackbox.sync(None)
            elif name == 'defer_timeout_s':
                self.defer_timeout_s = value
            elif name == 'offline_timeout_s':
                self.offline_timeout_s = value
            elif name == 'heartbeat_period_s':
                self.heartbeat_period_s = value
            elif name == 'aux_poll_period_s':
                self.aux_poll_period_s = value
            elif name == 'frame_id':
                self.frame_id = value
            elif name == 'auto_trigger_flag_layout':
                self.link.layout = value
            elif name == 'stream_status':
                self._stream_wanted = value
                self._schedule('stream')
            elif name == 'blackbox_dir':
                self.get_logger().info('blackbox_dir takes effect at the next start')
        return SetParametersResult(successful=True)

    def _write_desired(self, name: str, value: Any, deadline: float) -> Tuple[bool, str]:
        """Write one desired setting to the module and verify it; keep/-1 writes nothing."""
        if value in (-1, 'keep'):
            return True, 'left as the module has it'
        if not self._online:
            return False, f'module offline ({self._offline_reason}); {name} not written'
        timeout = max(0.05, min(0.8, (deadline - time.monotonic()) / 2))
        try:
            if name in SETTINGS:
                return self._write_setting(name, value, timeout)
            flags = self._write_flags(**{FLAG_PARAMS[name]: value == 'enable'}, timeout=timeout)
            return flags
        except LinkError as exc:
            return False, f'module did not confirm {name}: {exc}'

    # -- module I/O helpers -----------------------------------------------------------------

    def _req(self, frame: bytes, timeout: float = 1.0, retries: int = 0,
             silence_ok: bool = False) -> p.ModuleMessage:
        """Request with the P12 bookkeeping: an unanswered request makes the module offline."""
        token = None
        if not silence_ok:
            with self._state_lock:
                self._in_flight_seq += 1
                token = self._in_flight_seq
                self._in_flight[token] = time.monotonic()
        try:
            return self.link.request(frame, timeout=timeout, retries=retries)
        finally:
            if token is not None:
                with self._state_lock:
                    self._in_flight.pop(token, None)
            self._evaluate_online()

    def _write_setting(self, name: str, value: float, timeout: float) -> Tuple[bool, str]:
        to_raw, encode_set, encode_query, to_si = SETTINGS[name]
        raw = to_raw(value)
        reply = self._req(encode_set(value), timeout)
        if not p.is_set_ack(reply, raw):
            return False, (f'module answered {reply.raw.hex(" ")} to setting {name} = {value}: '
                           f'not an acknowledgement')
        back = self._req(encode_query(), timeout)
        with self._state_lock:
            self._cfg_raw[name] = back.value
        self._publish_config()
        if back.value != raw:
            return False, (f'{name}: wrote {to_si(raw)}, module reads back '
                           f'{to_si(back.value)}')
        return True, f'{name} = {to_si(raw)} verified'

    def _write_flags(self, attitude: Optional[bool] = None, freefall: Optional[bool] = None,
                     timeout: float = 1.0) -> Tuple[bool, str]:
        """Enable/disable auto triggers (None = leave); verified by the replies (P8)."""
        reply = None
        if attitude is not None:
            reply = self._req(p.encode_attitude_trigger(attitude), timeout)
            self._set_flags(reply)
        if freefall is not None:
            reply = self._req(p.encode_freefall_trigger(freefall), timeout)
            self._set_flags(reply)
        # No query afterwards: each set reply carries both flags (P8), and the query is a
        # hazard on firmware that ignores D3 (P14).
        self._publish_config()
        att, ff = self._flags
        wrong = []
        if attitude is not None and att != attitude:
            wrong.append(f'attitude trigger reads {"enabled" if att else "disabled"}')
        if freefall is not None and ff != freefall:
            wrong.append(f'free-fall trigger reads {"enabled" if ff else "disabled"}')
        if wrong:
            return False, ('module did not confirm: ' + ', '.join(wrong)
                           + f' (flag layout {self.link.layout})')
        return True, 'auto triggers verified'

    def _set_flags(self, reply: p.AutoTriggerFlags) -> None:
        with self._state_lock:
            self._flags = (reply.attitude_enabled, reply.freefall_enabled)

    def _read_config(self) -> None:
        """Read every setting afresh (raises LinkError)."""
        for name, (_, _, encode_query, _) in SETTINGS.items():
            reply = self._req(encode_query(), retries=1)
            with self._state_lock:
                self._cfg_raw[name] = reply.value
        count = self._req(p.encode_boot_count_query(), retries=1).count
        self._note_boot_count(count)
        if None in self._flags:
            # Once per run at most (P14: a firmware ignoring D3 would take it as "enable the
            # attitude trigger"); a real module may stay silent: the flags stay unknown.
            try:
                self._set_flags(self._req(p.encode_auto_trigger_query(),
                                          FLAGS_QUERY_TIMEOUT_S, silence_ok=True))
            except LinkTimeout:
                pass
        with self._state_lock:
            self._config_stamp = self.get_clock().now().to_msg()
        self._update_mismatch(log=False)

    def _note_boot_count(self, count: int) -> None:
        with self._state_lock:
            previous, self._boot_count = self._boot_count, count
        if previous is not None and previous != count:
            self.get_logger().warning(f'module boot count {previous} -> {count}: it rebooted')
            self._after_reboot()

    def _after_reboot(self) -> None:
        with self._state_lock:
            self._trigger_reported = False
            self._unacked_deploys = 0

    def _apply_desired(self) -> None:
        """Write every desired setting that differs from the module's, then verify."""
        for name in SETTINGS:
            value = self.desired[name]
            if value == -1:
                continue
            if self._cfg_raw[name] != SETTINGS[name][0](value):
                ok, reason = self._write_setting(name, value, 1.0)
                if not ok:
                    self.get_logger().warning(f'desired setting not applied: {reason}')
        flags = {FLAG_PARAMS[n]: self.desired[n] == 'enable' for n in FLAG_PARAMS
                 if self.desired[n] != 'keep'}
        if flags:
            ok, reason = self._write_flags(**flags)
            if not ok:
                self.get_logger().warning(f'desired auto triggers not applied: {reason}')
        self._update_mismatch()

    def _update_mismatch(self, log: bool = True) -> None:
        mismatch = []
        with self._state_lock:
            for name, (to_raw, _, _, to_si) in SETTINGS.items():
                value = self.desired[name]
                if value == -1:
                    continue
                have = self._cfg_raw[name]
                if have != to_raw(value):
                    mismatch.append(f'{name}: want {value}, module '
                                    f'{"unknown" if have is None else to_si(have)}')
            for name, which in FLAG_PARAMS.items():
                value = self.desired[name]
                if value == 'keep':
                    continue
                have = self._flags[0 if which == 'attitude' else 1]
                if have is None or have != (value == 'enable'):
                    mismatch.append(f'{name}: want {value}, module '
                                    f'{"unknown" if have is None else have}')
            changed = mismatch != self._mismatch
            self._mismatch = mismatch
        if changed:
            self._diag_dirty = True
            if mismatch and log:
                self.get_logger().warning('settings do not match: ' + '; '.join(mismatch))
        self._publish_config()

    # -- reader thread --------------------------------------------------------------------------

    def _on_message(self, msg: p.ModuleMessage) -> None:
        if self._stop.is_set():
            return
        if isinstance(msg, p.TriggerRequest):
            self._on_trigger_request(msg)
        elif isinstance(msg, p.Status):
            self._on_status(msg)
        elif isinstance(msg, p.Heartbeat):
            # P5: nobody asked, so the module has just (re)booted. It sends two, 50 ms apart:
            # one reboot. The boot count read by the re-initialization confirms it.
            now = time.monotonic()
            if now - self._last_boot_heartbeat > POWER_UP_HEARTBEATS_S:
                self.get_logger().warning('unsolicited heartbeat: the module has (re)booted')
                self.blackbox.record('state', event='module reboot (unsolicited heartbeat)')
                with self._state_lock:
                    self._streaming = False
                self._schedule('init', force=True)
            self._last_boot_heartbeat = now
        elif isinstance(msg, p.DeployAck) and msg.success:
            self.get_logger().warning('late deploy acknowledgement: the module deployed')
            self._deployed_by_ack(msg, time.monotonic())
        elif isinstance(msg, p.AutoTriggerFlags):
            self._set_flags(msg)
        elif isinstance(msg, p.ShutdownAck):
            self.get_logger().warning('the module announced that it is switching off')
            self._shutdown_expected = True
        self._evaluate_online()

    def _on_trigger_request(self, msg: p.TriggerRequest) -> None:
        t_rx = time.monotonic()
        policy = self.policy
        if policy == 'confirm':
            try:
                self.link.write(p.encode_trigger_confirm())
            except LinkDown as exc:
                self._trigger_decision(TriggerRequest.DENIED, policy,
                                       f'could not send the confirmation: {exc}', t_rx, None)
                return
            self._trigger_decision(TriggerRequest.CONFIRMED, policy,
                                   'policy confirm: confirmed at once', t_rx, time.monotonic())
        elif policy == 'deny':
            self._trigger_decision(TriggerRequest.DENIED, policy,
                                   'policy deny: no confirmation sent', t_rx, None)
        else:
            timer = threading.Timer(self.defer_timeout_s, self._defer_expired)
            timer.daemon = True
            with self._request_lock:
                old = self._pending_request
                self._pending_request = {'t': t_rx, 'timer': timer}
            if old is not None:
                old['timer'].cancel()
                self._trigger_decision(TriggerRequest.TIMED_OUT, policy,
                                       'superseded by a newer trigger request', old['t'], None)
            timer.start()
            self.blackbox.record('decision', what='trigger request deferred',
                                 deadline_s=self.defer_timeout_s)
            self.blackbox.sync(None)
            self.get_logger().warning(
                f'trigger request from the module: answer ~/answer_trigger_request within '
                f'{self.defer_timeout_s:.2f} s (else denied)')

    def _defer_expired(self) -> None:
        with self._request_lock:
            pending, self._pending_request = self._pending_request, None
        if pending is None:
            return
        self._trigger_decision(
            TriggerRequest.TIMED_OUT, 'defer',
            f'nobody answered within defer_timeout_s = {self.defer_timeout_s:.2f} s: denied',
            pending['t'], None)

    def _trigger_decision(self, decision: int, policy: str, reason: str, t_rx: float,
                          t_tx: Optional[float]) -> None:
        name = {TriggerRequest.CONFIRMED: 'confirmed', TriggerRequest.DENIED: 'denied',
                TriggerRequest.TIMED_OUT: 'timed_out'}[decision]
        latency = NAN if t_tx is None else (t_tx - t_rx) * 1000.0
        self.blackbox.record('decision', what='trigger request', decision=name, policy=policy,
                             reason=reason, latency_ms=None if t_tx is None else latency)
        self.blackbox.sync(None)
        msg = TriggerRequest(decision=decision, decision_name=name, policy=policy,
                             reason=reason, latency_ms=latency)
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.frame_id
        self.request_pub.publish(msg)
        if decision == TriggerRequest.CONFIRMED:
            self.get_logger().error(f'trigger request confirmed: {reason}')
        else:
            self.get_logger().warning(f'trigger request {name}: {reason}')

    def _on_status(self, status: p.Status) -> None:
        self._last_status_time = time.monotonic()
        with self._state_lock:
            self._tilt = float(status.tilt_deg)
            self._accel = float(status.accel_g)
            armed_before = self._armed
            self._armed = status.armed
        if armed_before is not None and armed_before != status.armed:
            self.blackbox.record('state', armed=status.armed, via='status')
            self.blackbox.sync(None)
            self._diag_dirty = True
        self._set_triggered(status.triggered, via='status')
        self._publish_status()

    def _on_connection(self, up: bool, reason: str) -> None:
        if self._stop.is_set():
            return
        with self._state_lock:
            self._port_open = up
            if up:
                self._port_open_time = time.monotonic()
                self._initialized = False
        self.blackbox.record('state', port_open=up, reason=reason)
        if up:
            self._schedule('init', force=True)
        self._evaluate_online()

    # -- online / offline ---------------------------------------------------------------------

    def _evaluate_online(self) -> None:
        now = time.monotonic()
        with self._state_lock:
            last = self.link.last_frame_time if hasattr(self, 'link') else None
            if not self._port_open:
                online, reason = False, self.link.serial.last_error or 'port closed'
            elif last is None or last < self._port_open_time:
                online, reason = False, 'no valid frame from the module since the port opened'
            elif not self._online and last <= self._offline_at:
                online, reason = False, self._offline_reason  # back only with a new frame
            else:
                online, reason = True, ''
                stale = [t for t in self._in_flight.values() if t > last]
                if stale and now - min(stale) >= self.offline_timeout_s:
                    online = False
                    reason = f'no reply within {self.offline_timeout_s:.1f} s of a request'
                elif self._streaming and now - last >= self.offline_timeout_s:
                    online = False
                    reason = f'no status frame for {self.offline_timeout_s:.1f} s while streaming'
            changed = online != self._online
            if changed:
                self._online = online
                if not online:
                    self._offline_reason = reason
                    self._offline_at = now
            schedule_init = changed and online and not self._init_queued_or_running
        if not changed:
            return
        if online:
            self.get_logger().info('module online')
        else:
            self.get_logger().error(f'module offline: {reason}')
        self.blackbox.record('state', online=online, reason=reason)
        self._diag_dirty = True
        if schedule_init:
            self._schedule('init')
        self._publish_status()
        self._publish_battery()

    _offline_at = 0.0
    _initialized_at = 0.0

    # -- worker thread ---------------------------------------------------------------------------

    def _schedule(self, job: str, force: bool = False) -> None:
        with self._jobs_cond:
            if job == 'init':
                if self._init_queued_or_running and not force:
                    return
                self._init_queued_or_running = True
            if job not in self._jobs:
                self._jobs.append(job)
            self._jobs_cond.notify()

    def _work(self) -> None:
        next_aux = 0.0
        next_heartbeat = 0.0
        while not self._stop.is_set():
            with self._jobs_cond:
                if not self._jobs:
                    self._jobs_cond.wait(0.02)
                job = self._jobs.popleft() if self._jobs else None
            try:
                if job is not None:
                    self._run_job(job)
                    continue
                if not self._port_open:
                    continue
                now = time.monotonic()
                if not self._initialized:
                    if now >= self._init_retry_at:
                        self._schedule('init', force=True)
                    continue
                if self._streaming and self._online and \
                        now - max(self._last_status_time, self._initialized_at) > \
                        self.offline_timeout_s:
                    # The module answers but its stream stopped: it rebooted unnoticed.
                    self.get_logger().warning('the status stream stopped; re-initializing')
                    self._schedule('init', force=True)
                    continue
                if now >= next_aux:
                    next_aux = now + self.aux_poll_period_s
                    self._poll()
                if not self._streaming and now >= next_heartbeat:
                    next_heartbeat = now + self.heartbeat_period_s
                    self._req(p.encode_heartbeat())
            except LinkError as exc:
                self.get_logger().warning(f'{exc}', throttle_duration_sec=5.0)
            except Exception as exc:  # noqa: BLE001 - the worker must survive a bug
                self.get_logger().error(f'worker failed: {exc!r}', throttle_duration_sec=5.0)

    def _run_job(self, job: str) -> None:
        if job == 'init':
            try:
                self._initialize()
            finally:
                with self._jobs_cond:
                    self._init_queued_or_running = 'init' in self._jobs
        elif job == 'trigger':
            self._trigger_job()
        elif job == 'records':
            self._fetch_new_records()
        elif job == 'stream':
            if self._online:
                self._set_streaming(self._stream_wanted)

    def _initialize(self) -> None:
        if not self._port_open:
            return
        self._init_retry_at = time.monotonic() + 1.0
        try:
            count = self._req(p.encode_boot_count_query(), retries=1).count
            self._note_boot_count(count)
            self._set_streaming(self._stream_wanted)
            armed = self._req(p.encode_armed_query(), retries=1).armed
            triggered = self._req(p.encode_triggered_query(), retries=1).triggered
            with self._state_lock:
                self._armed = armed
            self._read_config()
            self._apply_desired()
            self._report_records_at_init(triggered)
            self._set_triggered(triggered, via='query')
        except LinkError as exc:
            self.get_logger().warning(f'initialization failed ({exc}); retrying',
                                      throttle_duration_sec=5.0)
            return
        self._initialized = True
        self._initialized_at = time.monotonic()
        self.blackbox.record('state', event='initialized', boot_count=self._boot_count,
                             mismatch=self._mismatch)
        self.get_logger().info(
            f'module initialized: boot count {self._boot_count}, streaming {self._streaming}, '
            f'settings {"verified" if not self._mismatch else "MISMATCH"}')
        self._publish_config()
        self._publish_status()

    def _set_streaming(self, enabled: bool) -> bool:
        reply = self._req(p.encode_streaming(enabled), retries=1)
        with self._state_lock:
            self._streaming = reply.enabled
        return reply.enabled == enabled

    def _poll(self) -> None:
        light = self._req(p.encode_light_level_query()).volts
        charging = self._req(p.encode_charging_query()).charging
        voltage = self._req(p.encode_cell_voltage_query()).volts
        with self._state_lock:
            self._light, self._charging, self._voltage = light, charging, voltage
        if not self._streaming:
            self._on_status(self._req(p.encode_status_query()))
        else:
            self._publish_status()
        self._publish_battery()

    # -- deployments -----------------------------------------------------------------------

    def _set_triggered(self, triggered: bool, via: str) -> None:
        with self._state_lock:
            before, self._triggered = self._triggered, triggered
            reported = self._trigger_reported
            if not triggered:
                self._trigger_reported = False
        if before == triggered:
            return
        self._diag_dirty = True
        self.blackbox.record('state', triggered=triggered, via=via)
        self.triggered_pub.publish(Bool(data=triggered))
        if triggered:
            self.blackbox.sync(None)
            self.get_logger().error(f'the module reports TRIGGERED (via {via})')
            self._schedule('records' if reported else 'trigger')

    def _deployed_by_ack(self, ack: p.DeployAck, t_ack: float) -> None:
        with self._state_lock:
            already = self._trigger_reported
            self._trigger_reported = True
            self._armed = False
        if not already:
            self._publish_event(p.SOURCE_SERIAL, TriggerEvent.VIA_DEPLOY_ACK, None)
        self._set_triggered(True, via='deploy ack')
        self._schedule('records')

    def _publish_event(self, source: int, via: int, record: Optional[p.TriggerRecord]) -> None:
        msg = TriggerEvent(source=source, source_name=source_name(source), via=via,
                           record_known=record is not None)
        if record is not None:
            msg.record = record_msg(record)
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.frame_id
        self.blackbox.record('trigger_event', source=source_name(source), via=via,
                             record=None if record is None else record.raw.hex(' '))
        self.blackbox.sync(None)
        self.event_pub.publish(msg)
        self.get_logger().error(f'PARACHUTE DEPLOYED: source {source_name(source)}')

    def _fetch_new_records(self, initial: bool = False) -> List[p.TriggerRecord]:
        """Query the history; return records not seen before (all of them the first time)."""
        try:
            records = [r for r in self.link.query_records() if not r.is_empty]
        except LinkTimeout:
            if initial:
                return []  # a module without records may stay silent: not fatal at start
            raise
        with self._state_lock:
            known = self._known_records or set()
            new = [r for r in records if r.raw not in known]
            self._known_records = known | {r.raw for r in records}
        return new

    def _report_records_at_init(self, triggered: bool) -> None:
        """Report deployments found in the history at (re)connect that nobody reported yet."""
        first = self._known_records is None
        new = self._fetch_new_records(initial=True)
        with self._state_lock:
            reported = self._trigger_reported
            if triggered:
                self._trigger_reported = True
        if not first:
            # Deployments that happened while we were not watching (unplugged, rebooted).
            for record in new[:-1] if triggered and not reported else new:
                self._publish_event(record.source, TriggerEvent.VIA_RECORD, record)
        if triggered and not reported:
            record = new[-1] if new else None
            self._publish_event(record.source if record else TriggerEvent.SOURCE_UNKNOWN,
                                TriggerEvent.VIA_STATUS, record)

    def _trigger_job(self) -> None:
        new: List[p.TriggerRecord] = []
        for attempt in range(3):
            # A module may store the record a moment after raising the flag, and a loaded
            # host may cut a multi-frame answer short at the quiet gap: ask again, briefly.
            if attempt:
                time.sleep(0.2)
            try:
                new = self._fetch_new_records()
            except LinkError as exc:
                self.get_logger().warning(f'could not read the trigger record: {exc}')
            if new or self._trigger_reported:
                break
        with self._state_lock:
            if self._trigger_reported:
                return
            self._trigger_reported = True
        record = new[-1] if new else None
        self._publish_event(record.source if record else TriggerEvent.SOURCE_UNKNOWN,
                            TriggerEvent.VIA_STATUS, record)

    # -- services -------------------------------------------------------------------------------

    def _refuse(self, response, message: str):
        response.success = False
        response.message = message
        self.get_logger().warning(message)
        return response

    def _srv_arm(self, request, response):
        self.blackbox.record('request', what='arm' if request.data else 'lock')
        ok, message = self._arm(bool(request.data))
        response.success, response.message = ok, message
        if not ok:
            self.get_logger().warning(message)
        return response

    def _arm(self, want: bool) -> Tuple[bool, str]:
        word = 'arm' if want else 'lock'
        if not self._online:
            return False, f'cannot {word}: module offline ({self._offline_reason}); nothing sent'
        with self._arm_lock:
            try:
                reply = self._req(p.encode_arm(want), retries=1)
                if reply.armed != want:
                    return False, (f'module answered {reply.raw.hex(" ")} to {word}: '
                                   f'it stays {"armed" if reply.armed else "locked"}')
                state = self._req(p.encode_armed_query(), retries=1)
            except LinkError as exc:
                return False, f'{word} not confirmed: {exc}'
            with self._state_lock:
                self._armed = state.armed
            self._diag_dirty = True
            self.blackbox.record('state', armed=state.armed, via=word)
            self.blackbox.sync()
            self._publish_status()
            if state.armed != want:
                return False, (f'module acknowledged {word} but the query says '
                               f'{"armed" if state.armed else "locked"}')
        self.get_logger().info('module ARMED' if want else 'module locked')
        return True, 'armed (verified by query)' if want else 'locked (verified by query)'

    def _srv_deploy(self, request, response):
        t0 = time.monotonic()
        response.latency_ms = NAN
        self.blackbox.record('request', what='deploy', token_ok=request.confirm == DEPLOY_TOKEN,
                             arm_if_locked=request.arm_if_locked)
        if request.confirm != DEPLOY_TOKEN:
            return self._refuse_deploy(
                response, f"deploy refused: confirm must be exactly '{DEPLOY_TOKEN}' "
                f'(got {request.confirm!r}); nothing sent')
        if not self._online:
            return self._refuse_deploy(
                response, f'deploy refused: module offline ({self._offline_reason}); '
                'nothing sent')
        if self._armed is not True:
            if not request.arm_if_locked:
                return self._refuse_deploy(
                    response, 'deploy refused: the module is locked (a locked module cannot '
                    'deploy); arm it with ~/arm or set arm_if_locked; nothing sent')
            ok, message = self._arm(True)
            if not ok:
                return self._refuse_deploy(response, f'deploy refused: arming failed: {message}')
        with self._deploy_lock:
            attempts = 0
            while attempts < MAX_UNACKED_DEPLOYS:
                if self._unacked_deploys >= MAX_UNACKED_DEPLOYS:
                    return self._refuse_deploy(
                        response, f'deploy refused: {self._unacked_deploys} deploy frames in a '
                        'row went unacknowledged; a third could put the module into protection '
                        '(P11). Check the link; a module reboot clears this.')
                attempts += 1
                # The decision is on disk before the frame leaves: a crash between the two must
                # not leave a deployment the black box never heard of.
                self.blackbox.record('decision', what='deploy: sending the deploy frame',
                                     attempt=attempts)
                self.blackbox.sync()
                try:
                    ack = self._req(p.encode_deploy(), retries=0)
                except LinkTimeout:
                    self._unacked_deploys += 1
                    self.blackbox.record('decision', what='deploy unacknowledged',
                                         attempt=attempts)
                    continue
                except LinkError as exc:
                    return self._refuse_deploy(response, f'deploy failed: {exc}')
                t_ack = time.monotonic()
                self._unacked_deploys = 0
                response.latency_ms = (t_ack - t0) * 1000.0
                if not ack.success:
                    self.blackbox.record('decision', what='deploy refused by module',
                                         hex=ack.raw.hex(' '))
                    self.blackbox.sync()
                    return self._refuse_deploy(
                        response, f'the module answered {ack.raw.hex(" ")}: it did NOT deploy '
                        '(locked, already triggered, or in protection)')
                # The acknowledgement is on disk before anyone hears of it (SIGKILL-safe).
                self.blackbox.record('decision', what='deploy acknowledged',
                                     hex=ack.raw.hex(' '), latency_ms=response.latency_ms,
                                     attempts=attempts)
                self.blackbox.sync()
                self._deployed_by_ack(ack, t_ack)
                response.success = True
                response.message = (f'deployed: acknowledged after {attempts} attempt(s), '
                                    f'{response.latency_ms:.1f} ms')
                self._publish_status()
                return response
        return self._refuse_deploy(
            response, f'deploy NOT acknowledged after {attempts} attempts; not retrying '
            '(P11: three unsuccessful attempts put the module into protection)')

    def _refuse_deploy(self, response, message: str):
        self.blackbox.record('decision', what='deploy', success=False, reason=message)
        self.blackbox.sync()
        response.success = False
        response.message = message
        self.get_logger().warning(message)
        return response

    def _srv_answer(self, request, response):
        with self._request_lock:
            pending, self._pending_request = self._pending_request, None
        if pending is None:
            return self._refuse(response, 'no trigger request is pending')
        pending['timer'].cancel()
        if request.data:
            try:
                self.link.write(p.encode_trigger_confirm())
            except LinkDown as exc:
                self._trigger_decision(TriggerRequest.DENIED, 'defer',
                                       f'answered true but the link is down: {exc}',
                                       pending['t'], None)
                return self._refuse(response, f'confirmation not sent: {exc}')
            self._trigger_decision(TriggerRequest.CONFIRMED, 'defer',
                                   'answered true via ~/answer_trigger_request', pending['t'],
                                   time.monotonic())
            response.success, response.message = True, 'confirmation sent: the module deploys'
        else:
            self._trigger_decision(TriggerRequest.DENIED, 'defer',
                                   'answered false via ~/answer_trigger_request', pending['t'],
                                   None)
            response.success, response.message = True, 'denied: nothing sent'
        return response

    def _srv_set_thresholds(self, request, response):
        wanted = {}
        for name, value in (('attitude_threshold_deg', request.attitude_deg),
                            ('freefall_threshold_g', request.freefall_g),
                            ('freefall_time_s', request.freefall_time_s),
                            ('light_threshold_v', request.light_threshold_v)):
            if math.isnan(value):
                continue
            try:
                SETTINGS[name][0](value)
            except p.ProtocolError as exc:
                response.config = self._config_msg()
                return self._refuse(response, f'refused, nothing sent: {exc}')
            wanted[name] = value
        self.blackbox.record('request', what='set_thresholds', values=wanted)
        if not self._online:
            response.config = self._config_msg()
            return self._refuse(response, f'module offline ({self._offline_reason}); '
                                'nothing sent')
        results = []
        ok_all = True
        try:
            for name, value in wanted.items():
                ok, message = self._write_setting(name, value, 1.0)
                ok_all &= ok
                results.append(message)
        except LinkError as exc:
            ok_all = False
            results.append(f'no reply: {exc}')
        self._update_mismatch()
        response.success = ok_all
        response.message = '; '.join(results) or 'nothing to change'
        response.config = self._config_msg()
        return response

    def _srv_set_auto_triggers(self, request, response):
        self.blackbox.record('request', what='set_auto_triggers',
                             attitude=request.attitude_enabled, freefall=request.freefall_enabled)
        if not self._online:
            response.config = self._config_msg()
            return self._refuse(response, f'module offline ({self._offline_reason}); '
                                'nothing sent')
        try:
            ok, message = self._write_flags(request.attitude_enabled, request.freefall_enabled)
        except LinkError as exc:
            ok, message = False, f'no reply: {exc}'
        self._update_mismatch()
        response.success, response.message = ok, message
        response.config = self._config_msg()
        return response

    def _srv_get_config(self, request, response):
        if not self._online:
            response.config = self._config_msg()
            return self._refuse(response, f'module offline ({self._offline_reason}); '
                                'showing the last read-back')
        try:
            self._read_config()
        except LinkError as exc:
            response.config = self._config_msg()
            return self._refuse(response, f'could not read the settings: {exc}')
        response.success, response.message = True, 'read afresh from the module'
        response.config = self._config_msg()
        self._publish_config()
        return response

    def _srv_get_records(self, request, response):
        if not self._online:
            return self._refuse(response, f'module offline ({self._offline_reason})')
        try:
            records = [r for r in self.link.query_records() if not r.is_empty]
        except LinkError as exc:
            return self._refuse(response, f'no trigger records: {exc}')
        with self._state_lock:
            self._known_records = (self._known_records or set()) | {r.raw for r in records}
        response.records = [record_msg(r) for r in records]
        response.success = True
        response.message = f'{len(records)} record(s)'
        return response

    def _srv_set_streaming(self, request, response):
        if not self._online:
            return self._refuse(response, f'module offline ({self._offline_reason}); '
                                'nothing sent')
        try:
            ok = self._set_streaming(bool(request.data))
        except LinkError as exc:
            return self._refuse(response, f'streaming not confirmed: {exc}')
        self._stream_wanted = bool(request.data)
        response.success = ok
        response.message = f'status stream {"on" if self._streaming else "off"}'
        self._publish_status()
        return response

    def _srv_zero_sensor(self, request, response):
        if not self._online:
            return self._refuse(response, f'module offline ({self._offline_reason}); '
                                'nothing sent')
        try:
            ack = self._req(p.encode_sensor_zero(), retries=1)
        except LinkError as exc:
            return self._refuse(response, f'zeroing not confirmed: {exc}')
        self.blackbox.record('state', event='sensor zeroed', success=ack.success)
        response.success = ack.success
        response.message = 'attitude sensor zeroed at the present mounting' if ack.success \
            else f'module answered {ack.raw.hex(" ")}'
        return response

    def _srv_shutdown_module(self, request, response):
        if request.confirm != SHUTDOWN_TOKEN:
            return self._refuse(response, f"refused: confirm must be exactly '{SHUTDOWN_TOKEN}' "
                                f'(got {request.confirm!r}); nothing sent')
        if not self._online:
            return self._refuse(response, f'module offline ({self._offline_reason}); '
                                'nothing sent')
        self._shutdown_expected = True
        try:
            self._req(p.encode_shutdown(), retries=1)
        except LinkError as exc:
            self._shutdown_expected = False
            return self._refuse(response, f'shutdown not acknowledged: {exc}')
        self.blackbox.record('state', event='module shut down by request')
        self.blackbox.sync()
        response.success = True
        response.message = ('module acknowledged and is switching off; switch it on with its '
                            'button (2 s) or external power')
        return response

    # -- publishing ------------------------------------------------------------------------------

    def _stamp(self, msg) -> None:
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.frame_id

    def _publish_status(self) -> None:
        with self._state_lock:
            msg = ParachuteStatus(
                online=self._online, armed=bool(self._armed), triggered=bool(self._triggered),
                tilt_deg=_nan_if_none(self._tilt), accel_g=_nan_if_none(self._accel),
                streaming=self._streaming, light_level_v=_nan_if_none(self._light),
                charging=bool(self._charging), cell_voltage_v=_nan_if_none(self._voltage),
                attitude_trigger_enabled=bool(self._flags[0]),
                freefall_trigger_enabled=bool(self._flags[1]))
            threshold = self._cfg_raw['light_threshold_v']
            msg.bay_open = (self._light is not None and threshold is not None
                            and self._light > threshold / 10)
        self._stamp(msg)
        self.status_pub.publish(msg)

    def _publish_battery(self) -> None:
        msg = BatteryState()
        self._stamp(msg)
        with self._state_lock:
            online, voltage, charging = self._online, self._voltage, self._charging
        msg.voltage = _nan_if_none(voltage) if online else NAN
        for field in ('temperature', 'current', 'charge', 'capacity', 'design_capacity',
                      'percentage'):
            setattr(msg, field, NAN)
        if not online or charging is None:
            msg.power_supply_status = BatteryState.POWER_SUPPLY_STATUS_UNKNOWN
        elif charging:
            msg.power_supply_status = BatteryState.POWER_SUPPLY_STATUS_CHARGING
        else:
            msg.power_supply_status = BatteryState.POWER_SUPPLY_STATUS_DISCHARGING
        msg.power_supply_health = BatteryState.POWER_SUPPLY_HEALTH_UNKNOWN
        msg.power_supply_technology = BatteryState.POWER_SUPPLY_TECHNOLOGY_UNKNOWN
        msg.present = online
        msg.cell_voltage = [msg.voltage]
        msg.cell_temperature = [NAN]
        msg.location = self.port
        self.battery_pub.publish(msg)

    def _config_msg(self) -> ParachuteConfig:
        with self._state_lock:
            raw = dict(self._cfg_raw)
            msg = ParachuteConfig(
                valid=all(v is not None for v in raw.values()) and self._boot_count is not None,
                attitude_threshold_deg=raw['attitude_threshold_deg'] or 0,
                freefall_threshold_g=NAN if raw['freefall_threshold_g'] is None
                else raw['freefall_threshold_g'] / 10,
                freefall_time_s=NAN if raw['freefall_time_s'] is None
                else raw['freefall_time_s'] / 100,
                light_threshold_v=NAN if raw['light_threshold_v'] is None
                else raw['light_threshold_v'] / 10,
                attitude_trigger_enabled=bool(self._flags[0]),
                freefall_trigger_enabled=bool(self._flags[1]),
                auto_triggers_known=self._flags[0] is not None and self._flags[1] is not None,
                boot_count=-1 if self._boot_count is None else self._boot_count,
                baud_rate=self.baud, settings_verified=not self._mismatch,
                mismatch='; '.join(self._mismatch))
            if self._config_stamp is not None:
                msg.header.stamp = self._config_stamp
        msg.header.frame_id = self.frame_id
        return msg

    def _publish_config(self) -> None:
        self.config_pub.publish(self._config_msg())

    # -- monitor timer: online judgement and diagnostics -------------------------------------

    def _monitor(self) -> None:
        if self._stop.is_set():
            return
        try:
            self._evaluate_online()
            now = time.monotonic()
            if self._diag_dirty or now - self._last_diag >= 1.0:
                self._diag_dirty = False
                self._last_diag = now
                self._publish_diagnostics()
        except Exception as exc:  # noqa: BLE001 - a timer must not die
            self.get_logger().error(f'monitor failed: {exc!r}', throttle_duration_sec=5.0)

    def _link_problem(self) -> str:
        """Explain why the module is offline, with what to do about it."""
        if not self._port_open:
            return self.link.serial.last_error or f'{self.port} is not open'
        decoder = self.link.decoder
        if self.link.last_frame_time is None and self.link.serial.stats.bytes_in > 0:
            return (f'{self.port} is open but none of the {self.link.serial.stats.bytes_in} '
                    f'bytes received form a valid DPS-S frame ({decoder.checksum_errors} checksum '
                    f'errors): wrong baud rate? Check the `baud` parameter ({self.baud}; the '
                    'module default is 115200)')
        if self._shutdown_expected:
            return 'the module was shut down by request; switch it on again'
        return (f'{self._offline_reason}: is the module powered and connected, and is the '
                f'`baud` parameter ({self.baud}) right?')

    def _publish_diagnostics(self) -> None:
        name = self.get_name()
        stats = self.link.serial.stats
        decoder = self.link.decoder
        with self._state_lock:
            online, armed, triggered = self._online, self._armed, self._triggered
            voltage, charging, mismatch = self._voltage, self._charging, list(self._mismatch)
        link = DiagnosticStatus(name=f'{name}: link', hardware_id=self.port)
        if online:
            link.level, link.message = DiagnosticStatus.OK, 'online'
        else:
            link.level, link.message = DiagnosticStatus.ERROR, f'offline: {self._link_problem()}'
            self.get_logger().warning(link.message, throttle_duration_sec=5.0)
        link.values = _kv(online=online, port=self.port, baud=self.baud,
                          frames_in=stats.frames_in, frames_out=stats.frames_out,
                          checksum_errors=decoder.checksum_errors,
                          bytes_discarded=decoder.bytes_discarded, timeouts=self.link.timeouts,
                          reconnects=stats.reconnects, streaming=self._streaming,
                          blackbox=self.blackbox.path)
        state = DiagnosticStatus(name=f'{name}: state', hardware_id=self.port)
        if triggered:
            state.level, state.message = DiagnosticStatus.ERROR, 'TRIGGERED: parachute deployed'
        elif armed is None:
            state.level, state.message = DiagnosticStatus.WARN, 'state unknown'
        else:
            state.level = DiagnosticStatus.OK
            state.message = 'armed' if armed else 'locked (cannot deploy)'
        if not online:
            state.level = DiagnosticStatus.ERROR
            state.message = f'{state.message} (offline: last known)'
        state.values = _kv(armed=armed, triggered=triggered,
                           policy=self.policy, pending_trigger_request=(
                               self._pending_request is not None))
        battery = DiagnosticStatus(name=f'{name}: battery', hardware_id=self.port)
        if voltage is None:
            battery.level, battery.message = DiagnosticStatus.OK, 'not read yet'
        elif not charging and voltage < LOW_BATTERY_V:
            battery.level = DiagnosticStatus.WARN
            battery.message = f'battery low: {voltage:.2f} V < {LOW_BATTERY_V} V on battery'
        else:
            battery.level = DiagnosticStatus.OK
            battery.message = f'{voltage:.2f} V, {"charging" if charging else "on battery"}'
        battery.values = _kv(voltage_v=voltage, charging=charging)
        settings = DiagnosticStatus(name=f'{name}: settings', hardware_id=self.port)
        if mismatch:
            settings.level = DiagnosticStatus.WARN
            settings.message = 'settings do not match: ' + '; '.join(mismatch)
        else:
            settings.level, settings.message = DiagnosticStatus.OK, 'settings verified'
        settings.values = _kv(settings_verified=not mismatch, boot_count=self._boot_count)
        array = DiagnosticArray(status=[link, state, battery, settings])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(array)

    # -- shutdown --------------------------------------------------------------------------------

    def on_shutdown(self) -> None:
        """Stop the worker and the link, close the black box (the module is left as it is)."""
        self._stop.set()
        with self._request_lock:
            pending, self._pending_request = self._pending_request, None
        if pending is not None:
            pending['timer'].cancel()
        self.link.stop()
        self._worker.join(2.5)
        self.blackbox.record('stop')
        self.blackbox.close()


def _kv(**values: Any) -> List[KeyValue]:
    return [KeyValue(key=k, value=str(v)) for k, v in values.items()]


def main(args=None) -> int:
    """Run the parachute driver until Ctrl-C."""
    return run_node(ParachuteNode, args, threads=8)


if __name__ == '__main__':
    import sys
    sys.exit(main())
