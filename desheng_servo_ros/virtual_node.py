"""``virtual_servo_bus``: the simulated servo bus behind a pseudo-terminal, as a ROS node.

:class:`VirtualServoBus` (no ROS) joins the plain-Python :class:`ServoBusSim` to a
:class:`VirtualDeviceRunner`, which gives it real time, wire timing at the baud for request and
reply bytes, and the wire faults (``runner.faults``, ``runner.inject_garbage``). Tests use the
class directly; the node adds parameters and scenario services (``~/set_fault``,
``~/disconnect``, ``~/inject_garbage``).
"""

from __future__ import annotations

import sys
from typing import Iterable, List, Optional

from desheng_servo_ros.simulation import ServoBusSim
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_srvs.srv import SetBool, Trigger
from uav_serial_common.node_main import run_node
from uav_serial_common.virtual_device import VirtualDeviceRunner
from uav_serial_drivers.srv import SimServoFault

# A real servo answers a few hundred microseconds after the last request byte (firmware parse
# time); 0.2 ms is the order of magnitude, and what the virtual bus adds to every reply.
DEFAULT_RESPONSE_DELAY_S = 0.0002
GARBAGE = bytes((0xFF, 0xF5, 0x07, 0x13, 0xFF, 0x00, 0xA5, 0xFF, 0xFF, 0x5A))


class VirtualServoBus:
    """A :class:`ServoBusSim` behind a pty: ``start()``, ``stop()``, ``path``, ``sim``."""

    def __init__(self, link_path: Optional[str], ids: Iterable[int] = (1, 2, 3),
                 baud: int = 115200, response_delay_s: float = DEFAULT_RESPONSE_DELAY_S,
                 seed: Optional[int] = None, **sim_kwargs) -> None:
        self.runner = VirtualDeviceRunner(link_path, self._on_input, on_tick=self._on_tick,
                                          baud=baud, response_delay_s=response_delay_s,
                                          seed=seed)
        self.sim = ServoBusSim(ids, now=self.runner.now(), **sim_kwargs)

    @property
    def path(self) -> str:
        """Path the driver opens."""
        return self.runner.path

    def start(self) -> 'VirtualServoBus':
        """Open the pty and start the device thread."""
        self.runner.start()
        return self

    def stop(self) -> None:
        """Stop the device thread and remove the pty."""
        self.runner.stop()

    def _on_input(self, data: bytes, now: float) -> List[bytes]:
        return self.sim.feed(data, now)

    def _on_tick(self, now: float) -> None:
        self.sim.advance(now)
        return None

    def set_fault(self, servo_id: int, fault: str, active: bool = True) -> str:
        """Apply a scenario fault; returns what was done, raises ValueError/KeyError if not."""
        with self.runner.locked():
            sim = self.sim
            sim.advance(self.runner.now())
            if fault == 'stall':
                sim.stall(servo_id, active)
            elif fault == 'overheat':
                if active:
                    sim.overheat(servo_id)
                else:
                    sim.cool(servo_id)
                    sim.servo(servo_id).temperature_c = sim.ambient_c
            elif fault == 'voltage_fault':
                sim.set_voltage_fault(active, servo_id)
            elif fault == 'remove':
                sim.remove_servo(servo_id)
            elif fault == 'add':
                sim.add_servo(servo_id)
            elif fault == 'clear':
                sim.stall(servo_id, False)
                sim.cool(servo_id)
                sim.servo(servo_id).temperature_c = sim.ambient_c
                sim.set_voltage_fault(False, servo_id)
            else:
                raise ValueError(f'unknown fault {fault!r}: use stall, overheat, voltage_fault, '
                                 'remove, add or clear')
        state = '' if fault in ('remove', 'add', 'clear') else (' on' if active else ' off')
        return f'servo {servo_id}: {fault}{state}'


