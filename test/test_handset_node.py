"""handset_link_node (in the test's process) and virtual_handset (a process), installed.

The driver runs in the test's process (the `driver` fixture); the double-SIGINT test starts it
as a process, the one that has signals.
"""

import math
import signal
import struct

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from sensor_msgs.msg import BatteryState
from std_srvs.srv import SetBool, Trigger
from uav_serial_drivers.msg import Failsafe, HandsetAuxiliary, HandsetLink, HandsetSetpoint
from uav_serial_drivers.srv import SendRaw

from handset_link_ros import protocol as p
from uav_serial_common.process import wait_for, wait_scale, WaitTimeout

T = p.CommandType
STICKS = {'yaw_deg', 'pitch_deg', 'roll_deg', 'altitude_m'}


class Handset:
    """A virtual handset (a process) and the driver on it, with their topics recorded.

    The driver is started by `driver` (in this process) or, without it, by `launch`.
    """

    def __init__(self, ros, launch, tmp_path, namespace='', driver=None, **params):
        self.ros = ros
        self.ns = f'/{namespace}' if namespace else ''
        self.virtual = f'{self.ns}/virtual_handset'
        link = str(tmp_path / 'vhandset')
        self.handset = launch.start('virtual_handset', parameters={'link': link},
                                    namespace=self.ns or None, ros=ros,
                                    wait_service=f'{self.virtual}/send_raw')
        node = f'{self.ns}/handset_link'
        self.setpoints = ros.subscribe(HandsetSetpoint, f'{node}/setpoint')
        self.links = ros.subscribe(HandsetLink, f'{node}/link')
        self.failsafes = ros.subscribe(Failsafe, f'{node}/failsafe', latched=True)
        self.diags = ros.subscribe(DiagnosticArray, '/diagnostics')
        self.driver = (driver or launch).start(
            'handset_link_node', parameters={'port': link, **params},
            namespace=self.ns or None, ros=ros, wait_topic=f'{node}/failsafe')
        self.node = node
        # Reported at start-up, and latched for late subscribers.
        self.failsafes.wait(lambda m: True, 10, what='the start-up failsafe')

    def set_virtual(self, **values):
        request = SetParameters.Request(parameters=[
            Parameter(name, value=value).to_parameter_msg() for name, value in values.items()])
        results = self.ros.call(SetParameters, f'{self.virtual}/set_parameters', request).results
        assert all(r.successful for r in results), [r.reason for r in results]

    def refusal(self, **values):
        request = SetParameters.Request(parameters=[
            Parameter(name, value=value).to_parameter_msg() for name, value in values.items()])
        result = self.ros.call(SetParameters, f'{self.virtual}/set_parameters', request)
        return '' if result.results[0].successful else result.results[0].reason

    def call(self, service, srv_type, request=None):
        return self.ros.call(srv_type, f'{self.virtual}/{service}', request)

    def radio(self, up):
        assert self.call('set_radio_link', SetBool, SetBool.Request(data=up)).success

    def send_raw(self, data):
        reply = self.call('send_raw', SendRaw, SendRaw.Request(data=list(data)))
        assert reply.success, reply.message

    def setpoint(self, predicate, what, timeout=5.0):
        return self.setpoints.wait(predicate, timeout, what=what, start=len(self.setpoints))

    def diagnostic(self, task, predicate, what, timeout=10.0):
        name = f'{self.node}: {task}'
        msg = self.diags.wait(lambda m: any(s.name == name and predicate(s) for s in m.status),
                              timeout, what=what, start=len(self.diags))
        return next(s for s in msg.status if s.name == name)

    def statuses(self, task, start):
        """Return the statuses of `task` in every /diagnostics message from index `start`."""
        name = f'{self.node}: {task}'
        return [s for m in self.diags.messages[start:] for s in m.status if s.name == name]

    def log_line(self, level, words, timeout=5.0):
        def find():
            return next((line for line in self.driver.output().splitlines()
                         if f'[{level}]' in line and all(w in line for w in words)), None)
        return wait_for(find, timeout, what=f'a {level} log line with {words}')


