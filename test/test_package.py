"""The package as a ROS user gets it: manifest, interfaces, installed modules and executables."""

import ast
import configparser
import importlib
import re
import sys
from pathlib import Path

from catkin_pkg.package import parse_package
import pytest

ROOT = Path(__file__).resolve().parents[1]
MODULES = ['uav_serial_common', 'dps_parachute_ros', 'parachute_blackbox', 'desheng_servo_ros',
           'originman_board_ros', 'handset_link_ros', 'parachute_mavlink_ros']
CONTRACT_MESSAGES = {
    'ParachuteStatus': ['header', 'online', 'armed', 'triggered', 'tilt_deg', 'accel_g',
                        'streaming', 'light_level_v', 'bay_open', 'charging', 'cell_voltage_v',
                        'attitude_trigger_enabled', 'freefall_trigger_enabled'],
    'ParachuteConfig': [],
    'TriggerEvent': [],
    'TriggerRequest': [],
    'TriggerRecord': [],
    'ServoState': ['id', 'name', 'online', 'position_ticks', 'position_rad', 'speed_raw',
                   'current_ma', 'temperature_c', 'status', 'overload', 'over_temperature',
                   'voltage_fault', 'torque_enabled', 'error_count'],
    'ServoStateArray': [],
    'ServoCommand': ['names', 'ids', 'positions', 'move_time_ms'],
    'HandsetSetpoint': ['header', 'yaw_deg', 'pitch_deg', 'roll_deg', 'altitude_m', 'updated'],
    'HandsetAuxiliary': ['header', 'lights_percent', 'camera_angle_deg', 'camera_recording'],
    'HandsetLink': ['header', 'connected', 'frame_rate_hz', 'command_rate_hz', 'frames_accepted',
                    'frames_malformed', 'frames_out_of_range', 'frames_unknown_type',
                    'last_frame_age_s'],
    'Failsafe': ['header', 'link_lost', 'battery_low', 'action', 'reason'],
    'ButtonEvent': ['header', 'key_id', 'event', 'event_name'],
    'SbusFrame': ['header', 'channels', 'normalized', 'ch17', 'ch18', 'signal_loss',
                  'failsafe'],
    'LedPattern': ['led_id', 'on_s', 'off_s', 'repeat'],
    'BuzzerPattern': ['frequency_hz', 'on_s', 'off_s', 'repeat'],
    'RgbPixels': ['indices', 'red', 'green', 'blue'],
    'OledText': ['line', 'text'],
    'MotorSpeeds': ['motor_ids', 'rps'],
    'PwmServoCommand': ['ids', 'pulses_us', 'duration_s'],
    'BusServoCommand': ['ids', 'positions', 'duration_s'],
    'BusServoState': ['id', 'online', 'position', 'position_rad', 'voltage_v', 'temperature_c',
                      'torque_enabled', 'offset', 'min_position', 'max_position',
                      'min_voltage_v', 'max_voltage_v', 'max_temperature_c'],
    'BusServoStateArray': ['header', 'servos'],
}
CONTRACT_SERVICES = {
    'Deploy': (['confirm', 'arm_if_locked'], ['success', 'message', 'latency_ms']),
    'SetThresholds': (['attitude_deg', 'freefall_g', 'freefall_time_s', 'light_threshold_v'],
                      ['success', 'message', 'config']),
    'SetAutoTriggers': (['attitude_enabled', 'freefall_enabled'],
                        ['success', 'message', 'config']),
    'GetParachuteConfig': ([], ['config']),
    'GetTriggerRecords': ([], ['success', 'message', 'records']),
    'Confirmed': (['confirm'], ['success', 'message']),
    'WritePositions': (['names', 'ids', 'positions', 'move_time_ms', 'staged'],
                       ['success', 'message']),
    'SetTorque': (['ids', 'enable'], ['success', 'message']),
    'ReadRegister': (['id', 'register_name', 'address', 'length'], ['success', 'message']),
    'WriteRegister': (['id', 'register_name'], ['success', 'message']),
    'ScanBus': (['first_id', 'last_id'], ['ids']),
    'GoToPreset': (['ids', 'preset'], ['success', 'message']),
    'SetId': (['id', 'new_id'], ['success', 'message']),
    'FactoryReset': (['id', 'confirm'], ['success', 'message']),
    'SendRaw': (['data'], ['success', 'message']),
    'GetBusServoState': (['ids'], ['success', 'message', 'servos']),
    'SetBusServoTorque': (['ids', 'enable'], ['success', 'message']),
    'BusServoIds': (['ids'], ['success', 'message']),
    'SetBusServoId': (['id', 'new_id'], ['success', 'message']),
    'SetBusServoOffset': (['id', 'offset', 'save'], ['success', 'message']),
    'SetBusServoLimits': (['id', 'min_position', 'max_position', 'min_voltage_mv',
                           'max_voltage_mv', 'max_temperature_c'], ['success', 'message']),
    'GetPwmServoState': (['ids'], ['success', 'message', 'pulses_us', 'offsets_us']),
    'SetPwmServoOffset': (['id', 'offset_us'], ['success', 'message']),
}
# Imports that are not ROS packages of the same name, mapped to their rosdep keys.
ROSDEP_KEYS = {'serial': 'python3-serial', 'yaml': 'python3-yaml',
               'matplotlib': 'python3-matplotlib', 'pymavlink': 'python3-pymavlink-pip'}


