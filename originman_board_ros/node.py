"""``originman_board_node``: the ROS 2 adapter of the OriginMan expansion board driver.

The device is :class:`originman_board_ros.core.OriginManCore` (no ROS in it: link, online
judgement, desired settings, motor watchdog, bus servo poll, validation, SI units, its
threads). This node only translates: parameters into an ``OriginManConfig``, topics and
services into core calls, core callbacks into messages (:mod:`originman_board_ros.messages`)
and ``/diagnostics`` statuses. The board's reports are published straight from the link's
reader thread (rclpy's publish is thread-safe), so an IMU report reaches ``~/imu`` without a
hand-off to the executor. Services that wait on the board run in callback groups of their own
(bus servos, PWM servos, motors), so a slow read never holds up a topic or another service, and
no exception leaves a callback. Decisions O1.. are in ``docs/protocols.md``.
"""

from __future__ import annotations

from dataclasses import asdict
import sys
import threading
import time
from typing import Any, Callable, Dict, List, Sequence, Tuple

from builtin_interfaces.msg import Time
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import BatteryState, Imu, JointState, Joy
from std_msgs.msg import UInt8MultiArray
from std_srvs.srv import Trigger
from uav_serial_drivers.msg import (BusServoCommand, BusServoStateArray, ButtonEvent,
                                    BuzzerPattern, LedPattern, MotorSpeeds, OledText,
                                    PwmServoCommand, RgbPixels, SbusFrame)
from uav_serial_drivers.srv import (BusServoIds, GetBusServoState, GetPwmServoState,
                                    SetBusServoId, SetBusServoLimits, SetBusServoOffset,
                                    SetBusServoTorque, SetPwmServoOffset)

from originman_board_ros import messages as m
from originman_board_ros.core import (AsrSample, BatterySample, BusServoStatus, ButtonSample,
                                      ConfigError, GamepadSample, ImuSample, MOTOR_TYPES,
                                      OriginManConfig, OriginManCore, Outcome, PwmServoStates,
                                      Result, SbusSample)
from uav_serial_common.diagnostics import DiagnosticsUpdater
from uav_serial_common.logs import Throttle
from uav_serial_common.node_main import run_node
from uav_serial_common.params import declare_and_check, ParameterBinding, ParamSpec

REFUSAL_LOG_PERIOD_S = 5.0
"""A refused topic message is logged at most once per cause in this period (the contract)."""
SWITCH_INTERVAL_S = 0.001
"""The GIL switch interval of the driver process (Python's default is 5 ms)."""
EXECUTOR_THREADS = 6
"""One per callback group that can be busy at once: bus servo services, PWM services,
``~/stop_motors``, topics, diagnostics, parameter services."""


def _config_check(name: str) -> Callable[[Any], str]:
    """Check one value the way the core will (one source of truth for the ranges)."""
    def check(value: Any) -> str:
        if isinstance(value, (list, tuple)):
            value = tuple(value)
        try:
            OriginManConfig(**{name: value}).validated()
        except ConfigError as exc:
            return str(exc)
        return ''
    return check


PARAMS = (
    ParamSpec('port', '/dev/ttyS1', 'serial device or pyserial URL (the OriginMan: /dev/ttyS1)',
              read_only=True),
    ParamSpec('baud', 1000000, 'serial rate [bit/s]; the board runs at 1000000 (O20)',
              read_only=True, int_range=(1200, 4000000)),
    ParamSpec('imu_frame_id', 'imu_link', 'header.frame_id of ~/imu'),
    ParamSpec('frame_id', 'originman_board', 'header.frame_id of the other messages'),
    ParamSpec('offline_timeout_s', 2.5, 'no frame from the board for this long = offline [s]',
              float_range=(0.1, 60.0), check=_config_check('offline_timeout_s')),
    ParamSpec('low_battery_mv', -1, 'battery alarm threshold written to the board (SYS 0x01) at '
              'every (re)connect [mV]; -1 = leave the board\'s 6300 mV',
              int_range=(-1, 65535), check=_config_check('low_battery_mv')),
    ParamSpec('motor_type', 'keep', 'motor type written at every (re)connect (MOTOR 0x05)',
              choices=MOTOR_TYPES),
    ParamSpec('motor_timeout_s', 0.5, 'every motor is stopped when no ~/set_motor_speeds came '
              'for this long [s]; 0 = off', float_range=(0.0, 60.0)),
    ParamSpec('pwm_servo_offsets_us', Parameter.Type.INTEGER_ARRAY, 'desired PWM offsets of '
              'servos 1..4 [us], -100..100, written at every (re)connect; empty = leave',
              check=_config_check('pwm_servo_offsets_us')),
    ParamSpec('bus_servo_ids', Parameter.Type.INTEGER_ARRAY, 'bus servos (0..253) to poll',
              check=_config_check('bus_servo_ids')),
    ParamSpec('bus_servo_poll_hz', 10.0, 'position poll rate of bus_servo_ids [Hz]; 0 = none',
              float_range=(0.0, 200.0)),
    ParamSpec('bus_servo_telemetry_period_s', 2.0, 'voltage, temperature and torque refresh '
              'per polled servo [s]', float_range=(0.1, 3600.0)),
)
CONFIG_FIELDS = ('port', 'baud', 'offline_timeout_s', 'low_battery_mv', 'motor_type',
                 'motor_timeout_s', 'pwm_servo_offsets_us', 'bus_servo_ids',
                 'bus_servo_poll_hz', 'bus_servo_telemetry_period_s')


