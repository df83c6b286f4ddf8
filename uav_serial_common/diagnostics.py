"""A diagnostics updater with ``diagnostic_updater``'s conventions (that package is not on PyPI).

One `DiagnosticsUpdater` per node owns the ``/diagnostics`` publisher. Each status is a task that
fills a `Status` (``summary``, ``add``); the updater publishes every task's status together once a
period, and at once (at most every ``min_interval_s``) when a driver calls `force_update()` from
any thread because something changed. Status names are ``<fully qualified node name>: <task>``
(``/uav1/parachute: link``), so two drivers of one kind under two namespaces never report under
the same name, and every status carries the hardware id (the port).
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable, List, Optional, Tuple, Union

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import CallbackGroup, MutuallyExclusiveCallbackGroup
from rclpy.node import Node

OK = DiagnosticStatus.OK
WARN = DiagnosticStatus.WARN
ERROR = DiagnosticStatus.ERROR
STALE = DiagnosticStatus.STALE


class Status:
    """What one task reports: a level, a message, key/value pairs (DiagnosticStatusWrapper)."""

    def __init__(self) -> None:
        self.level = OK
        self.message = ''
        self.values: List[Tuple[str, str]] = []

    def summary(self, level: Union[int, bytes], message: str) -> None:
        """Set the level and the message."""
        self.level = _level(level)
        self.message = message

    def merge_summary(self, level: Union[int, bytes], message: str) -> None:
        """Raise the level to `level` if higher and append `message` (diagnostic_updater's)."""
        level = _level(level)
        if level > self.level:
            self.level = level
        self.message = f'{self.message}; {message}' if self.message else message

    def add(self, key: str, value: Any) -> None:
        """Add one key/value pair (the value as text; None as '')."""
        self.values.append((key, '' if value is None else str(value)))


Task = Callable[[Status], None]


class DiagnosticsUpdater:
    """Publishes the tasks' statuses on ``/diagnostics``: periodically and on change."""

    def __init__(self, node: Node, hardware_id: Union[str, Callable[[], str]],
                 period_s: float = 1.0, min_interval_s: float = 0.1,
                 callback_group: Optional[CallbackGroup] = None) -> None:
        self._node = node
        self._hardware_id = hardware_id
        self._min_interval = min_interval_s
        self._tasks: List[Tuple[str, Task]] = []
        self._lock = threading.Lock()
        self._last = 0.0
        self._pending = False
        self.publisher = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
        group = callback_group or MutuallyExclusiveCallbackGroup()
        self._timer = node.create_timer(period_s, self.update, callback_group=group)
        # A forced update that comes too soon after the last one is published by this timer,
        # which runs only while such an update is waiting.
        self._later = node.create_timer(min_interval_s, self._on_later, callback_group=group)
        self._later.cancel()
        self._wake = node.create_guard_condition(self._on_wake, callback_group=group)

    @property
    def prefix(self) -> str:
        """Return what every status name starts with: the node's fully qualified name."""
        return self._node.get_fully_qualified_name()

    def add(self, name: str, task: Task) -> None:
        """Add a status task; its status is named ``<node>: <name>``."""
        # Copy-on-write: update() iterates over the list it took, whatever thread adds.
        self._tasks = self._tasks + [(name, task)]

    def remove(self, name: str) -> None:
        """Remove the status task(s) called `name` (a device that is gone or renamed)."""
        self._tasks = [(n, t) for n, t in self._tasks if n != name]

    def force_update(self) -> None:
        """Publish soon (within ``min_interval_s``); callable from any thread."""
        with self._lock:
            self._pending = True
        try:
            self._wake.trigger()
        except Exception:  # noqa: BLE001 - the node is being destroyed: nothing to publish to
            pass

    def update(self) -> None:
        """Run every task and publish their statuses now (executor thread)."""
        with self._lock:
            self._pending = False
            self._last = time.monotonic()
        # The period counts from this publication: a driver that forces an update about once a
        # period (the parachute after each poll) publishes once a period, not twice.
        self._timer.reset()
        hardware_id = self._hardware_id() if callable(self._hardware_id) else self._hardware_id
        prefix = self.prefix
        array = DiagnosticArray()
        for name, task in self._tasks:
            status = Status()
            try:
                task(status)
            except Exception as exc:  # noqa: BLE001 - one broken task must not hide the others
                status = Status()
                status.summary(ERROR, f'diagnostics task failed: {exc!r}')
            array.status.append(DiagnosticStatus(
                level=_level_byte(status.level), name=f'{prefix}: {name}',
                message=status.message, hardware_id=hardware_id,
                values=[KeyValue(key=k, value=v) for k, v in status.values]))
        array.header.stamp = self._node.get_clock().now().to_msg()
        self.publisher.publish(array)

    def _on_wake(self) -> None:
        with self._lock:
            if not self._pending:
                return
            wait = self._last + self._min_interval - time.monotonic()
        if wait <= 0:
            self.update()
        else:
            self._later.reset()

    def _on_later(self) -> None:
        self._later.cancel()
        with self._lock:
            pending = self._pending
        if pending:
            self.update()


def _level(level: Union[int, bytes]) -> int:
    return level[0] if isinstance(level, (bytes, bytearray)) else int(level)


def _level_byte(level: int) -> bytes:
    return bytes([level])
