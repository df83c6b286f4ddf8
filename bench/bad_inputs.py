"""Every service of every driver called with malformed and out-of-range requests.

Each case must be refused (``success`` false) without a byte on the wire. The OriginMan
driver's topics get bad messages too: topics have no answer, so a message is refused when the
driver's ``link`` diagnostics count one more refused command within 5 s. The drivers keep
polling while the cases run, so "a byte on the wire" means a frame that the driver's own
background traffic does not contain: first the benchmark records, for a few seconds, every
distinct frame the idle driver sends (position/telemetry READs, status/aux queries); then any
other frame that reaches the device between a call and 50 ms after its response counts
against that case. The handset driver has no services: its bad inputs are frames on the wire,
battery messages and parameter sets (``handset``), and it must never write to the modem (H11).
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any, Dict, Iterable, List, Set, Tuple

from bench.common import (HandsetRig, OriginManRig, ParachuteRig, ros_client, ServoRig, wait_for,
                          workdir)

NAN = math.nan
INF = math.inf


def servo_cases() -> List[Tuple[str, str, Dict[str, Any]]]:
    """Return (service, srv type name, request fields) of the servo driver's bad requests."""
    wp = 'WritePositions'
    return [
        ('write_positions', wp, {'names': ['no_such_joint'], 'positions': [0.0]}),
        ('write_positions', wp, {'ids': [99], 'positions': [0.0]}),
        ('write_positions', wp, {'ids': [0], 'positions': [0.0]}),
        ('write_positions', wp, {'ids': [255], 'positions': [0.0]}),
        ('write_positions', wp, {'ids': [1, 2], 'positions': [0.0]}),
        ('write_positions', wp, {'ids': [1], 'positions': [0.0, 0.1]}),
        ('write_positions', wp, {'ids': [1], 'positions': [NAN]}),
        ('write_positions', wp, {'ids': [1], 'positions': [INF]}),
        ('write_positions', wp, {'ids': [1], 'positions': [100.0]}),
        ('write_positions', wp, {'ids': [1], 'names': ['servo_1'], 'positions': [0.0]}),
        ('write_positions', wp, {'ids': [1], 'positions': [0.0], 'move_time_ms': -5}),
        ('write_positions', wp, {'ids': [1], 'positions': [0.0], 'move_time_ms': 70000}),
        ('write_positions', wp, {'ids': [1], 'positions': [0.0], 'staged': True,
                                 'move_time_ms': 70000}),
        ('write_positions', wp, {}),
        ('set_torque', 'SetTorque', {'ids': [99], 'enable': True}),
        ('set_torque', 'SetTorque', {'ids': [0], 'enable': True}),
        ('read_register', 'ReadRegister', {'id': 0, 'register_name': 'present_position'}),
        ('read_register', 'ReadRegister', {'id': 255, 'register_name': 'present_position'}),
        ('read_register', 'ReadRegister', {'id': 1, 'register_name': 'no_such_register'}),
        ('read_register', 'ReadRegister', {'id': 1, 'address': 0x38, 'length': 0}),
        ('read_register', 'ReadRegister', {'id': 1, 'address': 0x38, 'length': 200}),
        ('read_register', 'ReadRegister', {'id': 1, 'address': 250, 'length': 20}),
        ('write_register', 'WriteRegister', {'id': 1, 'register_name': 'present_position',
                                             'value': 5}),
        ('write_register', 'WriteRegister', {'id': 1, 'register_name': 'current', 'value': 1}),
        ('write_register', 'WriteRegister', {'id': 1, 'register_name': 'torque_enable',
                                             'value': 300}),
        ('write_register', 'WriteRegister', {'id': 1, 'register_name': 'target_position',
                                             'value': -1}),
        ('write_register', 'WriteRegister', {'id': 1, 'register_name': 'target_position',
                                             'value': 1 << 40}),
        ('write_register', 'WriteRegister', {'id': 1, 'register_name': 'no_such_register',
                                             'value': 0}),
        ('write_register', 'WriteRegister', {'id': 0, 'register_name': 'torque_enable',
                                             'value': 0}),
        ('scan', 'ScanBus', {'first_id': 0, 'last_id': 10}),
        ('scan', 'ScanBus', {'first_id': 10, 'last_id': 5}),
        ('scan', 'ScanBus', {'first_id': 1, 'last_id': 251}),
        ('go_to_preset', 'GoToPreset', {'ids': [1], 'preset': 0}),
        ('go_to_preset', 'GoToPreset', {'ids': [1], 'preset': 4}),
        ('go_to_preset', 'GoToPreset', {'ids': [99], 'preset': 1}),
        ('set_id', 'SetId', {'id': 1, 'new_id': 0}),
        ('set_id', 'SetId', {'id': 1, 'new_id': 251}),
        ('set_id', 'SetId', {'id': 1, 'new_id': 254}),
        ('set_id', 'SetId', {'id': 0, 'new_id': 5}),
        ('factory_reset', 'FactoryReset', {'id': 1, 'confirm': ''}),
        ('factory_reset', 'FactoryReset', {'id': 1, 'confirm': 'reset'}),
        ('factory_reset', 'FactoryReset', {'id': 1, 'confirm': 'RESET '}),
        ('factory_reset', 'FactoryReset', {'id': 0, 'confirm': 'RESET'}),
        ('factory_reset', 'FactoryReset', {'id': 255, 'confirm': 'RESET'}),
    ]