def test_setpoints_arrive_per_frame_with_updated_and_auxiliary_is_latched(ros, launch, driver,
                                                                          tmp_path):
    h = Handset(ros, launch, tmp_path, driver=driver)
    first = h.setpoints.wait(lambda m: m.updated, 10, what='a first setpoint')
    assert set(first.updated) <= STICKS and first.header.frame_id == 'handset'
    # Every stick is updated every tick (H7, H22), each frame in a message naming it (H16).
    seen = set()
    h.setpoints.wait(lambda m: seen.update(m.updated) or seen == STICKS, 5,
                     what='all four sticks updated')
    h.set_virtual(yaw_deg=30.5, altitude_m=12.25, lights_percent=75, camera_recording=True)
    h.setpoint(lambda m: 'yaw_deg' in m.updated and m.yaw_deg == 30.5, 'yaw 30.5')
    h.setpoint(lambda m: 'altitude_m' in m.updated and m.altitude_m == 12.25, 'altitude 12.25')
    # A subscriber that comes later still gets the auxiliary state (transient local).
    aux = ros.subscribe(HandsetAuxiliary, f'{h.node}/auxiliary', latched=True)
    last = aux.wait(lambda m: m.lights_percent == 75 and m.camera_recording, 10,
                    what='lights 75 and recording, latched')
    assert last.camera_recording_known
    # The camera angle (0) comes within a second at the latest: the handset repeats every
    # auxiliary command once a second (H22), whenever the driver started to listen.
    aux.wait(lambda m: m.camera_angle_deg == 0.0, 5, what='camera angle 0')
    # Auxiliary is published on change only (H17): the once-a-second repeats add nothing.
    count = len(aux)
    h.set_virtual(camera_angle_deg=-30.0)
    aux.wait(lambda m: m.camera_angle_deg == -30.0 and m.updated == ['camera_angle_deg'], 5,
             what='camera angle -30', start=count)
    link = h.links.wait(lambda m: m.connected and m.command_rate_hz >= 40, 10,
                        what='connected at about 50 Hz')
    assert link.frames_out_of_range == link.frames_unknown_type == 0
    # The driver may open the port in the middle of a frame: its tail is discarded, and only a
    # tail holding 0xAA (a checksum) can make a false start, one malformed frame at most.
    assert link.frames_malformed <= 1
    assert h.failsafes.last.action == Failsafe.ACTION_NONE


def test_encodings_switched_at_runtime_carry_what_each_can(ros, launch, driver, tmp_path):
    h = Handset(ros, launch, tmp_path, driver=driver)
    h.setpoints.wait(lambda m: m.updated, 10, what='a first setpoint')
    float32_tenth = struct.unpack('<f', struct.pack('<f', 0.1))[0]
    # Each value tells the encodings apart: int8 rounds and saturates, int16 rounds, float32
    # carries the nearest float32, JSON the value as given (H23).
    for encoding, yaw, expected in (('int8', 150.4, 127.0), ('int16', 150.4, 150.0),
                                    ('float32', 0.1, float32_tenth), ('json', 0.1, 0.1),
                                    ('int8', -12.5, -13.0)):
        h.set_virtual(encoding=encoding, yaw_deg=yaw)
        h.setpoint(lambda m: 'yaw_deg' in m.updated and m.yaw_deg == expected,
                   f'{encoding}: yaw {expected}')
    assert 'encoding must be one of json, int8, int16, float32' in h.refusal(encoding='bcd')


def test_setpoint_in_drives_the_virtual_sticks(ros, launch, driver, tmp_path):
    h = Handset(ros, launch, tmp_path, driver=driver)
    h.setpoints.wait(lambda m: m.updated, 10, what='a first setpoint')
    pub = ros.publisher(HandsetSetpoint, f'{h.virtual}/setpoint_in')
    pub.publish(HandsetSetpoint(pitch_deg=-12.5, yaw_deg=99.0, updated=['pitch_deg']))
    got = h.setpoint(lambda m: 'pitch_deg' in m.updated and m.pitch_deg == -12.5, 'pitch -12.5')
    assert got.yaw_deg == 0.0  # not named in `updated`: left alone
    # Without `updated`, every finite field is taken; NaN leaves a stick alone.
    pub.publish(HandsetSetpoint(yaw_deg=45.0, pitch_deg=math.nan, roll_deg=-5.0,
                                altitude_m=100.0))
    h.setpoint(lambda m: (m.yaw_deg, m.roll_deg, m.altitude_m) == (45.0, -5.0, 100.0) and
               m.updated == ['altitude_m'], 'yaw 45, roll -5, altitude 100')
    assert h.setpoints.last.pitch_deg == -12.5


