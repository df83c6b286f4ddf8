"""``virtual_originman_board``: the OriginMan board's firmware model behind a pty, as a ROS node.

:class:`VirtualOriginManBoard` (no ROS) joins the plain-Python
:class:`~originman_board_ros.simulation.VirtualOriginManBoardModel` to a
:class:`~uav_serial_common.virtual_device.VirtualDeviceRunner`: real time, wire timing at the
baud, and the shared wire faults, applied to everything the board sends (its reports and its
bus-servo replies leave the model on ticks, so ``fault_unsolicited``). A
:class:`CommandRecorder` taps what the driver writes, parsed as the firmware's parser reads it,
so tests and the demo can see the wire. The node adds parameters, scenario services and a
``~/state`` topic (JSON); its cable, wire faults and their services are those of every virtual
device (:class:`uav_serial_common.virtual_node.VirtualDeviceNode`).
"""

from __future__ import annotations

from collections import deque
import json
import math
import sys
import threading
from typing import Any, Deque, Dict, List, Optional, Sequence, Tuple

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from std_msgs.msg import String
from std_srvs.srv import SetBool
from uav_serial_drivers.srv import PressKey, SetImu, SetSbus

from originman_board_ros import protocol as p
from originman_board_ros.simulation import VirtualOriginManBoardModel
from uav_serial_common.node_main import run_node
from uav_serial_common.params import declare_parameters, ParameterBinding, ParamSpec
from uav_serial_common.virtual_device import VirtualDeviceRunner
from uav_serial_common.virtual_node import VirtualDeviceNode, wire_fault_params

GARBAGE = bytes.fromhex('00 ff aa 13 aa 55 07 ff 41 55 aa 00 aa 55 0c')
"""Noise for ``~/inject_garbage``: stray bytes, a header with an impossible LENGTH (O34), and a
header cut short."""
RECENT_COMMANDS = 64
KEY_SEQUENCES = ('click', 'double', 'triple', 'long', 'down', 'up')


def describe(cmd: p.HostCommand) -> Dict[str, Any]:
    """Return a host command as JSON-friendly data: its kind and its fields."""
    out: Dict[str, Any] = {'kind': type(cmd).__name__}
    for name in getattr(cmd, '__slots__', ()):
        value = getattr(cmd, name)
        if isinstance(value, bytes):
            value = value.decode('utf-8', errors='replace')
        out[name] = value
    return out


class CommandRecorder:
    """What the driver wrote, as the firmware's parser reads it: counts and recent commands.

    Reads (PWM 0x05/0x09 and the bus-servo reads) are counted but not kept in ``recent``, so
    a driver's polling does not push the commands out. ``last_motor`` is the last command of
    FUNCTION 3 (MOTOR).
    """

    def __init__(self) -> None:
        self._parser = p.BoardParser()
        self._lock = threading.Lock()
        self.counts: Dict[str, int] = {}
        self.recent: Deque[Tuple[float, str, Dict[str, Any]]] = deque(maxlen=RECENT_COMMANDS)
        self.last_motor: Optional[Dict[str, Any]] = None
        self.frames = 0

    def tap(self, direction: str, data: bytes, t: float) -> None:
        """Parse what arrives at the board (a runner tap; 'rx' only)."""
        if direction != 'rx':
            return
        with self._lock:
            for frame in self._parser.feed(data):
                cmd = p.decode_host_command(frame)
                kind = type(cmd).__name__
                self.frames += 1
                self.counts[kind] = self.counts.get(kind, 0) + 1
                if isinstance(cmd, (p.PwmRead, p.BusRead)):
                    continue
                info = describe(cmd)
                self.recent.append((t, frame.raw.hex(' '), info))
                if frame.function == p.Function.MOTOR:
                    self.last_motor = info

    def state(self) -> Dict[str, Any]:
        """Return the counts, the recent commands (time, raw hex, fields), the last motor one."""
        with self._lock:
            return {'frames': self.frames, 'counts': dict(self.counts),
                    'recent': [{'t': t, 'raw': raw, **info} for t, raw, info in self.recent],
                    'last_motor': self.last_motor}


