"""`make demo`: both drivers against both virtual devices, and a short scripted mission.

Everything goes through the drivers' public ROS interfaces, as a user's mission logic would.
The four executables run as processes; this script is one more ROS node that watches them and
calls their services, with a compact live view. Exit code 0 on success, 1 with the reason else.
"""

from __future__ import annotations

import argparse
import math
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable, List, Optional, Sequence

ROOT = Path(__file__).resolve().parents[1]
# The process plumbing the tests and the benchmarks use as well.
from uav_serial_common.process import die_with_parent, executable_path  # noqa: E402


class DemoFailure(Exception):
    """A step of the mission did not do what it should."""


class Processes:
    """The executables the demo starts; all are stopped on exit, whatever happens."""

    def __init__(self, workdir: Path) -> None:
        self.workdir = workdir
        self.items: List[tuple] = []

    def start(self, executable: str, params: dict,
              ros_args: Sequence[str] = ()) -> subprocess.Popen:
        """Start an installed executable with a parameter file (and more ``--ros-args``)."""
        import yaml
        path = executable_path(executable)
        params_file = self.workdir / f'{executable}.yaml'
        params_file.write_text(yaml.safe_dump({'/**': {'ros__parameters': params}}))
        log = open(self.workdir / f'{executable}.log', 'wb')
        proc = subprocess.Popen([path, '--ros-args', *ros_args, '--params-file',
                                 str(params_file)],
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                                preexec_fn=die_with_parent)
        self.items.append((executable, proc, log))
        return proc

    def check_alive(self) -> None:
        """Fail the demo if a process died."""
        for name, proc, _ in self.items:
            if proc.poll() is not None:
                raise DemoFailure(f'{name} exited with {proc.returncode}:\n{self.tail(name)}')

    def tail(self, name: str, lines: int = 15) -> str:
        """Return the last lines of a process's output."""
        try:
            text = (self.workdir / f'{name}.log').read_text(errors='replace')
        except FileNotFoundError:
            return ''
        return '\n'.join(text.splitlines()[-lines:])

    def stop_all(self) -> None:
        """SIGINT every process (drivers first), then SIGKILL what is left."""
        for _, proc, _ in self.items:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 8.0
        for _, proc, log in self.items:
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(3)
            log.close()