def test_bad_frames_are_rejected_counted_and_never_published(ros, launch, driver, tmp_path):
    h = Handset(ros, launch, tmp_path, driver=driver, link_timeout_s=60.0)
    # Connected (all four sticks in) before the radio goes quiet: one setpoint is not enough
    # on a loaded host (campaign of 2026-11-27: three frames in, "waiting for the sticks").
    h.links.wait(lambda m: m.connected, 10, what='connected')
    h.radio(False)
    base = h.links.wait(lambda m: m.command_rate_hz == 0, 5, what='the handset silent',
                        start=len(h.links))
    published = len(h.setpoints)
    good_yaw = p.encode_command(T.SET_YAW, 45, 'int16')
    bad = [
        p.encode_command(T.SET_YAW, 500, 'int16', check=False),         # out of range
        p.build_frame(T.SET_PITCH, struct.pack('<f', math.nan)),         # NaN float32
        p.build_frame(T.SET_ROLL, struct.pack('<f', math.inf)),          # inf float32
        p.build_frame(T.SET_LIGHTS, b'{"lights": 50.5}'),                # fraction
        p.build_frame(T.SET_ALTITUDE, b'{"altitude": NaN}'),             # malformed JSON
        good_yaw[:-2] + bytes([good_yaw[-2] ^ 0xFF]) + good_yaw[-1:],    # bad checksum
        good_yaw[:-1] + b'\x56',                                         # bad end byte
        p.build_frame(0x0B, b'\x01'),                                    # unknown type
    ]
    for frame in bad:
        h.send_raw(frame)
    assert h.call('inject_garbage', Trigger).success
    link = h.links.wait(
        lambda m: (m.frames_out_of_range - base.frames_out_of_range,
                   m.frames_unknown_type - base.frames_unknown_type) == (4, 1)
        and m.frames_malformed - base.frames_malformed >= 3, 5,
        what='4 out of range, 1 unknown, 3+ malformed counted', start=len(h.links))
    assert link.frames_accepted == base.frames_accepted
    assert len(h.setpoints) == published, 'a refused frame was published'
    assert h.log_line('WARN', ['refused SET_YAW', 'not applied (H6)'])
    # Frames rejected within the last second make the link diagnostics a warning.
    # Every link status since the first unknown frame is looked at, not only the newest
    # /diagnostics message (other publishers on the topic may have sent that one).
    unknown = p.build_frame(0x0C, b'')
    start = len(h.diags)

    def rejected_shown():
        h.send_raw(unknown)
        return next((s for s in h.statuses('link', start)
                     if 'rejected in the last second' in s.message), None)
    try:
        diag = wait_for(rejected_shown, 10, interval=0.2,
                        what='rejected frames in the link diagnostics')
    except WaitTimeout as exc:
        seen = h.statuses('link', start)
        raise AssertionError(f'{exc}; {len(seen)} link statuses since, the last: '
                             f'{seen[-1] if seen else None}') from None
    assert diag.level == DiagnosticStatus.WARN
    # The same path takes a good frame at once (counted from before it is sent: it may be
    # published before the send_raw call returns).
    start = len(h.setpoints)
    h.send_raw(good_yaw)
    got = h.setpoints.wait(lambda m: m.updated, 5, what='the good frame', start=start)
    assert (got.updated, got.yaw_deg) == (['yaw_deg'], 45.0)
    assert h.driver.alive()


def test_frames_rejected_while_the_link_is_lost_are_in_its_diagnostics(ros, launch, driver,
                                                                       tmp_path):
    # Bad frames may be why the link is lost (a handset on another encoding): the lost link's
    # diagnostics say how many came, as a connected link's do.
    h = Handset(ros, launch, tmp_path, driver=driver, link_timeout_s=0.5)
    h.links.wait(lambda m: m.connected, 10, what='connected')
    h.radio(False)
    h.failsafes.wait(lambda m: m.link_lost, 5, what='link lost')
    unknown = p.build_frame(0x0C, b'')
    start = len(h.diags)

    def rejected_shown():
        h.send_raw(unknown)
        return next((s for s in h.statuses('link', start) if s.message.startswith('link lost')
                     and 'rejected in the last second' in s.message), None)
    diag = wait_for(rejected_shown, 10, interval=0.2,
                    what='rejected frames in the lost link\'s diagnostics')
    assert diag.level == DiagnosticStatus.ERROR


