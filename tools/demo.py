"""`make demo`: every driver against its virtual device, and a short scripted mission.

Everything goes through the drivers' public ROS interfaces, as a user's mission logic would.
The executables run as processes (the parachute module, the servo bus, the handset and the
OriginMan board, each virtual, each with its driver); this script is one more ROS node that
watches them and calls their services and topics, with a compact live view of each device.
Exit code 0 on success, 1 with the reason else.
"""

from __future__ import annotations

import argparse
import json
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
from typing import Any, Callable, Dict, List, Optional, Sequence

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

    def start_device(self, executable: str, params: dict, link: str) -> None:
        """Start a virtual device; wait until its port exists at `link` for its driver."""
        self.start(executable, dict(params, link=link))
        deadline = time.monotonic() + 15
        while not os.path.exists(link):
            self.check_alive()
            if time.monotonic() > deadline:
                raise DemoFailure(f'{executable} did not create its port {link}')
            time.sleep(0.05)

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
        # The other devices' parts of the mission keep what they see in views of their own.
        self.handset = HandsetView(self)
        self.board = BoardView(self)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        self.view_stop = threading.Event()
        self.view = threading.Thread(target=self._live_view, daemon=True)
        self.out = threading.Lock()  # the live view and the step lines share the terminal
        self.drawn = 0  # lines of the live view on the terminal (tty)
        self.printed: Dict[int, str] = {}  # view lines as last printed (no tty)

    def _set(self, attr: str, owner: Any = None) -> Callable[[Any], None]:
        """Return a callback keeping the last message in `owner.attr` (owner: this mission)."""
        target = self if owner is None else owner

        def callback(msg: Any) -> None:
            with self.lock:
                setattr(target, attr, msg)
                self.lock.notify_all()
        return callback

    def _append(self, attr: str, owner: Any = None) -> Callable[[Any], None]:
        """Return a callback appending each message to the list `owner.attr`."""
        target = self if owner is None else owner

        def callback(msg: Any) -> None:
            with self.lock:
                getattr(target, attr).append(msg)
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

    def step(self, procs: Processes, title: str) -> None:
        """Start a step of the mission: every process still alive, its title printed."""
        procs.check_alive()
        self.say(f'▶ {title}')

    # -- output -----------------------------------------------------------------------------------

    def say(self, text: str) -> None:
        """Print a line above the live view."""
        stamp = f'[{time.monotonic() - self.t0:5.1f}s]'
        with self.out:
            drawn = self.drawn
            self._erase_view()
            print(f'{stamp} {text}', flush=True)
            if drawn:
                self._draw_view()

    def view_lines(self) -> List[str]:
        """Lines of the live view: parachute, servo bus, handset, OriginMan board (two)."""
        with self.lock:
            status, battery, joints = self.status, self.battery, self.joints
        if status is None:
            chute = 'parachute: (no status yet)'
        else:
            state = 'TRIGGERED' if status.triggered else ('armed' if status.armed else 'locked')
            chute = (f'parachute: {"online" if status.online else "OFFLINE"} {state:<9} '
                     f'tilt {status.tilt_deg:4.0f}° accel {status.accel_g:3.1f} g '
                     f'bay {"open" if status.bay_open else "closed"}')
        if battery is not None and not math.isnan(battery.voltage):
            charging = battery.power_supply_status == battery.POWER_SUPPLY_STATUS_CHARGING
            chute += f' | cell {battery.voltage:4.2f} V{" charging" if charging else ""}'
        servos = 'servo bus: (no joint_states yet)'
        if joints is not None:
            servos = 'servo bus: ' + ' '.join(f'{n} {p:+.2f}' for n, p in
                                              zip(joints.name, joints.position)) + ' rad'
        return [chute, servos, self.handset.line(), *self.board.lines()]

    def _erase_view(self) -> None:
        # The cursor is at the end of the view's last line: up to its first line, clear below.
        if self.drawn:
            up = f'\033[{self.drawn - 1}A' if self.drawn > 1 else ''
            sys.stdout.write('\r' + up + '\033[J')
            sys.stdout.flush()
            self.drawn = 0

    def _draw_view(self) -> None:
        width = shutil.get_terminal_size((200, 24)).columns - 1  # no wrapping
        lines = [line[:width] for line in self.view_lines()]
        sys.stdout.write('\n'.join(lines))
        sys.stdout.flush()
        self.drawn = len(lines)

    def _live_view(self) -> None:
        period = 0.2 if self.tty else 2.0
        while not self.view_stop.wait(period):
            with self.out:
                if self.tty:
                    self._erase_view()
                    self._draw_view()
                    continue
                # A log: each device's line again only once it says something new.
                for i, line in enumerate(self.view_lines()):
                    if self.printed.get(i) != line:
                        self.printed[i] = line
                        print(f'[{time.monotonic() - self.t0:5.1f}s]   · {line}', flush=True)

    def close(self) -> None:
        """Stop the live view and ROS."""
        self.view_stop.set()
        if self.view.is_alive():
            self.view.join(1)
        with self.out:
            self._erase_view()
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def run_mission(m: Mission, procs: Processes) -> str:
    """Run the scripted mission; return the summary line."""
    from std_srvs.srv import SetBool, Trigger
    from uav_serial_drivers.srv import (Deploy, GetParachuteConfig, GetTriggerRecords,
                                        WritePositions)

    m.step(procs, 'waiting for the parachute and servo bus drivers to come online')
    m.wait(lambda: m.status is not None and m.status.online, 15, 'the parachute online')
    m.wait(lambda: m.joints is not None and len(m.joints.name) == 3, 15,
           'joint_states of three servos')
    m.view.start()

    m.step(procs, "reading the module's configuration (~/get_config)")
    config = m.call(GetParachuteConfig, '/parachute/get_config',
                    GetParachuteConfig.Request()).config
    boot_before = config.boot_count
    m.say(f'  attitude {config.attitude_threshold_deg}°, free fall '
          f'{config.freefall_threshold_g:.1f} g for {config.freefall_time_s:.2f} s, '
          f'light {config.light_threshold_v:.1f} V, '
          f'boot #{config.boot_count}, {config.baud_rate} baud')

    m.step(procs, 'setting thresholds (ros2 param set: written, read back, kept across reboots)')
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

    m.step(procs, 'a deploy without the confirmation token is refused (nothing is sent)')
    reply = m.call(Deploy, '/parachute/deploy', Deploy.Request(confirm='deploy'))
    if reply.success:
        raise DemoFailure('a deploy without the exact token was accepted')
    m.say(f'  refused: {reply.message}')

    m.step(procs, 'arming (~/arm)')
    reply = m.call(SetBool, '/parachute/arm', SetBool.Request(data=True))
    if not reply.success:
        raise DemoFailure(f'arming failed: {reply.message}')
    m.wait(lambda: m.status.armed, 5, 'status armed')
    m.say(f'  armed ✓ ({reply.message})')

    m.step(procs, 'sweeping the servos: one synchronized move (SYNC WRITE), then a staged one')
    # The joints configured (servo_ids 1..3, their default names), not those of the last
    # joint_states: it lists the servos online, and a servo whose read a loaded host's stall
    # failed can be missing from it for a moment (a CI run beside a busy loop).
    names = ['servo_1', 'servo_2', 'servo_3']
    for targets, staged in (([0.8, -0.8, 0.4], False), ([0.0, 0.0, 0.0], True)):
        request = WritePositions.Request(names=names, positions=targets, move_time_ms=1200,
                                         staged=staged)
        reply = m.call(WritePositions, '/servo_bus/write_positions', request)
        if not reply.success and 'did not acknowledge' in reply.message:
            # What the answer tells a user to do: nothing moved, so the move can be asked
            # again (a host loaded beside a busy loop once kept an acknowledgement from its
            # wait and its retry's).
            m.say(f'  {reply.message}: moving again')
            reply = m.call(WritePositions, '/servo_bus/write_positions', request)
        if not reply.success:
            raise DemoFailure(f'servo move failed: {reply.message}')

        def reached(targets: list = targets) -> bool:
            at = dict(zip(m.joints.name, m.joints.position))
            return all(name in at and abs(at[name] - t) < 0.05
                       for name, t in zip(names, targets))
        m.wait(reached, 8, f'servos at {targets}')
        m.say(f'  {"staged (REG WRITE + ACTION)" if staged else "synchronized"} move to '
              f'{targets} rad reached')

    m.step(procs, 'dropping the aircraft: a 1.2 s free fall on external power '
           '(the module must ask)')
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

    m.step(procs, "reading the module's trigger records (~/get_trigger_records)")
    records = m.call(GetTriggerRecords, '/parachute/get_trigger_records',
                     GetTriggerRecords.Request())
    if not records.success or not records.records:
        raise DemoFailure(f'no trigger record: {records.message}')
    newest = records.records[-1]
    m.say(f'  {len(records.records)} record(s); newest: {newest.source_name} at '
          f'{newest.uptime_s:.0f} s of boot #{newest.boot_count}, thresholds '
          f'{newest.attitude_threshold_deg}° / {newest.freefall_threshold_g:.1f} g / '
          f'{newest.freefall_time_s:.2f} s')

    m.step(procs, 'locking (~/arm false)')
    reply = m.call(SetBool, '/parachute/arm', SetBool.Request(data=False))
    if not reply.success:
        raise DemoFailure(f'locking failed: {reply.message}')

    m.step(procs, 'power-cycling the module: the driver sees the reboot and re-applies the '
           'settings')
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


