"""``parachute_mavlink``: the parachute driver as a MAVLink parachute component (ros-api.md).

A thin adapter around `parachute_mavlink_ros.core.LinkCore`. One thread owns the core: every
event (a MAVLink message from the reader thread of `MavlinkPort`, a message or a service answer
of the parachute node, a release-gate call, a handset failsafe) goes through one queue to it,
and it carries out the actions the core returns. It wakes at the core's next deadline, so the
heartbeat, the IN_PROGRESS acks and the motor-stop deadline never wait behind a ROS callback.

It talks to ``parachute_node`` through that node's topics and services only. The motor stop is
in the release gate: ``parachute_node`` with ``release_gate:=parachute_mavlink/release_gate``
calls ``~/release_gate`` before any release leaves (README, "The autopilot link").
"""

from __future__ import annotations

import itertools
import math
import queue
import threading
import time
from typing import Any, Dict, Optional, Tuple

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import SetBool, Trigger

from parachute_mavlink_ros import core as c
from parachute_mavlink_ros.port import MavlinkPort
from uav_serial_common.diagnostics import DiagnosticsUpdater, ERROR, OK, Status, WARN
from uav_serial_common.logs import log_at
from uav_serial_common.node_main import run_node
from uav_serial_common.params import declare_and_check, ParamSpec
from uav_serial_drivers.msg import (Failsafe, MavlinkLink, ParachuteStatus, TriggerEvent,
                                    TriggerRequest)
from uav_serial_drivers.srv import Deploy

PARAMS = (
    ParamSpec('mavlink_url', 'udpout:127.0.0.1:14550', 'pymavlink connection string: '
              'udpout:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT or DEVICE,BAUD', read_only=True),
    ParamSpec('system_id', 1, "the vehicle's system id (PX4 MAV_SYS_ID, ArduPilot "
              'SYSID_THISMAV); 0 = learn it from the first autopilot heartbeat',
              int_range=(0, 255), read_only=True),
    ParamSpec('component_id', 161, 'our component id (MAV_COMP_ID_PARACHUTE)',
              int_range=(1, 255), read_only=True),
    ParamSpec('parachute_ns', 'parachute', 'name of the parachute node (relative)',
              read_only=True),
    ParamSpec('release_arms_if_locked', False, 'DO_PARACHUTE RELEASE arms a locked module '
              'first', startup_only=True),
    ParamSpec('stop_motors_before_release', 'disarm', 'motor stop sent to the autopilot before '
              'any release: off, disarm (forced) or terminate', choices=c.STOP_MODES,
              startup_only=True),
    ParamSpec('motor_stop_wait_s', 0.3, "longest wait for the autopilot's ACK of the motor "
              'stop before releasing anyway (the parachute node waits at most its '
              'release_gate_timeout_s) [s]', float_range=(0.0, 0.9), startup_only=True),
    ParamSpec('handset_failsafe_to_autopilot', False, "forward the handset's RETURN_TO_HOME "
              'as MAV_CMD_NAV_RETURN_TO_LAUNCH', startup_only=True),
    ParamSpec('handset_ns', 'handset_link', 'name of the handset link node (relative)',
              read_only=True),
    ParamSpec('preflight_period_s', 10.0, "how often the parachute node's ~/preflight_check "
              'is asked (also on every change of online / armed) [s]',
              float_range=(1.0, 3600.0), startup_only=True),
)
GATE_MARGIN_S = 0.15
"""The gate service answers at the latest this long after motor_stop_wait_s."""


