"""The executor of every driver: a pool for callbacks that may wait, the spin thread for the rest.

rclpy's ``MultiThreadedExecutor`` hands every callback to a thread pool. That hand-off is where a
command waits: measured on the 2-core bench machine, a message from another process reaches a
callback in 0.6 ms at p99 when the spin thread runs it, and in 6-8 ms (20-50 ms under the servo
bus's read load) when a pool thread does, because the spin thread goes straight back to
rebuilding its wait set in Python while the woken worker waits for the GIL. A driver's command
topic only hands the message to its device core, which never waits on the device, so its
callback group is an `InlineCallbackGroup`: its callbacks run on the spin thread as soon as they
are taken. Everything else (services that wait for the device, timers) goes to the pool as
before, so the executor is never blocked by serial I/O.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
import threading
from typing import Callable, List, Optional

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.context import Context
from rclpy.executors import (ConditionReachedException, Executor, ExternalShutdownException,
                             ShutdownException, TimeoutException)
from rclpy.task import Task


class InlineCallbackGroup(MutuallyExclusiveCallbackGroup):
    """Callbacks that never block: `DriverExecutor` runs them on its own thread, no hand-off."""


class DriverExecutor(Executor):
    """A multi-threaded executor whose `InlineCallbackGroup` callbacks skip the pool."""

    def __init__(self, num_threads: int = 4, *, context: Optional[Context] = None) -> None:
        super().__init__(context=context)
        # Names of their own: rclpy's Executor keeps its coroutine tasks in self._tasks.
        self._workers = ThreadPoolExecutor(num_threads, thread_name_prefix='callback')
        self._pool_tasks: List[Task] = []
        self._start_pool(num_threads)

    def _start_pool(self, threads: int) -> None:
        """Start every worker thread now instead of on its first busy moment.

        The pool adds a thread whenever no idle one is there, so a driver's thread count would
        creep up over its first minutes of concurrent callbacks; fixed from the start, any
        growth later is a leak a check can see.
        """
        gate = threading.Barrier(threads + 1)
        for _ in range(threads):
            self._workers.submit(_pass, gate)
        _pass(gate)

    def spin_once(self, timeout_sec: Optional[float] = None) -> None:
        """Wait for one ready callback and run it (inline) or hand it to the pool."""
        self._run_one(timeout_sec)

    def spin_once_until_future_complete(self, future: Task,
                                        timeout_sec: Optional[float] = None) -> None:
        """As `spin_once`, returning early once `future` is done."""
        future.add_done_callback(lambda _: self.wake())
        self._run_one(timeout_sec, future.done)

    def _run_one(self, timeout_sec: Optional[float],
                 condition: Callable[[], bool] = lambda: False) -> None:
        try:
            handler, entity, _ = self.wait_for_ready_callbacks(timeout_sec, None, condition)
        except (ExternalShutdownException, ShutdownException, TimeoutException,
                ConditionReachedException):
            return
        # entity None: a task of create_task, e.g. a future's done callback (call_async).
        if entity is not None and isinstance(entity.callback_group, InlineCallbackGroup):
            handler()
            handler.result()  # raises what the callback raised, as rclpy's executors do
            return
        self._workers.submit(handler)
        self._pool_tasks.append(handler)
        for task in [t for t in self._pool_tasks if t.done()]:
            self._pool_tasks.remove(task)
            task.result()


def _pass(gate: threading.Barrier) -> None:
    try:
        gate.wait(5.0)
    except threading.BrokenBarrierError:
        pass
