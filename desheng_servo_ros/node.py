"""ROS 2 node of the Desheng servo bus: ``servo_bus_node`` (default node name ``servo_bus``).

The read loop runs in its own thread (one READ per servo per cycle, telemetry spread over cycles)
and publishes ``joint_states`` and ``~/servo_states``. Commands and services take the bus between
two reads through the priority lock of :class:`~desheng_servo_ros.link.ServoBusLink`; the
emergency stop overtakes everything. The contract is the "Servo bus driver" section of
``ros-api.md``; decisions where it is silent are in ``docs/protocols.md`` (Driver decisions).
"""

from __future__ import annotations

from contextlib import contextmanager
import math
import sys
import threading
import time
from typing import Iterator, List, Optional, Sequence, Tuple

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.link import (BusBusy, LinkDown, LinkError, LinkTimeout, PRIORITY_LOOP,
                                    PRIORITY_SERVICE, PRIORITY_URGENT, ReadItem, ServoBusLink)
from desheng_servo_ros.registers import (by_address, by_name, decode_block, decode_value,
                                         encode_value, RegisterError)
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from uav_serial_common.node_main import run_node
from uav_serial_drivers.msg import ServoCommand, ServoState, ServoStateArray
from uav_serial_drivers.srv import (FactoryReset, GoToPreset, ReadRegister, ScanBus, SetId,
                                    SetTorque, WritePositions, WriteRegister)

# A servo is offline after this many transactions in a row failed (each with its retries).
OFFLINE_AFTER_FAILURES = 3
# An offline servo is probed this often (one READ without retries), so it costs little bus time.
REPROBE_PERIOD_S = 1.0
# Telemetry READ: 0x28 (torque) .. 0x3F (temperature) in one transaction.
TELEMETRY_ADDRESS = 0x28
TELEMETRY_LENGTH = 0x3F - 0x28 + 1
POSITION_ADDRESS = 0x38
POSITION_LENGTH = 4
SCAN_RETRY_S = 5.0
DIAGNOSTICS_PERIOD_S = 1.0
DIAGNOSTICS_MIN_INTERVAL_S = 0.1
PAUSE_TIMEOUT_S = 2.0
TORQUE_ADDRESS = 0x28
ID_ADDRESS = 0x05
RUN_PRESET_ADDRESS = 0x3C
ALL_IDS = (proto.MIN_ID, proto.MAX_ID)
SWITCH_INTERVAL_S = 0.0005
# Replies beyond the requests of one id within a diagnostics period that mean "two servos share
# this id" (S24), and how long the fault is reported after the last sign of it.
DUPLICATE_SURPLUS = 2
DUPLICATE_HOLD_S = 5.0

# Parameters that shape the servo list or the units: fixed for the life of the node.
_STARTUP_ONLY = ('servo_ids', 'joint_names', 'ticks_per_revolution', 'zero_tick',
                 'torque_on_start')


class _Servo:
    """What the node knows about one servo (written by the read loop, read by everyone)."""

    __slots__ = ('id', 'name', 'index', 'read_frame', 'telemetry_frame', 'online', 'seen',
                 'failures', 'error_count', 'position_ticks', 'position_rad', 'speed_raw',
                 'velocity', 'current_ma', 'temperature_c', 'status', 'torque_enabled',
                 'next_telemetry', 'next_probe', 'direction', 'telemetry_started',
                 'surplus_mark', 'duplicate_until')

    def __init__(self, servo_id: int, name: str, index: int) -> None:
        self.id = servo_id
        self.name = name
        self.index = index
        self.read_frame = proto.encode_read(servo_id, POSITION_ADDRESS, POSITION_LENGTH)
        self.telemetry_frame = proto.encode_read(servo_id, TELEMETRY_ADDRESS, TELEMETRY_LENGTH)
        self.online = False
        self.seen = False
        self.failures = 0
        self.error_count = 0
        self.position_ticks = 0
        self.position_rad = math.nan
        self.speed_raw = 0
        self.velocity = 0.0
        self.current_ma = math.nan
        self.temperature_c = math.nan
        self.status = 0
        self.torque_enabled = False
        self.next_telemetry = 0.0
        self.next_probe = 0.0
        self.direction = 1.0
        self.telemetry_started = False
        self.surplus_mark: Optional[int] = None
        self.duplicate_until = 0.0

    @property
    def faults(self) -> List[str]:
        """Names of the documented fault bits set in the last status byte (S4)."""
        out = []
        if self.status & proto.STATUS_OVERLOAD:
            out.append('overload')
        if self.status & proto.STATUS_OVER_TEMPERATURE:
            out.append('over-temperature')
        if self.status & proto.STATUS_VOLTAGE_FAULT:
            out.append('voltage fault')
        return out


def _describe(desc: str, *, read_only: bool = False, int_range: Optional[Tuple[int, int]] = None,
              float_range: Optional[Tuple[float, float]] = None) -> ParameterDescriptor:
    d = ParameterDescriptor(description=desc, read_only=read_only)
    if int_range is not None:
        d.integer_range = [IntegerRange(from_value=int_range[0], to_value=int_range[1], step=1)]
    if float_range is not None:
        d.floating_point_range = [FloatingPointRange(from_value=float_range[0],
                                                     to_value=float_range[1], step=0.0)]
    return d