# -- the autopilot link ------------------------------------------------------------------------

MAVLINK_PORT = 14550 + random.randint(100, 900)
"""The loopback UDP port between parachute_mavlink and the virtual autopilot (per run)."""


def start_autopilot(procs: Processes) -> None:
    """Start the virtual autopilot and the autopilot link (the parachute's gate is set)."""
    procs.start('virtual_autopilot', {'mavlink_url': f'udpin:127.0.0.1:{MAVLINK_PORT}'})
    procs.start('parachute_mavlink', {'mavlink_url': f'udpout:127.0.0.1:{MAVLINK_PORT}'})


def run_autopilot(m: Mission, procs: Processes) -> str:
    """Release the parachute from the autopilot's side: DO_PARACHUTE ENABLE, then RELEASE."""
    from std_msgs.msg import String
    from std_srvs.srv import Trigger
    from uav_serial_drivers.msg import MavlinkLink
    received: List[str] = []
    links: List[Any] = []
    m.node.create_subscription(String, '/virtual_autopilot/received',
                               m._append('data', owner=_Lines(received)), 50,
                               callback_group=m.group)
    m.node.create_subscription(MavlinkLink, '/parachute_mavlink/link', m._append(
        'data', owner=_Lines(links)), 10, callback_group=m.group)
    m.step(procs, 'the autopilot link: the flight controller hears a MAVLink parachute')
    link = m.wait(lambda: next((x for x in links if x.autopilot_heard and
                                x.system_status != 0), None), 20,
                  'the autopilot heard and the parachute state known')
    m.say(f'  parachute 1/161 heartbeats with system_status {link.system_status}; autopilot '
          f'{link.autopilot_system_id}/{link.autopilot_component_id} heard')
    # The drop above may still be falling: arming in a free fall would fire at once, and the
    # driver refuses that (so would the autopilot's ENABLE be).
    m.wait(lambda: m.status is not None and m.status.accel_g >= 0.9, 10, 'the free fall over')
    m.step(procs, 'the autopilot arms the parachute: MAV_CMD_DO_PARACHUTE ENABLE')
    reply = m.call(Trigger, '/virtual_autopilot/parachute_enable', Trigger.Request(), 15.0)
    if not reply.success:
        raise DemoFailure(f'DO_PARACHUTE ENABLE: {reply.message}')
    m.say(f'  COMMAND_ACK {reply.message}')
    m.wait(lambda: m.status.armed, 5, 'status armed')
    m.step(procs, 'the autopilot releases it: MAV_CMD_DO_PARACHUTE RELEASE (motors stopped '
           'first)')
    start = len(received)
    reply = m.call(Trigger, '/virtual_autopilot/parachute_release', Trigger.Request(), 20.0)
    if not reply.success:
        raise DemoFailure(f'DO_PARACHUTE RELEASE: {reply.message}')
    m.wait(lambda: m.status.triggered, 5, 'status triggered')
    # What the autopilot received comes on a topic of its own, which may come after the reply
    # on a loaded host (a campaign run of 2026-11-28 looked too early).
    try:
        m.wait(lambda: any('command 400' in x.data for x in received[start:]), 5,
               'the motor stop at the autopilot')
    except DemoFailure:
        pass
    with m.lock:
        lines = [x.data for x in received[start:]]
    stop = next((x for x in lines if 'command 400' in x), None)
    if stop is None:
        raise DemoFailure(f'the autopilot got no motor stop; it received: {lines}')
    m.say(f'  the autopilot received: {stop}')
    for text in [x for x in lines if 'STATUSTEXT' in x][:4]:
        m.say(f'  the autopilot received: {text}')
    m.say(f'  COMMAND_ACK {reply.message}')
    return f'autopilot: motors stopped, then DO_PARACHUTE RELEASE → {reply.message}'