def test_radio_link_lost_requests_return_to_home_and_is_regained(ros, launch, driver,
                                                                 tmp_path):
    h = Handset(ros, launch, tmp_path, driver=driver, link_timeout_s=0.5)
    h.failsafes.wait(lambda m: m.action == Failsafe.ACTION_NONE, 5, what='start-up failsafe')
    h.links.wait(lambda m: m.connected, 10, what='connected')
    start = len(h.failsafes)
    h.radio(False)
    lost = h.failsafes.wait(lambda m: m.link_lost, 5, what='link lost', start=start)
    assert lost.action == Failsafe.ACTION_RETURN_TO_HOME and 'link lost' in lost.reason
    assert h.log_line('ERROR', ['handset link lost', '0.5 s', 'return to home'])
    h.links.wait(lambda m: not m.connected, 5, what='link not connected')
    diag = h.diagnostic('link', lambda s: s.message.startswith('link lost'), 'link lost ERROR')
    assert diag.level == DiagnosticStatus.ERROR
    # Counted from before the radio is back: the regain may be published before radio() returns.
    start = len(h.failsafes)
    h.radio(True)
    back = h.failsafes.wait(lambda m: not m.link_lost, 5, what='link regained', start=start)
    assert back.action == Failsafe.ACTION_NONE
    assert h.log_line('WARN', ['regained', 'failsafe now NONE'])
    h.links.wait(lambda m: m.connected, 5, what='connected again')


def test_low_battery_requests_return_to_home_and_clears_at_25_percent(ros, launch, driver,
                                                                      tmp_path):
    h = Handset(ros, launch, tmp_path, driver=driver)
    pub = ros.publisher(BatteryState, '/battery')

    def battery(level, until, what):
        # The driver subscribes best effort (a battery repeats): so does the aircraft here.
        def sent():
            pub.publish(BatteryState(percentage=level))
            return until()
        wait_for(sent, 10, interval=0.2, what=what)

    battery(0.15, lambda: h.failsafes.last.battery_low, 'battery low at 15 %')
    low = h.failsafes.last
    assert low.action == Failsafe.ACTION_RETURN_TO_HOME and 'battery low' in low.reason
    assert h.log_line('WARN', ['battery low: 15.0 % < 20 %'])
    # NaN says nothing (H9): the condition holds, and the last percentage stays.
    count = len(h.failsafes)
    received = int(_diag_value(h, 'messages_received'))
    battery(math.nan, lambda: int(_diag_value(h, 'messages_received')) > received,
            'the NaN battery message taken')
    assert len(h.failsafes) == count and h.failsafes.last.battery_low
    diag = h.diagnostic('battery', lambda s: True, 'battery diagnostics')
    assert diag.level == DiagnosticStatus.WARN and 'battery low: 15.0 % < 20 %' in diag.message
    # 24 % is not enough to clear it, 25 % is (H9, H20).
    battery(0.24, lambda: _diag_value(h, 'battery_fraction') == '0.240', '24 % taken')
    assert h.failsafes.last.battery_low
    battery(0.25, lambda: not h.failsafes.last.battery_low, 'cleared at 25 %')
    assert h.failsafes.last.action == Failsafe.ACTION_NONE
    assert h.log_line('WARN', ['cleared', 'failsafe now NONE'])
    # A threshold raised at runtime applies at once (H25); the topic is read at start only.
    results = set_params(ros, '/handset_link', low_battery_fraction=0.3)
    assert results[0].successful
    h.failsafes.wait(lambda m: m.battery_low, 5, what='low at 25 % < 30 %', start=count)
    results = set_params(ros, '/handset_link', battery_topic='other', port='/dev/null')
    assert not any(r.successful for r in results)
    assert 'read at start only' in results[0].reason and 'read-only' in results[1].reason


def set_params(ros, node, **values):
    request = SetParameters.Request(parameters=[
        Parameter(name, value=value).to_parameter_msg() for name, value in values.items()])
    return ros.call(SetParameters, f'{node}/set_parameters', request).results


def _diag_value(h, key):
    status = h.diagnostic('battery', lambda s: True, 'battery diagnostics')
    return next(kv.value for kv in status.values if kv.key == key)