class _ReadCycles:
    """The read loop's cycles (one READ per active servo) as a plan for a chain of READs.

    The bus link asks for each next READ the moment the previous reply is in, so consecutive
    cycles follow each other on the wire without a gap when ``publish_rate_hz`` asks for more
    than the bus carries; otherwise the chain ends after a cycle and the read loop waits for
    the next one. Runs on the link's reader thread (replies) and the read loop (timeouts).
    """

    def __init__(self, node: 'ServoBusNode') -> None:
        self.node = node
        self.plan: List[Tuple[_Servo, bool]] = []
        self.pos = 0
        self.started = 0.0
        self.next_cycle = time.monotonic()

    @property
    def in_cycle(self) -> bool:
        """Whether a cycle has READs left to send."""
        return self.pos < len(self.plan)

    def reset(self) -> None:
        """Drop the cycle in progress (the servo list or the port changed); next one is due."""
        self.plan = []
        self.pos = 0
        self.next_cycle = time.monotonic()

    def next_read(self) -> Optional[ReadItem]:
        """Return the next READ of this cycle or of the next one when it is due, else None."""
        node = self.node
        if node._pause or not node._running:
            return None
        if self.pos >= len(self.plan) and not self._start_cycle():
            return None
        s, telemetry = self.plan[self.pos]
        self.pos += 1
        tag = (s, telemetry, self.started, self.pos == len(self.plan))
        # A servo that already failed as often as it takes to be offline is probed without
        # retries, so a missing servo costs little bus time.
        retries = node.bus.max_retries if s.failures < OFFLINE_AFTER_FAILURES else 0
        if telemetry:
            return s.telemetry_frame, s.id, TELEMETRY_LENGTH, retries, tag
        return s.read_frame, s.id, POSITION_LENGTH, retries, tag

    def on_read(self, tag: Tuple[_Servo, bool, float, bool],
                reply: Optional[proto.Reply]) -> None:
        """Take the result of one READ; the last one of a cycle completes it."""
        s, telemetry, started, last = tag
        self.node._on_read(s, telemetry, started, reply)
        if last:
            self.node._cycle_done()

    def _start_cycle(self) -> bool:
        node = self.node
        now = time.monotonic()
        if now < self.next_cycle:
            return False
        period = 1.0 / node.publish_rate_hz
        if now - self.next_cycle > period:
            if not node._behind_logged and self.started:
                node._behind_logged = True
                node.get_logger().warning(
                    f'the bus cannot keep up with publish_rate_hz {node.publish_rate_hz:g} '
                    f'({len(node.servos)} servos at {node.baud} baud): publishing as fast as '
                    'it reads')
            self.next_cycle = now
        self.next_cycle += period
        self.started = now
        self.plan = node._plan_cycle(now)
        self.pos = 0
        if not self.plan:
            # Every servo is offline and none is due for a probe: publish that all the same.
            node._cycle_done()
            return False
        return True


class StartupError(RuntimeError):
    """A configuration the node cannot run with."""


