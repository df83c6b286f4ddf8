"""Drivers' nodes in the test's own process (the `driver` fixture), where a test needs no process.

A driver started by `InprocDrivers.start` is what ``main()`` runs, minus the process: its node
class in a Context of its own (a DDS participant of its own, as a process has; creating and
shutting it down never touches the test's `ros` context), the test's parameters as overrides
(the dict `launch.start(parameters=...)` takes, in the same YAML file as node arguments, so rcl
types them as for a process: ``[]`` fits an integer-array parameter, where rclpy's `Parameter`
would make it a byte array), an optional node name and namespace (remapped as ``--ros-args -r``
does), spun by the drivers' `DriverExecutor` in a thread with the thread
count of its ``main()``, and stopped by the shutdown of `run_node` (`NodeSpinner.shutdown`: stop
spinning, ``on_shutdown()``, destroy the node) before its context is shut down. It saves a
process start (Python, rclpy, a participant) per driver.

What stays with the subprocess (`launch`, and test/test_executables.py's smoke test of every
executable): signals, exit codes, the environment of the process, a kill and a respawn, and
anything written to stderr that is not a log line (a traceback, ``fatal: ...``). The handle's
`output()` holds the node's log lines only, as its own process prints them
(``[WARN] [stamp] [name]: message``), read from ``/rosout`` through the test's `ros` harness.

Its time-critical threads (a watchdog, a confirmation) now share the GIL with the test's
threads: the GIL switch interval of its ``main()`` is set while it runs, and a test that
measures what only a process boundary guarantees keeps the process.
"""

from __future__ import annotations

from dataclasses import dataclass
import importlib
from pathlib import Path
import sys
from typing import Any, Dict, List, Optional

import rclpy
from rclpy.context import Context
from rcl_interfaces.msg import Log
from uav_serial_common.node_main import NodeSpinner
from uav_serial_common.process import ros_args, wait_for
from uav_serial_common.ros_client import MessageLog


@dataclass(frozen=True)
class DriverMain:
    """The node class an executable's ``main()`` hands to `run_node`.

    Its thread count and GIL switch interval are the node module's own ``EXECUTOR_THREADS``
    and ``SWITCH_INTERVAL_S``, the constants its ``main()`` passes (one place for both).
    """

    module: str
    node_class: str


DRIVERS: Dict[str, DriverMain] = {
    'handset_link_node': DriverMain('handset_link_ros.node', 'HandsetLinkNode'),
    'parachute_node': DriverMain('dps_parachute_ros.node', 'ParachuteNode'),
    'servo_bus_node': DriverMain('desheng_servo_ros.node', 'ServoBusNode'),
    'originman_board_node': DriverMain('originman_board_ros.node', 'OriginManBoardNode'),
}
"""Each driver executable's node (the ``run_node(...)`` call of its node.py)."""

_SEVERITY = {Log.DEBUG: 'DEBUG', Log.INFO: 'INFO', Log.WARN: 'WARN', Log.ERROR: 'ERROR',
             Log.FATAL: 'FATAL'}


class InprocDriver:
    """One driver node running in this process (what `LaunchedProcess` is for a subprocess)."""

    def __init__(self, name: str, node: Any, spinner: NodeSpinner, context: Context,
                 logs: Optional[MessageLog]) -> None:
        self.name = name
        self.node = node
        self.context = context
        self._spinner = spinner
        self._logs = logs
        self._logger = node.get_logger().name
        self._stopped = False

    def alive(self) -> bool:
        """Return whether it still spins (an executor that failed ends it, as its process)."""
        return not self._stopped and self._spinner.spinning() and self.context.ok()

    def output(self) -> str:
        """Return the node's log lines so far, one a line as its process would print them."""
        if self._logs is None:
            return '(no log: started without a `ros` harness)\n'
        lines = []
        for msg in list(self._logs.messages):
            if msg.name == self._logger or msg.name.startswith(self._logger + '.'):
                level = _SEVERITY.get(msg.level, str(msg.level))
                lines.append(f'[{level}] [{msg.stamp.sec}.{msg.stamp.nanosec:09d}] '
                             f'[{msg.name}]: {msg.msg}\n')
        return ''.join(lines)

    def stop(self) -> None:
        """Shut it down as `run_node` does, then shut its context down (idempotent)."""
        if self._stopped:
            return
        self._stopped = True
        self._spinner.shutdown()
        self.context.try_shutdown()