def _config(values: Dict[str, Any], base: OriginManConfig = OriginManConfig()) -> OriginManConfig:
    fields = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()
              if k in CONFIG_FIELDS}
    return OriginManConfig(**{**asdict(base), **fields})


class OriginManBoardNode(Node):
    """The OriginMan board driver: a ROS face on an :class:`OriginManCore`."""

    def __init__(self, **node_options: Any) -> None:
        super().__init__('originman_board', **node_options)
        values = declare_and_check(self, PARAMS)
        self.frame_id: str = values['frame_id']
        self.imu_frame_id: str = values['imu_frame_id']
        self._log_lock = threading.Lock()
        self._log_throttle = Throttle()
        self._send_failures = 0
        self._closing = False
        self._rates = m.ReportRates()
        # The IMU path (reader thread): serialized bytes, stamped from the wall clock unless
        # the node runs on simulated time.
        self._imu = m.ImuPacker(self.imu_frame_id)
        self._sim_time = bool(self.get_parameter('use_sim_time').value)

        pub = self.create_publisher
        self.imu_pub = pub(Imu, '~/imu', 10)
        self.battery_pub = pub(BatteryState, '~/battery', 10)
        self.button_pub = pub(ButtonEvent, '~/button', 20)
        self.sbus_pub = pub(SbusFrame, '~/sbus', 10)
        self.joy_pub = pub(Joy, '~/joy', 10)
        self.asr_pub = pub(UInt8MultiArray, '~/asr', 10)
        self.joint_pub = pub(JointState, 'joint_states', 10)
        self.states_pub = pub(BusServoStateArray, '~/bus_servo/states', 10)

        config = _config(values)
        self.core = OriginManCore(
            config, on_imu=self._on_imu, on_battery=self._on_battery,
            on_button=self._on_button, on_sbus=self._on_sbus, on_gamepad=self._on_gamepad,
            on_asr=self._on_asr, on_bus_servo_states=self._on_states,
            on_online_change=self._on_online, logger=self.get_logger())
        self.diagnostics = DiagnosticsUpdater(self, config.port, period_s=1.0)
        self.diagnostics.add('link', self._diag_link)
        self.diagnostics.add('battery', lambda stat: m.battery_status(stat, self.core.snapshot()))
        self.diagnostics.add('bus servos',
                             lambda stat: m.bus_servo_status(stat, self.core.snapshot()))

        c = self.core
        for msg_type, name, handler in (
                (LedPattern, '~/set_led', lambda q: c.set_led(q.led_id, q.on_s, q.off_s,
                                                              q.repeat)),
                (BuzzerPattern, '~/set_buzzer', lambda q: c.set_buzzer(
                    q.frequency_hz, q.on_s, q.off_s, q.repeat)),
                (RgbPixels, '~/set_rgb', lambda q: c.set_rgb(q.indices, q.red, q.green,
                                                             q.blue)),
                (OledText, '~/set_oled', lambda q: c.set_oled(q.line, q.text)),
                (MotorSpeeds, '~/set_motor_speeds', lambda q: c.set_motor_speeds(
                    q.motor_ids, q.rps)),
                (PwmServoCommand, '~/pwm_servo/command', lambda q: c.set_pwm_servos(
                    q.ids, q.pulses_us, q.duration_s)),
                (BusServoCommand, '~/bus_servo/command', lambda q: c.set_bus_servos(
                    q.ids, q.positions, q.duration_s))):
            # A group per topic: a flood on one (a servo stream) never holds a motor command
            # or another topic's message behind its callbacks (issue 21 item 7).
            self._topic(msg_type, name, handler, MutuallyExclusiveCallbackGroup())

        # Bus servo services share the board's one outstanding bus read (O41) anyway: one
        # group keeps them from holding several executor threads waiting on the same lock.
        bus, pwm, motors = (MutuallyExclusiveCallbackGroup() for _ in range(3))
        self._service(GetBusServoState, '~/bus_servo/get_state', self._get_bus_state, bus)
        self._service(SetBusServoTorque, '~/bus_servo/set_torque',
                      lambda q, r: self._reply(r, c.set_bus_servo_torque(q.ids, q.enable)), bus)
        self._service(BusServoIds, '~/bus_servo/stop',
                      lambda q, r: self._reply(r, c.stop_bus_servos(q.ids)), bus)
        self._service(SetBusServoId, '~/bus_servo/set_id',
                      lambda q, r: self._reply(r, c.set_bus_servo_id(q.id, q.new_id)), bus)
        self._service(SetBusServoOffset, '~/bus_servo/set_offset', lambda q, r: self._reply(
            r, c.set_bus_servo_offset(q.id, q.offset, q.save)), bus)
        self._service(SetBusServoLimits, '~/bus_servo/set_limits', lambda q, r: self._reply(
            r, c.set_bus_servo_limits(q.id, q.min_position, q.max_position, q.min_voltage_mv,
                                      q.max_voltage_mv, q.max_temperature_c)), bus)
        self._service(GetPwmServoState, '~/pwm_servo/get_state', self._get_pwm_state, pwm)
        self._service(SetPwmServoOffset, '~/pwm_servo/set_offset', lambda q, r: self._reply(
            r, c.set_pwm_servo_offset(q.id, q.offset_us)), pwm)
        self._service(Trigger, '~/stop_motors',
                      lambda q, r: self._reply(r, c.stop_all_motors()), motors)

        # Every parameter but port and baud may change at runtime: the core takes the new
        # configuration as a whole; changed desired settings are written to the board at once.
        ParameterBinding(self, PARAMS, apply=self._apply)
        self.core.start()
        self.get_logger().info(
            f'OriginMan board driver on {config.port} at {config.baud} baud; bus servos '
            f'{list(config.bus_servo_ids) or "none"}; motor timeout '
            f'{config.motor_timeout_s:g} s')

    # -- parameters -----------------------------------------------------------------------------

    def _apply(self, changes: Dict[str, Any]) -> None:
        if 'use_sim_time' in changes:
            self._sim_time = bool(changes['use_sim_time'])
        if 'frame_id' in changes:
            self.frame_id = changes['frame_id']
        if 'imu_frame_id' in changes:
            self.imu_frame_id = changes['imu_frame_id']
            self._imu = m.ImuPacker(self.imu_frame_id)
        if any(k in CONFIG_FIELDS for k in changes):
            self.core.reconfigure(_config(changes, self.core.config))
            self.diagnostics.force_update()

    # -- reports (link reader thread, core worker) -----------------------------------------------

    def _now(self) -> Tuple[int, int]:
        """Return the ROS time now as (sec, nanosec), cheaply when it is the wall clock."""
        if self._sim_time:
            stamp = self.get_clock().now().to_msg()
            return stamp.sec, stamp.nanosec
        return divmod(time.time_ns(), 1_000_000_000)

    def _stamp(self) -> Time:
        sec, nanosec = self._now()
        return Time(sec=sec, nanosec=nanosec)

    def _on_imu(self, sample: ImuSample) -> None:
        self.imu_pub.publish(self._imu.pack(sample, *self._now()))

    def _on_battery(self, sample: BatterySample) -> None:
        self.battery_pub.publish(m.battery_msg(sample, self._stamp(), self.frame_id))

    def _on_button(self, sample: ButtonSample) -> None:
        self.button_pub.publish(m.button_msg(sample, self._stamp(), self.frame_id))

    def _on_sbus(self, sample: SbusSample) -> None:
        self.sbus_pub.publish(m.sbus_msg(sample, self._stamp(), self.frame_id))

    def _on_gamepad(self, sample: GamepadSample) -> None:
        self.joy_pub.publish(m.joy_msg(sample, self._stamp(), self.frame_id))

    def _on_asr(self, sample: AsrSample) -> None:
        self.asr_pub.publish(m.asr_msg(sample))

    def _on_states(self, statuses: List[BusServoStatus]) -> None:
        stamp = self._stamp()
        joints = m.joint_states_msg(statuses, stamp, self.frame_id)
        if joints is not None:
            self.joint_pub.publish(joints)
        self.states_pub.publish(m.bus_servo_states_msg(statuses, stamp, self.frame_id))

    def _on_online(self, online: bool, reason: str) -> None:
        self.diagnostics.force_update()

    def _diag_link(self, stat: Any) -> None:
        snap = self.core.snapshot()
        rates = self._rates.update(time.monotonic(), snap.reports)
        m.link_status(stat, snap, rates, self.core.config.baud, self._send_failures)

    # -- topics and services --------------------------------------------------------------------

    def _topic(self, msg_type: Any, name: str, handler: Callable[[Any], Result],
               group: Any) -> None:
        def callback(msg: Any) -> None:
            if self._closing:
                return
            try:
                result = handler(msg)
            except Exception as exc:  # noqa: BLE001 - no input ends the process
                self._log_once('internal', f'{name}: internal error: {exc!r}')
                return
            if result.ok:
                return
            if result.outcome is Outcome.REFUSED:
                # Refused before anything was sent; the core counted it for diagnostics, which
                # show it at once (the updater publishes at most every 0.1 s).
                self._log_once(result.cause, f'{name}: refused ({result.cause}), nothing '
                                             f'sent: {result.message}')
                self.diagnostics.force_update()
            else:
                self._send_failures += 1
                self._log_once('not_sent', f'{name}: {result.message}')
        self.create_subscription(msg_type, name, callback, 10, callback_group=group)

    def _log_once(self, cause: str, text: str) -> None:
        """Log ``text`` unless a line of its cause was logged in the last 5 s (then counted)."""
        with self._log_lock:
            note = self._log_throttle.admit(cause, time.monotonic(), REFUSAL_LOG_PERIOD_S)
        if note is not None:
            self.get_logger().warning(text + note)

    def _service(self, srv_type: Any, name: str, handler: Callable[[Any, Any], Any],
                 group: Any) -> None:
        def call(request: Any, response: Any) -> Any:
            try:
                return handler(request, response)
            except Exception as exc:  # noqa: BLE001 - a failure, never an exception in rclpy
                self.get_logger().error(f'{name} failed: {exc!r}')
                response.success = False
                response.message = f'internal error: {exc!r}'
                return response
        self.create_service(srv_type, name, call, callback_group=group)

    def _reply(self, response: Any, result: Result) -> Any:
        response.success, response.message = bool(result.ok), result.message
        if not result.ok:
            self.get_logger().warning(result.message)
        return response

    def _get_bus_state(self, request: Any, response: Any) -> Any:
        result = self.core.get_bus_servo_state(list(request.ids))
        response.servos = [m.bus_servo_state(s) for s in result.value or ()]
        return self._reply(response, result)

    def _get_pwm_state(self, request: Any, response: Any) -> Any:
        result = self.core.get_pwm_servo_state(list(request.ids))
        states = result.value or PwmServoStates()
        response.pulses_us = [int(v) for v in states.pulses_us]
        response.offsets_us = [int(v) for v in states.offsets_us]
        return self._reply(response, result)

    # -- shutdown -------------------------------------------------------------------------------

    def on_shutdown(self) -> None:
        """Stop every motor (the board would keep them turning), then the worker and the link.

        ``run_node`` calls this after the executor stopped, and a second SIGINT cannot cut it
        short; it is bounded by the link's write and the worker's current read.
        """
        self._closing = True
        connected = self.core.link.port_open
        self.core.stop(stop_motors=True)
        self.get_logger().info('shutdown: every motor stopped' if connected else
                               'shutdown: the port is not open, no motor stop could be sent')


def main(args: Sequence[str] = None) -> int:
    """Run ``originman_board_node`` until SIGINT/SIGTERM."""
    # The reader thread publishes each IMU report as it arrives; when another thread holds
    # the GIL, it would wait up to the 5 ms default switch interval (imu_latency_p99_ms).
    return run_node(OriginManBoardNode, args, threads=EXECUTOR_THREADS,
                    switch_interval_s=SWITCH_INTERVAL_S)


if __name__ == '__main__':
    sys.exit(main())