class ServoBusNode(Node):
    """Driver of one bus of Desheng servos."""

    def __init__(self, node_name: str = 'servo_bus') -> None:
        super().__init__(node_name)
        self._declare_parameters()
        p = self.get_parameter
        self.port = p('port').value
        self.baud = p('baud').value
        self.frame_id = p('frame_id').value
        self.ticks_per_rev = p('ticks_per_revolution').value
        self.zero_tick = p('zero_tick').value
        self.publish_rate_hz = p('publish_rate_hz').value
        self.telemetry_period_s = p('telemetry_period_s').value
        self.default_move_time_ms = p('default_move_time_ms').value
        self.torque_on_start = p('torque_on_start').value
        self.torque_off_on_shutdown = p('torque_off_on_shutdown').value
        self._rad_per_tick = 2.0 * math.pi / self.ticks_per_rev
        self.servos: List[_Servo] = self._servo_list(self._array('servo_ids'),
                                                     self._array('joint_names'))
        self._scan_at_start = not self.servos

        self.bus = ServoBusLink(self.port, self.baud,
                                response_timeout_ms=p('response_timeout_ms').value,
                                max_retries=p('max_retries').value,
                                on_connection=self._on_connection, logger=self.get_logger())
        self._running = True
        self._pause = 0
        self._loop_idle = False
        self._pause_cond = threading.Condition()
        self._cycle_count = 0
        self._cycle_rate_hz = 0.0
        self._rate_mark = (time.monotonic(), 0)
        self._behind_logged = False
        self._diag_dirty = True
        self._last_diag = 0.0
        self._diag_lock = threading.Lock()
        self._link_state = 'opening'
        self._startup_done = False

        self.joint_pub = self.create_publisher(JointState, 'joint_states', 10)
        self.state_pub = self.create_publisher(ServoStateArray, '~/servo_states', 10)
        self.diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)

        cmd_group = MutuallyExclusiveCallbackGroup()
        srv_group = MutuallyExclusiveCallbackGroup()
        estop_group = MutuallyExclusiveCallbackGroup()
        diag_group = MutuallyExclusiveCallbackGroup()
        self.create_subscription(ServoCommand, '~/command', self._on_command, 10,
                                 callback_group=cmd_group)
        for srv_type, name, handler in (
                (WritePositions, '~/write_positions', self._srv_write_positions),
                (SetTorque, '~/set_torque', self._srv_set_torque),
                (ReadRegister, '~/read_register', self._srv_read_register),
                (WriteRegister, '~/write_register', self._srv_write_register),
                (ScanBus, '~/scan', self._srv_scan),
                (GoToPreset, '~/go_to_preset', self._srv_go_to_preset),
                (SetId, '~/set_id', self._srv_set_id),
                (FactoryReset, '~/factory_reset', self._srv_factory_reset)):
            self.create_service(srv_type, name, self._guarded(handler), callback_group=srv_group)
        self.create_service(Trigger, '~/emergency_stop', self._guarded(self._srv_emergency_stop),
                            callback_group=estop_group)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._on_diag_timer, callback_group=diag_group)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)

        self._pub_cond = threading.Condition()
        self._pub_due = False
        self._publisher = threading.Thread(target=self._publisher_main, name='servo-publisher',
                                           daemon=True)
        self._publisher.start()
        self.bus.start()
        self._loop = threading.Thread(target=self._loop_main, name='servo-read-loop',
                                      daemon=True)
        self._loop.start()
        ids = ', '.join(str(s.id) for s in self.servos) or 'scan 1..250'
        self.get_logger().info(f'servo bus on {self.port} at {self.baud} baud, servos: {ids}')

    # -- parameters ---------------------------------------------------------------------------

    def _declare_parameters(self) -> None:
        params = [
            ('port', '/dev/ttyUSB1', _describe('serial device or pyserial URL', read_only=True)),
            ('baud', 115200, _describe('bus baud rate (8N1)', read_only=True,
                                       int_range=(1200, 4000000))),
            ('servo_ids', Parameter.Type.INTEGER_ARRAY,
             _describe('servo ids 1..250 on the bus; empty = scan 1..250 at start')),
            ('joint_names', Parameter.Type.STRING_ARRAY,
             _describe('joint name per servo id; empty = servo_<id>')),
            ('ticks_per_revolution', 4096, _describe('position ticks per full turn',
                                                     int_range=(1, 1000000))),
            ('zero_tick', 2048, _describe('tick at 0 rad', int_range=(0, 4095))),
            ('publish_rate_hz', 50.0, _describe(
                'joint_states / servo_states rate [Hz]; the loop runs as fast as the bus '
                'allows when it cannot keep up', float_range=(0.1, 1000.0))),
            ('telemetry_period_s', 1.0, _describe(
                'period of the current/temperature/torque read per servo [s]',
                float_range=(0.0, 3600.0))),
            ('default_move_time_ms', 0, _describe(
                'run time when a command gives -1 [ms]; 0 = fastest', int_range=(0, 65535))),
            ('response_timeout_ms', 0.0, _describe(
                'wait for a reply beyond its wire time [ms]; 0 = derived (34 ms)',
                float_range=(0.0, 10000.0))),
            ('max_retries', 1, _describe('retries per transaction', int_range=(0, 10))),
            ('torque_on_start', False, _describe('turn torque on for every servo at start')),
            ('torque_off_on_shutdown', True, _describe(
                'broadcast torque off as the last act on shutdown')),
            ('frame_id', 'servo_bus', _describe('header frame_id of published messages')),
        ]
        for name, default, descriptor in params:
            self.declare_parameter(name, default, descriptor)

    def _array(self, name: str) -> list:
        # An array parameter declared by type stays uninitialized when not given: empty.
        try:
            return list(self.get_parameter(name).value or [])
        except ParameterUninitializedException:
            return []

    def _servo_list(self, ids: List[int], names: List[str]) -> List[_Servo]:
        bad = [i for i in ids if not proto.is_servo_id(i)]
        if bad:
            raise StartupError(f'servo_ids must be 1..250, got {bad}')
        if len(set(ids)) != len(ids):
            raise StartupError(f'servo_ids lists an id twice: {ids}')
        if names and len(names) != len(ids):
            raise StartupError(
                f'joint_names has {len(names)} names but servo_ids has {len(ids)} ids: give one '
                'name per id, or no names (servo_<id>)')
        if not names:
            names = [f'servo_{i}' for i in ids]
        if len(set(names)) != len(names):
            raise StartupError(f'joint_names lists a name twice: {names}')
        return [_Servo(i, n, k) for k, (i, n) in enumerate(zip(ids, names))]

    def _on_set_parameters(self, params: List[Parameter]) -> SetParametersResult:
        for param in params:
            if param.name in _STARTUP_ONLY:
                return SetParametersResult(
                    successful=False, reason=f'{param.name} is read at start only; restart the '
                                             'node to change it')
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, params: List[Parameter]) -> None:
        for param in params:
            if param.name == 'publish_rate_hz':
                self.publish_rate_hz = param.value
                self._behind_logged = False
            elif param.name == 'telemetry_period_s':
                self.telemetry_period_s = param.value
            elif param.name == 'default_move_time_ms':
                self.default_move_time_ms = param.value
            elif param.name == 'response_timeout_ms':
                self.bus.response_timeout_ms = param.value
            elif param.name == 'max_retries':
                self.bus.max_retries = param.value
            elif param.name == 'torque_off_on_shutdown':
                self.torque_off_on_shutdown = param.value
            elif param.name == 'frame_id':
                self.frame_id = param.value

    # -- units --------------------------------------------------------------------------------

    def ticks_to_rad(self, ticks: int) -> float:
        """Convert a position in ticks to rad (REP-103, zero at ``zero_tick``)."""
        return (ticks - self.zero_tick) * self._rad_per_tick

    def rad_range(self) -> Tuple[float, float]:
        """Return the positions in rad that map into 0..4095 ticks."""
        return self.ticks_to_rad(proto.POSITION_MIN), self.ticks_to_rad(proto.POSITION_MAX)

    def rad_to_ticks(self, rad: float, name: str) -> int:
        """Convert rad to ticks; ValueError naming the servo when it maps outside 0..4095."""
        lo, hi = self.rad_range()
        if not math.isfinite(rad):
            raise ValueError(f'{name}: position {rad} is not a number')
        ticks = int(round(self.zero_tick + rad / self._rad_per_tick))
        if not proto.POSITION_MIN <= ticks <= proto.POSITION_MAX:
            raise ValueError(f'{name}: position {rad:.4f} rad is outside the valid range '
                             f'{lo:.4f}..{hi:.4f} rad (ticks 0..4095)')
        return ticks

    # -- servo lookup -------------------------------------------------------------------------

    def _by_id(self, servo_id: int) -> Optional[_Servo]:
        for s in self.servos:
            if s.id == servo_id:
                return s
        return None

    def _select(self, ids: Sequence[int]) -> List[_Servo]:
        """Servos of ``ids`` (empty = all configured); ValueError on unknown ids."""
        ids = list(ids)
        if not ids:
            if not self.servos:
                raise ValueError('no servos configured (yet)')
            return list(self.servos)
        unknown = [i for i in ids if self._by_id(i) is None]
        if unknown:
            raise ValueError(f'unknown servo id(s) {unknown}; configured: '
                             f'{[s.id for s in self.servos]} (~/scan lists the bus)')
        if len(set(ids)) != len(ids):
            raise ValueError(f'servo id listed twice in {ids}')
        return [self._by_id(i) for i in ids]

    def resolve_targets(self, names: Sequence[str], ids: Sequence[int],
                        positions: Sequence[float], move_time_ms: int
                        ) -> List[Tuple[int, int, int]]:
        """Turn a command into (id, ticks, ms) triples; ValueError says what is wrong."""
        names, ids, positions = list(names), list(ids), list(positions)
        if names and ids:
            raise ValueError('give names or ids, not both')
        if not names and not ids:
            raise ValueError('give the servos by names or by ids')
        keys = names or ids
        if len(keys) != len(positions):
            raise ValueError(f'{len(keys)} {"names" if names else "ids"} but '
                             f'{len(positions)} positions')
        if len(set(keys)) != len(keys):
            raise ValueError(f'a servo is listed twice: {keys}')
        if move_time_ms == -1:
            move_time_ms = self.default_move_time_ms
        if not 0 <= move_time_ms <= proto.RUN_TIME_MAX_MS:
            raise ValueError(f'move_time_ms must be -1 (default) or 0..65535, got {move_time_ms}')
        if names:
            by_name_ = {s.name: s for s in self.servos}
            unknown = [n for n in names if n not in by_name_]
            if unknown:
                raise ValueError(f'unknown joint name(s) {unknown}; known: {list(by_name_)}')
            servos = [by_name_[n] for n in names]
        else:
            servos = self._select(ids)
        return [(s.id, self.rad_to_ticks(rad, f'{s.name} (id {s.id})'), move_time_ms)
                for s, rad in zip(servos, positions)]

    # -- read loop ----------------------------------------------------------------------------

    def _loop_main(self) -> None:
        try:
            self._startup()
            self._run_cycles()
        except Exception as exc:  # noqa: BLE001 - report, never die silently
            self.get_logger().error(f'read loop stopped: {exc!r}')

    def _sleep(self, seconds: float, until_pause: bool = True) -> None:
        # In short steps, so a pause (scan, id change) or shutdown never waits for a slow rate.
        deadline = time.monotonic() + seconds
        while self._running and not (until_pause and self._pause) and \
                time.monotonic() < deadline:
            time.sleep(min(0.05, max(0.0, deadline - time.monotonic())))

    def _wait_connected(self) -> bool:
        while self._running:
            if self.bus.wait_connected(0.1):
                return True
        return False

    def _startup(self) -> None:
        while self._scan_at_start and self._running:
            if not self._wait_connected():
                return
            self.get_logger().info('servo_ids is empty: scanning ids 1..250')
            try:
                found = self.bus.scan(range(ALL_IDS[0], ALL_IDS[1] + 1), priority=PRIORITY_LOOP)
            except LinkError as exc:
                self.get_logger().warning(f'scan interrupted: {exc}')
                continue
            if found:
                self.servos = self._servo_list(found, [])
                self._scan_at_start = False
                self.get_logger().info(f'found servos {found}')
                break
            self.get_logger().error(
                f'no servo answers on {self.port} at {self.baud} baud: check power, wiring and '
                f'the baud parameter; scanning again in {SCAN_RETRY_S:.0f} s')
            self._sleep(SCAN_RETRY_S, until_pause=False)
        if self.torque_on_start and self._wait_connected():
            for s in self.servos:
                try:
                    self.bus.write(s.id, TORQUE_ADDRESS, b'\x01', PRIORITY_LOOP)
                    s.torque_enabled = True
                except LinkError as exc:
                    self.get_logger().warning(f'torque on at start: {s.name} (id {s.id}): {exc}')
        self._startup_done = True

    def _run_cycles(self) -> None:
        plan = _ReadCycles(self)
        while self._running:
            if self._pause:
                self._idle_while_paused()
                plan.reset()
                continue
            if not self.bus.connected:
                # Keep servo_states (all offline) and diagnostics coming while the port is away.
                self._publish(time.monotonic(), joints=False)
                self.bus.wait_connected(1.0 / self.publish_rate_hz)
                plan.reset()
                continue
            if not plan.in_cycle:
                delay = plan.next_cycle - time.monotonic()
                if delay > 0:
                    self._sleep(delay)
                    continue
            try:
                # Returns between cycles when the next one is not due yet, or early when a
                # command, a service or a pause wants the bus.
                self.bus.read_chain(plan, PRIORITY_LOOP)
            except (LinkDown, BusBusy):
                continue

    def _idle_while_paused(self) -> None:
        with self._pause_cond:
            while self._pause and self._running:
                self._loop_idle = True
                self._pause_cond.notify_all()
                self._pause_cond.wait(0.1)
            self._loop_idle = False

    @contextmanager
    def _loop_paused(self) -> Iterator[None]:
        """Hold the read loop between two cycles (scan, id change, reset)."""
        with self._pause_cond:
            self._pause += 1
            self._pause_cond.wait_for(lambda: self._loop_idle or not self._loop.is_alive(),
                                      PAUSE_TIMEOUT_S)
        try:
            yield
        finally:
            with self._pause_cond:
                self._pause -= 1
                self._pause_cond.notify_all()

    def _plan_cycle(self, now: float) -> List[Tuple[_Servo, bool]]:
        """Return (servo, telemetry READ?) for each servo to read in a cycle starting now."""
        plan = []
        for s in self.servos:
            if s.failures >= OFFLINE_AFTER_FAILURES:
                if now < s.next_probe:
                    continue
                s.next_probe = now + REPROBE_PERIOD_S
            plan.append((s, now >= s.next_telemetry))
        return plan

    def _on_read(self, s: _Servo, telemetry: bool, now: float,
                 reply: Optional[proto.Reply]) -> None:
        """Take the result of one READ of the cycle that started at ``now`` (the hot path)."""
        if reply is None:
            self._failed(s)
        elif telemetry:
            period = self.telemetry_period_s
            if s.telemetry_started or period <= 0:
                s.next_telemetry = now + period
            else:
                # Spread the telemetry reads of the servos evenly over the period.
                s.telemetry_started = True
                s.next_telemetry = now + period * (s.index + 1) / len(self.servos)
            self._update_telemetry(s, reply)
        else:
            p = reply.params
            self._update_position(s, (p[0] << 8) | p[1], (p[2] << 8) | p[3], reply.status)

    def _cycle_done(self) -> None:
        """Count a complete read cycle and have the publisher thread publish it."""
        self._cycle_count += 1
        # Building and publishing messages runs on its own thread, while the next cycle's
        # bytes are on the wire, instead of adding to every cycle.
        with self._pub_cond:
            self._pub_due = True
            self._pub_cond.notify()
        if self._cycle_count == OFFLINE_AFTER_FAILURES + 1:
            self._report_missing()

    def _update_position(self, s: _Servo, ticks: int, speed: int, status: int) -> None:
        if ticks != s.position_ticks and s.seen:
            s.direction = 1.0 if ticks > s.position_ticks else -1.0
        s.position_ticks = ticks
        s.position_rad = (ticks - self.zero_tick) * self._rad_per_tick
        s.speed_raw = speed
        s.velocity = s.direction * speed * self._rad_per_tick if speed else 0.0
        if status != s.status or not s.online:
            self._diag_dirty = True
            if not s.online and s.seen:
                self.get_logger().info(f'{s.name} (id {s.id}) is back online')
        s.status = status
        s.online = True
        s.seen = True
        s.failures = 0

    def _update_telemetry(self, s: _Servo, reply: proto.Reply) -> None:
        d = reply.params
        s.torque_enabled = d[0] != 0
        s.current_ma = float((d[6] << 8) | d[7])
        s.temperature_c = float(d[23])
        self._update_position(s, (d[16] << 8) | d[17], (d[18] << 8) | d[19], reply.status)

    def _failed(self, s: _Servo) -> None:
        s.error_count += 1
        s.failures += 1
        if s.failures == OFFLINE_AFTER_FAILURES and s.online:
            s.online = False
            self._diag_dirty = True
            self.get_logger().warning(
                f'{s.name} (id {s.id}) stopped answering: offline, probing it every '
                f'{REPROBE_PERIOD_S:g} s (check its power and cable; ~/scan lists the bus)')

    def _report_missing(self) -> None:
        missing = [s for s in self.servos if not s.seen]
        if missing and self.bus.connected:
            listed = ', '.join(f'{s.name} (id {s.id})' for s in missing)
            self.get_logger().warning(
                f'servo(s) {listed} do not answer on {self.port}: check their ids with the '
                '~/scan service, their power and wiring')

    def _publisher_main(self) -> None:
        while self._running:
            with self._pub_cond:
                if not self._pub_due:
                    self._pub_cond.wait(0.5)
                due, self._pub_due = self._pub_due, False
            if due and self._running:
                self._publish(time.monotonic())

    def _publish(self, now: float, joints: bool = True) -> None:
        try:
            stamp = self.get_clock().now().to_msg()
            js = JointState()
            js.header.stamp = stamp
            js.header.frame_id = self.frame_id
            states = ServoStateArray()
            states.header = js.header
            online = [s for s in self.servos if s.online]
            js.name = [s.name for s in online]
            js.position = [s.position_rad for s in online]
            js.velocity = [s.velocity for s in online]
            for s in self.servos:
                states.servos.append(ServoState(
                    id=s.id, name=s.name, online=s.online, position_ticks=s.position_ticks,
                    position_rad=s.position_rad, speed_raw=s.speed_raw, current_ma=s.current_ma,
                    temperature_c=s.temperature_c, status=s.status,
                    overload=bool(s.status & proto.STATUS_OVERLOAD),
                    over_temperature=bool(s.status & proto.STATUS_OVER_TEMPERATURE),
                    voltage_fault=bool(s.status & proto.STATUS_VOLTAGE_FAULT),
                    torque_enabled=s.torque_enabled, error_count=s.error_count))
            if joints:
                self.joint_pub.publish(js)
            self.state_pub.publish(states)
            if self._diag_dirty and now - self._last_diag >= DIAGNOSTICS_MIN_INTERVAL_S:
                self._publish_diagnostics()
        except Exception as exc:  # noqa: BLE001 - e.g. the context is shutting down
            if self._running:
                self.get_logger().warning(f'publish failed: {exc}', throttle_duration_sec=5.0)

    # -- diagnostics --------------------------------------------------------------------------

    def _on_connection(self, up: bool, reason: str) -> None:
        # Reader thread: only flags here, never a transaction.
        self._link_state = 'open' if up else f'closed: {reason}'
        if up:
            for s in self.servos:
                # Re-probe at full rate at once: the servos were most likely fine all along.
                s.failures = min(s.failures, OFFLINE_AFTER_FAILURES - 1)
                s.next_probe = 0.0
        else:
            for s in self.servos:
                s.online = False
        self._diag_dirty = True

    def _on_diag_timer(self) -> None:
        try:
            now = time.monotonic()
            t0, c0 = self._rate_mark
            if now > t0:
                self._cycle_rate_hz = (self._cycle_count - c0) / (now - t0)
            self._rate_mark = (now, self._cycle_count)
            self._check_duplicate_ids(now)
            self._publish_diagnostics()
        except Exception as exc:  # noqa: BLE001
            self.get_logger().warning(f'diagnostics failed: {exc}', throttle_duration_sec=5.0)

    def _check_duplicate_ids(self, now: float) -> None:
        for s in self.servos:
            surplus = self.bus.surplus_replies(s.id)
            mark, s.surplus_mark = s.surplus_mark, surplus
            if mark is None or surplus - mark < DUPLICATE_SURPLUS:
                continue
            if now >= s.duplicate_until:
                self.get_logger().error(
                    f'{s.name} (id {s.id}): more replies than requests, {surplus - mark} in '
                    f'{DIAGNOSTICS_PERIOD_S:g} s: two servos answer to id {s.id}; their replies '
                    'collide and its readings cannot be trusted. Connect them one at a time and '
                    'give each its own id with ~/set_id')
            s.duplicate_until = now + DUPLICATE_HOLD_S

    def bus_problem(self) -> Optional[Tuple[int, str]]:
        """Return (level, message) when the bus as a whole is in trouble."""
        if not self.bus.connected:
            msg = self.bus.link.last_error or f'{self.port} is not open'
            return DiagnosticStatus.ERROR, msg
        if not self._startup_done and self._scan_at_start:
            return DiagnosticStatus.WARN, 'scanning the bus for servos'
        if self.servos and not any(s.online for s in self.servos) and self._cycle_count > \
                OFFLINE_AFTER_FAILURES:
            stats = self.bus.link.stats
            if stats.bytes_in and not self.bus.decoder.frames_decoded:
                return DiagnosticStatus.ERROR, (
                    f'{stats.bytes_in} bytes received but not one valid reply: check the baud '
                    f'parameter ({self.baud}) against the servos\' baud rate')
            return DiagnosticStatus.ERROR, (
                'no servo answers: check power, wiring, the servo ids (try ~/scan) and the baud '
                f'parameter ({self.baud})')
        return None

    def _publish_diagnostics(self) -> None:
        with self._diag_lock:
            self._diag_dirty = False
            now = self._last_diag = time.monotonic()
            arr = DiagnosticArray()
            arr.header.stamp = self.get_clock().now().to_msg()
            servos = list(self.servos)
            online = sum(1 for s in servos if s.online)
            stats = self.bus.link.stats
            bus = DiagnosticStatus(name='servo_bus: bus', hardware_id=self.port)
            problem = self.bus_problem()
            offline = [s for s in servos if not s.online]
            duplicates = [s for s in servos if now < s.duplicate_until]
            if problem is not None:
                bus.level, bus.message = problem
                self.get_logger().warning(problem[1], throttle_duration_sec=10.0)
            elif duplicates:
                bus.level = DiagnosticStatus.ERROR
                bus.message = ('more than one servo answers to id(s) '
                               + ', '.join(str(s.id) for s in duplicates)
                               + ': give each servo its own id (~/set_id)')
            elif offline:
                bus.level = DiagnosticStatus.WARN
                bus.message = (f'{online}/{len(servos)} servos online; offline: '
                               + ', '.join(f'{s.name} (id {s.id})' for s in offline))
            else:
                bus.level = DiagnosticStatus.OK
                bus.message = f'{online}/{len(servos)} servos online'
            bus.values = [KeyValue(key=k, value=str(v)) for k, v in (
                ('port', self.port), ('baud', self.baud), ('link', self._link_state),
                ('online servos', f'{online}/{len(servos)}'),
                ('cycle rate [Hz]', f'{self._cycle_rate_hz:.1f}'),
                ('publish_rate_hz', f'{self.publish_rate_hz:g}'),
                ('transactions', self.bus.transactions),
                ('failed transactions', self.bus.failed_transactions),
                ('timeouts', stats.timeouts), ('retries', stats.retries),
                ('checksum errors', self.bus.checksum_errors),
                ('unexpected frames', self.bus.unexpected_frames),
                ('reconnects', stats.reconnects),
                ('bytes in', stats.bytes_in), ('bytes out', stats.bytes_out))]
            arr.status.append(bus)
            for s in servos:
                st = DiagnosticStatus(name=f'servo_bus: {s.name} (id {s.id})',
                                      hardware_id=self.port)
                faults = s.faults
                if now < s.duplicate_until:
                    st.level = DiagnosticStatus.ERROR
                    st.message = (f'{s.name} (id {s.id}): duplicate id, more than one servo '
                                  'answers; give each its own id (~/set_id)')
                elif not s.online:
                    st.level = DiagnosticStatus.ERROR
                    st.message = (f'{s.name} (id {s.id}) offline: no reply '
                                  f'({s.error_count} failed transactions); check its power, cable '
                                  'and id (~/scan)')
                elif faults:
                    st.level = DiagnosticStatus.WARN
                    st.message = f'{s.name} (id {s.id}): ' + ', '.join(faults)
                else:
                    st.level = DiagnosticStatus.OK
                    st.message = 'ok'
                st.values = [KeyValue(key=k, value=str(v)) for k, v in (
                    ('id', s.id), ('online', s.online), ('position [ticks]', s.position_ticks),
                    ('position [rad]', f'{s.position_rad:.4f}'),
                    ('current [mA]', s.current_ma), ('temperature [degC]', s.temperature_c),
                    ('status', f'0x{s.status:02X}'), ('torque', s.torque_enabled),
                    ('error count', s.error_count))]
                arr.status.append(st)
            self.diag_pub.publish(arr)

    # -- commands -----------------------------------------------------------------------------

    def _on_command(self, msg: ServoCommand) -> None:
        try:
            targets = self.resolve_targets(msg.names, msg.ids, msg.positions, msg.move_time_ms)
        except ValueError as exc:
            self.get_logger().warning(f'~/command refused, nothing sent: {exc}',
                                      throttle_duration_sec=5.0)
            return
        try:
            self.bus.sync_write_positions(targets, PRIORITY_SERVICE)
        except LinkError as exc:
            self.get_logger().warning(f'~/command not sent: {exc}', throttle_duration_sec=5.0)
        except Exception as exc:  # noqa: BLE001
            self.get_logger().error(f'~/command failed: {exc!r}', throttle_duration_sec=5.0)

    def _guarded(self, handler):
        """Wrap a service handler: no exception escapes, the response says what went wrong."""
        def call(request, response):
            try:
                return handler(request, response)
            except (ValueError, RegisterError) as exc:
                response.success = False
                response.message = f'refused: {exc}'
            except LinkDown as exc:
                response.success = False
                response.message = f'port not open: {exc}'
            except LinkError as exc:
                response.success = False
                response.message = f'bus error: {exc}'
            except Exception as exc:  # noqa: BLE001
                self.get_logger().error(f'service failed: {exc!r}')
                response.success = False
                response.message = f'internal error: {exc!r}'
            return response
        return call

    def _srv_write_positions(self, req: WritePositions.Request,
                             resp: WritePositions.Response) -> WritePositions.Response:
        targets = self.resolve_targets(req.names, req.ids, req.positions, req.move_time_ms)
        if not req.staged:
            self.bus.sync_write_positions(targets)
            resp.success = True
            resp.message = f'SYNC WRITE sent to {len(targets)} servo(s)'
            return resp
        for servo_id, ticks, ms in targets:
            try:
                self.bus.reg_write(servo_id, proto.TARGET_POSITION_ADDRESS,
                                   proto.encode_position_payload(ticks, ms))
            except LinkTimeout:
                resp.success = False
                resp.message = (f'servo {servo_id} did not acknowledge its REG WRITE; ACTION not '
                                'sent, nothing moved')
                return resp
        self.bus.action()
        resp.success = True
        resp.message = f'REG WRITE to {len(targets)} servo(s), then ACTION'
        return resp

    def _srv_set_torque(self, req: SetTorque.Request,
                        resp: SetTorque.Response) -> SetTorque.Response:
        servos = self._select(req.ids)
        value = b'\x01' if req.enable else b'\x00'
        failed = []
        for s in servos:
            try:
                self.bus.write(s.id, TORQUE_ADDRESS, value)
                back = self.bus.read(s.id, TORQUE_ADDRESS, 1).params[0] != 0
            except LinkTimeout:
                failed.append(f'{s.name} (id {s.id}) did not answer')
                continue
            s.torque_enabled = back
            if back != req.enable:
                failed.append(f'{s.name} (id {s.id}) reads back torque {"on" if back else "off"}')
        state = 'on' if req.enable else 'off'
        resp.success = not failed
        resp.message = (f'torque {state}: ' + '; '.join(failed)) if failed else \
            f'torque {state} for {len(servos)} servo(s), verified by read-back'
        return resp

    def _srv_emergency_stop(self, req: Trigger.Request,
                            resp: Trigger.Response) -> Trigger.Response:
        self.bus.write(proto.BROADCAST_ID, TORQUE_ADDRESS, b'\x00', PRIORITY_URGENT)
        for s in self.servos:
            s.torque_enabled = False
        self.get_logger().warning('emergency stop: torque off broadcast to every servo')
        resp.success = True
        resp.message = 'torque off broadcast to every servo (id 254)'
        return resp

    def _srv_read_register(self, req: ReadRegister.Request,
                           resp: ReadRegister.Response) -> ReadRegister.Response:
        if not proto.is_servo_id(req.id):
            raise ValueError(f'id must be 1..250 (READ cannot be broadcast), got {req.id}')
        if req.register_name:
            reg = by_name(req.register_name)
            if not reg.readable:
                raise ValueError(f'{reg.name} is a command register (write only); nothing to read')
            address, length = reg.address, reg.size
        else:
            address, length = req.address, req.length
            if not 1 <= length <= proto.MAX_READ_LENGTH or address + length > 256:
                raise ValueError(f'length must be 1..{proto.MAX_READ_LENGTH} and address + length '
                                 f'<= 256, got address 0x{address:02X} length {length}')
            try:
                reg = by_address(address)
                if reg.size != length or not reg.readable:
                    reg = None
            except RegisterError:
                reg = None
        reply = self.bus.read(req.id, address, length)
        data = bytes(reply.params)
        resp.data = list(data)
        resp.status = reply.status
        if reg is not None:
            value = decode_value(reg, data)
            resp.value = int.from_bytes(data, 'big', signed=reg.signed)
            resp.text = value if isinstance(value, str) else \
                f'{value} {reg.unit}'.strip()
            label = reg.name
        else:
            resp.value = int.from_bytes(data, 'big') if length <= 8 else 0
            block = decode_block(address, data)
            resp.text = ', '.join(f'{k}={v}' for k, v in block.items()) or data.hex(' ')
            label = f'{length} byte(s) at 0x{address:02X}'
        resp.success = True
        faults = proto.describe_status(reply.status)
        resp.message = f'servo {req.id} {label}: {resp.text}' + \
            (f' (status: {", ".join(faults)})' if faults else '')
        return resp

    def _srv_write_register(self, req: WriteRegister.Request,
                            resp: WriteRegister.Response) -> WriteRegister.Response:
        if not (proto.is_servo_id(req.id) or req.id == proto.BROADCAST_ID):
            raise ValueError(f'id must be 1..250 or 254 (broadcast), got {req.id}')
        reg = by_name(req.register_name)
        if reg.name == 'id':
            raise ValueError('change ids with ~/set_id (it checks the new id is free)')
        data = encode_value(reg, None if reg.address_only else int(req.value))
        self.bus.write(req.id, reg.address, data)
        if req.id == proto.BROADCAST_ID:
            resp.success = True
            resp.message = f'{reg.name} written to every servo (broadcast, no reply)'
            return resp
        if reg.address_only or not reg.readable:
            resp.success = True
            resp.message = f'servo {req.id} acknowledged {reg.name}'
            return resp
        back = decode_value(reg, bytes(self.bus.read(req.id, reg.address, reg.size).params))
        if reg.name == 'torque_enable':
            s = self._by_id(req.id)
            if s is not None:
                s.torque_enabled = bool(back)
        resp.success = back == req.value
        resp.message = f'servo {req.id} {reg.name} = {back} {reg.unit}'.strip() + \
            ('' if resp.success else f' after writing {req.value} (the servo did not take it)')
        return resp

    def _srv_scan(self, req: ScanBus.Request, resp: ScanBus.Response) -> ScanBus.Response:
        first, last = req.first_id, req.last_id
        if not (proto.is_servo_id(first) and proto.is_servo_id(last) and first <= last):
            raise ValueError(f'need 1 <= first_id <= last_id <= 250, got {first}..{last}')
        with self._loop_paused():
            surplus = [self.bus.surplus_replies(i) for i in range(first, last + 1)]
            found = self.bus.scan(range(first, last + 1))
            versions = []
            for servo_id in found:
                try:
                    data = bytes(self.bus.read(servo_id, 0x03, 2).params)
                    versions.append(decode_value(by_name('firmware_version'), data))
                except LinkTimeout:
                    versions.append('')
            # An id that answered one of these requests twice belongs to more than one servo.
            twice = [i for i in found if self.bus.surplus_replies(i) > surplus[i - first]]
        resp.ids = found
        resp.firmware_versions = versions
        resp.success = True
        resp.message = (f'found {len(found)} servo(s) in {first}..{last}: ' +
                        ', '.join(f'{i} ({v})' for i, v in zip(found, versions)))
        if twice:
            resp.message += ('; more than one servo answers to id(s) '
                             + ', '.join(map(str, twice))
                             + ': connect them one at a time and give each its own id')
        return resp

    def _srv_go_to_preset(self, req: GoToPreset.Request,
                          resp: GoToPreset.Response) -> GoToPreset.Response:
        if not 1 <= req.preset <= 3:
            raise ValueError(f'preset must be 1..3, got {req.preset}')
        servos = self._select(req.ids)
        failed = []
        for s in servos:
            try:
                self.bus.write(s.id, RUN_PRESET_ADDRESS + req.preset - 1)
            except LinkTimeout:
                failed.append(f'{s.name} (id {s.id})')
        resp.success = not failed
        resp.message = (f'no acknowledgement from {", ".join(failed)}' if failed else
                        f'{len(servos)} servo(s) running to preset {req.preset}')
        return resp

    def _answers(self, servo_id: int) -> bool:
        try:
            self.bus.ping(servo_id, retries=1)
            return True
        except LinkTimeout:
            return False

    def _srv_set_id(self, req: SetId.Request, resp: SetId.Response) -> SetId.Response:
        old, new = req.id, req.new_id
        if not (proto.is_servo_id(old) and proto.is_servo_id(new)):
            raise ValueError(f'id and new_id must be 1..250, got {old} -> {new}')
        if old == new:
            raise ValueError(f'servo already has id {new}')
        with self._loop_paused():
            if self._answers(new):
                raise ValueError(f'id {new} already answers on the bus; pick a free id (~/scan)')
            if not self._answers(old):
                resp.success = False
                resp.message = f'servo {old} does not answer; nothing changed'
                return resp
            self.bus.write(old, ID_ADDRESS, bytes((new,)))
            if not self._answers(new):
                resp.success = False
                resp.message = f'servo {old} acknowledged but does not answer at id {new}'
                return resp
            self._rename(old, new)
        resp.success = True
        resp.message = f'servo {old} now answers at id {new}'
        self.get_logger().info(resp.message)
        return resp

    def _rename(self, old: int, new: int) -> None:
        servos = []
        for s in self.servos:
            if s.id == old:
                name = f'servo_{new}' if s.name == f'servo_{old}' else s.name
                fresh = _Servo(new, name, s.index)
                servos.append(fresh)
            else:
                servos.append(s)
        self.servos = servos  # one assignment: readers see the old or the new list
        self._diag_dirty = True

    def _srv_factory_reset(self, req: FactoryReset.Request,
                           resp: FactoryReset.Response) -> FactoryReset.Response:
        if req.confirm != 'RESET':
            raise ValueError('confirm must be exactly "RESET"; nothing sent')
        if not proto.is_servo_id(req.id):
            raise ValueError(f'id must be 1..250 (RESET is never broadcast), got {req.id}')
        with self._loop_paused():
            self.bus.reset(req.id)
            at_own = self._answers(req.id)
            at_one = at_own if req.id == 1 else (not at_own and self._answers(1))
        resp.success = True
        if at_own:
            resp.message = f'servo {req.id} reset to factory settings (torque off)'
        elif at_one:
            resp.message = (f'servo {req.id} reset to factory settings and now answers at the '
                            'factory id 1; use ~/set_id to give it its id back')
        else:
            resp.message = f'servo {req.id} acknowledged RESET but no longer answers'
        return resp

    # -- shutdown -----------------------------------------------------------------------------

    def on_shutdown(self) -> None:
        """Stop the read loop, then broadcast torque off as the very last frame (if enabled)."""
        self._running = False
        with self._pause_cond:
            self._pause_cond.notify_all()
        with self._pub_cond:
            self._pub_cond.notify_all()
        self._loop.join(2.0)
        self._publisher.join(1.0)
        try:
            if self.torque_off_on_shutdown and self.bus.connected:
                self.bus.write(proto.BROADCAST_ID, TORQUE_ADDRESS, b'\x00', PRIORITY_URGENT)
                self.bus.drain()
        except LinkError as exc:
            print(f'torque off on shutdown failed: {exc}', file=sys.stderr)
        finally:
            self.bus.stop()


def main(args: Optional[List[str]] = None) -> int:
    """Run ``servo_bus_node``."""
    # The hot path hands the GIL between the reader thread and the read loop on every reply;
    # the default 5 ms switch interval would add up to that much to each transaction.
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    return run_node(ServoBusNode, args)


if __name__ == '__main__':
    sys.exit(main())