def parachute_cases() -> List[Tuple[str, str, Dict[str, Any]]]:
    """Return (service, srv type name, request fields) of the parachute driver's bad requests."""
    th = 'SetThresholds'
    nan4 = {'attitude_deg': NAN, 'freefall_g': NAN, 'freefall_time_s': NAN,
            'light_threshold_v': NAN}

    def thresholds(**kw: float) -> Dict[str, float]:
        return dict(nan4, **kw)
    cases = [('deploy', 'Deploy', {'confirm': c}) for c in
             ('', 'deploy', 'DEPLOY ', ' DEPLOY', 'DEPLOYDEPLOY', 'SHUTDOWN')]
    # The module starts locked: the right token without arm_if_locked is refused too.
    cases.append(('deploy', 'Deploy', {'confirm': 'DEPLOY', 'arm_if_locked': False}))
    for key, values in (('attitude_deg', (5.0, 91.0, 45.5, -10.0, 1e9, INF, -INF)),
                        ('freefall_g', (0.0, 0.04, 1.0, -1.0, INF)),
                        ('freefall_time_s', (0.0, 2.6, 100.0, -0.5, INF)),
                        ('light_threshold_v', (-0.1, 25.6, 1e6, -INF))):
        cases += [('set_thresholds', th, thresholds(**{key: v})) for v in values]
    cases += [('shutdown_module', 'Confirmed', {'confirm': c})
              for c in ('', 'shutdown', 'SHUTDOWN ', 'DEPLOY')]
    cases += [('answer_trigger_request', 'std_srvs/SetBool', {'data': d}) for d in (True, False)]
    return cases


