"""Launch files and parameter files, as a ROS user gets them from the install."""

import ast
import py_compile
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from rcl_interfaces.srv import ListParameters
import pytest
import yaml

from uav_serial_common.process import executable_path

ROOT = Path(__file__).resolve().parents[1]
LAUNCH_FILES = ['parachute.launch.py', 'servo_bus.launch.py', 'handset_link.launch.py',
                'originman_board.launch.py', 'virtual_bringup.launch.py',
                'parachute_mavlink.launch.py']
CONFIGS = {'parachute.yaml': ('parachute_node', '/parachute'),
           'servo_bus.yaml': ('servo_bus_node', '/servo_bus'),
           'handset_link.yaml': ('handset_link_node', '/handset_link'),
           'originman_board.yaml': ('originman_board_node', '/originman_board'),
           'parachute_mavlink.yaml': ('parachute_mavlink', '/parachute_mavlink')}


def _string_args(tree, func_name):
    """Yield the keyword string arguments of every call to `func_name`."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, 'id', None) == func_name:
            yield {k.arg: k.value.value for k in node.keywords
                   if isinstance(k.value, ast.Constant)}


@pytest.mark.parametrize('name', LAUNCH_FILES)
def test_launch_file_is_installed_compiles_and_names_installed_things(name, tmp_path):
    installed = Path(get_package_share_directory('uav_serial_drivers'), 'launch', name)
    assert installed.exists(), f'{name} is not installed'
    py_compile.compile(str(installed), cfile=str(tmp_path / 'x.pyc'), doraise=True)
    tree = ast.parse(installed.read_text())
    nodes = list(_string_args(tree, 'Node'))
    assert nodes, f'{name} starts no node'
    for node in nodes:
        assert node['package'] == 'uav_serial_drivers'
        executable_path(node['executable'])  # raises if it is not installed
    share = Path(get_package_share_directory('uav_serial_drivers'))
    for call in ast.walk(tree):
        if isinstance(call, ast.List):
            parts = [e.value for e in call.elts if isinstance(e, ast.Constant)]
            if parts[:1] == ['config']:
                assert (share / Path(*parts)).exists(), f'{name} names missing {parts}'


def test_virtual_bringup_wires_each_driver_to_its_virtual_device():
    tree = ast.parse((ROOT / 'launch' / 'virtual_bringup.launch.py').read_text())
    executables = sorted(n['executable'] for n in _string_args(tree, 'Node'))
    assert executables == ['handset_link_node', 'originman_board_node', 'parachute_mavlink',
                           'parachute_node', 'servo_bus_node', 'virtual_autopilot',
                           'virtual_handset', 'virtual_originman_board', 'virtual_parachute',
                           'virtual_servo_bus']


@pytest.mark.parametrize('config', sorted(CONFIGS))
def test_config_keys_are_exactly_the_declared_parameters_of_the_node(config, ros, launch,
                                                                     tmp_path):
    executable, node_name = CONFIGS[config]
    path = Path(get_package_share_directory('uav_serial_drivers'), 'config', config)
    document = yaml.safe_load(path.read_text())
    assert list(document) == ['/**'], 'parameter files must work under any namespace'
    keys = set(document['/**']['ros__parameters'])
    # A missing device must not stop the node from starting (it keeps retrying the port).
    overrides = {'port': str(tmp_path / 'no-such-device'),
                 'blackbox_dir': str(tmp_path / 'blackbox')}
    params = dict(document['/**']['ros__parameters'])
    params.update({k: v for k, v in overrides.items() if k in params})
    launch.start(executable, parameters=params, ros=ros,
                 wait_service=f'{node_name}/list_parameters')
    reply = ros.call(ListParameters, f'{node_name}/list_parameters', ListParameters.Request())
    # Parameters every Jazzy node has are not the driver's to document.
    declared = {n for n in reply.result.names
                if n not in ('use_sim_time', 'start_type_description_service')
                and not n.startswith('qos_overrides')}
    assert keys - declared == set(), f'{config} has keys the node does not declare'
    assert declared - keys == set(), f'{config} lacks declared parameters'


def test_originman_config_gives_every_parameter_its_default_with_a_comment():
    from originman_board_ros.node import PARAMS
    from rclpy.parameter import Parameter
    path = ROOT / 'config' / 'originman_board.yaml'
    values = yaml.safe_load(path.read_text())['/**']['ros__parameters']
    for spec in PARAMS:
        default = [] if isinstance(spec.default, Parameter.Type) else spec.default
        assert values[spec.name] == default, spec.name
    lines = [line for line in path.read_text().splitlines()
             if line.startswith('    ') and not line.strip().startswith('#')]
    assert len(lines) == len(PARAMS) and all('  # ' in line for line in lines)
