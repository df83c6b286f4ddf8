"""``virtual_handset``: the handset as the drone's radio modem delivers it, on a pseudo-terminal.

The model (``simulation.VirtualHandset``) runs in a ``VirtualDeviceRunner`` thread in real time:
frames at ``rate_hz``, paced at ``baud``, one frame per write so that the wire faults (drop,
corrupt, garbage) hit single frames; the handset sends only unsolicited output, so the runner
applies them to it (``fault_unsolicited``; a corrupted frame has its checksum flipped, the byte
before the end byte). Parameters set the sticks, the auxiliary controls and the encoding at
runtime; ``~/setpoint_in`` drives the sticks from a topic; services unplug the
modem (``~/disconnect``), cut the radio link (``~/set_radio_link``), and send noise or any bytes.
The modem's cable, the wire faults and their services are those of every virtual device
(:class:`uav_serial_common.virtual_node.VirtualDeviceNode`).
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any, Callable, Dict, List, Optional

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from std_srvs.srv import SetBool
from uav_serial_drivers.msg import HandsetSetpoint
from uav_serial_drivers.srv import SendRaw

from handset_link_ros import protocol as p
from handset_link_ros.simulation import VirtualHandset
from uav_serial_common.node_main import run_node
from uav_serial_common.params import declare_and_check, ParameterBinding, ParamSpec
from uav_serial_common.virtual_device import VirtualDeviceRunner
from uav_serial_common.virtual_node import VirtualDeviceNode, wire_fault_params

GARBAGE = bytes.fromhex('00 ff 55 aa ff 13 7b 22 7d aa 01 55 aa')
"""Noise for ~/inject_garbage: stray bytes, a false start (LEN 0xFF), LEN < 2, a lone 0xAA."""
STICKS = ('yaw_deg', 'pitch_deg', 'roll_deg', 'altitude_m')
MODEL_VALUES = STICKS + ('lights_percent', 'camera_angle_deg', 'camera_recording')


def _finite(name: str):
    def check(value: Any) -> str:
        return '' if math.isfinite(value) else f'{name} must be a finite number, got {value!r}'
    return check


def _spec(name: str, default: Any, description: str, **kw: Any) -> ParamSpec:
    if isinstance(default, float):
        kw.setdefault('check', _finite(name))
    return ParamSpec(name, default, description, **kw)


SPECS = (
    _spec('link', '/tmp/vhandset', 'path of the symlink to the pty the driver opens',
          read_only=True),
    _spec('baud', 115200, 'wire rate in bit/s; 0 = no wire delay', read_only=True,
          int_range=(0, 4_000_000)),
    _spec('rate_hz', 50.0, 'stick frames per second (H7, H22) [Hz]', float_range=(0.1, 1000.0)),
    _spec('yaw_deg', 0.0, 'SET_YAW value [deg] (H4: -180..180; beyond is sent, and refused)'),
    _spec('pitch_deg', 0.0, 'SET_PITCH value [deg] (-90..90)'),
    _spec('roll_deg', 0.0, 'SET_ROLL value [deg] (-90..90)'),
    _spec('altitude_m', 0.0, 'SET_ALTITUDE value [m] (-100..1000)'),
    _spec('lights_percent', 0, 'SET_LIGHTS value [%] (0..100)'),
    _spec('camera_angle_deg', 0.0, 'SET_CAMERA_ANGLE value [deg] (-90..90)'),
    _spec('camera_recording', False, 'SET_CAMERA_RECORD: recording on or off'),
    _spec('encoding', 'json', 'payload encoding of every frame (H5; int8/int16 round and '
          'saturate, H23)', choices=p.ENCODINGS),
    # The handset only sends: no reply, no reply delay.
    *wire_fault_params('frame', reply_delay_max_s=None),
)


def create_runner(sim: VirtualHandset, link_path: Optional[str], baud: int = 115200,
                  seed: Optional[int] = None,
                  on_tick: Optional[Callable[[float], List[bytes]]] = None) -> VirtualDeviceRunner:
    """Wire a handset model to a pty runner (not started); the model's clock is monotonic.

    ``on_tick`` replaces ``sim.step_frames`` (the benchmarks number their ticks through it).
    """
    return VirtualDeviceRunner(link_path, on_input=sim.receive,
                               on_tick=on_tick or sim.step_frames,
                               next_event=sim.next_event_time, baud=baud, seed=seed,
                               fault_unsolicited=True, checksum_from_end=2)


class VirtualHandsetNode(VirtualDeviceNode):
    """ROS wrapper of one virtual handset behind its radio modem."""

    garbage = GARBAGE
    unplugged_message = 'modem unplugged: its port is gone'
    replugged_message = 'modem plugged back in'

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__('virtual_handset', **node_kwargs)
        values = declare_and_check(self, SPECS)
        self.sim = VirtualHandset(now=time.monotonic(), rate_hz=values['rate_hz'],
                                  encoding=values['encoding'])
        self.runner = create_runner(self.sim, values['link'], values['baud'])
        self._apply(values)
        ParameterBinding(self, SPECS, apply=self._apply)
        group = MutuallyExclusiveCallbackGroup()
        self.create_subscription(HandsetSetpoint, '~/setpoint_in', self._on_setpoint_in, 10,
                                 callback_group=group)
        self.serve_wire(self.runner, callback_group=group)
        self.create_service(SetBool, '~/set_radio_link', self._set_radio_link,
                            callback_group=group)
        self.create_service(SendRaw, '~/send_raw', self._send_raw, callback_group=group)
        self.runner.start()
        self.get_logger().info(f'virtual handset on {values["link"]} '
                               f'({self.runner.port.device_name}): {values["rate_hz"]:g} Hz, '
                               f'{values["encoding"]}, {values["baud"]} baud')

    def _apply(self, changes: Dict[str, Any]) -> None:
        sim = self.sim
        with self.runner.locked():
            for name, value in changes.items():
                if name in MODEL_VALUES:
                    setattr(sim, name, value)
                elif name == 'encoding':
                    sim.set_encoding(value)
                elif name == 'rate_hz':
                    sim.set_rate(value)
            self.apply_wire_faults(changes, self.runner)

    def _on_setpoint_in(self, msg: HandsetSetpoint) -> None:
        # The fields the message names in `updated`; all of them when it names none.
        names = [n for n in msg.updated if n in STICKS] if msg.updated else list(STICKS)
        values = {n: getattr(msg, n) for n in names}
        finite = {n: v for n, v in values.items() if math.isfinite(v)}
        if msg.updated and len(finite) < len(values):
            self.get_logger().warning(
                f'~/setpoint_in: ignoring non-finite {sorted(set(values) - set(finite))} (use '
                f'~/send_raw for frames the handset cannot send)', throttle_duration_sec=1.0)
        with self.runner.locked():
            self.sim.set_sticks(**finite)

    def _set_radio_link(self, request: SetBool.Request, response: SetBool.Response) -> Any:
        with self.runner.locked():
            self.sim.set_radio_link(request.data)
        response.success = True
        response.message = 'radio link up: transmitting' if request.data else \
            'radio link down: nothing is transmitted'
        return response

    def _send_raw(self, request: SendRaw.Request, response: SendRaw.Response) -> Any:
        data = bytes(request.data)
        if not data:
            response.success, response.message = False, 'no bytes given: nothing sent'
            return response
        with self.runner.locked():
            self.sim.send_raw(data)
        response.success, response.message = True, f'{len(data)} bytes queued: {data.hex(" ")}'
        return response


def main(args: Optional[List[str]] = None) -> int:
    """Run ``virtual_handset`` until Ctrl-C."""
    # Frames are paced on the device thread; a short GIL switch interval keeps them on time.
    return run_node(VirtualHandsetNode, args, threads=2, switch_interval_s=0.0005)


if __name__ == '__main__':
    sys.exit(main())