class VirtualServoBusNode(Node):
    """ROS wrapper of :class:`VirtualServoBus`."""

    def __init__(self) -> None:
        super().__init__('virtual_servo_bus')
        prob = [FloatingPointRange(from_value=0.0, to_value=1.0, step=0.0)]
        self.declare_parameter('link', '/tmp/vservobus', ParameterDescriptor(
            description='symlink to the pty the driver opens', read_only=True))
        self.declare_parameter('baud', 115200, ParameterDescriptor(
            description='wire timing baud rate; 0 = no wire delay', read_only=True))
        self.declare_parameter('servo_ids', [1, 2, 3], ParameterDescriptor(
            description='ids of the simulated servos', read_only=True))
        self.declare_parameter('response_delay_s', DEFAULT_RESPONSE_DELAY_S, ParameterDescriptor(
            description='the servo\'s own reply latency after a request [s]',
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=1.0, step=0.0)]))
        for name, desc in (('drop_probability', 'chance that a reply is lost'),
                           ('corrupt_probability', 'chance that a reply has a bad checksum'),
                           ('garbage_probability', 'chance of noise before a reply')):
            self.declare_parameter(name, 0.0, ParameterDescriptor(description=desc,
                                                                  floating_point_range=prob))
        self.declare_parameter('reply_delay_s', 0.0, ParameterDescriptor(
            description='extra delay before every reply (fault) [s]',
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=1.0, step=0.0)]))
        p = self.get_parameter
        self.bus = VirtualServoBus(p('link').value, list(p('servo_ids').value),
                                   baud=p('baud').value,
                                   response_delay_s=p('response_delay_s').value)
        self._apply([p(n) for n in ('drop_probability', 'corrupt_probability',
                                    'garbage_probability', 'reply_delay_s')])
        self.add_on_set_parameters_callback(self._on_set)
        self.create_service(SimServoFault, '~/set_fault', self._srv_set_fault)
        self.create_service(SetBool, '~/disconnect', self._srv_disconnect)
        self.create_service(Trigger, '~/inject_garbage', self._srv_garbage)
        self.bus.start()
        self.get_logger().info(f'virtual servo bus {list(p("servo_ids").value)} at '
                               f'{self.bus.path} ({p("baud").value} baud)')

    def _apply(self, params: List[Parameter]) -> None:
        runner = self.bus.runner
        with runner.locked():
            for param in params:
                if param.name == 'reply_delay_s':
                    runner.faults.reply_delay_s = float(param.value)
                elif param.name == 'response_delay_s':
                    runner.response_delay_s = float(param.value)
                elif param.name in ('drop_probability', 'corrupt_probability',
                                    'garbage_probability'):
                    setattr(runner.faults, param.name, float(param.value))

    def _on_set(self, params: List[Parameter]) -> SetParametersResult:
        self._apply(params)
        return SetParametersResult(successful=True)

    def _srv_set_fault(self, req: SimServoFault.Request,
                       resp: SimServoFault.Response) -> SimServoFault.Response:
        try:
            resp.message = self.bus.set_fault(req.id, req.fault, req.active)
            resp.success = True
        except (ValueError, KeyError) as exc:
            resp.success = False
            resp.message = str(exc).strip('"')
        return resp

    def _srv_disconnect(self, req: SetBool.Request, resp: SetBool.Response) -> SetBool.Response:
        if req.data:
            self.bus.runner.unplug()
            resp.message = 'unplugged'
        else:
            self.bus.runner.replug()
            resp.message = 'plugged in'
        resp.success = True
        return resp

    def _srv_garbage(self, req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
        self.bus.runner.inject_garbage(GARBAGE)
        resp.success = True
        resp.message = f'{len(GARBAGE)} bytes of noise sent'
        return resp

    def on_shutdown(self) -> None:
        """Remove the pty."""
        self.bus.stop()


def main(args: Optional[List[str]] = None) -> int:
    """Run ``virtual_servo_bus``."""
    # Replies are paced on the device thread; a short GIL switch interval keeps them on time.
    sys.setswitchinterval(0.0005)
    return run_node(VirtualServoBusNode, args)


if __name__ == '__main__':
    sys.exit(main())
