"""ROS 2 node of the Desheng servo bus: ``servo_bus_node`` (default node name ``servo_bus``).

A thin adapter around :class:`~desheng_servo_ros.core.ServoBusCore`, which owns the bus, the read
loop and every rule: parameters become its config, services and ``~/command`` become its calls,
its snapshots become ``joint_states`` and ``~/servo_states`` (``messages.py``, published as
serialized bytes, stamped with the time the positions came off the wire), its health becomes
``/diagnostics``. The contract is the "Servo bus driver" section of the README; decisions
are in ``docs/protocols.md`` (Driver decisions).
"""

from __future__ import annotations

import sys
import time
from typing import Any, Callable, Dict, List, Optional, Tuple

from desheng_servo_ros import messages
from desheng_servo_ros.core import BusSnapshot, Health, Result, ServoBusConfig, ServoBusCore
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from uav_serial_common.diagnostics import DiagnosticsUpdater, Status
from uav_serial_common.executor import InlineCallbackGroup
from uav_serial_common.node_main import run_node
from uav_serial_common.params import declare_and_check, ParameterBinding, ParamSpec
from uav_serial_common.text import clip
from uav_serial_drivers.msg import ServoCommand, ServoStateArray
from uav_serial_drivers.srv import (FactoryReset, GoToPreset, ReadRegister, ScanBus, SetId,
                                    SetTorque, WritePositions, WriteRegister)

SWITCH_INTERVAL_S = 0.0005
DIAGNOSTICS_PERIOD_S = 1.0
DIAGNOSTICS_MIN_INTERVAL_S = 0.1

PARAMETERS = (
    ParamSpec('port', '/dev/ttyUSB1', 'serial device or pyserial URL', read_only=True),
    ParamSpec('baud', 115200, 'bus baud rate (8N1)', read_only=True, int_range=(1200, 4000000)),
    ParamSpec('servo_ids', Parameter.Type.INTEGER_ARRAY,
              'servo ids 1..250 on the bus; empty = scan 1..250 at start', startup_only=True),
    ParamSpec('joint_names', Parameter.Type.STRING_ARRAY,
              'joint name per servo id; empty = servo_<id>', startup_only=True),
    ParamSpec('ticks_per_revolution', 4096, 'position ticks per full turn',
              int_range=(1, 1000000), startup_only=True),
    ParamSpec('zero_tick', 2048, 'tick at 0 rad', int_range=(0, 4095), startup_only=True),
    ParamSpec('publish_rate_hz', 50.0, 'joint_states / servo_states rate [Hz]; the loop runs as '
              'fast as the bus allows when it cannot keep up', float_range=(0.1, 1000.0)),
    ParamSpec('telemetry_period_s', 1.0,
              'period of the current/temperature/torque read per servo [s]',
              float_range=(0.0, 3600.0)),
    ParamSpec('default_move_time_ms', 0, 'run time when a command gives -1 [ms]; 0 = fastest',
              int_range=(0, 65535)),
    ParamSpec('response_timeout_ms', 0.0,
              'wait for a reply beyond its wire time [ms]; 0 = derived from the port (a few ms '
              'on a pty, an on-board UART or a 1 ms USB adapter; 2 latency timer periods + 2 ms '
              'otherwise)', float_range=(0.0, 10000.0)),
    ParamSpec('max_retries', 1, 'retries per transaction', int_range=(0, 10)),
    ParamSpec('torque_on_start', False, 'turn torque on for every servo at start',
              startup_only=True),
    ParamSpec('torque_off_on_shutdown', True, 'broadcast torque off as the last act on shutdown'),
    ParamSpec('frame_id', 'servo_bus', 'header frame_id of published messages'),
    ParamSpec('adjust_latency_timer', True, 'on every open of a USB serial adapter, lower its '
              'latency timer to 1 ms where the driver may (low-latency mode, else sysfs)',
              read_only=True),
)


EXECUTOR_THREADS = 4
"""Threads of the executor's pool (``main()``; the tests' in-process driver reads it)."""


class StartupError(RuntimeError):
    """A configuration the node cannot run with."""


