"""``parachute_node``: the ROS 2 adapter of the DPS-S parachute driver.

The device is `dps_parachute_ros.session.ParachuteSession` (no ROS in it: link, black box,
state, rules, policies, its threads). This node only translates: parameters into a
`SessionConfig` (desired module settings committed to the module all or nothing, local settings
applied once a set is accepted), services into session calls, session callbacks into messages
(`dps_parachute_ros.messages`) and ``/diagnostics`` statuses. Every service has a callback group
of its own, so a deploy never waits behind a slow query, and no exception leaves a callback.

Decisions where the contract and the vendor document are silent are in ``docs/protocols.md``
(DPS-S, "Driver decisions"); the rules of deploy in the README, "Safety model of deploy".
"""

from __future__ import annotations

from dataclasses import asdict
import math
import sys
import threading
import time
from typing import Any, Callable, Dict, Optional, Tuple

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import BatteryState
from std_msgs.msg import Bool
from std_srvs.srv import SetBool, Trigger

from dps_parachute_ros import messages as m
from dps_parachute_ros.release_gate import ReleaseGate
from dps_parachute_ros.session import LOW_BATTERY_V, ParachuteSession
from dps_parachute_ros.state import (Deployment, FLAG_SETTINGS, LAYOUTS, Listener, POLICIES,
                                     RequestDecision, Result, SessionConfig, SETTINGS, Snapshot,
                                     TRIGGER_MODES, value_problem)
from uav_serial_common.diagnostics import DiagnosticsUpdater, ERROR, OK, Status, WARN
from uav_serial_common.logs import log_at
from uav_serial_common.node_main import run_node
from uav_serial_common.params import declare_and_check, ParameterBinding, ParamSpec
from uav_serial_drivers.msg import (ParachuteConfig, ParachuteStatus, TriggerEvent,
                                    TriggerRequest)
from uav_serial_drivers.srv import (Confirmed, Deploy, GetParachuteConfig, GetTriggerRecords,
                                    SetAutoTriggers, SetThresholds)


def _check(name: str) -> Callable[[Any], str]:
    return lambda value: value_problem(name, value)


SWITCH_INTERVAL_S = 0.001
"""The GIL switch interval of the driver process (Python's default is 5 ms)."""

PARAMS = (
    ParamSpec('port', '/dev/ttyUSB0', 'serial device or pyserial URL', read_only=True),
    ParamSpec('baud', 115200, 'serial rate [bit/s] (module default 115200)', read_only=True,
              int_range=(300, 4000000)),
    ParamSpec('frame_id', 'parachute', 'header frame_id of published messages'),
    ParamSpec('offline_timeout_s', 1.0, 'no reply / no stream frame for this long = offline '
              '[s]', float_range=(0.1, 30.0)),
    ParamSpec('heartbeat_period_s', 10.0, 'host heartbeat period while the stream is off [s]',
              float_range=(0.5, 60.0)),
    ParamSpec('stream_status', True, 'turn the module status stream on at connect'),
    ParamSpec('aux_poll_period_s', 1.0, 'poll period of light level, charging, cell voltage '
              '[s]', float_range=(0.05, 60.0)),
    ParamSpec('trigger_request_policy', 'confirm', 'answer to the module trigger requests',
              choices=POLICIES),
    ParamSpec('defer_timeout_s', 0.8, 'under defer: answer deadline, then deny (< 1 s window) '
              '[s]', float_range=(0.05, 0.95), check=_check('defer_timeout_s')),
    ParamSpec('auto_trigger_flag_layout', 'table', 'reading of the 0x16 reply nibbles (P8)',
              choices=LAYOUTS),
    ParamSpec('blackbox_dir', '~/.ros/uav_serial_drivers/blackbox',
              'directory of the black-box files (one JSON-lines file per run)'),
    ParamSpec('blackbox_max_mb', 200.0, 'the black-box files together stay below this [MB]; '
              'oldest runs are removed first, never the current one; 0 = no bound',
              float_range=(0.0, 1e6)),
    ParamSpec('attitude_threshold_deg', -1, 'desired attitude threshold [deg], 10..90; -1 = '
              'leave', int_range=(-1, 90), check=_check('attitude_threshold_deg')),
    ParamSpec('freefall_threshold_g', -1.0, 'desired free-fall threshold [g], 0.1..0.9; -1 = '
              'leave', float_range=(-1.0, 0.9), check=_check('freefall_threshold_g')),
    ParamSpec('freefall_time_s', -1.0, 'desired free-fall time [s], 0.01..2.55; -1 = leave',
              float_range=(-1.0, 2.55), check=_check('freefall_time_s')),
    ParamSpec('light_threshold_v', -1.0, 'desired light threshold [V], 0..25.5; -1 = leave',
              float_range=(-1.0, 25.5), check=_check('light_threshold_v')),
    ParamSpec('attitude_trigger', 'keep', 'desired attitude auto-trigger',
              choices=TRIGGER_MODES),
    ParamSpec('freefall_trigger', 'keep', 'desired free-fall auto-trigger',
              choices=TRIGGER_MODES),
    ParamSpec('release_gate', 'parachute_mavlink/release_gate', 'std_srvs/Trigger service '
              'called just before a release leaves, when it is there (the motor stop of '
              'parachute_mavlink); empty = never', startup_only=True),
    ParamSpec('release_gate_timeout_s', 0.5, 'longest wait for the release gate; a trigger '
              "request's confirmation never waits past its 1 s window [s]",
              float_range=(0.01, 1.0), startup_only=True),
)
THRESHOLD_FIELDS = (('attitude_threshold_deg', 'attitude_deg'),
                    ('freefall_threshold_g', 'freefall_g'),
                    ('freefall_time_s', 'freefall_time_s'),
                    ('light_threshold_v', 'light_threshold_v'))