def setup_cfg() -> configparser.ConfigParser:
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / 'setup.cfg')
    return cfg


def test_package_xml_is_format_3_with_the_contract_name_and_build_type():
    package = parse_package(str(ROOT / 'package.xml'))
    package.validate()
    assert package.package_format == 3
    assert package.name == 'uav_serial_drivers'
    assert package.get_build_type() == 'ament_cmake'
    assert 'rosidl_interface_packages' in [g.name for g in package.member_of_groups]


def test_package_xml_declares_the_runtime_dependencies():
    package = parse_package(str(ROOT / 'package.xml'))
    runtime = {d.name for d in package.exec_depends + package.build_export_depends}
    runtime |= {d.name for d in package.build_depends} & runtime
    for key in ['rclpy', 'std_msgs', 'std_srvs', 'sensor_msgs', 'diagnostic_msgs',
                'python3-serial', 'rosidl_default_runtime']:
        assert key in runtime, f'package.xml does not declare {key}'
    build = {d.name for d in package.buildtool_depends}
    assert {'ament_cmake', 'rosidl_default_generators'} <= build


def _imports(path: Path):
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name.split('.')[0]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module.split('.')[0]


def test_every_imported_ros_package_is_declared_in_package_xml():
    package = parse_package(str(ROOT / 'package.xml'))
    declared = {d.name for d in package.exec_depends + package.build_export_depends}
    own = set(MODULES) | {'uav_serial_drivers'}
    sources = [p for m in MODULES for p in (ROOT / m).rglob('*.py')]
    sources += list((ROOT / 'launch').glob('*.py'))
    missing = set()
    for path in sources:
        for name in _imports(path):
            if name in sys.stdlib_module_names or name in own or name == '__future__':
                continue
            if ROSDEP_KEYS.get(name, name) not in declared:
                missing.add(f'{name} (in {path.relative_to(ROOT)})')
    assert not missing, f'imported but not declared in package.xml: {sorted(missing)}'


def test_cmake_installs_exactly_the_modules_setup_cfg_declares():
    declared = setup_cfg()['options']['packages'].split()
    cmake = (ROOT / 'CMakeLists.txt').read_text()
    installed = re.findall(r'ament_python_install_package\((\w+)', cmake)
    assert sorted(installed) == sorted(declared)
    assert sorted(declared) == sorted(MODULES)


def test_installed_executables_are_the_console_scripts_of_setup_cfg():
    from ament_index_python.packages import get_package_prefix
    scripts = setup_cfg()['options.entry_points']['console_scripts'].split('\n')
    names = sorted(line.split('=')[0].strip() for line in scripts if line.strip())
    assert names == ['blackbox_report', 'handset_link_node', 'originman_board_node',
                     'parachute_mavlink', 'parachute_node', 'servo_bus_node',
                     'virtual_autopilot', 'virtual_handset', 'virtual_originman_board',
                     'virtual_parachute', 'virtual_servo_bus']
    lib = Path(get_package_prefix('uav_serial_drivers'), 'lib', 'uav_serial_drivers')
    assert sorted(p.name for p in lib.iterdir()) == names
    for line in scripts:
        if line.strip():
            target = line.split('=')[1].strip()
            module, func = target.split(':')
            assert callable(getattr(importlib.import_module(module), func)), target