class _Lines:
    """A holder whose ``data`` list the mission's `_append` callback fills."""

    def __init__(self, data: List[Any]) -> None:
        self.data = data


def write_report(blackbox: Path, earlier_runs: set) -> str:
    """Write the black-box report of this run (blackbox_report) beside its file."""
    from parachute_blackbox.report import build_report
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
    procs.start_device('virtual_handset', {}, link)
    procs.start('handset_link_node', {'port': link, 'link_timeout_s': HANDSET_LINK_TIMEOUT_S})


class HandsetView:
    """What the demo sees of the handset driver: its setpoints and failsafe changes."""

    def __init__(self, m: Mission) -> None:
        from rclpy.qos import DurabilityPolicy, QoSProfile
        from uav_serial_drivers.msg import Failsafe, HandsetSetpoint
        self.m = m
        self.setpoint: Optional[Any] = None
        self.failsafes: List[Any] = []
        latched = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        m.node.create_subscription(HandsetSetpoint, '/handset_link/setpoint',
                                   m._set('setpoint', self), 10, callback_group=m.group)
        m.node.create_subscription(Failsafe, '/handset_link/failsafe',
                                   m._append('failsafes', self), latched, callback_group=m.group)

    def line(self) -> str:
        """Return the handset's line of the live view: sticks and the failsafe's action."""
        with self.m.lock:
            sp = self.setpoint
            failsafe = self.failsafes[-1] if self.failsafes else None
        if sp is None:
            return 'handset: (no setpoint yet)'
        action = '' if failsafe is None or failsafe.action == 'NONE' else f' {failsafe.action}!'
        return (f'handset: yaw {sp.yaw_deg:+4.0f}° pitch {sp.pitch_deg:+3.0f}° roll '
                f'{sp.roll_deg:+3.0f}° alt {sp.altitude_m:3.0f} m{action}')


