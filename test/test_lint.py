"""Lint in the ROS style: flake8 (99 columns), pep257 docstrings, a valid package.xml."""

import subprocess
import sys
from pathlib import Path
from xml.dom import minidom

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ['uav_serial_common', 'dps_parachute_ros', 'desheng_servo_ros',
            'originman_board_ros', 'handset_link_ros', 'parachute_mavlink_ros',
            'parachute_blackbox']
PYTHON_DIRS = PACKAGES + ['test', 'bench', 'launch', 'tools']


def _run(args):
    return subprocess.run([sys.executable, '-m'] + args, cwd=ROOT, capture_output=True,
                          text=True)


def test_flake8():
    targets = [d for d in PYTHON_DIRS + ['setup.py'] if (ROOT / d).exists()]
    result = _run(['flake8', '--max-line-length=99', *targets])
    assert result.returncode == 0, f'flake8 found problems:\n{result.stdout}{result.stderr}'


def test_pep257_on_package_modules():
    result = _run(['pydocstyle', '--convention=pep257', '--add-ignore=D105,D107', *PACKAGES])
    assert result.returncode == 0, f'pydocstyle:\n{result.stdout}{result.stderr}'


def test_pep257_on_tests_tools_and_launch_files():
    # Test functions name what they check; module, class and function docstrings are optional.
    targets = [d for d in ['test', 'bench', 'launch', 'tools'] if (ROOT / d).exists()]
    result = _run(['pydocstyle', '--convention=pep257',
                   '--add-ignore=D100,D101,D102,D103,D105,D107', *targets])
    assert result.returncode == 0, f'pydocstyle:\n{result.stdout}{result.stderr}'


def test_package_xml_is_well_formed_and_names_the_format_3_schema():
    document = minidom.parse(str(ROOT / 'package.xml'))
    root = document.documentElement
    assert root.tagName == 'package'
    assert root.getAttribute('format') == '3'
    schema = [n for n in document.childNodes if n.nodeType == n.PROCESSING_INSTRUCTION_NODE]
    assert any('package_format3.xsd' in n.data for n in schema)
