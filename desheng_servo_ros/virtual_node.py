"""``virtual_servo_bus``: the simulated servo bus behind a pseudo-terminal, as a ROS node.

:class:`VirtualServoBus` (no ROS) joins the plain-Python :class:`ServoBusSim` to a
:class:`VirtualDeviceRunner`, which gives it real time, wire timing at the baud for request and
reply bytes, and the wire faults (``runner.faults``, ``runner.inject_garbage``). Tests use the
class directly; the node adds parameters and scenario services (``~/set_fault``, and the
``~/disconnect`` and ``~/inject_garbage`` of every virtual device,
:class:`uav_serial_common.virtual_node.VirtualDeviceNode`).
"""

from __future__ import annotations

import sys
from typing import Any, Dict, Iterable, List, Optional

from desheng_servo_ros.simulation import ServoBusSim
from uav_serial_common.node_main import run_node
from uav_serial_common.params import declare_parameters, ParameterBinding, ParamSpec
from uav_serial_common.virtual_device import VirtualDeviceRunner
from uav_serial_common.virtual_node import VirtualDeviceNode, WIRE_FAULTS, wire_fault_params
from uav_serial_drivers.srv import SimServoFault

# A real servo answers a few hundred microseconds after the last request byte (firmware parse
# time); 0.2 ms is the order of magnitude, and what the virtual bus adds to every reply.
DEFAULT_RESPONSE_DELAY_S = 0.0002
GARBAGE = bytes((0xFF, 0xF5, 0x07, 0x13, 0xFF, 0x00, 0xA5, 0xFF, 0xFF, 0x5A))
PARAMETERS = (
    ParamSpec('link', '/tmp/vservobus', 'symlink to the pty the driver opens', read_only=True),
    ParamSpec('baud', 115200, 'wire timing baud rate; 0 = no wire delay. A driver at another '
              'rate reads garbage, as on a real bus', read_only=True, int_range=(0, 4000000)),
    ParamSpec('servo_ids', [1, 2, 3], 'ids of the simulated servos', read_only=True),
    ParamSpec('response_delay_s', DEFAULT_RESPONSE_DELAY_S,
              "the servo's own reply latency after a request [s]", float_range=(0.0, 1.0)),
    *wire_fault_params('reply', reply_delay_max_s=1.0),
)


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


class VirtualServoBusNode(VirtualDeviceNode):
    """ROS wrapper of :class:`VirtualServoBus`."""

    garbage = GARBAGE

    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__('virtual_servo_bus', **node_kwargs)
        values = declare_parameters(self, PARAMETERS)
        self.bus = VirtualServoBus(values['link'], list(values['servo_ids']),
                                   baud=values['baud'],
                                   response_delay_s=values['response_delay_s'])
        self._apply({name: values[name] for name in WIRE_FAULTS})
        ParameterBinding(self, PARAMETERS, apply=self._apply)
        self.create_service(SimServoFault, '~/set_fault', self._srv_set_fault)
        self.serve_wire(self.bus.runner)
        self.bus.start()
        self.get_logger().info(f'virtual servo bus {list(values["servo_ids"])} at '
                               f'{self.bus.path} ({values["baud"]} baud)')

    def _apply(self, changes: Dict[str, Any]) -> None:
        runner = self.bus.runner
        with runner.locked():
            for name, value in changes.items():
                if name == 'response_delay_s':
                    runner.response_delay_s = float(value)
            self.apply_wire_faults(changes, runner)

    def _srv_set_fault(self, req: SimServoFault.Request,
                       resp: SimServoFault.Response) -> SimServoFault.Response:
        try:
            resp.message = self.bus.set_fault(req.id, req.fault, req.active)
            resp.success = True
        except (ValueError, KeyError) as exc:
            resp.success = False
            resp.message = str(exc).strip('"')
        return resp


def main(args: Optional[List[str]] = None) -> int:
    """Run ``virtual_servo_bus``."""
    # Replies are paced on the device thread; a short GIL switch interval keeps them on time.
    return run_node(VirtualServoBusNode, args, switch_interval_s=0.0005)


if __name__ == '__main__':
    sys.exit(main())
