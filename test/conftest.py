"""Test harness: real rclpy, a private ROS domain per session, nodes as real processes.

- Every pytest session claims its own ``ROS_DOMAIN_ID`` (with a lock file, so parallel sessions on
  one machine never share one) and keeps discovery on localhost; its services wait for a new
  caller to be discovered before they answer (``fastdds_profiles.xml``).
- `ros` gives a test its own rclpy Context, a node in it and an executor spinning in a thread,
  with helpers to wait for messages and call services with timeouts.
- `launch` starts an installed executable as a subprocess with parameters, waits for a topic or
  service of it, and stops it by PID at the end of the test (stderr goes into failure messages).
- `driver` starts a driver's node in the test's own process instead (test/inproc.py): same
  arguments, no process start; for tests that need no signal, exit code, stderr or kill.
"""

from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys
import time
from typing import Any

import pytest

sys.path.insert(0, os.path.dirname(__file__))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from hypothesis import HealthCheck, settings  # noqa: E402

from uav_serial_common.process import claim_domain_id  # noqa: E402

# No property here is about speed, and a loaded host (the suite beside a busy loop) made an
# example take over hypothesis's default 200-ms deadline: timing goals belong to bench/.
settings.register_profile('uav', deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile('uav')


FASTDDS_PROFILES = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'fastdds_profiles.xml')
"""The session's Fast DDS profiles: a service waits for its client's response reader."""


def pytest_configure(config: pytest.Config) -> None:
    """Isolate this session's ROS traffic before anything imports rclpy."""
    config.addinivalue_line('markers', 'core: the fast tier (no process, pty or ROS graph)')
    # Each process claims its own: the session, and each of its pytest-xdist workers (which
    # inherit the session's environment), so tests running side by side never share a graph.
    os.environ['ROS_DOMAIN_ID'] = str(claim_domain_id())
    # Waits end when their condition holds; their bounds are stretched for a loaded machine.
    os.environ.setdefault('UAV_WAIT_SCALE', '3')
    # Virtual devices keep their device's time on a busy host (process.device_process).
    os.environ.setdefault('UAV_DEVICE_NICE', '-10')
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    # Every service of the session waits for its caller's response reader before it answers,
    # instead of dropping the answer after 100 ms (fastdds_profiles.xml says why).
    os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE', FASTDDS_PROFILES)
    os.environ.pop('ROS_LOCALHOST_ONLY', None)  # deprecated in Jazzy; it would warn
    os.environ.setdefault('RCUTILS_COLORIZED_OUTPUT', '0')
    os.environ.setdefault('PYTHONUNBUFFERED', '1')
    if config.getoption('numprocesses', None) and 'PYTEST_XDIST_WORKER' not in os.environ:
        _compile_once_before_the_workers(config)


TEST_DIR = Path(__file__).resolve().parent
ROOT = TEST_DIR.parent
_COMPILED = pytest.StashKey[float]()
"""How long a cold cache's compile before the workers took (seconds)."""


def _stale_test_modules() -> list:
    """Name the test modules whose rewritten bytecode is missing or older than their source."""
    from _pytest.assertion.rewrite import get_cache_dir, PYC_TAIL
    stale = []
    for source in [TEST_DIR / 'conftest.py', *TEST_DIR.glob('test_*.py')]:
        pyc = get_cache_dir(source) / (source.stem + PYC_TAIL)
        if not pyc.exists() or pyc.stat().st_mtime < source.stat().st_mtime:
            stale.append(source.name)
    return stale


def _compile_once_before_the_workers(config: pytest.Config) -> None:
    """With a cold bytecode cache, compile once in one process instead of once in each worker.

    Every xdist worker collects every test module, and pytest rewrites each for its asserts
    (about 5 s of CPU for this suite): started together on a cold cache, all the workers did that
    same work at once, and their node processes compiled the drivers' modules at once too.
    """
    if sys.dont_write_bytecode or not _stale_test_modules():
        return
    import compileall
    started = time.monotonic()
    # The installed modules (the node processes' path to the sources, --symlink-install).
    for site in ROOT.glob('install/*/lib/python3*/site-packages'):
        compileall.compile_dir(str(site), quiet=2, workers=0)
    # One collection rewrites the test modules and compiles everything they import.
    # Its errors are the run's own collection errors, which the workers report.
    try:
        subprocess.run([sys.executable, '-m', 'pytest', str(TEST_DIR), '--collect-only', '-q',
                        '-p', 'no:xdist', '-p', 'no:cacheprovider'],
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=120,
                       check=False)
    except subprocess.TimeoutExpired:
        pass  # the workers compile what is left, as without this step
    config.stash[_COMPILED] = time.monotonic() - started


CORE_TIER = frozenset({
    'test_deadline_timer.py', 'test_dps_protocol.py', 'test_dps_simulation.py',
    'test_handset_messages.py',
    'test_handset_model.py', 'test_handset_protocol.py', 'test_handset_simulation.py',
    'test_mavlink_core.py', 'test_node_main.py', 'test_originman_messages.py',
    'test_originman_plan.py',
    'test_originman_protocol.py', 'test_originman_simulation.py', 'test_parachute_messages.py',
    'test_parachute_deploy_core.py', 'test_parachute_model.py',
    'test_parachute_online_model.py', 'test_result.py',
    'test_servo_messages.py',
    'test_servo_model.py', 'test_servo_protocol.py', 'test_servo_registers.py',
    'test_servo_simulation.py', 'test_settings_model.py', 'test_stream_decoder.py',
    'test_trigger_model.py', 'test_uart.py',
})
"""The test tier that runs in seconds: protocols, cores, device models and the model searches,
with no process, pty or ROS graph (``make test-core``; ``make test`` runs every tier)."""