class InprocDrivers:
    """Starts drivers' nodes in this process for one test and stops them all afterwards."""

    def __init__(self, tmp_path: Path) -> None:
        self.tmp_path = tmp_path
        self.drivers: List[InprocDriver] = []
        self._switch_interval: Optional[float] = None
        self._rosout: Dict[int, MessageLog] = {}

    def start(self, executable: str, parameters: Optional[Dict[str, Any]] = None,
              node_name: Optional[str] = None, namespace: Optional[str] = None,
              wait_service: Optional[str] = None, wait_topic: Optional[str] = None,
              ros: Optional[Any] = None, timeout: float = 20.0) -> InprocDriver:
        """Start `executable`'s node here with `parameters`; wait for a service or topic via `ros`.

        The arguments are those of `LaunchedProcesses.start`. `ros` (a `RosHarness`) also
        records ``/rosout``, the node's `output()`.
        """
        spec = DRIVERS[executable]
        module = importlib.import_module(spec.module)
        interval = getattr(module, 'SWITCH_INTERVAL_S', None)
        if interval is not None:
            if self._switch_interval is None:
                self._switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(min(interval, sys.getswitchinterval()))
        logs = self._rosout_of(ros)
        cli_args = ros_args(
            self.tmp_path / f'{executable}-inproc-{len(self.drivers)}.params.yaml', parameters,
            node_name, namespace)
        context = Context()
        rclpy.init(context=context)
        try:
            node = getattr(module, spec.node_class)(
                context=context, cli_args=cli_args)
        except Exception as exc:
            context.try_shutdown()
            # A process would print this as "fatal: ..." and exit 1.
            raise AssertionError(f'{executable} failed to start: {exc!r}') from exc
        spinner = NodeSpinner(node)
        driver = InprocDriver(executable, node, spinner, context, logs)
        self.drivers.append(driver)
        spinner.start(module.EXECUTOR_THREADS)
        if ros is not None and wait_service:
            wait_for(lambda: not driver.alive() or any(
                n == wait_service for n, _ in ros.node.get_service_names_and_types()),
                timeout, interval=0.05, what=f'service {wait_service} of {executable}')
        if ros is not None and wait_topic:
            wait_for(lambda: not driver.alive() or ros.node.count_publishers(wait_topic) > 0,
                     timeout, interval=0.05, what=f'topic {wait_topic} of {executable}')
        if not driver.alive():
            raise AssertionError(f'{executable} stopped spinning\n--- log ---\n'
                                 f'{driver.output()}')
        return driver

    def _rosout_of(self, ros: Optional[Any]) -> Optional[MessageLog]:
        """Return the record of ``/rosout`` kept by `ros` (one subscription per harness)."""
        if ros is None:
            return None
        log = self._rosout.get(id(ros))
        if log is None:
            # As rosout publishes: reliable, transient local (lines from before the match).
            log = ros.subscribe(Log, '/rosout', latched=True, depth=1000)
            self._rosout[id(ros)] = log
        return log

    def stop_all(self) -> None:
        """Stop every driver started here (newest first) and restore the GIL switch interval."""
        errors = []
        for driver in reversed(self.drivers):
            try:
                driver.stop()
            except Exception as exc:  # noqa: BLE001 - stop the others regardless
                errors.append(f'{driver.name}: {exc!r}')
        if self._switch_interval is not None:
            sys.setswitchinterval(self._switch_interval)
            self._switch_interval = None
        if errors:
            raise AssertionError('stopping in-process drivers failed: ' + '; '.join(errors))