class Mission:
    """The demo node: subscriptions for the live view, service calls for the mission."""

    def __init__(self, tty: bool) -> None:
        import rclpy
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile
        from sensor_msgs.msg import BatteryState, JointState
        from uav_serial_drivers.msg import (ParachuteConfig, ParachuteStatus, TriggerEvent,
                                            TriggerRequest)
        self.rclpy = rclpy
        self.tty = tty
        self.t0 = time.monotonic()
        rclpy.init()
        self.node = rclpy.create_node('demo_mission')
        self.group = ReentrantCallbackGroup()
        self.lock = threading.Condition()
        self.status: Optional[Any] = None
        self.battery: Optional[Any] = None
        self.joints: Optional[Any] = None
        self.configs: List[Any] = []
        self.events: List[Any] = []
        self.requests: List[Any] = []
        latched = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        sub = self.node.create_subscription
        sub(ParachuteStatus, '/parachute/status', self._set('status'), 10,
            callback_group=self.group)
        sub(BatteryState, '/parachute/battery', self._set('battery'), 10,
            callback_group=self.group)
        sub(JointState, '/joint_states', self._set('joints'), 10, callback_group=self.group)
        sub(ParachuteConfig, '/parachute/config', self._append('configs'), latched,
            callback_group=self.group)
        sub(TriggerEvent, '/parachute/trigger_event', self._append('events'), latched,
            callback_group=self.group)
        sub(TriggerRequest, '/parachute/trigger_request', self._append('requests'), 10,
            callback_group=self.group)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        self.view_stop = threading.Event()
        self.view = threading.Thread(target=self._live_view, daemon=True)
        # Set by a later part of the mission to show its own device in the live view.
        self.view_override: Optional[Callable[[], str]] = None

    def _set(self, attr: str) -> Callable[[Any], None]:
        def callback(msg: Any) -> None:
            with self.lock:
                setattr(self, attr, msg)
                self.lock.notify_all()
        return callback

    def _append(self, attr: str) -> Callable[[Any], None]:
        def callback(msg: Any) -> None:
            with self.lock:
                getattr(self, attr).append(msg)
                self.lock.notify_all()
        return callback

    # -- waiting and calling ---------------------------------------------------------------------

    def wait(self, predicate: Callable[[], Any], timeout: float, what: str) -> Any:
        """Wait until `predicate()` is truthy (it reads state under the lock)."""
        deadline = time.monotonic() + timeout
        with self.lock:
            while True:
                value = predicate()
                if value:
                    return value
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DemoFailure(f'timed out after {timeout:.0f} s waiting for {what}')
                self.lock.wait(min(remaining, 0.1))

    def call(self, srv_type: Any, name: str, request: Any, timeout: float = 10.0) -> Any:
        """Call a service; fail the demo if it is missing or silent."""
        client = self.node.create_client(srv_type, name, callback_group=self.group)
        try:
            if not client.wait_for_service(timeout_sec=timeout):
                raise DemoFailure(f'service {name} is not available')
            future = client.call_async(request)
            done = threading.Event()
            future.add_done_callback(lambda _f: done.set())
            if not done.wait(timeout):
                raise DemoFailure(f'service {name} did not answer within {timeout:.0f} s')
            return future.result()
        finally:
            self.node.destroy_client(client)

    def set_params(self, node: str, values: dict) -> List[Any]:
        """Set parameters of another node (what `ros2 param set` does)."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter
        request = SetParameters.Request(
            parameters=[Parameter(k, value=v).to_parameter_msg() for k, v in values.items()])
        return self.call(SetParameters, f'{node}/set_parameters', request).results

    # -- output -----------------------------------------------------------------------------------

    def say(self, text: str) -> None:
        """Print a line above the live view."""
        stamp = f'[{time.monotonic() - self.t0:5.1f}s]'
        if self.tty:
            sys.stdout.write('\r\033[K')
        print(f'{stamp} {text}', flush=True)

    def view_line(self) -> str:
        """One line: parachute status, battery, servo positions."""
        if self.view_override is not None:
            return self.view_override()
        with self.lock:
            status, battery, joints = self.status, self.battery, self.joints
        if status is None:
            chute = 'parachute: (no status yet)'
        else:
            state = 'TRIGGERED' if status.triggered else ('armed' if status.armed else 'locked')
            chute = (f'parachute: {"online" if status.online else "OFFLINE"} {state:<9} '
                     f'tilt {status.tilt_deg:4.0f}° accel {status.accel_g:3.1f} g '
                     f'bay {"open" if status.bay_open else "closed"}')
        power = ''
        if battery is not None and not math.isnan(battery.voltage):
            charging = battery.power_supply_status == battery.POWER_SUPPLY_STATUS_CHARGING
            power = f' | cell {battery.voltage:4.2f} V{" charging" if charging else ""}'
        servos = ''
        if joints is not None:
            servos = ' | ' + ' '.join(f'{n} {p:+.2f}' for n, p in
                                      zip(joints.name, joints.position)) + ' rad'
        return chute + power + servos

    def _live_view(self) -> None:
        period = 0.2 if self.tty else 2.0
        while not self.view_stop.wait(period):
            line = self.view_line()
            if self.tty:
                sys.stdout.write('\r\033[K' + line[:200])
                sys.stdout.flush()
            else:
                print(f'[{time.monotonic() - self.t0:5.1f}s]   · {line}', flush=True)

    def close(self) -> None:
        """Stop the live view and ROS."""
        self.view_stop.set()
        if self.view.is_alive():
            self.view.join(1)
        if self.tty:
            sys.stdout.write('\r\033[K')
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def run_mission(m: Mission, procs: Processes) -> str:
    """Run the scripted mission; return the summary line."""
    from std_srvs.srv import SetBool, Trigger
    from uav_serial_drivers.srv import (Deploy, GetParachuteConfig, GetTriggerRecords,
                                        WritePositions)

    def step(title: str) -> None:
        procs.check_alive()
        m.say(f'▶ {title}')

    step('waiting for both drivers to come online')
    m.wait(lambda: m.status is not None and m.status.online, 15, 'the parachute online')
    m.wait(lambda: m.joints is not None and len(m.joints.name) == 3, 15,
           'joint_states of three servos')
    m.view.start()

    step("reading the module's configuration (~/get_config)")
    config = m.call(GetParachuteConfig, '/parachute/get_config',
                    GetParachuteConfig.Request()).config
    boot_before = config.boot_count
    m.say(f'  attitude {config.attitude_threshold_deg}°, free fall '
          f'{config.freefall_threshold_g:.1f} g for {config.freefall_time_s:.2f} s, '
          f'light {config.light_threshold_v:.1f} V, '
          f'boot #{config.boot_count}, {config.baud_rate} baud')

    step('setting thresholds (ros2 param set: written, read back, kept across reboots)')
    desired = {'attitude_threshold_deg': 70, 'freefall_threshold_g': 0.6,
               'freefall_time_s': 0.5}
    results = m.set_params('/parachute', desired)
    refused = [r.reason for r in results if not r.successful]
    if refused:
        raise DemoFailure(f'thresholds refused: {refused}')
    config = m.call(GetParachuteConfig, '/parachute/get_config',
                    GetParachuteConfig.Request()).config
    if (config.attitude_threshold_deg, round(config.freefall_threshold_g, 2),
            round(config.freefall_time_s, 2)) != (70, 0.6, 0.5):
        raise DemoFailure(f'read-back does not match: {config}')
    m.say('  read back: attitude 70°, free fall 0.6 g for 0.50 s ✓')

    step('a deploy without the confirmation token is refused (nothing is sent)')
    reply = m.call(Deploy, '/parachute/deploy', Deploy.Request(confirm='deploy'))
    if reply.success:
        raise DemoFailure('a deploy without the exact token was accepted')
    m.say(f'  refused: {reply.message}')

    step('arming (~/arm)')
    reply = m.call(SetBool, '/parachute/arm', SetBool.Request(data=True))
    if not reply.success:
        raise DemoFailure(f'arming failed: {reply.message}')
    m.wait(lambda: m.status.armed, 5, 'status armed')
    m.say(f'  armed ✓ ({reply.message})')

    step('sweeping the servos: one synchronized move (SYNC WRITE), then a staged one')
    names = list(m.joints.name)
    for targets, staged in (([0.8, -0.8, 0.4], False), ([0.0, 0.0, 0.0], True)):
        reply = m.call(WritePositions, '/servo_bus/write_positions', WritePositions.Request(
            names=names, positions=targets, move_time_ms=1200, staged=staged))
        if not reply.success:
            raise DemoFailure(f'servo move failed: {reply.message}')
        m.wait(lambda: all(abs(p - t) < 0.05 for p, t in zip(m.joints.position, targets)),
               8, f'servos at {targets}')
        m.say(f'  {"staged (REG WRITE + ACTION)" if staged else "synchronized"} move to '
              f'{targets} rad reached')

    step('dropping the aircraft: a 1.2 s free fall on external power (the module must ask)')
    m.set_params('/virtual_parachute', {'external_power': True, 'free_fall_duration_s': 1.2})
    n_events = len(m.events)
    n_requests = len(m.requests)
    reply = m.call(Trigger, '/virtual_parachute/free_fall', Trigger.Request())
    if not reply.success:
        raise DemoFailure(f'free fall not started: {reply.message}')
    request = m.wait(lambda: m.requests[n_requests:] and m.requests[-1], 10,
                     'the module asking to deploy')
    m.say(f'  module asked "may I deploy?" → {request.decision_name} in '
          f'{request.latency_ms:.1f} ms ({request.reason})')
    event = m.wait(lambda: m.events[n_events:] and m.events[-1], 10, 'a trigger event')
    m.say(f'  trigger event: source {event.source_name}')
    m.wait(lambda: m.status.triggered, 5, 'status triggered')

    step("reading the module's trigger records (~/get_trigger_records)")
    records = m.call(GetTriggerRecords, '/parachute/get_trigger_records',
                     GetTriggerRecords.Request())
    if not records.success or not records.records:
        raise DemoFailure(f'no trigger record: {records.message}')
    newest = records.records[-1]
    m.say(f'  {len(records.records)} record(s); newest: {newest.source_name} at '
          f'{newest.uptime_s:.0f} s of boot #{newest.boot_count}, thresholds '
          f'{newest.attitude_threshold_deg}° / {newest.freefall_threshold_g:.1f} g / '
          f'{newest.freefall_time_s:.2f} s')

    step('locking (~/arm false)')
    reply = m.call(SetBool, '/parachute/arm', SetBool.Request(data=False))
    if not reply.success:
        raise DemoFailure(f'locking failed: {reply.message}')

    step('power-cycling the module: the driver sees the reboot and re-applies the settings')
    n_configs = len(m.configs)
    m.call(Trigger, '/virtual_parachute/power_cycle', Trigger.Request())
    config = m.wait(lambda: next((c for c in m.configs[n_configs:]
                                  if c.boot_count != boot_before and c.settings_verified
                                  and c.attitude_threshold_deg == 70), None),
                    15, 'the settings re-applied after the reboot')
    m.say(f'  boot #{config.boot_count}: attitude {config.attitude_threshold_deg}°, free fall '
          f'{config.freefall_threshold_g:.1f} g for {config.freefall_time_s:.2f} s, verified ✓')
    return (f'thresholds set and verified, servos swept, free fall → request '
            f'{request.decision_name} in {request.latency_ms:.1f} ms → {event.source_name} '
            f'deployment recorded, settings re-applied after reboot')


# ---------------------------------------------------------------------------------------------
# The OriginMan expansion board: virtual board + driver, IMU, a key press, a sweep, a motor stop
# ---------------------------------------------------------------------------------------------

BOARD_DRIVER_ARGS = ['-r', 'joint_states:=originman_board/joint_states']
"""The board's servos get a joint_states of their own here, so the servo bus's stays alone."""


def start_board(procs: Processes, workdir: Path) -> str:
    """Start virtual_originman_board and originman_board_node on it; return the link path."""
    link = str(workdir / 'voriginman')
    procs.start('virtual_originman_board', {'link': link, 'bus_servo_ids': [1, 2, 3]})
    deadline = time.monotonic() + 15
    while not os.path.exists(link):
        procs.check_alive()
        if time.monotonic() > deadline:
            raise DemoFailure('the virtual OriginMan board did not create its port')
        time.sleep(0.05)
    procs.start('originman_board_node', {'port': link, 'bus_servo_ids': [1, 2, 3],
                                         'motor_timeout_s': 0.5}, BOARD_DRIVER_ARGS)
    return link


class BoardView:
    """What the demo sees of the board: its topics and the virtual board's state."""

    def __init__(self, m: Mission) -> None:
        import json
        from sensor_msgs.msg import BatteryState, Imu, JointState
        from std_msgs.msg import String
        from uav_serial_drivers.msg import ButtonEvent
        self.m = m
        self.json = json
        self.imu: Optional[Any] = None
        self.battery: Optional[Any] = None
        self.joints: Optional[Any] = None
        self.state: Optional[dict] = None
        self.buttons: List[Any] = []
        sub = m.node.create_subscription
        sub(Imu, '/originman_board/imu', self._set('imu'), 10, callback_group=m.group)
        sub(BatteryState, '/originman_board/battery', self._set('battery'), 10,
            callback_group=m.group)
        sub(JointState, '/originman_board/joint_states', self._set('joints'), 10,
            callback_group=m.group)
        sub(ButtonEvent, '/originman_board/button', self._button, 20, callback_group=m.group)
        sub(String, '/virtual_originman_board/state', self._state, 10, callback_group=m.group)

    def _set(self, attr: str) -> Callable[[Any], None]:
        def callback(msg: Any) -> None:
            with self.m.lock:
                setattr(self, attr, msg)
                self.m.lock.notify_all()
        return callback

    def _button(self, msg: Any) -> None:
        with self.m.lock:
            self.buttons.append(msg)
            self.m.lock.notify_all()

    def _state(self, msg: Any) -> None:
        state = self.json.loads(msg.data)
        with self.m.lock:
            self.state = state
            self.m.lock.notify_all()

    def line(self) -> str:
        """One line: IMU, battery, last key event, bus servos, motors."""
        with self.m.lock:
            imu, battery, joints, state = self.imu, self.battery, self.joints, self.state
            key = self.buttons[-1].event_name if self.buttons else '-'
        parts = ['board:']
        if imu is not None:
            a, w = imu.linear_acceleration, imu.angular_velocity
            parts.append(f'IMU a ({a.x:+5.2f} {a.y:+5.2f} {a.z:+5.2f}) m/s² '
                         f'ω ({w.x:+4.2f} {w.y:+4.2f} {w.z:+4.2f}) rad/s')
        if battery is not None:
            parts.append(f'| {battery.voltage:4.2f} V')
        parts.append(f'| key {key}')
        if joints is not None:
            parts.append('| servos ' + ' '.join(f'{p:+.2f}' for p in joints.position) + ' rad')
        if state is not None:
            parts.append('| motors ' + ' '.join(f'{v:+.1f}' for v in state['motor_set_points'])
                         + ' r/s')
        return ' '.join(parts)