@pytest.mark.parametrize('name,fields', sorted(CONTRACT_MESSAGES.items()))
def test_contract_message_is_generated_with_its_fields(name, fields):
    msg_type = getattr(importlib.import_module('uav_serial_drivers.msg'), name)
    slots = msg_type.get_fields_and_field_types()
    for field in fields:
        assert field in slots, f'{name} lacks {field}'


@pytest.mark.parametrize('name,fields', sorted(CONTRACT_SERVICES.items()))
def test_contract_service_is_generated_with_its_fields(name, fields):
    srv_type = getattr(importlib.import_module('uav_serial_drivers.srv'), name)
    request_fields, response_fields = fields
    for field in request_fields:
        assert field in srv_type.Request.get_fields_and_field_types(), f'{name} request: {field}'
    for field in response_fields:
        assert field in srv_type.Response.get_fields_and_field_types(), \
            f'{name} response: {field}'


def test_every_interface_field_documents_itself():
    undocumented = []
    for path in sorted((ROOT / 'msg_defs').rglob('*.*')):
        for line in path.read_text().splitlines():
            text = line.strip()
            if not text or text.startswith('#') or text == '---':
                continue
            if '#' not in text and not text.startswith('std_msgs/Header'):
                undocumented.append(f'{path.name}: {text}')
    # Header, arrays of documented messages and self-explanatory success/message fields aside.
    undocumented = [u for u in undocumented
                    if not re.search(r': (bool success|string message|string confirm|'
                                     r'ServoState\[\] servos|TriggerRecord record|'
                                     r'ParachuteConfig config|TriggerRecord\[\] records|'
                                     r'bool enable|bool attitude_enabled|'
                                     r'bool freefall_enabled)$', u)]
    assert not undocumented, undocumented


HANDSET_FIELD_TYPES = {
    'HandsetSetpoint': {'header': 'std_msgs/Header', 'yaw_deg': 'double', 'pitch_deg': 'double',
                        'roll_deg': 'double', 'altitude_m': 'double',
                        'updated': 'sequence<string>'},
    'HandsetAuxiliary': {'header': 'std_msgs/Header', 'lights_percent': 'int16',
                         'camera_angle_deg': 'double', 'camera_recording': 'boolean'},
    'HandsetLink': {'header': 'std_msgs/Header', 'connected': 'boolean',
                    'frame_rate_hz': 'double', 'command_rate_hz': 'double',
                    'frames_accepted': 'uint64', 'frames_malformed': 'uint64',
                    'frames_out_of_range': 'uint64', 'frames_unknown_type': 'uint64',
                    'last_frame_age_s': 'double'},
    'Failsafe': {'header': 'std_msgs/Header', 'link_lost': 'boolean', 'battery_low': 'boolean',
                 'action': 'string', 'reason': 'string'},
}


@pytest.mark.parametrize('name,types', sorted(HANDSET_FIELD_TYPES.items()))
def test_handset_messages_have_the_contract_field_types(name, types):
    msg_type = getattr(importlib.import_module('uav_serial_drivers.msg'), name)
    slots = msg_type.get_fields_and_field_types()
    assert {f: slots.get(f) for f in types} == types


def test_failsafe_actions_are_constants_of_the_message():
    from handset_link_ros import core
    from uav_serial_drivers.msg import Failsafe
    assert (Failsafe.ACTION_NONE, Failsafe.ACTION_RETURN_TO_HOME) == \
        (core.ACTION_NONE, core.ACTION_RETURN_TO_HOME)