def originman_cases() -> List[Tuple[str, str, Dict[str, Any]]]:
    """Return (service, srv type name, request fields) of the OriginMan driver's bad requests."""
    limits = 'SetBusServoLimits'
    return [
        ('bus_servo/get_state', 'GetBusServoState', {'ids': [254]}),
        ('bus_servo/get_state', 'GetBusServoState', {'ids': [1, 1]}),
        ('bus_servo/set_torque', 'SetBusServoTorque', {'ids': [], 'enable': True}),
        ('bus_servo/set_torque', 'SetBusServoTorque', {'ids': [255], 'enable': False}),
        ('bus_servo/stop', 'BusServoIds', {'ids': []}),
        ('bus_servo/stop', 'BusServoIds', {'ids': [2, 2]}),
        ('bus_servo/set_id', 'SetBusServoId', {'id': 1, 'new_id': 254}),
        ('bus_servo/set_id', 'SetBusServoId', {'id': 254, 'new_id': 5}),
        ('bus_servo/set_id', 'SetBusServoId', {'id': 1, 'new_id': 1}),
        ('bus_servo/set_id', 'SetBusServoId', {'id': 1, 'new_id': 2}),  # 2 answers: taken
        ('bus_servo/set_offset', 'SetBusServoOffset', {'id': 1, 'offset': 126}),
        ('bus_servo/set_offset', 'SetBusServoOffset', {'id': 1, 'offset': -128}),
        ('bus_servo/set_limits', limits, {'id': 1, 'min_position': 900, 'max_position': 100}),
        ('bus_servo/set_limits', limits, {'id': 1, 'min_position': 0, 'max_position': 1001}),
        ('bus_servo/set_limits', limits, {'id': 1, 'min_voltage_mv': 4000,
                                          'max_voltage_mv': 8000}),
        ('bus_servo/set_limits', limits, {'id': 1, 'min_voltage_mv': 9000,
                                          'max_voltage_mv': 8000}),
        ('bus_servo/set_limits', limits, {'id': 1, 'max_temperature_c': 101}),
        ('pwm_servo/get_state', 'GetPwmServoState', {'ids': [0]}),
        ('pwm_servo/get_state', 'GetPwmServoState', {'ids': [5]}),
        ('pwm_servo/set_offset', 'SetPwmServoOffset', {'id': 0, 'offset_us': 0}),
        ('pwm_servo/set_offset', 'SetPwmServoOffset', {'id': 1, 'offset_us': 101}),
        ('pwm_servo/set_offset', 'SetPwmServoOffset', {'id': 1, 'offset_us': -101}),
    ]


def originman_topic_cases() -> List[Tuple[str, str, Dict[str, Any]]]:
    """Return (topic, msg type name, fields) of bad messages to the OriginMan driver."""
    return [
        ('set_led', 'LedPattern', {'led_id': 0, 'on_s': 0.1, 'off_s': 0.1}),
        ('set_led', 'LedPattern', {'led_id': 3, 'on_s': 0.1, 'off_s': 0.1}),
        ('set_led', 'LedPattern', {'led_id': 1, 'on_s': NAN}),
        ('set_led', 'LedPattern', {'led_id': 1, 'on_s': 65.6}),
        ('set_led', 'LedPattern', {'led_id': 1, 'off_s': -0.5}),
        ('set_buzzer', 'BuzzerPattern', {'frequency_hz': 2000, 'on_s': INF}),
        ('set_buzzer', 'BuzzerPattern', {'frequency_hz': 2000, 'off_s': 100.0}),
        ('set_rgb', 'RgbPixels', {'indices': [0], 'red': [1], 'green': [1], 'blue': [1]}),
        ('set_rgb', 'RgbPixels', {'indices': [3], 'red': [1], 'green': [1], 'blue': [1]}),
        ('set_rgb', 'RgbPixels', {'indices': [1], 'red': [1, 2], 'green': [1], 'blue': [1]}),
        ('set_rgb', 'RgbPixels', {'indices': [1, 1], 'red': [1, 2], 'green': [1, 2],
                                  'blue': [1, 2]}),
        ('set_rgb', 'RgbPixels', {}),
        ('set_oled', 'OledText', {'line': 0, 'text': 'x'}),
        ('set_oled', 'OledText', {'line': 3, 'text': 'x'}),
        ('set_oled', 'OledText', {'line': 1, 'text': 'x' * 24}),
        ('set_oled', 'OledText', {'line': 2, 'text': 'ü' * 12}),
        ('set_motor_speeds', 'MotorSpeeds', {'motor_ids': [0], 'rps': [1.0]}),
        ('set_motor_speeds', 'MotorSpeeds', {'motor_ids': [5], 'rps': [1.0]}),
        ('set_motor_speeds', 'MotorSpeeds', {'motor_ids': [1], 'rps': [6.01]}),
        ('set_motor_speeds', 'MotorSpeeds', {'motor_ids': [1], 'rps': [-INF]}),
        ('set_motor_speeds', 'MotorSpeeds', {'motor_ids': [1], 'rps': [NAN]}),
        ('set_motor_speeds', 'MotorSpeeds', {'motor_ids': [1, 2], 'rps': [1.0]}),
        ('set_motor_speeds', 'MotorSpeeds', {'motor_ids': [3, 3], 'rps': [1.0, 1.0]}),
        ('pwm_servo/command', 'PwmServoCommand', {'ids': [0], 'pulses_us': [1500],
                                                  'duration_s': 1.0}),
        ('pwm_servo/command', 'PwmServoCommand', {'ids': [1], 'pulses_us': [499],
                                                  'duration_s': 1.0}),
        ('pwm_servo/command', 'PwmServoCommand', {'ids': [1], 'pulses_us': [2501],
                                                  'duration_s': 1.0}),
        ('pwm_servo/command', 'PwmServoCommand', {'ids': [1], 'pulses_us': [1500],
                                                  'duration_s': 0.0}),
        ('pwm_servo/command', 'PwmServoCommand', {'ids': [1], 'pulses_us': [1500],
                                                  'duration_s': 31.0}),
        ('pwm_servo/command', 'PwmServoCommand', {'ids': [], 'pulses_us': [],
                                                  'duration_s': 1.0}),
        ('bus_servo/command', 'BusServoCommand', {'ids': [254], 'positions': [500],
                                                  'duration_s': 1.0}),
        ('bus_servo/command', 'BusServoCommand', {'ids': [1], 'positions': [1001],
                                                  'duration_s': 1.0}),
        ('bus_servo/command', 'BusServoCommand', {'ids': [1], 'positions': [500],
                                                  'duration_s': NAN}),
        ('bus_servo/command', 'BusServoCommand', {'ids': [1], 'positions': [500],
                                                  'duration_s': 65.6}),
        ('bus_servo/command', 'BusServoCommand', {'ids': [1, 2], 'positions': [500],
                                                  'duration_s': 1.0}),
    ]


