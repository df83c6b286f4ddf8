"""originman_board_node against virtual_originman_board (a process) and a ROS client.

The driver runs in the test's process (the `driver` fixture), except in the tests of what a
process has (a double SIGINT) and of the motor watchdog against a keep-alive (a time-critical
duty that must not share the GIL with this test's publisher).

What the driver sends is read from the virtual board's ``~/state`` (JSON): its model (motors,
servos, settings) and ``wire``, every command the board's parser read (counts by kind, the
recent non-read commands with their raw bytes, the last MOTOR command). Decisions O1.. are in
``docs/protocols.md``.
"""

import json
import math
import os
import re
import signal
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray
from originman_board_ros import protocol as p
from originman_board_ros.simulation import VirtualOriginManBoardModel
from rcl_interfaces.msg import Parameter
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter as RclpyParameter
from sensor_msgs.msg import BatteryState, Imu, JointState
from std_msgs.msg import String
from std_srvs.srv import SetBool, Trigger
from support import stamp_s
from uav_serial_common.process import wait_for, wait_scale
from uav_serial_drivers.msg import (BusServoCommand, BusServoStateArray, ButtonEvent,
                                    BuzzerPattern, LedPattern, MotorSpeeds, OledText,
                                    PwmServoCommand, RgbPixels, SbusFrame)
from uav_serial_drivers.srv import (BusServoIds, GetBusServoState, GetPwmServoState, PressKey,
                                    SetBusServoId, SetBusServoLimits, SetBusServoOffset,
                                    SetBusServoTorque, SetImu, SetPwmServoOffset, SetSbus)

G = 9.80665
DRIVER = '/originman_board'
BOARD = '/virtual_originman_board'


class Rig:
    """The virtual board (a process) and the driver, with the client's subscriptions.

    The driver is started by `driver` (in this process) or, without it, by `launch`.
    """

    def __init__(self, ros, launch, tmp_path, namespace='', board=None, driver=None, **params):
        self.ros = ros
        self.launch = launch
        self.link = str(tmp_path / 'voriginman')
        self.ns = f'/{namespace}' if namespace else ''
        self.state = ros.subscribe(String, f'{BOARD}/state')
        self.diagnostics = ros.subscribe(DiagnosticArray, '/diagnostics')
        self.board = launch.start('virtual_originman_board',
                                  parameters={'link': self.link, **(board or {})}, ros=ros,
                                  wait_service=f'{BOARD}/press_key')
        params.setdefault('bus_servo_ids', [1, 2, 3])
        self.driver = (driver or launch).start(
            'originman_board_node', parameters={'port': self.link, **params},
            namespace=self.ns or None, ros=ros, wait_service=f'{self.driver_name}/stop_motors')

    @property
    def driver_name(self):
        return f'{self.ns}{DRIVER}'

    def topic(self, name):
        return f'{self.driver_name}/{name}'

    def board_state(self, predicate=lambda s: True, timeout=10.0, what='a board state'):
        """Wait for a ``~/state`` published from now on that satisfies ``predicate``."""
        msg = self.state.wait(lambda m: predicate(json.loads(m.data)), timeout, what,
                              start=len(self.state))
        return json.loads(msg.data)

    def call(self, srv_type, name, **fields):
        return self.ros.call(srv_type, name, srv_type.Request(**fields))

    def answered(self, srv_type, name, **fields):
        """Call the driver's ``~/name`` until the board answered what the service reads back.

        The board here is a process on a loaded host, not a microcontroller: now and then it
        (or the driver's reader) is stalled past a read's 2 x 100 ms, and the driver rightly
        answers that it got no reply, the outcome unknown (never a success); a user asks again.
        Stalled past ``offline_timeout_s`` (2.7 s once, in a campaign run beside a busy loop),
        the board is judged offline and the call refused: asked again too.
        """
        replies = []

        def board_answered():
            replies.append(self.call(srv_type, f'{self.driver_name}/{name}', **fields))
            # The link's timeout, not the board's 'no reply within 5 ms' from the servo.
            return not re.search(r'no reply within \d+ ms after|the board is offline',
                                 replies[-1].message)
        wait_for(board_answered, 30, interval=0.0, what=f'{name} answered by the board')
        assert not any(r.success for r in replies[:-1]), (name, [r.message for r in replies])
        return replies[-1]

    def board_call(self, srv_type, name, **fields):
        reply = self.call(srv_type, f'{BOARD}/{name}', **fields)
        assert reply.success, reply.message
        return reply

    def set_board_params(self, **values):
        request = SetParameters.Request(parameters=[
            RclpyParameter(k, value=v).to_parameter_msg() for k, v in values.items()])
        results = self.ros.call(SetParameters, f'{BOARD}/set_parameters', request).results
        assert all(r.successful for r in results), results

    def diag(self, task, predicate=lambda s: True, timeout=10.0, what=None):
        """Wait for a status ``<node>: <task>`` from now on; return (status, its values)."""
        name = f'{self.driver_name}: {task}'

        def find(array):
            for status in array.status:
                if status.name == name and predicate(status):
                    return status
            return None
        msg = self.diagnostics.wait(lambda a: find(a) is not None, timeout,
                                    what or f'diagnostics {name}', start=len(self.diagnostics))
        status = find(msg)
        return status, {kv.key: kv.value for kv in status.values}

    def online(self):
        return self.diag('link', lambda s: s.level == b'\x00', 15, 'the driver online')


