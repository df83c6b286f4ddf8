"""DriverExecutor: inline callbacks on the spin thread, the rest in the pool, never blocked by it.

Real rclpy in a private context: a node with a topic in an `InlineCallbackGroup`, a service that
blocks in the pool, a publisher and a client in the test's `ros` harness.
"""

from __future__ import annotations

from contextlib import contextmanager
import gc
import threading
from types import SimpleNamespace
from typing import Iterator

import pytest
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.context import Context
from rclpy.node import Node
from std_msgs.msg import Int32
from std_srvs.srv import Trigger
from uav_serial_common.executor import DriverExecutor, InlineCallbackGroup
from uav_serial_common.process import wait_for, wait_scale


class _Driver:
    """A node of its own context, spun by a DriverExecutor in a thread named 'spin'."""

    def __init__(self, threads: int = 2) -> None:
        self.context = Context()
        rclpy.init(context=self.context)
        self.node = Node('executor_under_test', context=self.context)
        self.seen = []
        self.release = threading.Event()
        self.blocked = 0
        self._lock = threading.Lock()
        self.fail_on = None
        self.node.create_subscription(Int32, '~/fast', self._on_fast, 10,
                                      callback_group=InlineCallbackGroup())
        for k in range(threads):
            # A group each, so all of them can block the pool at once.
            self.node.create_service(Trigger, f'~/slow_{k}', self._on_slow,
                                     callback_group=MutuallyExclusiveCallbackGroup())
        self.executor = DriverExecutor(num_threads=threads, context=self.context)
        self.executor.add_node(self.node)
        self.errors = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, name='spin', daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            while not self.stop.is_set() and self.context.ok():
                self.executor.spin_once(timeout_sec=0.1)
        except Exception as exc:  # noqa: BLE001 - the test reads what ended spinning
            self.errors.append(exc)

    def _on_fast(self, msg: Int32) -> None:
        if msg.data == self.fail_on:
            raise RuntimeError(f'callback failed on {msg.data}')
        self.seen.append((msg.data, threading.current_thread().name))

    def _on_slow(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            self.blocked += 1
        self.release.wait(10.0)
        response.success = True
        response.message = threading.current_thread().name
        return response

    def close(self) -> None:
        self.release.set()
        self.stop.set()
        self.thread.join(2.0)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def driver():
    d = _Driver()
    try:
        yield d
    finally:
        d.close()


def _publish_until_seen(ros, driver, value: int) -> None:
    pub = ros.node.create_publisher(Int32, '/executor_under_test/fast', 10)
    wait_for(lambda: pub.get_subscription_count() > 0, 10, what='the subscription matched')
    pub.publish(Int32(data=value))
    wait_for(lambda: any(v == value for v, _ in driver.seen), 5, what=f'message {value} taken')


def test_an_inline_callback_runs_on_the_spin_thread_and_a_service_in_the_pool(ros, driver):
    _publish_until_seen(ros, driver, 1)
    assert driver.seen == [(1, 'spin')]
    driver.release.set()
    response = ros.call(Trigger, '/executor_under_test/slow_0', timeout=10.0)
    assert response.success and response.message.startswith('callback')


def test_an_inline_callback_is_taken_while_every_pool_thread_is_blocked(ros, driver):
    futures = []
    for k in range(2):
        client = ros.client(Trigger, f'/executor_under_test/slow_{k}')
        assert client.wait_for_service(timeout_sec=10.0 * wait_scale())
        futures.append(client.call_async(Trigger.Request()))
    wait_for(lambda: driver.blocked == 2, 5, what='both pool threads blocked in a service')
    _publish_until_seen(ros, driver, 7)
    assert not any(f.done() for f in futures)
    driver.release.set()
    wait_for(lambda: all(f.done() for f in futures), 5, what='the services answered')


def test_an_exception_in_an_inline_callback_ends_spinning_as_rclpys_executors_do(ros, driver):
    driver.fail_on = 3
    pub = ros.node.create_publisher(Int32, '/executor_under_test/fast', 10)
    wait_for(lambda: pub.get_subscription_count() > 0, 10, what='the subscription matched')
    pub.publish(Int32(data=3))
    wait_for(lambda: driver.errors, 5, what='the failure raised out of spin_once')
    assert 'callback failed on 3' in str(driver.errors[0])


@contextmanager
def _pool_held(name: str) -> Iterator[SimpleNamespace]:
    """A `DriverExecutor` of one pool thread, held by a timer's callback until ``release``.

    A second timer's callback (``ran`` gets 'queued' when it runs) is taken while the pool is
    held. Leaving shuts the executor down, destroys the node and shuts its context down.
    """
    context = Context()
    rclpy.init(context=context)
    node = Node(name, context=context)
    held = SimpleNamespace(holding=threading.Event(), release=threading.Event(), ran=[])

    def hold() -> None:
        held.ran.append('hold')
        if not held.holding.is_set():
            held.holding.set()
            held.release.wait(10.0)

    node.create_timer(0.01, hold, callback_group=MutuallyExclusiveCallbackGroup())
    node.create_timer(0.01, lambda: held.ran.append('queued'),
                      callback_group=MutuallyExclusiveCallbackGroup())
    held.executor = DriverExecutor(num_threads=1, context=context)
    held.executor.add_node(node)
    try:
        while not held.holding.is_set():
            held.executor.spin_once(timeout_sec=1.0)
        yield held
    finally:
        held.release.set()
        held.executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_round2_9_a_callback_queued_for_the_pool_at_shutdown_prints_nothing(capfd):
    """Issue 21 item 9: "exception was never retrieved" on a clean exit, made deterministic.

    A timer's callback holds the only pool thread, a second timer's handler is queued behind it,
    and the executor shuts down (as `run_node` does on SIGINT). rclpy's shutdown destroyed its
    guard condition at once; the queued handler then ran and failed on it, and its task's
    exception was printed when the task was collected.
    """
    with _pool_held('shutdown_under_test') as held:
        # The other timer is taken now and queued behind the held pool thread.
        held.executor.spin_once(timeout_sec=5.0)
        held.executor.shutdown(timeout_sec=0)
        held.release.set()
        held.executor._workers.shutdown(wait=True)  # whatever was queued has run (or dropped)
    ran = held.ran
    del held
    gc.collect()
    err = capfd.readouterr().err
    assert 'never retrieved' not in err, err
    assert 'Traceback' not in err, err
    assert ran.count('hold') == 1 and 'queued' not in ran, ran


def test_round2_23_a_done_callback_of_a_client_call_keeps_the_executor_spinning(ros, driver):
    # A future's done callback runs as a task of the executor, with no entity: parachute_node's
    # release gate and parachute_mavlink wait on call_async this way.
    driver.release.set()
    client = driver.node.create_client(Trigger, '/executor_under_test/slow_0')
    assert client.wait_for_service(timeout_sec=10.0 * wait_scale())
    done = threading.Event()
    future = client.call_async(Trigger.Request())
    future.add_done_callback(lambda _: done.set())
    assert done.wait(10.0 * wait_scale()), 'the done callback never ran'
    _publish_until_seen(ros, driver, 11)
    assert driver.errors == []


def test_issue22_6_stop_spinning_ends_a_wait_at_once_where_wake_did_not():
    # A node with no timer (a virtual device's): nothing wakes the executor's wait but the
    # stop. `wake()` alone let rclpy rebuild its wait set and wait on, which held every node's
    # exit for the 2-s join timeout of `run_node`.
    context = Context()
    rclpy.init(context=context)
    node = Node('no_timers', context=context)
    executor = DriverExecutor(num_threads=1, context=context)
    executor.add_node(node)
    returned = threading.Event()

    def spin_once() -> None:
        executor.spin_once()
        returned.set()

    spinner = threading.Thread(target=spin_once, daemon=True)
    try:
        spinner.start()
        executor.wake()
        assert not returned.wait(0.3)  # still waiting: wake() is not a stop
        executor.stop_spinning()
        wait_for(returned.is_set, 1.0, what='spin_once to return after stop_spinning()')
        executor.spin_once()  # and every later one returns at once too
    finally:
        executor.stop_spinning()
        spinner.join(2.0)
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown(context=context)


def test_issue22_a_handler_waiting_for_a_pool_thread_is_submitted_once():
    """rclpy yields a task again on every turn until a thread has started it. Each was handed to
    the pool again: a timer queued behind a busy pool became hundreds of submissions, and the
    spin thread turned hot doing it (the handset driver's CPU +50 %). It is submitted once, and
    runs once the pool thread is free."""
    with _pool_held('resubmit_under_test') as held:
        executor = held.executor
        # The other timer's handler is taken and queued behind the held pool thread; rclpy
        # yields it again on each of these turns.
        for _ in range(50):
            executor.spin_once(timeout_sec=0.05)
        with executor._pool_lock:
            submitted = [id(task) for task, _ in executor._pool_tasks]
        assert len(submitted) == len(set(submitted)) == 2, \
            f'{len(submitted)} pool submissions of {len(set(submitted))} handlers'
        held.release.set()
        wait_for(lambda: 'queued' in held.ran, 5, what='the queued timer ran')
        for _ in range(3):
            executor.spin_once(timeout_sec=0.05)