def _srv_type(name: str) -> Any:
    if name.startswith('std_srvs/'):
        import std_srvs.srv
        return getattr(std_srvs.srv, name.split('/')[1])
    import uav_serial_drivers.srv
    return getattr(uav_serial_drivers.srv, name)


class _FrameLog:
    """Every frame the device receives, keyed for 'is this background traffic?'."""

    def __init__(self, key) -> None:
        self.key = key
        self.frames: List[Tuple[float, Any]] = []
        self.lock = threading.Lock()

    def add(self, t: float, frame: Any) -> None:
        with self.lock:
            self.frames.append((t, frame))

    def keys_between(self, t0: float, t1: float) -> List[Tuple[Any, Any]]:
        with self.lock:
            return [(self.key(f), f) for t, f in self.frames if t0 <= t <= t1]


def _servo_key(req: Any) -> Any:
    return (req.servo_id, req.instruction, bytes(req.params[:2])) \
        if req.instruction == 2 else bytes(req.raw)


def _dps_key(frame: Any) -> Any:
    return bytes(frame.raw)


def _originman_key(cmd: Any) -> Any:
    from originman_board_ros import protocol as p
    if isinstance(cmd, (p.BusRead, p.PwmRead)):
        return (type(cmd).__name__, cmd.sub, cmd.servo_id)
    return repr(cmd)