def run_handset(m: Mission, procs: Processes) -> str:
    """Move the sticks, lose the radio link, get it back; return the summary."""
    from std_srvs.srv import SetBool
    from uav_serial_drivers.msg import HandsetSetpoint
    view = m.handset
    m.step(procs, 'handset: moving the sticks (a ground station on /virtual_handset/setpoint_in)')
    m.wait(lambda: view.setpoint is not None, 15, 'handset setpoints')
    pub = m.node.create_publisher(HandsetSetpoint, '/virtual_handset/setpoint_in', 10)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 4.0:
        t = time.monotonic() - t0
        pub.publish(HandsetSetpoint(yaw_deg=150.0 * math.sin(t * 1.5),
                                    pitch_deg=20.0 * math.sin(t * 2.5),
                                    roll_deg=-20.0 * math.sin(t * 2.0), altitude_m=10.0 * t))
        time.sleep(0.05)
    m.wait(lambda: view.setpoint.altitude_m > 30.0, 5, 'the sticks to reach the driver')
    m.say(f'  sticks followed: {view.line()[len("handset: "):]}')

    m.step(procs, 'handset: the radio link is lost (/virtual_handset/set_radio_link false)')
    n = len(view.failsafes)
    m.call(SetBool, '/virtual_handset/set_radio_link', SetBool.Request(data=False))
    lost = m.wait(lambda: next((f for f in view.failsafes[n:] if f.link_lost), None),
                  10, 'the failsafe after the link loss')
    m.say(f'  failsafe → {lost.action} ({lost.reason})')

    m.step(procs, 'handset: the radio link is back')
    n = len(view.failsafes)
    m.call(SetBool, '/virtual_handset/set_radio_link', SetBool.Request(data=True))
    back = m.wait(lambda: next((f for f in view.failsafes[n:] if not f.link_lost), None),
                  10, 'the link regained')
    m.say(f'  link regained → failsafe {back.action}')
    return (f'handset sticks followed, radio link lost → {lost.action} → regained '
            f'({back.action})')


