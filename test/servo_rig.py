"""Shared rig of the servo node tests: the simulated bus in this process, the node as a process."""

from __future__ import annotations

import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional

from desheng_servo_ros import state as servo_state
from desheng_servo_ros.protocol import Instruction, StreamDecoder
from desheng_servo_ros.virtual_node import VirtualServoBus
from diagnostic_msgs.msg import DiagnosticArray
from sensor_msgs.msg import JointState
from uav_serial_common.process import LaunchedProcess, LaunchedProcesses
from uav_serial_common.ros_client import RosHarness
from uav_serial_drivers.msg import ServoStateArray

NODE = '/servo_bus'
RIG_RESPONSE_TIMEOUT_MS = 250.0
# The read loop's own READs (position, position to temperature, torque and current): anything
# else is "on the wire".
LOOP_READS = set(servo_state.LOOP_READS)


class Wire:
    """Every byte the driver sent to the virtual bus (a tap on the runner), decoded on demand."""

    def __init__(self, runner: Any) -> None:
        self._rx: List[bytes] = []
        self._lock = threading.Lock()
        runner.add_tap(self._tap)

    def _tap(self, direction: str, data: bytes, t: float) -> None:
        if direction == 'rx':
            with self._lock:
                self._rx.append(bytes(data))
        else:
            self._reply(data)

    def _reply(self, data: bytes) -> None:
        """Take what the device put on the wire (nothing here)."""

    def mark(self) -> int:
        """Return a position; `requests(mark)` decodes what was sent after it."""
        with self._lock:
            return len(self._rx)

    def requests(self, mark: int = 0) -> list:
        """Return the requests sent since `mark`."""
        with self._lock:
            data = b''.join(self._rx[mark:])
        return StreamDecoder('request').feed(data)

    def requests_ending(self, mark: int = 0) -> list:
        """Return (the mark at which each request's last byte had come, the request).

        Taken after a call was queued, a mark tells what left after it: a request that ends
        after it was on the wire then, or sent later.
        """
        with self._lock:
            chunks = self._rx[mark:]
        decoder, found = StreamDecoder('request'), []
        for i, chunk in enumerate(chunks):
            found.extend((mark + i + 1, r) for r in decoder.feed(chunk))
        return found

    def commands(self, mark: int = 0) -> list:
        """Return the requests since `mark` other than the read loop's own READs."""
        return [r for r in self.requests(mark)
                if not (r.instruction == Instruction.READ and tuple(r.params) in LOOP_READS)]


@dataclass
class Rig:
    dev: VirtualServoBus
    wire: Wire
    ros: RosHarness
    procs: LaunchedProcesses
    node: LaunchedProcess
    joints: Any
    states: Any
    diags: Any

    @property
    def sim(self):
        return self.dev.sim

    def sim_servo(self, servo_id: int):
        return self.dev.sim.servo(servo_id)

    def locked(self):
        return self.dev.runner.locked()

    def call(self, srv_type, name: str, timeout: float = 10.0, **fields):
        req = srv_type.Request(**fields)
        return self.ros.call(srv_type, f'{NODE}/{name}', req, timeout=timeout)

    def state(self, servo_id: int, start: int = 0, timeout: float = 5.0, what: str = '',
              pred=lambda s: True):
        """Wait for a servo_states message whose entry for `servo_id` satisfies `pred`."""
        def ok(msg):
            return any(s.id == servo_id and pred(s) for s in msg.servos)
        msg = self.states.wait(ok, timeout, what=what or f'state of servo {servo_id}',
                               start=start)
        return next(s for s in msg.servos if s.id == servo_id)

    def diag(self, name: str, pred, timeout: float = 5.0, start: int = 0):
        """Wait for a diagnostics status called `name` that satisfies `pred`."""
        def ok(msg):
            return any(s.name == name and pred(s) for s in msg.status)
        msg = self.diags.wait(ok, timeout, what=f'diagnostics {name}', start=start)
        return next(s for s in msg.status if s.name == name)


def start_rig(tmp: Path, name: str, ids=(1, 2, 3), parameters: Optional[Dict] = None,
              **bus_kwargs) -> Rig:
    # The device thread shares this process with the ROS harness: hand the GIL over quickly,
    # as virtual_servo_bus does, or replies miss their deadline under load.
    sys.setswitchinterval(0.0005)
    dev = VirtualServoBus(str(tmp / 'servobus'), list(ids), **bus_kwargs).start()
    wire = Wire(dev.runner)
    ros = RosHarness()
    procs = LaunchedProcesses(tmp, name)
    # The virtual bus shares this process (and its GIL) with the test's rclpy executor, which is
    # busy right when the node publishes; its replies can then be tens of ms late, an artefact of
    # the rig that a real servo does not have. A wide reply window keeps that from looking like a
    # lost reply; tests of timeouts and offline detection set their own.
    params = {'port': dev.path, 'servo_ids': list(ids), 'telemetry_period_s': 0.2,
              'response_timeout_ms': RIG_RESPONSE_TIMEOUT_MS}
    params.update(parameters or {})
    joints = ros.subscribe(JointState, '/joint_states')
    states = ros.subscribe(ServoStateArray, f'{NODE}/servo_states')
    diags = ros.subscribe(DiagnosticArray, '/diagnostics')
    try:
        node = procs.start('servo_bus_node', parameters=params, ros=ros,
                           wait_service=f'{NODE}/emergency_stop', wait_topic='/joint_states')
    except BaseException:
        ros.close()
        dev.stop()
        raise
    return Rig(dev, wire, ros, procs, node, joints, states, diags)


def stop_rig(rig: Rig) -> None:
    try:
        rig.procs.stop_all()
        print(f'--- servo_bus_node output ---\n{rig.node.output()}')
    finally:
        rig.ros.close()
        rig.dev.stop()