def values_of(status):
    return {kv.key: kv.value for kv in status.values}


def model_key_events(key_id, kind):
    """The key events the board's firmware model sends for one press sequence of a fresh key."""
    model = VirtualOriginManBoardModel(0.0, imu_rate_hz=0.0)
    model.press_key(key_id, kind)
    out = model.advance(6.0)
    reports = [p.decode_board_frame(f) for f in p.StreamDecoder().feed(out)]
    return [(r.key_id, r.event, r.event_name) for r in reports if isinstance(r, p.KeyReport)]


# ----- reports ---------------------------------------------------------------------------------

def test_reports_are_published_in_si_units_with_the_keys_exact_events(ros, launch, driver,
                                                                      tmp_path):
    imu = ros.subscribe(Imu, f'{DRIVER}/imu')
    battery = ros.subscribe(BatteryState, f'{DRIVER}/battery')
    buttons = ros.subscribe(ButtonEvent, f'{DRIVER}/button')
    sbus = ros.subscribe(SbusFrame, f'{DRIVER}/sbus')
    rig = Rig(ros, launch, tmp_path, driver=driver)
    status, values = rig.online()
    assert status.hardware_id == rig.link
    first = imu.wait(lambda m: True, 10, 'an IMU message')
    assert first.header.frame_id == 'imu_link' and first.header.stamp.sec > 0
    assert first.orientation_covariance[0] == -1.0  # no orientation (REP-145)
    assert math.isclose(first.linear_acceleration.z, G, rel_tol=1e-6)  # 1 g at rest (O7)

    # O7: g and deg/s on the wire, m/s^2 and rad/s on the topic.
    rig.board_call(SetImu, 'set_imu', accel_g=[0.5, -0.25, 1.0], gyro_dps=[90.0, 0.0, -180.0],
                   rate_hz=-1.0)
    moved = imu.wait(lambda m: m.angular_velocity.z < -3.0, 10, 'the new IMU values',
                     start=len(imu))
    assert math.isclose(moved.linear_acceleration.x, 0.5 * G, rel_tol=1e-6)
    assert math.isclose(moved.linear_acceleration.y, -0.25 * G, rel_tol=1e-6)
    assert math.isclose(moved.angular_velocity.x, math.pi / 2, rel_tol=1e-6)
    assert math.isclose(moved.angular_velocity.z, -math.pi, rel_tol=1e-6)

    # O9: millivolts on the wire, volts on the topic, NaN where the board measures nothing.
    volts = battery.wait(lambda m: True, 10, 'a battery message')
    assert math.isclose(volts.voltage, 7.4, rel_tol=1e-6)
    assert all(math.isnan(x) for x in (volts.current, volts.temperature, volts.percentage,
                                       volts.charge, volts.capacity))
    rig.set_board_params(battery_mv=6100)
    battery.wait(lambda m: math.isclose(m.voltage, 6.1, rel_tol=1e-6), 10, '6.1 V')
    # low_battery_mv -1: the warning threshold is the board's own 6300 mV.
    rig.diag('battery', lambda s: s.level == b'\x01', 10, 'a battery warning')

    # O17: every key report, exactly the sequence the board's button driver sends (a key of
    # its own for each: a press within 300 ms of the last click would count as a second one).
    for key_id, kind in ((1, 'click'), (2, 'double')):
        start = len(buttons)
        expected = model_key_events(key_id, kind)
        rig.board_call(PressKey, 'press_key', key_id=key_id, sequence=kind, hold_s=0.0)
        buttons.wait(lambda m: m.event_name == 'click' and len(buttons) - start
                     >= len(expected), 10, f'the events of a {kind}', start=start)
        got = [(m.key_id, m.event, m.event_name) for m in buttons.messages[start:]]
        assert got == expected, kind
    assert [e[2] for e in model_key_events(1, 'click')] == [
        'pressed', 'release_from_short_press', 'click']

    # O16: raw channels on the wire; normalized = (raw - 992) / 820, clamped.
    raw = [172, 992, 1811, 2047, 0] + [992] * 11
    rig.board_call(SetSbus, 'set_sbus', channels=raw, signal_loss=True)
    frame = sbus.wait(lambda m: m.signal_loss, 10, 'an SBUS frame')
    assert list(frame.channels) == raw and not frame.failsafe
    assert [round(float(v), 4) for v in frame.normalized[:5]] == [-1.0, 0.0, 0.9988, 1.0, -1.0]

    # Noise on the wire is skipped; the board stays online.
    rig.board_call(Trigger, 'inject_garbage')
    rig.diag('link', lambda s: int(values_of(s)['bytes discarded']) > 0, 10, 'noise discarded')
    status, values = rig.diag('link', lambda s: s.level == b'\x00'
                              and values_of(s)['imu rate [Hz]'] != 'n/a', 10, 'IMU rate')
    assert float(values['imu rate [Hz]']) > 0 and int(values['frames']) > 0
    names = {s.name for s in rig.diagnostics.last.status if s.name.startswith(DRIVER)}
    assert names == {f'{DRIVER}: link', f'{DRIVER}: battery', f'{DRIVER}: bus servos'}