class ServoBusNode(Node):
    """Driver of one bus of Desheng servos."""

    def __init__(self, node_name: str = 'servo_bus', **node_options: Any) -> None:
        super().__init__(node_name, **node_options)
        values = declare_and_check(self, PARAMETERS)
        self.frame_id = values['frame_id']
        self._joints = messages.JointStatePacker(self.frame_id)
        self._states = messages.ServoStatesPacker(self.frame_id)
        # Stamps come from the wall clock (as the node's clock would give them) unless the node
        # runs on simulated time.
        self._sim_time = bool(self.get_parameter('use_sim_time').value)
        log = self.get_logger()
        try:
            self.core = ServoBusCore(ServoBusConfig.from_values(values), logger=log,
                                     on_cycle=self._publish, on_change=self._changed,
                                     on_servos=self._sync_servo_tasks)
        except ValueError as exc:
            raise StartupError(str(exc)) from None
        self.joint_pub = self.create_publisher(JointState, 'joint_states', 10)
        self.state_pub = self.create_publisher(ServoStateArray, '~/servo_states', 10)
        self.diagnostics = DiagnosticsUpdater(self, values['port'], DIAGNOSTICS_PERIOD_S,
                                              DIAGNOSTICS_MIN_INTERVAL_S)
        self.diagnostics.add('bus', lambda stat: _fill(stat, self.core.bus_health()))
        self._servo_tasks: List[str] = []
        self._sync_servo_tasks()
        ParameterBinding(self, PARAMETERS, apply=self._apply)

        # A command only queues targets for the core (or hands them to the running read chain):
        # it never waits on the bus, so it runs on the executor's thread, with no hand-off.
        self.create_subscription(ServoCommand, '~/command', self._on_command, 10,
                                 callback_group=InlineCallbackGroup())
        core = self.core
        services = MutuallyExclusiveCallbackGroup()
        for srv_type, name, call in (
                (WritePositions, '~/write_positions', lambda r: core.write_positions(
                    r.names, r.ids, r.positions, r.move_time_ms, r.staged)),
                (SetTorque, '~/set_torque', lambda r: core.set_torque(r.ids, r.enable)),
                (ReadRegister, '~/read_register', lambda r: core.read_register(
                    r.id, r.register_name, r.address, r.length)),
                (WriteRegister, '~/write_register', lambda r: core.write_register(
                    r.id, r.register_name, r.value)),
                (ScanBus, '~/scan', lambda r: core.scan(r.first_id, r.last_id)),
                (GoToPreset, '~/go_to_preset', lambda r: core.go_to_preset(r.ids, r.preset)),
                (SetId, '~/set_id', lambda r: core.set_id(r.id, r.new_id)),
                (FactoryReset, '~/factory_reset', lambda r: core.factory_reset(
                    r.id, r.confirm))):
            self.create_service(srv_type, name, self._serve(name, call), callback_group=services)
        # The emergency stop has a group of its own: it never waits behind another service.
        self.create_service(Trigger, '~/emergency_stop',
                            self._serve('~/emergency_stop', lambda r: core.emergency_stop()),
                            callback_group=MutuallyExclusiveCallbackGroup())
        core.start()
        ids = ', '.join(str(j.id) for j in core.servos) or 'scan 1..250'
        log.info(f'servo bus on {values["port"]} at {values["baud"]} baud, servos: {ids}')

    # -- parameters, commands, services ---------------------------------------------------------

    def _apply(self, changes: Dict[str, Any]) -> None:
        if 'frame_id' in changes:
            self.frame_id = changes['frame_id']
            self._joints.set_frame_id(self.frame_id)
            self._states.set_frame_id(self.frame_id)
        self.core.update_config(changes)

    def _on_command(self, msg: ServoCommand) -> None:
        try:
            result = self.core.command(msg.names, msg.ids, msg.positions, msg.move_time_ms)
        except Exception as exc:  # noqa: BLE001 - no message may end the process
            result = Result.failed(f'internal error: {exc!r}', cause='internal')
        if not result.ok:
            self.get_logger().warning(f'~/command refused, nothing sent: {clip(result.message)}',
                                      throttle_duration_sec=5.0)

    def _serve(self, name: str, call: Callable[[Any], Result]) -> Callable[[Any, Any], Any]:
        """Wrap a core call as a service handler: one error path for every service."""
        def handler(request: Any, response: Any) -> Any:
            try:
                result = call(request)
                for key, value in (result.value or {}).items():
                    setattr(response, key, value)
            except Exception as exc:  # noqa: BLE001 - the core answers; this is a last resort
                self.get_logger().error(f'{name} failed: {exc!r}')
                result = Result.failed(f'internal error: {exc!r}', cause='internal')
            response.success = result.ok
            response.message = clip(result.message)
            return response
        return handler

    # -- core callbacks -------------------------------------------------------------------------

    def _publish(self, snapshot: BusSnapshot) -> None:
        # The core's reporter thread, after every cycle (and while the port is away).
        sec, nanosec = self._stamp(snapshot.read_at)
        if snapshot.port_open:
            self.joint_pub.publish(self._joints.pack(snapshot, sec, nanosec))
        self.state_pub.publish(self._states.pack(snapshot, sec, nanosec))

    def _stamp(self, read_at: Optional[float]) -> Tuple[int, int]:
        """Return (sec, nanosec) of the moment `read_at` (monotonic), or of now if None.

        The messages carry the time their oldest position came off the wire, not the time
        they are published (docs/protocols.md, "Stamps").
        """
        now_ns = self.get_clock().now().nanoseconds if self._sim_time else time.time_ns()
        if read_at is not None:
            now_ns -= int((time.monotonic() - read_at) * 1e9)
        return divmod(now_ns, 1_000_000_000)

    def _changed(self) -> None:
        self.diagnostics.force_update()

    def _sync_servo_tasks(self) -> None:
        """Give each servo a diagnostics status, named after its joint and id."""
        for task in self._servo_tasks:
            self.diagnostics.remove(task)
        self._servo_tasks = []
        for joint in self.core.servos:
            task = f'{joint.name} (id {joint.id})'
            self.diagnostics.add(task, lambda stat, i=joint.id: _fill(
                stat, self.core.servo_health(i)))
            self._servo_tasks.append(task)

    def on_shutdown(self) -> None:
        """Stop the read loop, then broadcast torque off as the very last frame (if enabled)."""
        self.core.stop()


def _fill(stat: Status, health: Health) -> None:
    stat.summary(health.level, health.message)
    for key, value in health.values:
        stat.add(key, value)


def main(args: Optional[List[str]] = None) -> int:
    """Run ``servo_bus_node``."""
    # The hot path hands the GIL between the reader thread and the read loop on every reply;
    # the default 5 ms switch interval would add up to that much to each transaction.
    return run_node(ServoBusNode, args, threads=EXECUTOR_THREADS,
                    switch_interval_s=SWITCH_INTERVAL_S)


if __name__ == '__main__':
    sys.exit(main())
