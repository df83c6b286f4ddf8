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

Shutdown (issue 21 item 9): rclpy's ``Executor.shutdown`` destroys its guard condition without
waiting for the callbacks in flight (its wait on the work tracker sits behind a condition that is
never true in Jazzy), and a pool task taken just before it then fails in rclpy's own handler on
that guard ("cannot use Destroyable because destruction was requested"); nobody reads that
task's result, so its exception is printed as "never retrieved" when the task is collected, on a
clean exit. ``DriverExecutor.shutdown`` drops the handlers still queued for the pool, waits for
the running ones, and reads the result of every task that ends after shutdown began.

rclpy yields a task again, first thing, on every turn until a thread has started it. Handed to
the pool again each time, one 1-Hz timer callback became hundreds of pool submissions while the
worker waited for the GIL, and the spin thread turned hot doing it (the handset driver's CPU:
3.5 -> 5.1 %). A handler is submitted once; when rclpy yields it again, the spin thread waits
(GIL released) until a worker has started it, at most ``QUEUED_WAIT_S``, then turns again.
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor, wait
import sys
import threading
from typing import Callable, List, Optional, Set, Tuple

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.context import Context
from rclpy.executors import (ConditionReachedException, Executor, ExternalShutdownException,
                             ShutdownException, TimeoutException)
from rclpy.exceptions import InvalidHandle
from rclpy.task import Task

QUEUED_WAIT_S = 0.002
"""How long the spin thread waits for a worker to start a handler rclpy yielded again (a pool
whose every thread is busy: the spin thread's inline callbacks wait at most this long)."""


class InlineCallbackGroup(MutuallyExclusiveCallbackGroup):
    """Callbacks that never block: `DriverExecutor` runs them on its own thread, no hand-off."""


class DriverExecutor(Executor):
    """A multi-threaded executor whose `InlineCallbackGroup` callbacks skip the pool."""

    def __init__(self, num_threads: int = 4, *, context: Optional[Context] = None) -> None:
        super().__init__(context=context)
        # Names of their own: rclpy's Executor keeps its coroutine tasks in self._tasks.
        self._workers = ThreadPoolExecutor(num_threads, thread_name_prefix='callback')
        self._pool_tasks: List[Tuple[Task, Future]] = []
        self._pool_lock = threading.Lock()
        self._queued: Set[Task] = set()  # submitted, not started yet (guarded by the condition)
        self._started = threading.Condition(self._pool_lock)
        self._closing = False
        self._stop_spinning = False
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

    def stop_spinning(self) -> None:
        """Make a `spin_once` waiting now (and every later one) return at once.

        `wake()` alone does not end a wait: rclpy rebuilds its wait set and waits on, so a node
        with no timer (a virtual device) held its shutdown for the whole join timeout.
        """
        self._stop_spinning = True
        self.wake()

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
            handler, entity, _ = self.wait_for_ready_callbacks(
                timeout_sec, None, lambda: self._stop_spinning or condition())
        except (ExternalShutdownException, ShutdownException, TimeoutException,
                ConditionReachedException):
            return
        # entity None: a task of create_task, e.g. a future's done callback (call_async).
        if entity is not None and isinstance(entity.callback_group, InlineCallbackGroup):
            handler()
            handler.result()  # raises what the callback raised, as rclpy's executors do
            return
        with self._pool_lock:
            if self._closing:
                _drop(handler)  # shutting down: a callback taken now never runs
                return
            if handler in self._queued:
                # Yielded again before a worker started it: once in the pool is enough.
                self._started.wait_for(lambda: handler not in self._queued or
                                       handler.executing(), QUEUED_WAIT_S)
                return
            self._queued.add(handler)
            self._pool_tasks.append((handler, self._workers.submit(self._run_pooled, handler)))
            finished = [pair for pair in self._pool_tasks if pair[0].done()]
            for pair in finished:
                self._pool_tasks.remove(pair)
        for task, _ in finished:
            task.result()

    def _run_pooled(self, handler: Task) -> None:
        # Queued until it has run (or awaits): between a worker taking it and rclpy marking it
        # executing, rclpy may yield it again, and it must not go to the pool twice.
        try:
            handler()
        finally:
            with self._pool_lock:
                self._queued.discard(handler)
                self._started.notify_all()
        if self._closing:
            _settle(handler)  # nobody else reads it once shutdown has begun

    def shutdown(self, timeout_sec: Optional[float] = None) -> bool:
        """Stop taking callbacks, let the running ones finish, then release rclpy's resources.

        Handlers queued for the pool and not started are dropped; running ones get up to
        ``timeout_sec`` (None: no limit) before the guard condition they signal is destroyed,
        and the outcome of each is read here or when it ends, so none is reported as "never
        retrieved". Returns whether every running callback finished in time.
        """
        with self._pool_lock:
            self._closing = True
            pending = list(self._pool_tasks)
            self._pool_tasks.clear()
            self._queued.clear()
        self._workers.shutdown(wait=False, cancel_futures=True)
        running = [future for _, future in pending if not future.cancelled()]
        finished = not running or not wait(running, timeout_sec).not_done
        # A coroutine task that rclpy resumes later may have several submissions: it never ran
        # only if every one of them was cancelled.
        started = {id(task) for task, future in pending if not future.cancelled()}
        for task, _ in pending:
            if id(task) not in started:
                task.cancel()  # closes its coroutine, so none is reported "never awaited"
            elif task.done():
                _settle(task)
        return super().shutdown(timeout_sec=0) and finished


def _drop(task: Task) -> None:
    """Close a task that will not run, so its coroutine is not reported "never awaited"."""
    if not task.executing() and not task.done():
        try:
            task.cancel()
        except ValueError:
            pass  # a pool thread started it meanwhile: it ends, and is read, there


def _settle(task: Task) -> None:
    """Read a finished task's outcome; report a failure other than the shutdown's own."""
    if not task.done():
        return
    exc = task.exception()
    if exc is not None and not isinstance(exc, InvalidHandle):
        print(f'callback failed during shutdown: {exc!r}', file=sys.stderr, flush=True)


def _pass(gate: threading.Barrier) -> None:
    try:
        gate.wait(5.0)
    except threading.BrokenBarrierError:
        pass