# Everything below each node: the device cores, their links, protocols, units, state, the black
# box and the device models. None may import ROS (the layers are tested, and usable, without it).
ROS_FREE = {
    'dps_parachute_ros': ['protocol', 'link', 'state', 'session', 'session_online',
                          'session_worker', 'session_init', 'session_triggers',
                          'session_settings', 'session_events', 'session_deploy',
                          'session_preflight', 'deploy_core', 'deploy_events', 'deploy_knowledge',
                          'trigger_core', 'settings_core', 'settings_events', 'release_gate',
                          'blackbox', 'simulation'],
    'parachute_blackbox': ['read', 'analysis', 'report'],
    'desheng_servo_ros': ['protocol', 'registers', 'link', 'units', 'core', 'simulation'],
    'handset_link_ros': ['protocol', 'link', 'core', 'simulation'],
    'originman_board_ros': ['protocol', 'link', 'core', 'core_types', 'core_commands',
                            'core_services', 'core_settings', 'core_bus_poll', 'simulation',
                            'simulation_parts', 'simulation_handlers'],
    'parachute_mavlink_ros': ['events', 'core'],
    'uav_serial_common': ['core_events', 'core_runner', 'ticket'],  # (what every core may import)
}


def test_no_driver_module_imports_matplotlib():
    # The plots belong to the black-box report (parachute_blackbox), a tool for after a flight.
    drivers = [m for m in MODULES if m != 'parachute_blackbox']
    found = [str(path.relative_to(ROOT)) for m in drivers for path in (ROOT / m).rglob('*.py')
             if 'matplotlib' in set(_imports(path))
             or re.search(r'^\s*(from|import) matplotlib', path.read_text(), re.M)]
    assert not found, found


def test_issue22_4_no_module_of_the_parachute_session_over_600_lines():
    # Smaller rooms: ParachuteSession is assembled in session.py from one module per
    # responsibility (deploy, trigger requests, online, worker, init, settings, events, preflight).
    paths = sorted((ROOT / 'dps_parachute_ros').glob('session*.py'))
    long = {path.name: n for path in paths if (n := len(path.read_text().splitlines())) > 600}
    assert len(paths) > 1 and not long, long


def test_issue22_4_no_module_of_the_originman_core_over_600_lines():
    # Smaller rooms: OriginManCore is assembled in core.py from one module per responsibility
    # (types, commands, services, settings at connect, bus servo poll).
    paths = sorted((ROOT / 'originman_board_ros').glob('core*.py'))
    long = {path.name: n for path in paths if (n := len(path.read_text().splitlines())) > 600}
    assert len(paths) > 1 and not long, long


def test_issue22_4_no_module_of_the_originman_board_model_over_600_lines():
    # Smaller rooms: the firmware model is assembled in simulation.py from the board's parts
    # (simulation_parts) and its command handlers (simulation_handlers).
    paths = sorted((ROOT / 'originman_board_ros').glob('simulation*.py'))
    long = {path.name: n for path in paths if (n := len(path.read_text().splitlines())) > 600}
    assert len(paths) > 1 and not long, long


@pytest.mark.parametrize('package', sorted(ROS_FREE))
def test_the_device_core_and_everything_below_it_import_no_ros(package):
    import subprocess
    imports = ', '.join(f'{package}.{m}' for m in ROS_FREE[package])
    code = (f'import sys\nimport {imports}\n'
            "ros = sorted(m for m in sys.modules if m.split('.')[0] in "
            "('rclpy', 'rcl_interfaces', 'uav_serial_drivers') or m.endswith('_msgs'))\n"
            'print(ros)\n')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=60, cwd=str(ROOT))
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == '[]', f'{package}: {result.stdout.strip()}'


def test_issue22_4_no_protocol_module_or_shared_module_over_600_lines():
    # Smaller rooms: the protocols, the shared runtime and the virtual nodes are split by
    # responsibility (the cores are checked as their splits land).
    paths = sorted((ROOT / 'uav_serial_common').glob('*.py'))
    for package in ('dps_parachute_ros', 'desheng_servo_ros', 'handset_link_ros',
                    'originman_board_ros'):
        paths += sorted((ROOT / package).glob('protocol*.py'))
        paths += sorted((ROOT / package).glob('virtual_node.py'))
    long = {str(path.relative_to(ROOT)): n for path in paths
            if (n := len(path.read_text().splitlines())) > 600}
    assert not long, long


