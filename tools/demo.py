"""`make demo`: every driver against its virtual device, and a short scripted mission.

Everything goes through the drivers' public ROS interfaces, as a user's mission logic would.
The executables run as processes; this script is one more ROS node that watches them and
calls their services, with a compact live view. Exit code 0 on success, 1 with the reason else.
"""

from __future__ import annotations

import argparse
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable, List, Optional

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

    def start(self, executable: str, params: dict) -> subprocess.Popen:
        """Start an installed executable with a parameter file."""
        import yaml
        path = executable_path(executable)
        params_file = self.workdir / f'{executable}.yaml'
        params_file.write_text(yaml.safe_dump({'/**': {'ros__parameters': params}}))
        log = open(self.workdir / f'{executable}.log', 'wb')
        proc = subprocess.Popen([path, '--ros-args', '--params-file', str(params_file)],
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
        subscribe_handset(self)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        self.view_stop = threading.Event()
        self.view = threading.Thread(target=self._live_view, daemon=True)

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
        return chute + power + servos + handset_view(self)

    def _live_view(self) -> None:
        period = 0.2 if self.tty else 2.0
        while not self.view_stop.wait(period):
            line = self.view_line()
            if self.tty:
                width = shutil.get_terminal_size((200, 24)).columns - 1  # no wrapping
                sys.stdout.write('\r\033[K' + line[:width])
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


def write_report(blackbox: Path, earlier_runs: set) -> str:
    """Write the black-box report of this run (blackbox_report) beside its file."""
    from dps_parachute_ros.report import build_report
    runs = sorted(set(blackbox.glob('parachute-*.jsonl')) - earlier_runs)
    if not runs:
        raise DemoFailure(f'the driver wrote no black box in {blackbox}')
    report = build_report([str(runs[-1])], progress=False)
    print(f'demo: black-box report of this run: {report.html_path} (timeline '
          f'{report.png_path}: {report.counts.get("deployments", 0)} deployment(s), '
          f'{report.counts.get("reboots", 0)} reboot(s))', flush=True)
    return report.html_path


# -- the handset link ----------------------------------------------------------------------

HANDSET_LINK_TIMEOUT_S = 1.0
"""Short for the demo (the product's is 5 s, H8): the failsafe shows up at once."""


def start_handset(procs: Processes, workdir: Path) -> None:
    """Start the virtual handset and the handset link driver on it."""
    link = str(workdir / 'vhandset')
    procs.start('virtual_handset', {'link': link})
    deadline = time.monotonic() + 15
    while not os.path.exists(link):
        procs.check_alive()
        if time.monotonic() > deadline:
            raise DemoFailure('the virtual handset did not create its port')
        time.sleep(0.05)
    procs.start('handset_link_node', {'port': link, 'link_timeout_s': HANDSET_LINK_TIMEOUT_S})


def subscribe_handset(m: Mission) -> None:
    """Record the handset driver's setpoints and failsafe changes for the view and the steps."""
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from uav_serial_drivers.msg import Failsafe, HandsetSetpoint
    m.handset_setpoint = None
    m.handset_failsafes = []
    latched = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    m.node.create_subscription(HandsetSetpoint, '/handset_link/setpoint',
                               m._set('handset_setpoint'), 10, callback_group=m.group)
    m.node.create_subscription(Failsafe, '/handset_link/failsafe',
                               m._append('handset_failsafes'), latched, callback_group=m.group)


def handset_view(m: Mission) -> str:
    """Return the handset's part of the live view: sticks and the failsafe's action."""
    with m.lock:
        sp = m.handset_setpoint
        failsafe = m.handset_failsafes[-1] if m.handset_failsafes else None
    if sp is None:
        return ' | handset: (no setpoint yet)'
    action = '' if failsafe is None or failsafe.action == 'NONE' else f' {failsafe.action}!'
    return (f' | handset yaw {sp.yaw_deg:+4.0f}° pitch {sp.pitch_deg:+3.0f}° roll '
            f'{sp.roll_deg:+3.0f}° alt {sp.altitude_m:3.0f} m{action}')


def run_handset(m: Mission, procs: Processes) -> str:
    """Move the sticks, lose the radio link, get it back; return the summary."""
    from std_srvs.srv import SetBool
    from uav_serial_drivers.msg import HandsetSetpoint
    procs.check_alive()
    m.say('▶ handset: moving the sticks (a ground station on /virtual_handset/setpoint_in)')
    m.wait(lambda: m.handset_setpoint is not None, 15, 'handset setpoints')
    pub = m.node.create_publisher(HandsetSetpoint, '/virtual_handset/setpoint_in', 10)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 4.0:
        t = time.monotonic() - t0
        pub.publish(HandsetSetpoint(yaw_deg=150.0 * math.sin(t * 1.5),
                                    pitch_deg=20.0 * math.sin(t * 2.5),
                                    roll_deg=-20.0 * math.sin(t * 2.0), altitude_m=10.0 * t))
        time.sleep(0.05)
    m.wait(lambda: m.handset_setpoint.altitude_m > 30.0, 5, 'the sticks to reach the driver')
    m.say(f'  sticks followed: {handset_view(m)[3:]}')

    procs.check_alive()
    m.say('▶ handset: the radio link is lost (/virtual_handset/set_radio_link false)')
    n = len(m.handset_failsafes)
    m.call(SetBool, '/virtual_handset/set_radio_link', SetBool.Request(data=False))
    lost = m.wait(lambda: next((f for f in m.handset_failsafes[n:] if f.link_lost), None),
                  10, 'the failsafe after the link loss')
    m.say(f'  failsafe → {lost.action} ({lost.reason})')

    procs.check_alive()
    m.say('▶ handset: the radio link is back')
    n = len(m.handset_failsafes)
    m.call(SetBool, '/virtual_handset/set_radio_link', SetBool.Request(data=True))
    back = m.wait(lambda: next((f for f in m.handset_failsafes[n:] if not f.link_lost), None),
                  10, 'the link regained')
    m.say(f'  link regained → failsafe {back.action}')
    return (f'handset sticks followed, radio link lost → {lost.action} → regained '
            f'({back.action})')


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
    earlier_runs = set(blackbox.glob('parachute-*.jsonl'))
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
        start_handset(procs, workdir)
        mission = Mission(tty)
        summary = run_mission(mission, procs)
        summary += '; ' + run_handset(mission, procs)
        mission.close()
        mission = None
        procs.stop_all()  # the driver closes its black box: the report sees the whole run
        report = write_report(blackbox, earlier_runs)
        print(f'demo: OK in {time.monotonic() - start:.1f} s — {summary}; '
              f'black box in {blackbox}; report {report}', flush=True)
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
