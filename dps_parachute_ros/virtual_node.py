"""``virtual_parachute``: the simulated DPS-S module behind a pseudo-terminal, as a ROS node.

The device model (``simulation.VirtualParachute``) runs in a ``VirtualDeviceRunner`` thread in
real time with wire timing; a driver opens the ``link`` path as it would a USB adapter.
Parameters set the scene (tilt, acceleration, light, external power) and the wire faults;
services script events (power cycle, free fall, cable pulled, noise, lost or spoiled replies).
The cable, the wire faults and their services are those of every virtual device
(:class:`uav_serial_common.virtual_node.VirtualDeviceNode`).
"""

from __future__ import annotations

import json
import time
from typing import Any, Dict, List, Optional

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.parameter import Parameter
from std_msgs.msg import String
from std_srvs.srv import Trigger

from dps_parachute_ros.simulation import VirtualParachute
from uav_serial_common.node_main import run_node
from uav_serial_common.params import declare_parameters, ParameterBinding, ParamSpec
from uav_serial_common.virtual_device import VirtualDeviceRunner
from uav_serial_common.virtual_node import VirtualDeviceNode, wire_fault_params

GARBAGE = bytes.fromhex('00 ff 41 13 75 42 61 37 a5')
"""Noise for ~/inject_garbage: stray bytes and broken headers of both directions."""


def create_runner(sim: VirtualParachute, link_path: Optional[str], baud: int = 115200,
                  seed: Optional[int] = None) -> VirtualDeviceRunner:
    """Wire a device model to a pty runner (not started); the model's clock is monotonic."""
    return VirtualDeviceRunner(
        link_path,
        on_input=lambda data, now: sim.receive(data, now),
        on_tick=sim.step,
        next_event=sim.next_event_time,
        baud=baud,
        seed=seed,
    )


def _codes_problem(codes: List[int]) -> str:
    return '' if all(0 <= code <= 255 for code in codes or ()) else \
        'lost_commands: codes are 0..255'


PARAMS = (
    ParamSpec('link', '/tmp/vparachute', 'path of the symlink to the pty', read_only=True),
    ParamSpec('baud', 115200, 'wire rate in bit/s; 0 = no wire delay', read_only=True,
              int_range=(0, 4000000)),
    ParamSpec('stream_rate_hz', 10.0, 'status stream rate when streaming is on',
              float_range=(0.5, 100.0)),
    ParamSpec('external_power', True, 'external power connected (then crashes ask the host '
              'first)'),
    ParamSpec('tilt_deg', 0.0, 'true tilt to the horizontal plane [deg]',
              float_range=(0.0, 180.0)),
    ParamSpec('accel_g', 1.0, 'measured acceleration magnitude [g]', float_range=(0.0, 16.0)),
    ParamSpec('light_v', -1.0, 'force the light sensor [V]; -1 = modelled bay light',
              float_range=(-1.0, 25.5)),
    ParamSpec('free_fall_duration_s', 2.0, 'length of a ~/free_fall [s]',
              float_range=(0.0, 60.0)),
    *wire_fault_params('reply', reply_delay_max_s=5.0),
    ParamSpec('lost_commands', Parameter.Type.INTEGER_ARRAY, 'command codes 0..255 of host '
              'frames lost before the module sees them, e.g. [17] (0x11): every deploy frame',
              check=_codes_problem),
    ParamSpec('stream_dead', False, 'the status stream stops and stream on/off (0x13) is '
              'ignored; every other query is answered'),
)


class VirtualParachuteNode(VirtualDeviceNode):
    """ROS wrapper of one virtual DPS-S module."""

    garbage = GARBAGE

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__('virtual_parachute', **node_kwargs)
        values = declare_parameters(self, PARAMS)
        link, baud = values['link'], values['baud']
        self.sim = VirtualParachute(now=time.monotonic(),
                                    stream_period_s=1.0 / values['stream_rate_hz'])
        self.runner = create_runner(self.sim, link, baud)
        self._apply_all(values)
        self.runner.start()
        ParameterBinding(self, PARAMS, apply=self._apply_all)

        group = MutuallyExclusiveCallbackGroup()
        self.create_service(Trigger, '~/power_cycle', self._power_cycle, callback_group=group)
        self.create_service(Trigger, '~/free_fall', self._free_fall, callback_group=group)
        self.serve_wire(self.runner, callback_group=group, next_reply_services=True)
        self._state_pub = self.create_publisher(String, '~/state', 10)
        self.create_timer(0.2, self._publish_state, callback_group=group)
        self.get_logger().info(f'virtual DPS-S module on {link} ({self.runner.port.device_name}) '
                               f'at {baud} baud')

    def _apply_all(self, values: Dict[str, Any]) -> None:
        self.apply_wire_faults(values, self.runner)
        for name, value in values.items():
            self._apply(name, value)

    def _apply(self, name: str, value) -> None:
        sim = self.sim
        with self.runner.locked():
            if name == 'stream_rate_hz':
                sim.stream_period_s = 1.0 / value
            elif name == 'external_power':
                sim.set_external_power(bool(value))
            elif name == 'tilt_deg':
                sim.set_tilt(value)
            elif name == 'accel_g':
                sim.set_accel(value)
            elif name == 'light_v':
                sim.set_light(None if value < 0 else value)
            elif name == 'lost_commands':
                sim.lost_commands = set(value or ())
            elif name == 'stream_dead':
                sim.stream_dead = bool(value)

    # -- services -------------------------------------------------------------------------------

    def _power_cycle(self, request, response):
        with self.runner.locked():
            self.sim.power_cycle()
            count = self.sim.boot_count
        response.success, response.message = True, f'power cycled; boot count {count}'
        return response

    def _free_fall(self, request, response):
        duration = self.get_parameter('free_fall_duration_s').value
        with self.runner.locked():
            self.sim.start_free_fall(duration)
        response.success, response.message = True, f'free fall for {duration:.2f} s'
        return response

    def _publish_state(self) -> None:
        sim = self.sim
        with self.runner.locked():
            state = {
                'powered': sim.powered, 'armed': sim.armed, 'triggered': sim.triggered,
                'streaming': sim.streaming, 'stream_dead': sim.stream_dead,
                'protection': sim.protection,
                'external_power': sim.external_power, 'boot_count': sim.boot_count,
                'tilt_deg': sim.tilt_deg, 'accel_g': sim.accel_g,
                'light_level_v': sim.light_level_v, 'pending_request': sim.pending_request,
                'attitude_threshold_deg': sim.attitude_threshold_deg,
                'freefall_threshold_g': sim.freefall_threshold_raw / 10,
                'freefall_time_s': sim.freefall_time_raw / 100,
                'light_threshold_v': sim.light_threshold_raw / 10,
                'attitude_trigger_enabled': sim.attitude_trigger_enabled,
                'freefall_trigger_enabled': sim.freefall_trigger_enabled,
                'deployments': sim.deployments, 'records': len(sim.records),
                'plugged': self.runner.port.plugged,
            }
        self._state_pub.publish(String(data=json.dumps(state)))


def main(args=None) -> int:
    """Run the virtual module until Ctrl-C."""
    return run_node(VirtualParachuteNode, args)


if __name__ == '__main__':
    import sys
    sys.exit(main())