# ----- bus servos, PWM servos, motors --------------------------------------------------------

def test_a_servo_sweep_shows_in_joint_states_and_every_service_answers(ros, launch, driver,
                                                                       tmp_path):
    joints = ros.subscribe(JointState, '/joint_states')
    states = ros.subscribe(BusServoStateArray, f'{DRIVER}/bus_servo/states')
    rig = Rig(ros, launch, tmp_path, driver=driver, motor_timeout_s=2.0)
    rig.online()
    joints.wait(lambda m: m.name == ['bus_servo_1', 'bus_servo_2', 'bus_servo_3'], 10,
                'joint_states of three servos')
    command = ros.publisher(BusServoCommand, f'{DRIVER}/bus_servo/command')

    # A sweep: rad rise with the raw position, (raw - 500) x 0.24 deg. A move of 1.5 s: beside
    # a busy loop the driver or the board stalls for up to 0.9 s now and then, and a 0.6 s move
    # could start and end within one stall (no position in between was read).
    for target in (800, 200):
        start = len(joints)
        command.publish(BusServoCommand(ids=[1], positions=[target], duration_s=1.5))
        want = math.radians((target - 500) * 0.24)
        joints.wait(lambda m: abs(m.position[0] - want) < 1e-9, 10, f'servo 1 at {target}',
                    start=start)
        path = [m.position[0] for m in joints.messages[start:]]
        path = path[:next(i for i, v in enumerate(path) if abs(v - want) < 1e-9) + 1]
        steps = [b - a for a, b in zip(path, path[1:])]
        assert all(s >= 0 for s in steps) if target > 500 else all(s <= 0 for s in steps)
        assert any(min(path[0], want) < v < max(path[0], want) for v in path), path
    assert [s.online for s in states.last.servos] == [True, True, True]

    answered = rig.answered

    # O14: a read the board answers with success -1 is a failure with its reason.
    reply = answered(GetBusServoState, 'bus_servo/get_state', ids=[1, 9])
    assert not reply.success and 'servo 9' in reply.message and 'success -1' in reply.message
    good, bad = reply.servos
    assert good.online and good.position == 200 and good.max_position == 1000
    assert math.isclose(good.voltage_v, 7.4) and good.temperature_c == 30.0
    assert not bad.online and bad.id == 9
    for srv, name, fields in (
            (SetBusServoTorque, 'set_torque', {'ids': [9], 'enable': True}),
            (SetBusServoOffset, 'set_offset', {'id': 9, 'offset': 5, 'save': False}),
            (SetBusServoLimits, 'set_limits', {'id': 9, 'min_position': 10,
                                               'max_position': 990})):
        reply = answered(srv, f'bus_servo/{name}', **fields)
        assert not reply.success and 'success -1' in reply.message, (name, reply.message)

    # O6: torque on is sub-command 0x0C on the wire, off is 0x0B; both read back.
    for enable, sub in ((False, 0x0B), (True, 0x0C)):
        reply = answered(SetBusServoTorque, 'bus_servo/set_torque', ids=[2], enable=enable)
        assert reply.success, reply.message
        frame = p.encode_frame(p.Function.BUS_SERVO, bytes([sub, 2])).hex(' ')
        rig.board_state(lambda s: any(c['raw'] == frame for c in s['wire']['recent']), 5,
                        f'torque frame {frame}')
    assert rig.call(BusServoIds, f'{DRIVER}/bus_servo/stop', ids=[2, 3]).success
    reply = answered(SetBusServoOffset, 'bus_servo/set_offset', id=1, offset=-12, save=True)
    assert reply.success, reply.message
    reply = answered(SetBusServoLimits, 'bus_servo/set_limits', id=1, min_position=100,
                     max_position=900, min_voltage_mv=5000, max_voltage_mv=8400,
                     max_temperature_c=70)
    assert reply.success, reply.message
    servo = rig.board_state(lambda s: s['bus_servos'][0]['angle_limits'] == [100, 900], 5,
                            'limits')['bus_servos'][0]
    assert (servo['offset'], servo['voltage_limits'], servo['temperature_limit_c']) == \
        (-12, [5000, 8400], 70)
    taken = answered(SetBusServoId, 'bus_servo/set_id', id=3, new_id=2)  # (reads only)
    assert not taken.success and 'taken' in taken.message
    assert rig.call(SetBusServoId, f'{DRIVER}/bus_servo/set_id', id=3, new_id=7).success
    states.wait(lambda m: [s.id for s in m.servos] == [1, 2, 7] and m.servos[2].online, 10,
                'servo 3 polled as 7', start=len(states))

    # PWM servos: moves, offsets read back, state of all four.
    pwm = ros.publisher(PwmServoCommand, f'{DRIVER}/pwm_servo/command')
    pwm.publish(PwmServoCommand(ids=[1, 3], pulses_us=[2000, 1000], duration_s=0.2))
    rig.board_state(lambda s: s['pwm_servos']['1']['pulse_us'] == 2000
                    and s['pwm_servos']['3']['pulse_us'] == 1000, 5, 'PWM servos moved')
    reply = answered(SetPwmServoOffset, 'pwm_servo/set_offset', id=2, offset_us=-20)
    assert reply.success, reply.message
    reply = answered(GetPwmServoState, 'pwm_servo/get_state', ids=[])
    assert reply.success, reply.message
    assert list(reply.pulses_us) == [2000, 1500, 1000, 1500]
    assert list(reply.offsets_us) == [0, -20, 0, 0]

    # O3: motors 1..4 on the topic are wire ids 0..3; ~/stop_motors stops all four (O4).
    motors = ros.publisher(MotorSpeeds, f'{DRIVER}/set_motor_speeds')
    motors.publish(MotorSpeeds(motor_ids=[1, 4], rps=[0.5, -1.0]))
    state = rig.board_state(lambda s: (s['wire']['last_motor'] or {}).get('kind')
                            == 'SetMotorSpeeds', 5, 'a motor command')
    assert state['wire']['last_motor']['items'] == [[0, 0.5], [3, -1.0]]
    reply = rig.call(Trigger, f'{DRIVER}/stop_motors')
    assert reply.success, reply.message
    state = rig.board_state(lambda s: s['wire']['last_motor']['kind'] == 'StopMotors', 5,
                            'the stop')
    assert state['wire']['last_motor']['wire_ids'] == [0, 1, 2, 3]
    assert state['motor_set_points'] == [0.0] * 4