class ParachuteMavlinkNode(Node):
    """The autopilot link of the parachute driver."""

    def __init__(self) -> None:
        super().__init__('parachute_mavlink')
        values = declare_and_check(self, PARAMS)
        self.config = c.CoreConfig(
            system_id=values['system_id'], component_id=values['component_id'],
            release_arms_if_locked=values['release_arms_if_locked'],
            stop_motors_before_release=values['stop_motors_before_release'],
            motor_stop_wait_s=values['motor_stop_wait_s'],
            handset_failsafe_to_autopilot=values['handset_failsafe_to_autopilot'],
            preflight_period_s=values['preflight_period_s'])
        self.url = values['mavlink_url']
        self.core = c.LinkCore(self.config, time.monotonic())
        self._events: 'queue.Queue[Any]' = queue.Queue()
        self._stopping = threading.Event()
        self._gate_ids = itertools.count(1_000_000_000)
        self._gates: Dict[int, Tuple[threading.Event, list]] = {}
        self._gates_lock = threading.Lock()
        self._calls: Dict[int, Tuple[Any, Any, float]] = {}  # id -> (client, future, deadline)
        self._link_snapshot: Dict[str, Any] = {}
        self._snapshot_lock = threading.Lock()
        self._last_state: Optional[Tuple[bool, bool, bool]] = None
        self._write_errors = 0

        ns = values['parachute_ns'].rstrip('/')
        group = ReentrantCallbackGroup()
        self._parachute_clients = {
            'deploy': self.create_client(Deploy, f'{ns}/deploy', callback_group=group),
            'arm': self.create_client(SetBool, f'{ns}/arm', callback_group=group),
            'preflight_check': self.create_client(Trigger, f'{ns}/preflight_check',
                                                  callback_group=group),
        }
        latched = QoSProfile(depth=8, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
        # Depth 10: a NONE and a RETURN_TO_HOME in quick succession are two transitions.
        failsafe_qos = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                  reliability=ReliabilityPolicy.RELIABLE)
        subs = MutuallyExclusiveCallbackGroup()
        self.create_subscription(ParachuteStatus, f'{ns}/status', self._on_status, 10,
                                 callback_group=subs)
        self.create_subscription(TriggerEvent, f'{ns}/trigger_event', self._on_trigger_event,
                                 latched, callback_group=subs)
        self.create_subscription(TriggerRequest, f'{ns}/trigger_request',
                                 self._on_trigger_request, 10, callback_group=subs)
        if self.config.handset_failsafe_to_autopilot:
            handset = values['handset_ns'].rstrip('/')
            self.create_subscription(Failsafe, f'{handset}/failsafe', self._on_failsafe,
                                     failsafe_qos, callback_group=subs)
        self.create_service(Trigger, '~/release_gate', self._release_gate,
                            callback_group=ReentrantCallbackGroup())
        self.link_pub = self.create_publisher(MavlinkLink, '~/link', 10)
        self.diagnostics = DiagnosticsUpdater(self, self.url, period_s=1.0)
        self.diagnostics.add('mavlink link', self._diag_link)
        self.diagnostics.add('last command', self._diag_command)
        self.create_timer(1.0, self._publish_link, callback_group=MutuallyExclusiveCallbackGroup())

        self.port = MavlinkPort(self.url, self.config.component_id, self._events.put,
                                self._on_port_error)
        self.port.sysid = self.config.system_id
        self._worker = threading.Thread(target=self._run, name='mavlink-core', daemon=True)
        self._worker.start()
        self.port.start()
        self.get_logger().info(
            f'MAVLink parachute component {self.config.system_id or "(system id learned)"}/'
            f'{self.config.component_id} on {self.url}; parachute node: {ns}; motor stop '
            f'before release: {self.config.stop_motors_before_release} (wait '
            f'{self.config.motor_stop_wait_s:.2f} s)')

    # -- the core's thread --------------------------------------------------------------------

    def _run(self) -> None:
        while not self._stopping.is_set():
            now = time.monotonic()
            timeout = min(max(self.core.next_deadline() - now, 0.0), 0.5)
            try:
                event = self._events.get(timeout=timeout)
            except queue.Empty:
                event = c.Tick()
            try:
                actions = self.core.handle(event, time.monotonic())
                for action in actions:
                    self._do(action)
                self._expire_calls()
                self._snapshot()
            except Exception as exc:  # noqa: BLE001 - the link's thread never dies
                self.get_logger().error(f'autopilot link: {exc!r}', throttle_duration_sec=5.0)

    def _do(self, action: Any) -> None:
        if isinstance(action, c.Send):
            if self.port.send(action.kind, action.fields, self.core.sysid or 0):
                self._write_errors = 0
        elif isinstance(action, c.Call):
            self._call(action)
        elif isinstance(action, c.AnswerGate):
            with self._gates_lock:
                gate = self._gates.get(action.gate_id)
            if gate is not None:
                gate[1].extend([action.stopped, action.message])
                gate[0].set()
        elif isinstance(action, c.Log):
            log_at(self.get_logger(), action.level, action.text)

    def _call(self, action: c.Call) -> None:
        client = self._parachute_clients[action.service]
        if not client.service_is_ready():
            self._events.put(c.Answer(action.call_id, None,
                                      f'{client.srv_name} is not available'))
            return
        request = client.srv_type.Request()
        for key, value in action.args.items():
            setattr(request, key, value)
        if action.service == 'deploy':
            request.confirm = 'DEPLOY'
        future = client.call_async(request)
        self._calls[action.call_id] = (client, future, time.monotonic() + action.timeout_s)

        def done(fut: Any, call_id: int = action.call_id) -> None:
            try:
                reply = fut.result()
                answer = c.Answer(call_id, bool(reply.success), str(reply.message))
            except Exception as exc:  # noqa: BLE001 - a failed call is an answer "none"
                answer = c.Answer(call_id, None, f'call failed: {exc!r}')
            self._events.put(answer)
        future.add_done_callback(done)

    def _expire_calls(self) -> None:
        now = time.monotonic()
        for call_id, (client, future, deadline) in list(self._calls.items()):
            if future.done():
                del self._calls[call_id]
            elif now >= deadline:
                del self._calls[call_id]
                client.remove_pending_request(future)
                self._events.put(c.Answer(call_id, None, f'no answer from {client.srv_name}'))

    def _on_port_error(self, text: str) -> None:
        self._write_errors += 1
        self.get_logger().warning(f'MAVLink: {text}', throttle_duration_sec=5.0)

    # -- ROS callbacks ------------------------------------------------------------------------

    def _on_status(self, msg: ParachuteStatus) -> None:
        state = (bool(msg.online), bool(msg.armed), bool(msg.triggered))
        if state != self._last_state:  # the stream runs at the module's rate: changes only
            self._last_state = state
            self._events.put(c.ParachuteState(*state))

    def _on_trigger_event(self, msg: TriggerEvent) -> None:
        self._events.put(c.Deployed(msg.source_name or 'unknown'))

    def _on_trigger_request(self, msg: TriggerRequest) -> None:
        self._events.put(c.RequestDecided(msg.decision_name, msg.reason))

    def _on_failsafe(self, msg: Failsafe) -> None:
        self._events.put(c.Failsafe(msg.action, msg.reason))

    def _release_gate(self, request: Trigger.Request, response: Trigger.Response) -> Any:
        """``~/release_gate``: stop the motors; answer by motor_stop_wait_s at the latest."""
        try:
            gate_id = next(self._gate_ids)
            done = threading.Event()
            result: list = []
            with self._gates_lock:
                self._gates[gate_id] = (done, result)
            self._events.put(c.GateRequest(gate_id))
            if done.wait(self.config.motor_stop_wait_s + GATE_MARGIN_S):
                response.success, response.message = bool(result[0]), str(result[1])
            else:
                response.success = False
                response.message = 'the autopilot link did not decide in time'
            with self._gates_lock:
                self._gates.pop(gate_id, None)
        except Exception as exc:  # noqa: BLE001 - a gate answers, whatever happens
            response.success, response.message = False, f'internal error: {exc!r}'
        return response

    # -- ~/link and /diagnostics --------------------------------------------------------------

    def _snapshot(self) -> None:
        core = self.core
        now = time.monotonic()
        snap = dict(
            port_open=core.port_open, port_error=core.port_error, system_id=core.sysid or 0,
            system_status=core.status_sent, autopilot_heard=not core.autopilot_lost,
            autopilot=core.autopilot or (0, 0), age=core.autopilot_age(now), at=now,
            counts=dict(core.counts), acks=dict(core.acks), last_command=core.last_command,
            last_level=core.last_command_level,
            ignored=sum(core.ignored_autopilots.values()),
            ignored_ids=sorted(core.ignored_autopilots))
        with self._snapshot_lock:
            changed = self._link_snapshot.get('autopilot_heard') != snap['autopilot_heard']
            self._link_snapshot = snap
        if changed:
            self._publish_link()
            self.diagnostics.force_update()

    def _snap(self) -> Dict[str, Any]:
        with self._snapshot_lock:
            return dict(self._link_snapshot)

    def _publish_link(self) -> None:
        snap = self._snap()
        if not snap:
            return
        age = snap['age'] + (time.monotonic() - snap['at']) if not math.isnan(snap['age']) \
            else math.nan
        msg = MavlinkLink()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.url = self.url
        msg.port_open = snap['port_open']
        msg.port_error = snap['port_error']
        msg.system_id = snap['system_id']
        msg.component_id = self.config.component_id
        msg.system_status = snap['system_status']
        msg.autopilot_heard = snap['autopilot_heard']
        msg.autopilot_system_id, msg.autopilot_component_id = snap['autopilot']
        msg.autopilot_heartbeat_age_s = age
        counts, acks = snap['counts'], snap['acks']
        msg.messages_received = counts['messages']
        msg.bad_data = counts['bad_data']
        msg.ignored_autopilot_heartbeats = snap['ignored']
        msg.commands_received = counts['commands']
        msg.commands_ignored = counts['ignored']
        msg.acks_accepted = acks['ACCEPTED']
        msg.acks_in_progress = acks['IN_PROGRESS']
        msg.acks_denied = acks['DENIED']
        msg.acks_failed = acks['FAILED']
        msg.acks_unsupported = acks['UNSUPPORTED']
        msg.motor_stops_sent = counts['motor_stops']
        msg.motor_stops_confirmed = counts['motor_stops_confirmed']
        msg.last_command = snap['last_command']
        self.link_pub.publish(msg)

    def _diag_link(self, stat: Status) -> None:
        snap = self._snap()
        if not snap:
            stat.summary(WARN, 'starting')
            return
        if not snap['port_open']:
            stat.summary(ERROR, f'MAVLink port not open: {snap["port_error"]}')
        elif not snap['autopilot_heard']:
            age = snap['age']
            stat.summary(ERROR, 'no autopilot heartbeat ever' if math.isnan(age) else
                         f'no autopilot heartbeat for {age:.1f} s')
        else:
            stat.summary(OK, f'autopilot {snap["autopilot"][0]}/{snap["autopilot"][1]} heard')
        if snap['counts']['bad_data']:
            stat.add('bad_data', snap['counts']['bad_data'])
        if snap['ignored']:
            stat.merge_summary(WARN, f'heartbeats of other autopilots ignored (system ids '
                                     f'{snap["ignored_ids"]})')
        stat.add('url', self.url)
        stat.add('system_id', snap['system_id'])
        stat.add('system_status', c.STATUS_NAMES.get(snap['system_status']))
        stat.add('autopilot_heartbeat_age_s', snap['age'])
        stat.add('messages_received', snap['counts']['messages'])
        stat.add('bad_data', snap['counts']['bad_data'])
        stat.add('write_errors', self._write_errors)

    def _diag_command(self, stat: Status) -> None:
        snap = self._snap()
        if not snap or not snap['last_command']:
            stat.summary(OK, 'no DO_PARACHUTE received')
            return
        level = {0: OK, 1: WARN, 2: ERROR}[snap['last_level']]
        stat.summary(level, snap['last_command'][:200])
        stat.add('commands_received', snap['counts']['commands'])
        stat.add('commands_ignored', snap['counts']['ignored'])
        for name, count in snap['acks'].items():
            stat.add(f'acks_{name.lower()}', count)
        stat.add('motor_stops_sent', snap['counts']['motor_stops'])
        stat.add('motor_stops_confirmed', snap['counts']['motor_stops_confirmed'])

    def on_shutdown(self) -> None:
        """Stop the core's thread and close the port."""
        self._stopping.set()
        self._events.put(c.Tick())
        self._worker.join(2.0)
        self.port.stop()


def main(args: Optional[list] = None) -> int:
    """Run the autopilot link until Ctrl-C."""
    return run_node(ParachuteMavlinkNode, args, threads=6)


if __name__ == '__main__':
    import sys
    sys.exit(main())