class VirtualOriginManBoard:
    """The board model on a pty: ``start()``, ``stop()``, ``path``, ``model``, ``runner``.

    The wire faults hit every frame the board sends (``fault_unsolicited``); with False, only
    output that answers the driver's bytes at once.
    """

    def __init__(self, link_path: Optional[str], baud: int = p.BAUD, seed: Optional[int] = None,
                 fault_unsolicited: bool = True, **model_kwargs: Any) -> None:
        self.runner = VirtualDeviceRunner(link_path, self._on_input, on_tick=self._on_tick,
                                          next_event=self._next_event, baud=baud, seed=seed,
                                          fault_unsolicited=fault_unsolicited)
        self.model = VirtualOriginManBoardModel(self.runner.now(), **model_kwargs)
        self.recorder = CommandRecorder()
        self.runner.add_tap(self.recorder.tap)

    @property
    def path(self) -> str:
        """Path the driver opens."""
        return self.runner.path

    def start(self) -> 'VirtualOriginManBoard':
        """Open the pty and start the device thread."""
        self.runner.start()
        return self

    def stop(self) -> None:
        """Stop the device thread and remove the pty."""
        self.runner.stop()

    def locked(self) -> Any:
        """Hold the model lock (to change the model from another thread)."""
        return self.runner.locked()

    def _on_input(self, data: bytes, now: float) -> bytes:
        return self.model.receive(data, now)

    def _on_tick(self, now: float) -> bytes:
        return self.model.step(now)

    def _next_event(self) -> Optional[float]:
        return self.model.next_event_time()

    def state(self) -> Dict[str, Any]:
        """Return the board as a user would see it, and what came over the wire (JSON-friendly)."""
        model = self.model
        with self.runner.locked():
            t = model.now
            state = {
                'time': t, 'powered': model.powered, 'plugged': self.runner.port.plugged,
                'boots': model.boots, 'battery_mv': model.battery_mv,
                'battery_limit_mv': model.battery_limit_mv, 'imu_rate_hz': model.imu_rate_hz,
                'accel_g': list(model.accel_g), 'gyro_dps': list(model.gyro_dps),
                'motor_type': p.MotorType(model.motor_type).name,
                'motor_set_points': list(model.motor_set_points),
                'motor_speeds': [model.motor_speed(i) for i in range(p.MOTOR_COUNT)],
                'pwm_servos': {str(i): {'pulse_us': s.pulse_at(t), 'target_us': s.target_us,
                                        'offset_us': s.offset_us}
                               for i, s in model.pwm_servos.items()},
                'bus_servos': [{'id': s.servo_id, 'position': s.read_position(t),
                                'target': s.target, 'moving': s.moving_at(t),
                                'loaded': s.loaded, 'offset': s.offset,
                                'angle_limits': list(s.angle_limits),
                                'voltage_limits': list(s.voltage_limits),
                                'temperature_limit_c': s.temperature_limit_c}
                               for s in model.bus_servos],
                'leds': {str(i): {'lit': led.active_at(t), 'on_ms': led.on_ms,
                                  'off_ms': led.off_ms, 'repeat': led.repeat}
                         for i, led in model.leds.items()},
                'buzzer': {'sounding': model.buzzer.active_at(t),
                           'frequency_hz': model.buzzer.frequency_hz,
                           'on_ms': model.buzzer.on_ms, 'off_ms': model.buzzer.off_ms,
                           'repeat': model.buzzer.repeat,
                           'beeps': len(model.buzzer_log)},
                'oled': [model.oled_text(i) for i in p.OLED_LINES],
                'rgb': [list(c) for c in model.rgb],
                'sbus': None if model.sbus is None else {
                    'channels': list(model.sbus.channels), 'signal_loss': model.sbus.signal_loss,
                    'failsafe': model.sbus.failsafe},
                'frames_handled': model.frames_handled,
                'commands_ignored': model.commands_ignored,
                'bad_motor_ids': model.bad_motor_ids, 'bus_reads': model.bus_reads,
                'bus_read_failures': model.bus_read_failures,
                'reports_sent': model.reports_sent,
                'replies_dropped': self.runner.replies_dropped,
                'replies_corrupted': self.runner.replies_corrupted,
            }
        state['wire'] = self.recorder.state()
        return state


PARAMS = (
    ParamSpec('link', '/tmp/voriginman', 'path of the symlink to the pty the driver opens',
              read_only=True),
    ParamSpec('baud', p.BAUD, 'wire timing [bit/s]; 0 = no wire delay', read_only=True,
              int_range=(0, 4000000)),
    ParamSpec('bus_servo_ids', [1, 2, 3], 'ids of the bus servos behind the board',
              read_only=True),
    ParamSpec('battery_mv', 7400, 'battery voltage the board measures [mV]',
              int_range=(0, 65535)),
    ParamSpec('imu_rate_hz', 50.0, 'IMU report rate [Hz]; 0 = silent (O8)',
              float_range=(0.0, 1000.0)),
    *wire_fault_params('frame of the board', checksum='CRC', reply_delay_max_s=5.0),
    ParamSpec('answer_reads', True, 'False: reads get no reply while reports go on (a fault)'),
    ParamSpec('state_period_s', 0.1, 'period of ~/state [s]', read_only=True,
              float_range=(0.02, 10.0)),
)