def run_board_mission(m: Mission, procs: Processes) -> str:
    """Show the board: IMU in SI units, a key press, a servo sweep, a motor stop."""
    from uav_serial_drivers.msg import BusServoCommand, MotorSpeeds
    from uav_serial_drivers.srv import PressKey, SetImu

    def step(title: str) -> None:
        procs.check_alive()
        m.say(f'▶ {title}')

    view = BoardView(m)
    step('the OriginMan board: waiting for its IMU, battery and bus servos')
    m.wait(lambda: view.imu is not None and view.battery is not None
           and view.joints is not None and len(view.joints.name) == 3, 15,
           'the board online with three bus servos')
    m.view_override = view.line
    if not m.view.is_alive():
        m.view.start()

    step('tilting the board 30° and turning it at 45°/s (the board sends g and deg/s)')
    reply = m.call(SetImu, '/virtual_originman_board/set_imu', SetImu.Request(
        accel_g=[0.0, 0.5, 0.866], gyro_dps=[0.0, 0.0, 45.0], rate_hz=-1.0))
    if not reply.success:
        raise DemoFailure(f'set_imu failed: {reply.message}')
    imu = m.wait(lambda: view.imu if view.imu.angular_velocity.z > 0.7 else None, 5,
                 'the tilted IMU')
    a = imu.linear_acceleration
    m.say(f'  ~/imu: a = ({a.x:.2f}, {a.y:.2f}, {a.z:.2f}) m/s², ω z = '
          f'{imu.angular_velocity.z:.3f} rad/s, orientation unknown (covariance[0] = '
          f'{imu.orientation_covariance[0]:.0f})')

    step('pressing key 1 (a click)')
    n_buttons = len(view.buttons)
    reply = m.call(PressKey, '/virtual_originman_board/press_key',
                   PressKey.Request(key_id=1, sequence='click'))
    if not reply.success:
        raise DemoFailure(f'press_key failed: {reply.message}')
    m.wait(lambda: any(b.event_name == 'click' for b in view.buttons[n_buttons:]), 5,
           'the click')
    events = ' → '.join(b.event_name for b in view.buttons[n_buttons:])
    m.say(f'  ~/button: key 1: {events}')

    step('sweeping the bus servos (~/bus_servo/command): out, then back to the centre')
    pub = m.node.create_publisher(BusServoCommand, '/originman_board/bus_servo/command', 10)
    for positions in ([800, 200, 650], [500, 500, 500]):
        pub.publish(BusServoCommand(ids=[1, 2, 3], positions=positions, duration_s=1.0))
        want = [math.radians((p - 500) * 0.24) for p in positions]
        m.wait(lambda: all(abs(p - w) < 1e-6 for p, w in zip(view.joints.position, want)), 8,
               f'bus servos at {positions}')
        m.say(f'  raw {positions} reached: ' + ', '.join(f'{w:+.3f}' for w in want) + ' rad')

    step('running the motors, then going silent: the driver stops them (the board would not)')
    motors = m.node.create_publisher(MotorSpeeds, '/originman_board/set_motor_speeds', 10)
    motors.publish(MotorSpeeds(motor_ids=[1, 2, 3, 4], rps=[1.0, 1.0, -1.0, -1.0]))
    m.wait(lambda: view.state and view.state['motor_set_points'] == [1.0, 1.0, -1.0, -1.0], 5,
           'the motors turning')
    started = time.monotonic()
    m.wait(lambda: view.state['motor_set_points'] == [0.0] * 4, 5, 'the motors stopped')
    last = view.state['wire']['last_motor']
    m.say(f'  motors stopped by the motor timeout after {time.monotonic() - started:.1f} s: '
          f'{last["kind"]} of wire ids {last["wire_ids"]}')
    return 'board: IMU in SI units, key click, servo sweep, motors stopped by the timeout'