def test_modem_unplugged_and_replugged_the_setpoints_resume(ros, launch, driver, tmp_path):
    # A long link timeout: the port closing is no failsafe of its own (H21).
    h = Handset(ros, launch, tmp_path, driver=driver, link_timeout_s=30.0)
    h.links.wait(lambda m: m.connected and m.port_open, 10, what='connected')
    assert h.call('disconnect', SetBool, SetBool.Request(data=True)).success
    h.links.wait(lambda m: not m.port_open, 5, what='port closed', start=len(h.links))
    closed = len(h.links)
    h.set_virtual(yaw_deg=-77.0)
    assert h.call('disconnect', SetBool, SetBool.Request(data=False)).success
    h.setpoint(lambda m: m.yaw_deg == -77.0, 'setpoints from the new port', timeout=10)
    assert h.links.wait(lambda m: m.port_open, 5, what='port open', start=closed).connected
    # Back within link_timeout_s: no failsafe was requested (H21).
    assert not any(m.link_lost for m in h.failsafes.messages)


def test_double_sigint_exits_cleanly(ros, launch, tmp_path):
    h = Handset(ros, launch, tmp_path)
    h.setpoints.wait(lambda m: m.updated, 10, what='a first setpoint')
    for proc in (h.driver, h.handset):
        proc.popen.send_signal(signal.SIGINT)
        proc.popen.send_signal(signal.SIGINT)  # ros2 launch's Ctrl-C arrives twice
    for proc in (h.driver, h.handset):
        assert proc.popen.wait(10 * wait_scale()) == 0, proc.output()
    assert 'Traceback' not in h.driver.output() + h.handset.output()


def test_diagnostics_carry_the_node_name_and_the_rate_warning(ros, launch, driver, tmp_path):
    h = Handset(ros, launch, tmp_path, driver=driver)
    ok = h.diagnostic('link', lambda s: s.level == DiagnosticStatus.OK, 'link OK')
    assert ok.name == '/handset_link: link' and ok.message.startswith('receiving')
    assert h.diagnostic('battery', lambda s: True, 'battery').name == '/handset_link: battery'
    h.set_virtual(rate_hz=20.0)
    warn = h.diagnostic('link', lambda s: 'below 80 %' in s.message, 'low rate warning')
    assert warn.level == DiagnosticStatus.WARN and 'expected 50 Hz' in warn.message


def test_under_a_namespace_names_carry_it(ros, launch, driver, tmp_path):
    h = Handset(ros, launch, tmp_path, driver=driver, namespace='uav3')
    status = h.diagnostic('link', lambda s: s.level == DiagnosticStatus.OK, 'link OK')
    assert status.name == '/uav3/handset_link: link'
    h.setpoints.wait(lambda m: m.updated, 10, what='a setpoint under /uav3')
    pub = ros.publisher(BatteryState, '/uav3/battery')
    wait_for(lambda: pub.publish(BatteryState(percentage=0.1)) or
             h.failsafes.last.battery_low, 10, interval=0.2, what='battery of /uav3')


def test_round2_8_node_auxiliary_frames_keep_no_link_and_a_silent_battery_is_unknown(
        ros, launch, driver, tmp_path):
    h = Handset(ros, launch, tmp_path, driver=driver, link_timeout_s=1.0,
                battery_timeout_s=1.0)
    h.links.wait(lambda m: m.connected, 10, what='the link up')
    # The radio carries lights only (send_raw goes out with the radio link down, H22).
    h.radio(False)
    start = len(h.failsafes)

    def lights_until_lost():
        h.send_raw(p.encode_set_lights(30))
        return any(m.link_lost for m in h.failsafes.messages[start:])
    wait_for(lights_until_lost, 10, interval=0.2, what='link lost while lights frames arrive')
    assert h.failsafes.last.action == Failsafe.ACTION_RETURN_TO_HOME
    h.radio(True)
    h.failsafes.wait(lambda m: not m.link_lost, 10, what='link regained', start=start)
    # A battery that stops reporting is unknown after battery_timeout_s: WARN, no return home.
    pub = ros.publisher(BatteryState, '/battery')
    wait_for(lambda: pub.publish(BatteryState(percentage=0.5)) or
             _diag_value(h, 'battery_fraction') == '0.500', 10, interval=0.2,
             what='50 % taken')
    unknown = h.failsafes.wait(lambda m: 'battery unknown' in m.reason, 10,
                               what='the battery unknown', start=start)
    assert unknown.action == Failsafe.ACTION_NONE and math.isnan(unknown.battery_fraction)
    diag = h.diagnostic('battery', lambda s: 'battery unknown' in s.message, 'stale WARN')
    assert diag.level == DiagnosticStatus.WARN and 'last 50.0 %' in diag.message
    assert h.log_line('WARN', ['battery unknown', 'no reading for 1 s'])