def test_the_core_tier_names_test_files_that_exist_and_start_no_process_or_pty():
    # `make test-core` is the tier that runs in seconds: every file it names is there, and none
    # of them reaches for a process, a pty, a launched node or a ROS graph.
    from conftest import CORE_TIER
    for name in sorted(CORE_TIER):
        path = ROOT / 'test' / name
        assert path.is_file(), name
        source = path.read_text()
        for marker in ('subprocess', 'VirtualSerialPort', 'create_runner', 'RosHarness',
                       'openpty', 'launch.start', 'rclpy.init('):
            assert marker not in source, (name, marker)


# Issue 22 item 5, one name per concept: the events and actions every core shares are written
# once (uav_serial_common.core_events; the release gate's pair in release_gate), so run_core
# carries two cores' Log (or Record, LinkDown ...) with one handler. A class of one of these
# names elsewhere is another concept, and says so here.
SHARED_EVENTS = {'Log', 'Record', 'Request', 'Answer', 'LinkUp', 'LinkDown', 'Rebooted', 'Reply',
                 'Timeout', 'Busy', 'PassGate', 'GateDone', 'SetTimer', 'Tick'}
OTHER_CONCEPTS = {
    ('uav_serial_common/core_events.py', name) for name in SHARED_EVENTS} | {
    ('dps_parachute_ros/release_gate.py', 'PassGate'),
    ('dps_parachute_ros/release_gate.py', 'GateDone'),
    ('uav_serial_common/serial_errors.py', 'LinkDown'),       # an exception, not an event
    ('parachute_mavlink_ros/events.py', 'Tick'),               # its core takes `now` apart
    ('desheng_servo_ros/protocol.py', 'Reply'),                # a decoded status frame
    ('desheng_servo_ros/protocol.py', 'Request'),              # a decoded host frame
    ('desheng_servo_ros/bus_events.py', 'Answer'),             # (token, ok, text): not a Result
    ('parachute_mavlink_ros/events.py', 'Answer'),             # an event: a service answered
}


def test_round2_22_5_the_shared_events_and_actions_are_written_once():
    found = set()
    for module in MODULES:
        for path in (ROOT / module).rglob('*.py'):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ClassDef) and node.name in SHARED_EVENTS:
                    found.add((str(path.relative_to(ROOT)), node.name))
    assert found - OTHER_CONCEPTS == set()


def test_round2_22_5_every_core_takes_one_log_record_and_link_type():
    from dps_parachute_ros import deploy_core, release_gate, settings_core, trigger_core
    from handset_link_ros import rules
    from parachute_mavlink_ros import events
    from uav_serial_common import core_events as ce
    for core in (deploy_core, settings_core, trigger_core):
        assert core.Log is ce.Log and core.Record is ce.Record and core.LinkDown is ce.LinkDown
    assert rules.Log is ce.Log and events.Log is ce.Log
    assert deploy_core.Rebooted is trigger_core.Rebooted is ce.Rebooted
    assert deploy_core.LinkUp is trigger_core.LinkUp is ce.LinkUp
    assert deploy_core.Request is settings_core.Request is ce.Request
    assert deploy_core.PassGate is trigger_core.PassGate is release_gate.PassGate
    assert settings_core.Answer is trigger_core.Answer is ce.Answer
    assert trigger_core.SetTimer is rules.SetTimer is ce.SetTimer
    assert trigger_core.Tick is rules.Tick is ce.Tick
    from desheng_servo_ros import bus_schedule
    assert bus_schedule.Tick is ce.Tick and bus_schedule.SetTimer is ce.SetTimer
    assert bus_schedule.Reply is ce.Reply and bus_schedule.LinkDown is ce.LinkDown
    assert bus_schedule.Log is ce.Log
    # Two guarantees kept apart: the deploy decision waits for the disk, a trigger decision not.
    assert {ce.SYNC_WAIT, ce.SYNC_ASK, ce.NO_SYNC} == set(ce.SYNCS) and len(ce.SYNCS) == 3
    with pytest.raises(ValueError):
        ce.Record('decision', (), sync=True)  # the old bool meant either guarantee