class KeepAlive:
    """A thread that sends a motor command, then an empty one every ``period_s``.

    It notes when each publish began and ended, so a test judges the driver against the gaps
    this publisher really had: a loaded host can hold this thread (or this whole process) longer
    than the driver's timeout, and the driver then rightly takes it for silence.
    """

    def __init__(self, publisher, first, period_s=0.05):
        self.publisher = publisher
        self.first = first
        self.period_s = period_s
        self.sent = []  # (began, ended) of each publish, time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()

    def _run(self):
        msg = self.first
        while True:
            began = time.monotonic()
            self.publisher.publish(msg)
            self.sent.append((began, time.monotonic()))
            msg = MotorSpeeds()
            if self._stop.wait(self.period_s):
                return

    def longest_gap(self):
        """The longest time the driver can have gone without a message from this publisher."""
        if len(self.sent) < 2:
            return math.inf
        # From a publish's start to the next one's end: never shorter than the true gap.
        return max(b[1] - a[0] for a, b in zip(self.sent, self.sent[1:]))


def test_motors_stop_when_the_commands_stop_and_any_message_keeps_them(ros, launch,
                                                                       tmp_path):
    # The driver runs as a process of its own: its watchdog must not share a GIL with the
    # keep-alive's publisher.
    timeout = 1.0
    running = [1.0, -1.0, 0.0, 0.0]
    imu = ros.subscribe(Imu, f'{DRIVER}/imu')
    rig = Rig(ros, launch, tmp_path, bus_servo_ids=[], motor_timeout_s=timeout)
    rig.online()
    motors = ros.publisher(MotorSpeeds, f'{DRIVER}/set_motor_speeds')
    # The keep-alive starts with the command itself (waiting to see the motors turn before
    # starting it took 1.4 s beside a busy loop, and the driver rightly stopped them meanwhile).
    # A window proves nothing when this publisher was held for half the timeout, or the driver
    # itself was (its IMU messages, 50 Hz, stamped as it publishes them, had such a gap: a
    # driver that cannot run cannot take a keep-alive, and its watchdog rightly does not wait
    # for the queue); such a window is run again. In a window where both kept their pace, any
    # stop is the driver's fault.
    gaps = []
    for _ in range(5):
        # The watchdog idle (its stop at the connect, O38, or after the last window), so that
        # a stop from before this window cannot land in it.
        rig.board_state(lambda s: s['motor_set_points'] == [0.0] * 4 and
                        s['wire']['counts'].get('StopMotors', 0) >= 1, 10, 'the motors stopped')
        start, imu_start = len(rig.state), max(0, len(imu) - 1)
        with KeepAlive(motors, MotorSpeeds(motor_ids=[1, 2], rps=running[:2])) as keep_alive:
            t0 = rig.board_state()['time']
            first = rig.board_state(lambda s: s['motor_set_points'] == running or
                                    s['time'] > t0 + 2 * timeout, 10, 'motors on')
            if first['motor_set_points'] == running:
                # Empty messages (a keep-alive) restart the timeout as well: four timeouts
                # later the motors still turn.
                end = rig.board_state(lambda s: s['time'] > first['time'] + 4 * timeout, 15,
                                      'time passing')
        ended = time.time()
        imu.wait(lambda m: stamp_s(m) >= ended, 10, 'an IMU message after the window',
                 start=imu_start)
        stamps = [stamp_s(m) for m in imu.messages[imu_start:]]
        stamps = stamps[:next(i for i, t in enumerate(stamps) if t >= ended) + 1]
        gaps.append((round(keep_alive.longest_gap(), 3),
                     round(max(b - a for a, b in zip(stamps, stamps[1:])), 3)))
        if max(gaps[-1]) < timeout / 2:
            break
        print(f'keep-alive window run again: longest gaps (publisher, driver) {gaps[-1]} s')
    else:
        raise AssertionError(f"this test's publisher or the driver never kept its pace (the "
                             f'longest gaps of each window, publisher and driver: {gaps} s): '
                             'the driver cannot be judged')
    assert first['motor_set_points'] == running, 'the motors were stopped before they were seen'
    states = [json.loads(m.data) for m in rig.state.messages[start:]]
    window = [s for s in states if first['time'] <= s['time'] <= end['time']]
    assert [s['motor_set_points'] for s in window] == [running] * len(window)
    # No stop was ever sent while the keep-alive came.
    assert {s['wire']['counts'].get('StopMotors', 0) for s in window} == \
        {first['wire']['counts'].get('StopMotors', 0)}
    # Silence: the driver stops every motor (the board itself never would).
    state = rig.board_state(lambda s: s['motor_set_points'] == [0.0] * 4, 5, 'motors stopped')
    assert state['wire']['last_motor'] == {'kind': 'StopMotors', 'sub': 3,
                                           'wire_ids': [0, 1, 2, 3]}
    _, values = rig.diag('link', lambda s: int(values_of(s)['motor timeout stops']) >= 1, 5,
                         'the stop in diagnostics')