LONGEST_FIRST = (
    # Run whole on one worker (WHOLE_FILES): one long unit each.
    'test_blackbox_report.py', 'test_mavlink_link.py', 'test_servo_node_faults.py',
    'test_parachute_node.py',
    # By their longest test.
    'test_demo.py', 'test_servo_safety.py', 'test_originman_node.py', 'test_lint.py',
    'test_fault_campaign.py', 'test_handset_model.py', 'test_shutdown_noise.py',
    'test_handset_node.py', 'test_originman_plan.py', 'test_parachute_core.py',
    'test_parachute_settings_model.py', 'test_settings_model.py', 'test_servo_model.py',
    'test_parachute_safety.py', 'test_servo_node_rate.py', 'test_parachute_round2_stream.py',
    'test_servo_core.py', 'test_trigger_model.py', 'test_servo_link.py',
    'test_parachute_virtual.py', 'test_user_errors.py', 'test_executables.py',
)
"""The files with the longest tests (measured 2026-11-28), longest first. `make test` hands
tests to its workers one at a time, in collection order (``--no-loadscope-reorder``): started
first, the long tests do not make the tail of the run while the other workers idle (a model
search last in the queue kept one worker busy 11 s after the others had finished). Files not
named follow in their usual order."""

WHOLE_FILES = frozenset({
    'test_blackbox_report.py', 'test_mavlink_link.py', 'test_parachute_node.py',
    'test_servo_link.py', 'test_servo_node.py', 'test_servo_node_faults.py',
})
"""The files whose tests share a fixture set up once (a node and its virtual device for the
whole module): each runs whole on one worker, so that fixture is set up once. Collection checks
that every such file is named here."""


def _shares_a_fixture(item: pytest.Item) -> bool:
    """Whether `item` uses a fixture set up once for its module or class (not per test)."""
    info = getattr(item, '_fixtureinfo', None)
    return info is not None and any(
        defs[-1].scope in ('module', 'class', 'package')
        for defs in info.name2fixturedefs.values() if defs)


def pytest_collection_modifyitems(config: pytest.Config, items: list) -> None:
    """Mark the core tier ``core``; check `WHOLE_FILES`; put the longest files first."""
    unnamed = {item.path.name for item in items if _shares_a_fixture(item)} - WHOLE_FILES
    if unnamed:
        raise pytest.UsageError(f'conftest.WHOLE_FILES must name {sorted(unnamed)}: their '
                                'tests share a module fixture')
    for item in items:
        if item.path.name in CORE_TIER:
            item.add_marker(pytest.mark.core)
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: same file order


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """With ``--dist loadgroup``: each test on its own, the `WHOLE_FILES` whole.

    (pytest-xdist's own loadgroup reads ``xdist_group`` marks through a node id that pytest 9
    no longer keeps: it would hand out each test alone, splitting the shared fixtures.)
    """
    if config.getvalue('dist') != 'loadgroup':
        return None
    from xdist.scheduler import LoadScopeScheduling

    class TestsAloneFilesWhole(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split('::', 1)[0]
            return path if os.path.basename(path) in WHOLE_FILES else nodeid

    return TestsAloneFilesWhole(config, log)


def pytest_report_header(config: pytest.Config) -> list:
    """Show the domain id, to tell parallel sessions' logs apart; and a cold cache's compile."""
    lines = [f'ROS_DOMAIN_ID={os.environ.get("ROS_DOMAIN_ID")} (localhost discovery)']
    compiled = config.stash.get(_COMPILED, None)
    if compiled is not None:
        lines.append(f'a cold bytecode cache: compiled once before the workers ({compiled:.1f} s)')
    return lines


from uav_serial_common.process import LaunchedProcesses  # noqa: E402
from uav_serial_common.ros_client import RosHarness  # noqa: E402


@pytest.fixture
def ros():
    """Give a test its own rclpy context, node and spinning executor."""
    harness = RosHarness()
    try:
        yield harness
    finally:
        harness.close()


@pytest.fixture
def launch(request, tmp_path):
    """Start installed executables as processes; all are stopped at the end of the test."""
    processes = LaunchedProcesses(tmp_path, request.node.name)
    try:
        yield processes
    finally:
        processes.stop_all()
        report = getattr(request.node, 'rep_call', None)
        if report is not None and report.failed:
            for proc in processes.processes:
                print(f'--- {proc.name} (pid {proc.pid}, exit {proc.popen.returncode}) ---')
                print(proc.output())


@pytest.fixture
def driver(request, tmp_path):
    """Start drivers' nodes in this process (`InprocDrivers.start`); all stop after the test."""
    from inproc import InprocDrivers
    drivers = InprocDrivers(tmp_path)
    try:
        yield drivers
    finally:
        try:
            drivers.stop_all()
        finally:
            report = getattr(request.node, 'rep_call', None)
            if report is not None and report.failed:
                for node in drivers.drivers:
                    print(f'--- {node.name} (in process) log ---')
                    print(node.output())


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Keep each phase's report on the item, so fixtures can tell that a test failed."""
    outcome = yield
    report = outcome.get_result()
    setattr(item, f'rep_{report.when}', report)