def main() -> int:
    """Run the demo; return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--no-tty', action='store_true', help='plain line output')
    args = parser.parse_args()
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.randint(150, 220)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.pop('ROS_LOCALHOST_ONLY', None)
    tty = sys.stdout.isatty() and not args.no_tty
    start = time.monotonic()
    workdir = Path(tempfile.mkdtemp(prefix='uav-demo-'))
    blackbox = ROOT / 'log' / 'demo-blackbox'
    procs = Processes(workdir)
    mission = None
    try:
        chute, bus = str(workdir / 'vparachute'), str(workdir / 'vservobus')
        print(f'uav_serial_drivers demo (ROS_DOMAIN_ID={os.environ["ROS_DOMAIN_ID"]}): '
              f'virtual devices at {workdir}', flush=True)
        procs.start('virtual_parachute', {'link': chute, 'external_power': False})
        procs.start('virtual_servo_bus', {'link': bus, 'servo_ids': [1, 2, 3]})
        deadline = time.monotonic() + 15
        while not (os.path.exists(chute) and os.path.exists(bus)):
            procs.check_alive()
            if time.monotonic() > deadline:
                raise DemoFailure('the virtual devices did not create their ports')
            time.sleep(0.05)
        procs.start('parachute_node', {'port': chute, 'blackbox_dir': str(blackbox),
                                       'trigger_request_policy': 'confirm'})
        procs.start('servo_bus_node', {'port': bus, 'servo_ids': [1, 2, 3],
                                       'torque_on_start': True})
        start_board(procs, workdir)
        mission = Mission(tty)
        summary = run_mission(mission, procs)
        summary += '; ' + run_board_mission(mission, procs)
        mission.close()
        mission = None
        print(f'demo: OK in {time.monotonic() - start:.1f} s — {summary}; '
              f'black box in {blackbox}', flush=True)
        return 0
    except DemoFailure as exc:
        print(f'\ndemo: FAILED — {exc}', file=sys.stderr, flush=True)
        for name, _, _ in procs.items:
            print(f'--- last output of {name} ---\n{procs.tail(name)}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print('\ndemo: interrupted', file=sys.stderr)
        return 130
    finally:
        if mission is not None:
            mission.close()
        procs.stop_all()
        for path in workdir.iterdir():
            path.unlink()
        workdir.rmdir()


if __name__ == '__main__':
    sys.exit(main())