# ----- bad input -------------------------------------------------------------------------------

BAD_TOPICS = [
    (LedPattern, 'set_led', LedPattern(led_id=3, on_s=0.1, off_s=0.1, repeat=1), 'out_of_range'),
    (LedPattern, 'set_led', LedPattern(led_id=1, on_s=math.nan, off_s=0.1), 'not_finite'),
    (LedPattern, 'set_led', LedPattern(led_id=1, on_s=70.0, off_s=0.1), 'out_of_range'),
    (BuzzerPattern, 'set_buzzer', BuzzerPattern(frequency_hz=2000, on_s=-0.1), 'out_of_range'),
    (RgbPixels, 'set_rgb', RgbPixels(indices=[3], red=[1], green=[1], blue=[1]),
     'out_of_range'),
    (RgbPixels, 'set_rgb', RgbPixels(indices=[1, 2], red=[1], green=[1, 2], blue=[1, 2]),
     'length_mismatch'),
    (OledText, 'set_oled', OledText(line=3, text='hi'), 'out_of_range'),
    (OledText, 'set_oled', OledText(line=1, text='é' * 12), 'too_long'),
    (MotorSpeeds, 'set_motor_speeds', MotorSpeeds(motor_ids=[5], rps=[1.0]), 'out_of_range'),
    (MotorSpeeds, 'set_motor_speeds', MotorSpeeds(motor_ids=[1], rps=[6.5]), 'out_of_range'),
    (MotorSpeeds, 'set_motor_speeds', MotorSpeeds(motor_ids=[1], rps=[math.inf]), 'not_finite'),
    (MotorSpeeds, 'set_motor_speeds', MotorSpeeds(motor_ids=[1, 2], rps=[1.0]),
     'length_mismatch'),
    (PwmServoCommand, 'pwm_servo/command', PwmServoCommand(ids=[5], pulses_us=[1500],
                                                           duration_s=1.0), 'out_of_range'),
    (PwmServoCommand, 'pwm_servo/command', PwmServoCommand(ids=[1], pulses_us=[400],
                                                           duration_s=1.0), 'out_of_range'),
    (PwmServoCommand, 'pwm_servo/command', PwmServoCommand(ids=[1], pulses_us=[1500],
                                                           duration_s=0.01), 'out_of_range'),
    (BusServoCommand, 'bus_servo/command', BusServoCommand(ids=[254], positions=[500],
                                                           duration_s=1.0), 'out_of_range'),
    (BusServoCommand, 'bus_servo/command', BusServoCommand(ids=[1], positions=[1001],
                                                           duration_s=1.0), 'out_of_range'),
    (BusServoCommand, 'bus_servo/command', BusServoCommand(ids=[1, 1], positions=[1, 2],
                                                           duration_s=1.0), 'duplicate'),
    (BusServoCommand, 'bus_servo/command', BusServoCommand(ids=[1], positions=[500],
                                                           duration_s=66.0), 'out_of_range'),
]
BAD_SERVICES = [
    (GetBusServoState, 'bus_servo/get_state', {'ids': [254]}),
    (SetBusServoTorque, 'bus_servo/set_torque', {'ids': [], 'enable': True}),
    (BusServoIds, 'bus_servo/stop', {'ids': [1, 1]}),
    (SetBusServoId, 'bus_servo/set_id', {'id': 1, 'new_id': 254}),
    (SetBusServoOffset, 'bus_servo/set_offset', {'id': 1, 'offset': 126, 'save': True}),
    (SetBusServoLimits, 'bus_servo/set_limits', {'id': 1, 'min_position': 900,
                                                 'max_position': 100}),
    (SetBusServoLimits, 'bus_servo/set_limits', {'id': 1, 'min_voltage_mv': 4000,
                                                 'max_voltage_mv': 8000}),
    (SetBusServoLimits, 'bus_servo/set_limits', {'id': 1, 'max_temperature_c': 101}),
    (GetPwmServoState, 'pwm_servo/get_state', {'ids': [0]}),
    (SetPwmServoOffset, 'pwm_servo/set_offset', {'id': 5, 'offset_us': 0}),
    (SetPwmServoOffset, 'pwm_servo/set_offset', {'id': 1, 'offset_us': 101}),
]