class _Refusals:
    """The ``refused commands`` count of a driver's ``link`` status, as it is published."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.count = -1
        self.cond = threading.Condition()

    def __call__(self, array: Any) -> None:
        for status in array.status:
            if status.name == self.name:
                values = {kv.key: kv.value for kv in status.values}
                with self.cond:
                    self.count = int(values.get('refused commands', -1))
                    self.cond.notify_all()

    def wait_above(self, count: int, timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: self.count > count, timeout)


def _run_topic_cases(client, namespace: str, cases, log: _FrameLog,
                     background: Set[Any]) -> Dict:
    """Publish each bad message; refused = counted in diagnostics; nothing new on the wire."""
    from diagnostic_msgs.msg import DiagnosticArray
    import uav_serial_drivers.msg
    refusals = _Refusals(f'{namespace}: link')
    client.subscribe(DiagnosticArray, '/diagnostics', refusals)
    if not refusals.wait_above(-1, 10.0):
        return {'cases': len(cases), 'refused': 0, 'accepted': [], 'bytes_on_wire': [],
                'errors': ['no diagnostics from the driver']}
    publishers: Dict[str, Any] = {}
    refused = 0
    wire: List[str] = []
    accepted: List[str] = []
    errors: List[str] = []
    for topic, type_name, fields in cases:
        msg_type = getattr(uav_serial_drivers.msg, type_name)
        try:
            if topic not in publishers:
                pub = client.node.create_publisher(msg_type, f'{namespace}/{topic}', 10)
                wait_for(lambda: pub.get_subscription_count() > 0, 10.0, what=topic)
                publishers[topic] = pub
            msg = msg_type(**fields)
        except (TimeoutError, AttributeError, TypeError, ValueError, AssertionError) as exc:
            errors.append(f'{topic} {fields}: {exc}'[:200])
            continue
        with refusals.cond:
            before = refusals.count
        t_call = time.monotonic()
        publishers[topic].publish(msg)
        if refusals.wait_above(before, 5.0):
            refused += 1
        else:
            accepted.append(f'{topic} {fields}: not counted as refused within 5 s')
        time.sleep(0.05)
        extra = [f for k, f in log.keys_between(t_call, time.monotonic()) if k not in background]
        if extra:
            wire.append(f'{topic} {fields}: ' + ' | '.join(repr(f) for f in extra[:3]))
    return {'cases': len(cases), 'refused': refused, 'accepted': accepted,
            'bytes_on_wire': wire, 'errors': errors}


def _background(log: _FrameLog, observe_s: float, polled: Iterable[Any] = (),
                longest_s: float = 30.0) -> Set[Any]:
    """Return the keys of the frames the idle driver sends in `observe_s` and until `polled`.

    `polled`: keys the driver sends on its own within a period (a servo's telemetry READs).
    A loaded host can hold the driver past a period, or a servo can come online late: a
    polled frame missing from the window would count against the first case it comes in.
    """
    t0 = time.monotonic()
    time.sleep(observe_s)
    wanted = set(polled)
    end = t0 + longest_s
    while True:
        background = {k for k, _ in log.keys_between(t0, time.monotonic())}
        if wanted <= background or time.monotonic() > end:
            return background
        time.sleep(0.1)


def _run_cases(client, namespace: str, cases, log: _FrameLog, background: Set[Any]) -> Dict:
    refused = 0
    wire: List[str] = []
    accepted: List[str] = []
    errors: List[str] = []
    clients: Dict[str, Any] = {}
    for service, type_name, fields in cases:
        srv = _srv_type(type_name)
        name = f'{namespace}/{service}'
        try:
            if name not in clients:
                clients[name] = client.client(srv, name)
            request = srv.Request()
            for key, value in fields.items():
                setattr(request, key, value)
        except (TimeoutError, AttributeError, TypeError, ValueError, AssertionError) as exc:
            errors.append(f'{service} {fields}: {exc}'[:200])
            continue
        t_call = time.monotonic()
        try:
            response = client.call(clients[name], request, timeout=15.0)
        except TimeoutError as exc:
            errors.append(f'{service} {fields}: {exc}')
            continue
        time.sleep(0.05)
        extra = [f for k, f in log.keys_between(t_call, time.monotonic()) if k not in background]
        if response.success:
            accepted.append(f'{service} {fields}: {response.message}'[:200])
        else:
            refused += 1
        if extra:
            wire.append(f'{service} {fields}: ' + ' | '.join(
                bytes(f.raw).hex(' ') if hasattr(f, 'raw') else repr(f) for f in extra[:3]))
    return {'cases': len(cases), 'refused': refused, 'accepted': accepted,
            'bytes_on_wire': wire, 'errors': errors}


def servo(observe_s: float = 3.0) -> Dict:
    """Run the servo driver's bad requests; return the figures."""
    with workdir() as directory, ServoRig(directory, [1, 2, 3], 115200) as rig, \
            ros_client('bench_bad_inputs_servo') as client:
        log = _FrameLog(_servo_key)
        from desheng_servo_ros.protocol import Instruction, Request, StreamDecoder
        from desheng_servo_ros.state import LOOP_READS
        decoder = StreamDecoder('request')
        rig.runner.add_tap(lambda d, data, t: [log.add(t, f) for f in decoder.feed(data)]
                           if d == 'rx' else None)
        rig.wait_ready()
        # Each servo's position READ, and its telemetry (the state and the wide READ).
        polled = [_servo_key(Request(i, Instruction.READ, bytes(block), b''))
                  for i in rig.ids for block in LOOP_READS]
        return _run_cases(client, '/servo_bus', servo_cases(), log,
                          _background(log, observe_s, polled))


def parachute(observe_s: float = 3.0) -> Dict:
    """Run the parachute driver's bad requests; return the figures."""
    with workdir() as directory, ParachuteRig(directory) as rig, \
            ros_client('bench_bad_inputs_parachute') as client:
        log = _FrameLog(_dps_key)
        from dps_parachute_ros.protocol import StreamDecoder
        decoder = StreamDecoder('from_host')
        rig.runner.add_tap(lambda d, data, t: [log.add(t, f) for f in decoder.feed(data)]
                           if d == 'rx' else None)
        rig.wait_ready()
        # What the driver sends of its own when it reads the module afresh (a module process
        # stalled past the offline judgement on a loaded host, then back): its queries and the
        # stream turned on. None of them changes the module.
        from dps_parachute_ros import protocol as p
        own = {p.encode_heartbeat(), p.encode_streaming(True)} | {
            getattr(p, name)() for name in dir(p)
            if name.startswith('encode_') and name.endswith('_query')}
        return _run_cases(client, '/parachute', parachute_cases(), log,
                          _background(log, observe_s) | own)


def originman(observe_s: float = 3.0) -> Dict:
    """Run the OriginMan driver's bad requests and bad messages; return the figures."""
    with workdir() as directory, OriginManRig(directory) as rig, \
            ros_client('bench_bad_inputs_originman') as client:
        log = _FrameLog(_originman_key)
        from originman_board_ros import protocol as p
        parser = p.BoardParser()
        rig.runner.add_tap(lambda d, data, t: [log.add(t, p.decode_host_command(f))
                                               for f in parser.feed(data)]
                           if d == 'rx' else None)
        rig.wait_ready()
        # Each bus servo's position READ and its telemetry READs (one period, 2 s, apart: a
        # loaded host once held the third servo's past the window, campaign s14d, run 9).
        subs = (p.BusSub.READ_POSITION, p.BusSub.READ_VOLTAGE, p.BusSub.READ_TEMPERATURE,
                p.BusSub.READ_LOAD)
        polled = [('BusRead', sub, i) for i in rig.parameters['bus_servo_ids'] for sub in subs]
        background = _background(log, observe_s, polled)
        services = _run_cases(client, '/originman_board', originman_cases(), log, background)
        topics = _run_topic_cases(client, '/originman_board', originman_topic_cases(), log,
                                  background)
    return {key: services[key] + topics[key] for key in services}


# -- the handset link: bad frames on the wire, bad battery messages, bad parameters --------

def handset_frame_cases() -> List[Tuple[str, bytes, str]]:
    """Return (name, bytes, expected counter) of frames the handset driver must refuse."""
    import struct
    from handset_link_ros import protocol as hp
    T = hp.CommandType
    good = hp.encode_command(T.SET_YAW, 45, 'int16')

    def raw(type_: int, payload: bytes) -> bytes:
        return hp.build_frame(type_, payload)

    def f32(value: float) -> bytes:
        return struct.pack('<f', value)

    def out(type_: int, value: float, encoding: str) -> bytes:
        return hp.encode_command(type_, value, encoding, check=False)
    oor, bad, unk = 'out_of_range', 'malformed', 'unknown_type'
    return [
        ('yaw 500 int16', out(T.SET_YAW, 500, 'int16'), oor),
        ('yaw -181 json', out(T.SET_YAW, -181, 'json'), oor),
        ('pitch 91 json', out(T.SET_PITCH, 91, 'json'), oor),
        ('roll -90.5 json', out(T.SET_ROLL, -90.5, 'json'), oor),
        ('altitude 1000.5 float32', raw(T.SET_ALTITUDE, f32(1000.5)), oor),
        ('altitude -101 int16', out(T.SET_ALTITUDE, -101, 'int16'), oor),
        ('lights 101 int8', out(T.SET_LIGHTS, 101, 'int8'), oor),
        ('lights -1 int8', out(T.SET_LIGHTS, -1, 'int8'), oor),
        ('lights 50.5 json', raw(T.SET_LIGHTS, b'{"lights": 50.5}'), oor),
        ('camera angle 95 json', out(T.SET_CAMERA_ANGLE, 95, 'json'), oor),
        ('record 2 int8', out(T.SET_CAMERA_RECORD, 2, 'int8'), oor),
        ('record 0.5 float32', raw(T.SET_CAMERA_RECORD, f32(0.5)), oor),
        ('pitch NaN float32', raw(T.SET_PITCH, f32(math.nan)), oor),
        ('yaw inf float32', raw(T.SET_YAW, f32(math.inf)), oor),
        ('roll -inf float32', raw(T.SET_ROLL, f32(-math.inf)), oor),
        ('bad checksum', good[:-2] + bytes([good[-2] ^ 0x01]) + good[-1:], bad),
        ('bad end byte', good[:-1] + b'\x56', bad),
        ('LEN 1', b'\xaa\x01\x01\x55', bad),
        ('json NaN', raw(T.SET_ALTITUDE, b'{"altitude": NaN}'), bad),
        ('json Infinity', raw(T.SET_YAW, b'{"yaw": Infinity}'), bad),
        ('json 1e400', raw(T.SET_YAW, b'{"yaw": 1e400}'), bad),
        ('json duplicate key', raw(T.SET_YAW, b'{"yaw": 1, "yaw": 2}'), bad),
        ('json wrong key', raw(T.SET_YAW, b'{"pitch": 1}'), bad),
        ('json trailing comma', raw(T.SET_YAW, b'{"yaw": 1,}'), bad),
        ('json single quotes', raw(T.SET_YAW, b"{'yaw': 1}"), bad),
        ('json string value', raw(T.SET_YAW, b'{"yaw": "1"}'), bad),
        ('json not UTF-8', raw(T.SET_YAW, b'{"yaw": \xff}'), bad),
        ('json true for yaw', raw(T.SET_YAW, b'{"yaw": true}'), bad),
        ('3-byte payload', raw(T.SET_YAW, b'\x01\x02\x03'), bad),
        ('empty payload', raw(T.SET_YAW, b''), bad),
        ('truncated frame', good[:4], bad),
        ('unknown type 0x00', raw(0x00, b'\x01'), unk),
        ('unknown type 0x08', raw(0x08, b'{"x": 1}'), unk),
        ('unknown type 0xFF', raw(0xFF, b''), unk),
    ]


def _refused_params() -> List[Tuple[str, Any]]:
    return [('link_timeout_s', 0.0), ('link_timeout_s', -1.0), ('link_timeout_s', NAN),
            ('link_timeout_s', INF), ('expected_rate_hz', 0.0), ('low_battery_fraction', 1.5),
            ('low_battery_fraction', -0.1), ('battery_topic', 'elsewhere'),
            ('port', '/dev/null'), ('baud', 9600), ('frame_id', 42)]


def handset(observe_s: float = 1.0) -> Dict:
    """Feed the handset driver bad frames, bad battery messages and bad parameters."""
    from handset_link_ros import protocol as hp
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import BatteryState
    from uav_serial_drivers.msg import Failsafe, HandsetLink, HandsetSetpoint
    setpoints: List[Any] = []
    links: List[Any] = []
    failsafes: List[Any] = []
    accepted: List[str] = []
    errors: List[str] = []
    cases = handset_frame_cases()
    # The sentinels are yaw frames only, which keep no link (H26): a long link timeout, so
    # that no lost link changes the failsafe while the bad battery messages must not.
    with workdir() as directory, \
            HandsetRig(directory, parameters={'link_timeout_s': 600.0}) as rig, \
            ros_client('bench_bad_inputs_handset') as client:
        client.subscribe(HandsetSetpoint, '/handset_link/setpoint', setpoints.append, depth=200)
        client.subscribe(HandsetLink, '/handset_link/link', links.append)
        client.subscribe(Failsafe, '/handset_link/failsafe', failsafes.append, latched=True)
        rig.wait_ready()
        wait_for(lambda: setpoints and failsafes, 20, what='the first setpoint')
        with rig.runner.locked():
            rig.sim.set_radio_link(False)  # from now on the wire carries only these cases
        n = len(links)
        base = wait_for(lambda: links[n + 1:] and links[-1], 5, what='a quiet link report')
        time.sleep(observe_s)
        refused = 0
        for i, (name, data, _) in enumerate(cases):
            # A valid frame after each case: once its setpoint is here, the case was read too.
            sentinel_yaw = -100.0 - 0.25 * i
            sentinel = hp.encode_command(hp.CommandType.SET_YAW, sentinel_yaw)
            start = len(setpoints)
            with rig.runner.locked():
                rig.sim.send_raw(data)
                rig.sim.send_raw(sentinel)
            try:
                wait_for(lambda: any(m.yaw_deg == sentinel_yaw for m in setpoints[start:]), 3,
                         what=f'the sentinel after {name}')
            except TimeoutError:
                errors.append(f'{name}: the valid frame after it never arrived')
                continue
            others = [m for m in setpoints[start:] if m.yaw_deg != sentinel_yaw or
                      m.updated != ['yaw_deg']]
            if others:
                accepted.append(f'{name}: published {others[0].updated}')
            else:
                refused += 1
        expected = {k: sum(1 for c in cases if c[2] == k)
                    for k in ('out_of_range', 'malformed', 'unknown_type')}

        def counted() -> bool:
            last = links[-1]
            return all(getattr(last, f'frames_{k}') - getattr(base, f'frames_{k}') >= v
                       for k, v in expected.items())
        try:
            wait_for(counted, 5, what='the rejections counted in ~/link')
        except TimeoutError:
            pass
        last = links[-1]
        got = {k: getattr(last, f'frames_{k}') - getattr(base, f'frames_{k}') for k in expected}
        if got != expected:
            errors.append(f'counted {got}, expected {expected}')
        # Battery messages that say nothing about the battery (H9): the failsafe stays.
        pub = client.node.create_publisher(BatteryState, '/battery', 10)
        n_failsafes = len(failsafes)
        battery_cases = [math.nan, -0.5, 1.5, INF, -INF]
        for level in battery_cases:
            pub.publish(BatteryState(percentage=level))
        time.sleep(0.5)
        battery_refused = len(battery_cases) if len(failsafes) == n_failsafes else 0
        if not battery_refused:
            accepted.append(f'bad battery messages changed the failsafe: {failsafes[-1]}')
        # Parameters: each set must be refused.
        service = client.client(SetParameters, '/handset_link/set_parameters')
        param_refused = 0
        for name, value in _refused_params():
            request = SetParameters.Request(
                parameters=[Parameter(name, value=value).to_parameter_msg()])
            result = client.call(service, request).results[0]
            if result.successful:
                accepted.append(f'parameter {name}={value!r} accepted')
            else:
                param_refused += 1
        alive = rig.node.alive()
        wire = [f'{rig.tap.rx_bytes} bytes written to the modem (H11: none)'] \
            if rig.tap.rx_bytes else []
    if not alive:
        errors.append('handset_link_node died')
    total = len(cases) + len(battery_cases) + len(_refused_params())
    return {'cases': total, 'refused': refused + battery_refused + param_refused,
            'accepted': accepted, 'bytes_on_wire': wire, 'errors': errors}


def run() -> Dict:
    """Every driver; return per-driver results and the summary figures."""
    results = {'servo': servo(), 'parachute': parachute(), 'handset': handset(),
               'originman': originman()}
    return {
        'per_driver': results,
        'bad_inputs_cases': sum(r['cases'] for r in results.values()),
        'bad_inputs_refused': sum(r['refused'] for r in results.values()),
        'bad_inputs_bytes_on_wire': sum(len(r['bytes_on_wire']) for r in results.values()),
        'bad_inputs_errors': sum(len(r['errors']) for r in results.values()),
    }


if __name__ == '__main__':
    import pprint
    pprint.pprint(run())