# -- the OriginMan expansion board: IMU, a key press, a sweep, the motor timeout's stop ----

BOARD_DRIVER_ARGS = ['-r', 'joint_states:=originman_board/joint_states']
"""The board's servos get a joint_states of their own here, so the servo bus's stays alone."""


def start_board(procs: Processes, workdir: Path) -> None:
    """Start virtual_originman_board and originman_board_node on it."""
    link = str(workdir / 'voriginman')
    procs.start_device('virtual_originman_board', {'bus_servo_ids': [1, 2, 3]}, link)
    procs.start('originman_board_node', {'port': link, 'bus_servo_ids': [1, 2, 3],
                                         'motor_timeout_s': 0.5}, BOARD_DRIVER_ARGS)


class BoardView:
    """What the demo sees of the board: its topics and the virtual board's state."""

    def __init__(self, m: Mission) -> None:
        from sensor_msgs.msg import BatteryState, Imu, JointState
        from std_msgs.msg import String
        from uav_serial_drivers.msg import ButtonEvent
        self.m = m
        self.imu: Optional[Any] = None
        self.battery: Optional[Any] = None
        self.joints: Optional[Any] = None
        self.state: Optional[dict] = None
        self.buttons: List[Any] = []
        sub = m.node.create_subscription
        sub(Imu, '/originman_board/imu', m._set('imu', self), 10, callback_group=m.group)
        sub(BatteryState, '/originman_board/battery', m._set('battery', self), 10,
            callback_group=m.group)
        sub(JointState, '/originman_board/joint_states', m._set('joints', self), 10,
            callback_group=m.group)
        sub(ButtonEvent, '/originman_board/button', m._append('buttons', self), 20,
            callback_group=m.group)
        sub(String, '/virtual_originman_board/state', self._state, 10, callback_group=m.group)

    def _state(self, msg: Any) -> None:
        state = json.loads(msg.data)
        with self.m.lock:
            self.state = state
            self.m.lock.notify_all()

    def lines(self) -> List[str]:
        """Return the board's lines of the live view: IMU, battery, last key; servos, motors."""
        with self.m.lock:
            imu, battery, joints, state = self.imu, self.battery, self.joints, self.state
            key = self.buttons[-1].event_name if self.buttons else '-'
        if imu is None:
            return ['OriginMan board: (no IMU yet)']
        a, w = imu.linear_acceleration, imu.angular_velocity
        sensors = [f'OriginMan board: IMU a {a.x:+4.1f} {a.y:+4.1f} {a.z:+4.1f} m/s² '
                   f'ω {w.x:+4.2f} {w.y:+4.2f} {w.z:+4.2f} rad/s']
        if battery is not None:
            sensors.append(f'{battery.voltage:4.2f} V')
        sensors.append(f'key {key}')
        actuators = []
        if joints is not None:
            actuators.append('bus servos ' + ' '.join(f'{p:+.2f}' for p in joints.position)
                             + ' rad')
        if state is not None:
            actuators.append('motors ' + ' '.join(f'{v:+.1f}' for v in
                                                  state['motor_set_points']) + ' r/s')
        return [' | '.join(sensors), 'OriginMan board: ' + ' | '.join(actuators or ['-'])]