class VirtualOriginManBoardNode(VirtualDeviceNode):
    """ROS wrapper of :class:`VirtualOriginManBoard`."""

    garbage = GARBAGE

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__('virtual_originman_board', **node_kwargs)
        values = declare_parameters(self, PARAMS)
        self.board = VirtualOriginManBoard(
            values['link'], baud=values['baud'], bus_servo_ids=list(values['bus_servo_ids']),
            battery_mv=values['battery_mv'], imu_rate_hz=values['imu_rate_hz'])
        self._apply(values)
        ParameterBinding(self, PARAMS, apply=self._apply)
        group = MutuallyExclusiveCallbackGroup()
        for srv_type, name, handler in (
                (PressKey, '~/press_key', self._press_key), (SetImu, '~/set_imu', self._set_imu),
                (SetSbus, '~/set_sbus', self._set_sbus),
                (SetBool, '~/set_power', self._set_power)):
            self.create_service(srv_type, name, self._guarded(handler), callback_group=group)
        self.serve_wire(self.board.runner, callback_group=group)
        self._state_pub = self.create_publisher(String, '~/state', 10)
        self.create_timer(values['state_period_s'], self._publish_state, callback_group=group)
        self.board.start()
        self.get_logger().info(
            f'virtual OriginMan board at {self.board.path} ({self.board.runner.port.device_name})'
            f', {values["baud"]} baud, bus servos {list(values["bus_servo_ids"])}')

    def _apply(self, values: Dict[str, Any]) -> None:
        runner, model = self.board.runner, self.board.model
        with runner.locked():
            for name, value in values.items():
                if name == 'battery_mv':
                    model.set_battery_mv(int(value))
                elif name == 'imu_rate_hz':
                    model.set_imu(rate_hz=float(value))
                elif name == 'answer_reads':
                    model.answer_reads = bool(value)
            self.apply_wire_faults(values, runner)

    def _guarded(self, handler: Any) -> Any:
        def call(request: Any, response: Any) -> Any:
            try:
                response.message = handler(request)
                response.success = True
            except (ValueError, KeyError) as exc:
                response.success, response.message = False, str(exc).strip('"')
            except Exception as exc:  # noqa: BLE001 - a failure, never an exception in rclpy
                response.success, response.message = False, f'internal error: {exc!r}'
            return response
        return call

    # -- services -------------------------------------------------------------------------------

    def _press_key(self, q: PressKey.Request) -> str:
        if q.sequence not in KEY_SEQUENCES:
            raise ValueError(f'sequence must be one of {", ".join(KEY_SEQUENCES)}, '
                             f'got {q.sequence!r}')
        if not (math.isfinite(q.hold_s) and 0.0 <= q.hold_s <= 60.0):
            raise ValueError(f'hold_s must be 0..60 s (0 = default), got {q.hold_s!r}')
        with self.board.locked():
            self.board.model.press_key(q.key_id, q.sequence, q.hold_s or None)
        return f'key {q.key_id}: {q.sequence}'

    def _set_imu(self, q: SetImu.Request) -> str:
        accel = _triple_or_none(q.accel_g, 'accel_g')
        gyro = _triple_or_none(q.gyro_dps, 'gyro_dps')
        rate = None if q.rate_hz < 0 else float(q.rate_hz)
        with self.board.locked():
            self.board.model.set_imu(accel, gyro, rate)
            model = self.board.model
            return (f'IMU {list(model.accel_g)} g, {list(model.gyro_dps)} deg/s at '
                    f'{model.imu_rate_hz:g} Hz')

    def _set_sbus(self, q: SetSbus.Request) -> str:
        channels = [int(c) for c in q.channels]
        if channels and len(channels) != p.SBUS_CHANNELS:
            raise ValueError(f'SBUS needs {p.SBUS_CHANNELS} channels (or none to stop), got '
                             f'{len(channels)}')
        with self.board.locked():
            self.board.model.set_sbus(channels or None, q.ch17, q.ch18, q.signal_loss,
                                      q.failsafe)
        return 'SBUS stopped' if not channels else 'SBUS frames every 14 ms'

    def _set_power(self, q: SetBool.Request) -> str:
        with self.board.locked():
            if q.data:
                self.board.model.power_on()
            else:
                self.board.model.power_off()
            return f'powered {"on" if q.data else "off"}; boots {self.board.model.boots}'

    def _publish_state(self) -> None:
        self._state_pub.publish(String(data=json.dumps(self.board.state())))


def _triple_or_none(values: Sequence[float], name: str) -> Optional[List[float]]:
    values = [float(v) for v in values]
    if not values:
        return None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ValueError(f'{name} needs three finite values (or none), got {values}')
    return values


def main(args: Optional[List[str]] = None) -> int:
    """Run ``virtual_originman_board`` until Ctrl-C."""
    # Reports are paced on the device thread; a short GIL switch interval keeps them on time.
    return run_node(VirtualOriginManBoardNode, args, switch_interval_s=0.0005)


if __name__ == '__main__':
    sys.exit(main())
