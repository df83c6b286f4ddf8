"""What the parachute tests share: a node rig, the host frames a module received, the black box."""

from __future__ import annotations

import json
from pathlib import Path
import signal
import threading
import time
from typing import List, Optional

from diagnostic_msgs.msg import DiagnosticArray
from dps_parachute_ros import protocol as p
from inproc import InprocDrivers
from dps_parachute_ros.simulation import VirtualParachute
from dps_parachute_ros.virtual_node import create_runner
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from sensor_msgs.msg import BatteryState
from std_msgs.msg import Bool
from support import arm_parachute
from uav_serial_common.process import LaunchedProcesses, wait_for
from uav_serial_common.ros_client import RosHarness
from uav_serial_drivers.msg import ParachuteConfig, ParachuteStatus, TriggerEvent, TriggerRequest

NODE = '/parachute'
DESIRED = dict(attitude_threshold_deg=70, freefall_threshold_g=0.4, freefall_time_s=0.5,
               light_threshold_v=1.5)


class Wire:
    """Every host frame the virtual module received, with its time (a tap on the runner)."""

    def __init__(self, runner, on_frame=None) -> None:
        self.frames: list = []
        self._lock = threading.Lock()
        self._decoder = p.StreamDecoder('from_host')
        self._on_frame = on_frame
        runner.add_tap(self._tap)

    def _tap(self, direction: str, data: bytes, t: float) -> None:
        if direction == 'rx':
            for frame in self._decoder.feed(data):
                with self._lock:
                    self.frames.append((t, frame.raw))
                if self._on_frame is not None:
                    self._on_frame(frame.raw)

    def mark(self) -> int:
        """Return a position to look from (`since`)."""
        with self._lock:
            return len(self.frames)

    def since(self, mark: int, code: Optional[int] = None) -> List[bytes]:
        """Return the host frames received since `mark` (of command `code` if given)."""
        with self._lock:
            return [raw for _, raw in self.frames[mark:] if code is None or raw[2] == code]


def blackbox_records(directory: Path, pattern: str = 'parachute-*.jsonl') -> List[dict]:
    """Return every complete record of the black-box files in `directory`, oldest first."""
    records = []
    for path in sorted(Path(directory).glob(pattern)):
        for line in path.read_text().splitlines():
            try:
                records.append(json.loads(line))
            except ValueError:
                pass  # a line cut short by a kill
    return records


def parameter_value(value) -> ParameterValue:
    """Return the ParameterValue of a Python str, float, bool or int."""
    if isinstance(value, str):
        return ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)
    if isinstance(value, bool):
        return ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value)
    if isinstance(value, float):
        return ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
    return ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=value)


class Rig:
    """A virtual module in this process (its wire tapped) and parachute_node as a process.

    With `inproc`, the node runs in this process too (test/inproc.py): no `respawn` then.
    """

    def __init__(self, tmp, baud: int = 115200, inproc: bool = False, **parameters) -> None:
        self.tmp = tmp
        self.sim = VirtualParachute(now=time.monotonic())
        self.runner = create_runner(self.sim, str(tmp / 'vpara'), baud).start()
        self.wire = Wire(self.runner)
        self.ros = RosHarness()
        self.procs = InprocDrivers(tmp) if inproc else LaunchedProcesses(tmp, 'parachute_node')
        sub = self.ros.subscribe
        self.status = sub(ParachuteStatus, f'{NODE}/status')
        self.config = sub(ParachuteConfig, f'{NODE}/config', latched=True)
        self.events = sub(TriggerEvent, f'{NODE}/trigger_event', latched=True)
        self.requests = sub(TriggerRequest, f'{NODE}/trigger_request')
        self.battery = sub(BatteryState, f'{NODE}/battery')
        self.triggered = sub(Bool, f'{NODE}/triggered', latched=True)
        self.diagnostics = sub(DiagnosticArray, '/diagnostics')
        params = dict(port=self.runner.path, blackbox_dir=str(tmp / 'bb'),
                      defer_timeout_s=0.5, aux_poll_period_s=0.5, **DESIRED)
        params.update(parameters)
        self.blackbox_dir = Path(params['blackbox_dir'])
        self.params = params
        self.proc = self.procs.start('parachute_node', parameters=params, ros=self.ros,
                                     wait_service=f'{NODE}/deploy')

    def respawn(self, **parameters):
        """Kill the node (a crash) and start it again, as a respawn would; return it."""
        assert isinstance(self.procs, LaunchedProcesses), 'a respawn needs the node a process'
        self.proc.stop(signal.SIGKILL)
        self.params.update(parameters)
        self.proc = self.procs.start('parachute_node', parameters=self.params, ros=self.ros,
                                     wait_service=f'{NODE}/deploy')
        return self.proc

    def call(self, srv, name, request=None, timeout=10.0):
        return self.ros.call(srv, f'{NODE}/{name}', request, timeout)

    def model(self):
        return self.runner.locked()

    def wait_ready(self, timeout: float = 15.0) -> None:
        """Wait until the driver has read the module and streams its status."""
        self.config.wait(lambda m: m.valid and m.settings_verified, timeout,
                         what='verified config')
        self.status.wait(lambda m: m.online and m.streaming, timeout, what='online status')

    def fresh(self, external_power=True):
        """Power-cycle the module and wait until the node has re-initialized it."""
        with self.model():
            self.sim.set_tilt(0)
            self.sim.set_accel(1.0)
            self.sim.set_external_power(external_power)
            self.sim.power_cycle()
            boot = self.sim.boot_count
        self.config.wait(lambda m: m.boot_count == boot and m.settings_verified, 10,
                         what=f'config re-read after power cycle (boot {boot})')
        # The initialization goes on after the settings (the trigger records are read last):
        # a deployment before its end is reported by the records it reads (via RECORD), not by
        # the status the test may be waiting for.
        wait_for(lambda: any(r.get('event') == 'initialized' and r.get('boot_count') == boot
                             for r in self.blackbox()), 10, interval=0.05,
                 what=f'the initialization of boot {boot} in the black box')
        start = len(self.status)
        self.status.wait(lambda m: m.online and m.streaming and not m.triggered and
                         not m.armed, 10, what='fresh streaming status', start=start)

    def arm(self):
        return arm_parachute(self.ros, f'{NODE}/arm')

    def set_param(self, name, value):
        request = SetParameters.Request(parameters=[Parameter(name=name,
                                                              value=parameter_value(value))])
        return self.ros.call(SetParameters, f'{NODE}/set_parameters', request).results[0]

    def blackbox(self) -> List[dict]:
        """Return the records of the node's black box so far."""
        return blackbox_records(self.blackbox_dir)

    def close(self, failed):
        self.procs.stop_all()
        if failed:
            print(f'--- parachute_node output ---\n{self.proc.output()}')
        self.ros.close()
        self.runner.stop()