def run_board_mission(m: Mission, procs: Processes) -> str:
    """Show the board: IMU in SI units, a key press, a servo sweep, a motor stop."""
    from uav_serial_drivers.msg import BusServoCommand, MotorSpeeds
    from uav_serial_drivers.srv import PressKey, SetImu
    view = m.board
    m.step(procs, 'the OriginMan board: waiting for its IMU, battery and bus servos')
    m.wait(lambda: view.imu is not None and view.battery is not None
           and view.joints is not None and len(view.joints.name) == 3, 15,
           'the board online with three bus servos')

    m.step(procs, 'board: tilted 30° and turning at 45°/s (the board sends g and deg/s)')
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

    m.step(procs, 'board: pressing key 1 (a click)')
    n_buttons = len(view.buttons)
    reply = m.call(PressKey, '/virtual_originman_board/press_key',
                   PressKey.Request(key_id=1, sequence='click'))
    if not reply.success:
        raise DemoFailure(f'press_key failed: {reply.message}')
    m.wait(lambda: any(b.event_name == 'click' for b in view.buttons[n_buttons:]), 5,
           'the click')
    events = ' → '.join(b.event_name for b in view.buttons[n_buttons:])
    m.say(f'  ~/button: key 1: {events}')

    m.step(procs, 'board: sweeping the bus servos (~/bus_servo/command) out and back to centre')
    pub = m.node.create_publisher(BusServoCommand, '/originman_board/bus_servo/command', 10)
    for positions in ([800, 200, 650], [500, 500, 500]):
        pub.publish(BusServoCommand(ids=[1, 2, 3], positions=positions, duration_s=1.0))
        want = [math.radians((p - 500) * 0.24) for p in positions]
        m.wait(lambda: all(abs(p - w) < 1e-6 for p, w in zip(view.joints.position, want)), 8,
               f'bus servos at {positions}')
        m.say(f'  raw {positions} reached: ' + ', '.join(f'{w:+.3f}' for w in want) + ' rad')

    m.step(procs, 'board: the motors run, then no command comes: the driver stops them '
           '(the board would not)')
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
    earlier_runs = set(blackbox.glob('parachute-*.jsonl'))
    procs = Processes(workdir)
    mission = None
    try:
        chute, bus = str(workdir / 'vparachute'), str(workdir / 'vservobus')
        print(f'uav_serial_drivers demo (ROS_DOMAIN_ID={os.environ["ROS_DOMAIN_ID"]}): '
              f'virtual devices at {workdir}', flush=True)
        procs.start_device('virtual_parachute', {'external_power': False}, chute)
        procs.start_device('virtual_servo_bus', {'servo_ids': [1, 2, 3]}, bus)
        procs.start('parachute_node', {'port': chute, 'blackbox_dir': str(blackbox),
                                       'trigger_request_policy': 'confirm',
                                       'release_gate': 'parachute_mavlink/release_gate'})
        start_autopilot(procs)
        # The virtual bus is a process on this machine: on a busy one it answers when the
        # scheduler lets it, later than the few ms derived for a pty (a REG WRITE went
        # unacknowledged twice under make test beside a busy loop).
        procs.start('servo_bus_node', {'port': bus, 'servo_ids': [1, 2, 3],
                                       'torque_on_start': True, 'response_timeout_ms': 50.0})
        start_handset(procs, workdir)
        start_board(procs, workdir)
        mission = Mission(tty)
        summary = run_mission(mission, procs)
        summary += '; ' + run_autopilot(mission, procs)
        summary += '; ' + run_handset(mission, procs)
        summary += '; ' + run_board_mission(mission, procs)
        mission.close()
        mission = None
        procs.stop_all()  # the driver closes its black box: the report sees the whole run
        report = write_report(blackbox, earlier_runs)
        print(f'demo: OK in {time.monotonic() - start:.1f} s — {summary}; '
              f'black box in {blackbox}; report {report}', flush=True)
        return 0
    except DemoFailure as exc:
        if mission is not None:
            mission.close()  # the live view leaves the terminal before the reason is printed
            mission = None
        print(f'\ndemo: FAILED — {exc}', file=sys.stderr, flush=True)
        for name, _, _ in procs.items:
            print(f'--- last output of {name} ---\n{procs.tail(name)}', file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        if mission is not None:
            mission.close()
            mission = None
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