EXECUTOR_THREADS = 12
"""Threads of the executor's pool (``main()``; the tests' in-process driver reads it)."""


class ParachuteNode(Node, Listener):
    """The DPS-S parachute driver: a ROS face on a `ParachuteSession`."""

    def __init__(self, **node_options: Any) -> None:
        super().__init__('parachute', **node_options)
        values = declare_and_check(self, PARAMS)
        self.frame_id: str = values['frame_id']
        self._status = m.StatusPacker(self.frame_id)
        config = SessionConfig.from_values(values)
        self._stamp_lock = threading.Lock()  # guards the two below (session threads, services)
        self._config_stamp = None
        self._config_reads = -1

        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
        events_qos = QoSProfile(depth=8, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                reliability=ReliabilityPolicy.RELIABLE)
        self.status_pub = self.create_publisher(ParachuteStatus, '~/status', 10)
        self.config_pub = self.create_publisher(ParachuteConfig, '~/config', latched)
        self.triggered_pub = self.create_publisher(Bool, '~/triggered', latched)
        self.event_pub = self.create_publisher(TriggerEvent, '~/trigger_event', events_qos)
        # One message per deployment on ~/trigger_event; a source learned later goes here.
        self.event_update_pub = self.create_publisher(TriggerEvent, '~/trigger_event_update',
                                                      events_qos)
        self.request_pub = self.create_publisher(TriggerRequest, '~/trigger_request', 10)
        self.battery_pub = self.create_publisher(BatteryState, '~/battery', 10)

        self.session = ParachuteSession(config, listener=self)
        self.diagnostics = DiagnosticsUpdater(self, config.port, period_s=1.0)
        for name, task in (('link', self._diag_link), ('state', self._diag_state),
                           ('battery', self._diag_battery), ('settings', self._diag_settings),
                           ('black box', self._diag_blackbox)):
            self.diagnostics.add(name, task)

        s = self.session
        self._service(Deploy, 'deploy', lambda q, r: self._deploy(q, r))
        self._service(SetBool, 'arm', lambda q, r: self._reply(r, s.arm(bool(q.data)),
                                                               log=False))
        self._service(SetBool, 'answer_trigger_request',
                      lambda q, r: self._reply(r, s.answer_trigger_request(bool(q.data))))
        self._service(SetThresholds, 'set_thresholds', self._set_thresholds)
        self._service(SetAutoTriggers, 'set_auto_triggers', lambda q, r: self._with_config(
            r, s.set_auto_triggers(q.attitude_enabled, q.freefall_enabled)))
        self._service(GetParachuteConfig, 'get_config',
                      lambda q, r: self._with_config(r, s.get_config()))
        self._service(GetTriggerRecords, 'get_trigger_records', self._get_records)
        self._service(SetBool, 'set_streaming',
                      lambda q, r: self._reply(r, s.set_streaming(bool(q.data))))
        self._service(Trigger, 'zero_sensor', lambda q, r: self._reply(r, s.zero_sensor()))
        self._service(Confirmed, 'shutdown_module',
                      lambda q, r: self._reply(r, s.shutdown_module(q.confirm)))
        self._service(Trigger, 'preflight_check',
                      lambda q, r: self._reply(r, s.preflight_check(), log=False))

        if values['release_gate']:
            s.release_gate = self._make_gate(values['release_gate'],
                                             values['release_gate_timeout_s'])
        self.on_config(s.snapshot)
        # Desired module settings must be confirmed by the module (commit, all or nothing);
        # the rest only changes the driver (apply, once the whole set is accepted). The commit
        # waits on the module (bounded): it runs in the parameter services' callback group,
        # the node's default one, which nothing else uses.
        ParameterBinding(self, PARAMS, apply=self._apply, commit=s.commit_desired)
        s.start()
        status = s.blackbox.status()
        self.get_logger().info(
            f'DPS-S parachute driver on {config.port} at {config.baud} baud; trigger requests: '
            f'{config.trigger_request_policy}; black box: '
            f'{status.path or "NONE (" + status.error + ")"}')

    # -- the release gate (release_gate.py) ----------------------------------------------------

    def _make_gate(self, name: str, timeout_s: float) -> ReleaseGate:
        client = self.create_client(Trigger, name, callback_group=ReentrantCallbackGroup())

        def call(timeout: float) -> Tuple[Optional[bool], str]:
            if not client.service_is_ready():
                return None, f'{client.srv_name} is not available'
            done = threading.Event()
            future = client.call_async(Trigger.Request())
            future.add_done_callback(lambda _: done.set())
            if not done.wait(timeout):
                client.remove_pending_request(future)
                return None, f'no answer within {timeout * 1000:.0f} ms'
            reply = future.result()
            return bool(reply.success), reply.message
        return ReleaseGate(name, call, timeout_s, self.session.blackbox.record, self.on_log,
                           ready=client.service_is_ready)

    # -- parameters -------------------------------------------------------------------------

    def _apply(self, changes: Dict[str, Any]) -> None:
        if 'frame_id' in changes:
            self.frame_id = changes['frame_id']
            self._status.set_frame_id(self.frame_id)
        if 'blackbox_dir' in changes:
            self.get_logger().info('blackbox_dir takes effect at the next start')
        values = {**asdict(self.session.config), **changes}
        self.session.reconfigure(SessionConfig.from_values(values))

    # -- services ---------------------------------------------------------------------------

    def _service(self, srv_type: Any, name: str, handler: Callable[[Any, Any], Any]) -> None:
        def call(request: Any, response: Any) -> Any:
            try:
                return handler(request, response)
            except Exception as exc:  # noqa: BLE001 - a refusal, never an exception in rclpy
                self.get_logger().error(f'~/{name} failed: {exc!r}')
                response.success = False
                response.message = f'internal error: {exc!r}'
                return response
        self.create_service(srv_type, f'~/{name}', call,
                            callback_group=MutuallyExclusiveCallbackGroup())

    def _reply(self, response: Any, result: Result, log: bool = True) -> Any:
        response.success, response.message = result.ok, result.message
        if log and not result.ok:
            self.get_logger().warning(result.message)
        return response

    def _with_config(self, response: Any, result: Result) -> Any:
        response.config = self._config_msg(self.session.snapshot)
        return self._reply(response, result)

    def _deploy(self, request: Deploy.Request, response: Deploy.Response) -> Any:
        result = self.session.deploy(request.confirm, request.arm_if_locked)
        response.success, response.message = result.ok, result.message
        response.latency_ms = math.nan if result.latency_ms is None else result.latency_ms
        return response

    def _set_thresholds(self, request: SetThresholds.Request,
                        response: SetThresholds.Response) -> Any:
        values = {name: getattr(request, field) for name, field in THRESHOLD_FIELDS
                  if not math.isnan(getattr(request, field))}
        return self._with_config(response, self.session.set_thresholds(values))

    def _get_records(self, request: Any, response: GetTriggerRecords.Response) -> Any:
        result = self.session.get_trigger_records()
        response.records = [m.record_msg(r) for r in result.value or ()]
        return self._reply(response, result)

    # -- session callbacks (the session's threads) ----------------------------------------------

    def _now(self) -> Any:
        return self.get_clock().now().to_msg()

    def _now_ns(self) -> Tuple[int, int]:
        """Return the ROS time now as (sec, nanosec); the wall clock unless on simulated time."""
        clock = self.get_clock()
        if clock.ros_time_is_active:
            return clock.now().seconds_nanoseconds()
        return divmod(time.time_ns(), 1_000_000_000)

    def on_status(self, snap: Snapshot) -> None:
        """Publish ``~/status`` (serialized by `m.StatusPacker`: it goes out with every frame)."""
        self.status_pub.publish(self._status.pack(snap, *self._now_ns()))

    def on_battery(self, snap: Snapshot) -> None:
        """Publish ``~/battery``."""
        self.battery_pub.publish(m.battery_msg(snap, self._now(), self.frame_id,
                                               self.session.config.port))

    def _config_msg(self, snap: Snapshot) -> ParachuteConfig:
        # Stamped with the time of the read-back it shows, not of the publication.
        with self._stamp_lock:
            if snap.config_reads != self._config_reads:
                self._config_reads = snap.config_reads
                self._config_stamp = self._now() if snap.config_reads else None
            stamp = self._config_stamp
        return m.config_msg(snap, stamp, self.frame_id, self.session.config.baud)

    def on_config(self, snap: Snapshot) -> None:
        """Publish ``~/config`` (latched)."""
        self.config_pub.publish(self._config_msg(snap))

    def on_triggered(self, triggered: bool) -> None:
        """Publish ``~/triggered`` (latched)."""
        self.triggered_pub.publish(m.triggered_msg(triggered))

    def on_deployment(self, event: Deployment) -> None:
        """Publish ``~/trigger_event``, or ``~/trigger_event_update`` for an amended source."""
        publisher = self.event_update_pub if event.amends else self.event_pub
        publisher.publish(m.event_msg(event, self._now(), self.frame_id))

    def on_trigger_request(self, decision: RequestDecision) -> None:
        """Publish ``~/trigger_request``."""
        self.request_pub.publish(m.request_msg(decision, self._now(), self.frame_id))

    def on_log(self, level: str, text: str) -> None:
        """Write a line of the session to the ROS log."""
        log_at(self.get_logger(), level, text)

    def on_diagnostics(self) -> None:
        """Publish the diagnostics soon (rate-limited by the updater)."""
        self.diagnostics.force_update()

    # -- diagnostics ------------------------------------------------------------------------------

    def _diag_link(self, stat: Status) -> None:
        snap = self.session.snapshot
        config = self.session.config
        if snap.online and snap.stream_problem:
            stat.summary(WARN, f'online; {snap.stream_problem}')
        elif snap.online:
            stat.summary(OK, 'online')
        else:
            stat.summary(ERROR, f'offline: {self.session.link_problem()}')
            self.get_logger().warning(stat.message, throttle_duration_sec=5.0)
        stat.add('online', snap.online)
        stat.add('port', config.port)
        stat.add('baud', config.baud)
        for key, value in self.session.link_info().items():
            stat.add(key, value)
        stat.add('streaming', snap.streaming)
        stat.add('stream_problem', snap.stream_problem)

    def _diag_state(self, stat: Status) -> None:
        snap = self.session.snapshot
        if snap.triggered:
            stat.summary(ERROR, 'TRIGGERED: parachute deployed')
        elif snap.armed is None:
            stat.summary(WARN, 'state unknown')
        else:
            stat.summary(OK, 'armed' if snap.armed else 'locked (cannot deploy)')
        if not snap.online:
            stat.summary(ERROR, f'{stat.message} (offline: last known)')
        if snap.deploy_outcome_unknown:
            stat.merge_summary(ERROR, 'the outcome of a deploy is UNKNOWN until the module '
                                      'answers again')
        if snap.failed_deploys:
            stat.merge_summary(WARN, f'{snap.failed_deploys} unsuccessful deploy attempt(s) '
                                     'since power-up (3 put the module into protection)')
        for key in ('armed', 'triggered', 'policy', 'pending_request', 'unacked_deploys',
                    'failed_deploys'):
            stat.add(key, getattr(snap, key))

    def _diag_battery(self, stat: Status) -> None:
        snap = self.session.snapshot
        volts, charging = snap.voltage_v, snap.charging
        if volts is None:
            stat.summary(OK, 'not read yet')
        elif not charging and volts < LOW_BATTERY_V:
            stat.summary(WARN, f'battery low: {volts:.2f} V < {LOW_BATTERY_V} V on battery')
        else:
            stat.summary(OK, f'{volts:.2f} V, {"charging" if charging else "on battery"}')
        stat.add('voltage_v', volts)
        stat.add('charging', charging)

    def _diag_settings(self, stat: Status) -> None:
        snap = self.session.snapshot
        if snap.held:
            stat.summary(WARN, 'desired setting held back (written once it no longer would '
                               'deploy the armed module): ' + '; '.join(snap.held))
        elif snap.mismatch:
            stat.summary(WARN, 'settings do not match: ' + '; '.join(snap.mismatch))
        else:
            stat.summary(OK, 'settings verified')
        stat.add('settings_verified', not snap.mismatch)
        stat.add('boot_count', snap.boot_count)
        config = self.session.config
        for name in (*SETTINGS, *FLAG_SETTINGS):
            stat.add(f'desired_{name}', config.desired(name))

    def _diag_blackbox(self, stat: Status) -> None:
        status = self.session.blackbox.status()
        problem = self.session.blackbox_problem(status)
        if problem:
            stat.summary(ERROR, f'black box: {problem}')
        elif status.over_budget:
            stat.summary(WARN, f'black box: this run alone ({status.run_bytes / 1e6:.1f} MB) '
                               f'exceeds blackbox_max_mb ({status.max_bytes / 1e6:g} MB)')
        elif status.lost:
            stat.summary(WARN, f'black box: writing again; {status.lost} records were lost')
        else:
            stat.summary(OK, f'black box: writing to {status.path}')
        for key in ('path', 'records', 'lost', 'error', 'removed_runs'):
            stat.add(key, getattr(status, key))
        stat.add('run_mb', round(status.run_bytes / 1e6, 3))
        stat.add('directory_mb', round(status.total_bytes / 1e6, 3))
        stat.add('max_mb', None if status.max_bytes is None else status.max_bytes / 1e6)

    # -- shutdown --------------------------------------------------------------------------------

    def on_shutdown(self) -> None:
        """Stop the session and close the black box (the module is left as it is, D10)."""
        self.get_logger().info('parachute driver shutting down')
        self.session.stop()


def main(args: Optional[list] = None) -> int:
    """Run the parachute driver until Ctrl-C."""
    # A deploy call waited ~6 ms for the GIL behind the driver's other threads at Python's 5 ms
    # switch interval (deploy latency p50 10.3 -> 5.5 ms with 1 ms), as the servo and OriginMan
    # drivers already found.
    return run_node(ParachuteNode, args, threads=EXECUTOR_THREADS,
                    switch_interval_s=SWITCH_INTERVAL_S)


if __name__ == '__main__':
    sys.exit(main())