def test_bad_values_are_refused_with_nothing_on_the_wire_and_counted(ros, launch, driver,
                                                                     tmp_path):
    # No polling and no motor timeout: the driver sends nothing of its own.
    rig = Rig(ros, launch, tmp_path, driver=driver, bus_servo_ids=[], motor_timeout_s=0.0)
    rig.online()
    before = rig.board_state(lambda s: True, 5, 'the wire before')['wire']
    assert before['frames'] == 0
    publishers = {}
    for msg_type, name, msg, _ in BAD_TOPICS:
        if name not in publishers:
            publishers[name] = ros.publisher(msg_type, f'{DRIVER}/{name}')
        publishers[name].publish(msg)
    for srv_type, name, fields in BAD_SERVICES:
        reply = rig.call(srv_type, f'{DRIVER}/{name}', **fields)
        assert not reply.success and reply.message, (name, fields)
    total = len(BAD_TOPICS) + len(BAD_SERVICES)
    _, values = rig.diag('link', lambda s: int(values_of(s)['refused commands']) >= total, 10,
                         f'{total} refusals in diagnostics')
    assert int(values['refused commands']) == total
    for cause in {c for *_, c in BAD_TOPICS}:
        assert int(values[f'refused: {cause}']) >= sum(1 for *_, c in BAD_TOPICS if c == cause)
    # A read after them all: whatever the driver wrote before it has reached the board. (Two
    # reads, pulse and offset; a loaded host may send one again, or stall the board past both
    # tries, answered as no reply: asked again.)
    reply = rig.answered(GetPwmServoState, 'pwm_servo/get_state', ids=[1])
    assert reply.success, reply.message
    after = rig.board_state(lambda s: s['wire']['counts'].get('PwmRead', 0) >= 2, 5,
                            'the read at the board')['wire']
    assert set(after['counts']) == {'PwmRead'} and before['recent'] == after['recent'] == []
    assert rig.driver.alive()
    # Each cause is logged, at most once per 5 s.
    log = rig.driver.output()
    assert log.count('refused (out_of_range)') == 1, log
    assert 'set_oled: refused (too_long)' in log


# ----- settings, reconnects, shutdown ----------------------------------------------------------

def test_desired_settings_are_written_at_connect_and_after_the_board_comes_back(
        ros, launch, driver, tmp_path):
    desired = {'battery_limit_mv': 7000, 'motor_type': 'JGB37'}
    offsets = {'1': 10, '2': -20, '3': 0, '4': 5}

    def applied(s):
        return all(s[k] == v for k, v in desired.items()) and \
            {i: v['offset_us'] for i, v in s['pwm_servos'].items()} == offsets
    rig = Rig(ros, launch, tmp_path, driver=driver, bus_servo_ids=[], low_battery_mv=7000,
              motor_type='JGB37',
              pwm_servo_offsets_us=[10, -20, 0, 5], offline_timeout_s=0.5)
    rig.board_state(lambda s: applied(s) and s['boots'] == 1, 10, 'the settings at connect')
    rig.diag('link', lambda s: s.level == b'\x00' and 'written' in values_of(s)['settings'],
             10, 'settings confirmed')
    # A reboot loses them: the board goes silent (offline), comes back, gets them again.
    rig.board_call(SetBool, 'set_power', data=False)
    rig.diag('link', lambda s: s.level == b'\x02', 10, 'offline while the board is off')
    rig.board_call(SetBool, 'set_power', data=True)
    rig.board_state(lambda s: applied(s) and s['boots'] == 2, 10, 'the settings after a reboot')
    # Unplugged, rebooted meanwhile, plugged back in: written again once frames arrive.
    rig.board_call(SetBool, 'disconnect', data=True)
    rig.diag('link', lambda s: s.level == b'\x02', 10, 'offline while unplugged')
    rig.board_call(SetBool, 'set_power', data=False)
    rig.board_call(SetBool, 'set_power', data=True)
    state = rig.board_state(lambda s: s['boots'] == 3, 5, 'the reboot while unplugged')
    assert state['battery_limit_mv'] == 6300 and state['motor_type'] == 'JGB520'
    rig.board_call(SetBool, 'disconnect', data=False)
    rig.board_state(lambda s: applied(s) and s['boots'] == 3, 15, 'the settings after the '
                    'cable came back')
    # A runtime change of a desired setting is written at once.
    request = SetParameters.Request(parameters=[
        RclpyParameter('low_battery_mv', value=6800).to_parameter_msg()])
    assert ros.call(SetParameters, f'{DRIVER}/set_parameters', request).results[0].successful
    rig.board_state(lambda s: s['battery_limit_mv'] == 6800, 10, 'the new threshold')
    request = SetParameters.Request(parameters=[Parameter(
        name='motor_type', value=RclpyParameter('x', value='JGB99').get_parameter_value())])
    assert not ros.call(SetParameters, f'{DRIVER}/set_parameters', request).results[0].successful


def test_a_double_sigint_exits_0_and_the_last_motor_frame_is_a_stop(ros, launch, tmp_path):
    rig = Rig(ros, launch, tmp_path, motor_timeout_s=0.0)
    rig.online()
    motors = ros.publisher(MotorSpeeds, f'{DRIVER}/set_motor_speeds')
    motors.publish(MotorSpeeds(motor_ids=[1, 2, 3, 4], rps=[1.0, 1.0, -1.0, 0.5]))
    rig.board_state(lambda s: s['motor_set_points'] == [1.0, 1.0, -1.0, 0.5], 5, 'motors on')
    # ros2 launch's Ctrl-C: the terminal's SIGINT and launch's own, close together.
    os.kill(rig.driver.pid, signal.SIGINT)
    os.kill(rig.driver.pid, signal.SIGINT)
    assert rig.driver.popen.wait(10 * wait_scale()) == 0, rig.driver.output()
    state = rig.board_state(lambda s: s['motor_set_points'] == [0.0] * 4, 5, 'motors stopped')
    assert state['wire']['last_motor'] == {'kind': 'StopMotors', 'sub': 3,
                                           'wire_ids': [0, 1, 2, 3]}
    assert 'shutdown: every motor stopped' in rig.driver.output()


def test_diagnostics_and_topics_follow_the_namespace(ros, launch, driver, tmp_path):
    imu = ros.subscribe(Imu, '/uav1/originman_board/imu')
    joints = ros.subscribe(JointState, '/uav1/joint_states')
    rig = Rig(ros, launch, tmp_path, driver=driver, namespace='uav1')
    status, _ = rig.online()
    assert status.name == '/uav1/originman_board: link'
    imu.wait(lambda m: True, 10, 'IMU under the namespace')
    joints.wait(lambda m: len(m.name) == 3, 10, 'joint_states under the namespace')
    names = {s.name for s in rig.diagnostics.last.status}
    assert not any(n.startswith('/originman_board') for n in names)
    wait_for(lambda: '/uav1/originman_board/bus_servo/get_state' in
             [n for n, _ in ros.node.get_service_names_and_types()], 5, what='services')
