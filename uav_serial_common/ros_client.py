"""A ROS client for tests, benchmarks and the demo: a private rclpy context with one spinning node.

- `RosHarness`: its own rclpy Context (on the environment's ROS_DOMAIN_ID, or a given one), a node
  and a single-threaded executor spinning in a thread, with helpers to record topics, publish,
  and call services with timeouts.
- `MessageLog`: every message of one subscription, with a condition to wait on.
"""

from __future__ import annotations

import sys
import threading
import time
import traceback
from typing import Any, Callable, Dict, List, Optional

import rclpy
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from uav_serial_common.process import wait_for, wait_scale


class MessageLog:
    """Every message received on one subscription, with a condition to wait on."""

    def __init__(self) -> None:
        self.messages: List[Any] = []
        self._cond = threading.Condition()

    def append(self, msg: Any) -> None:
        """Record one message (subscription callback)."""
        with self._cond:
            self.messages.append(msg)
            self._cond.notify_all()

    def wait(self, predicate: Callable[[Any], bool] = lambda m: True, timeout: float = 5.0,
             what: str = 'a matching message', start: int = 0) -> Any:
        """Return the first message from index `start` that satisfies `predicate`."""
        timeout *= wait_scale()
        deadline = time.monotonic() + timeout
        checked = start
        with self._cond:
            while True:
                # Only look at what arrived since the last look: rescanning everything on each
                # message would hog the GIL that the in-process virtual devices need.
                for msg in self.messages[checked:]:
                    if predicate(msg):
                        return msg
                checked = max(checked, len(self.messages))
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    last = self.messages[-1] if self.messages else None
                    raise AssertionError(
                        f'timed out after {timeout:.1f} s waiting for {what}; '
                        f'{len(self.messages)} received, last: {last}')
                self._cond.wait(remaining)

    @property
    def last(self) -> Any:
        """Return the newest message, or None."""
        with self._cond:
            return self.messages[-1] if self.messages else None

    def __len__(self) -> int:
        with self._cond:
            return len(self.messages)


class RosHarness:
    """A private rclpy Context with one node and an executor spinning in a thread."""

    def __init__(self, node_name: str = 'test_client', domain_id: Optional[int] = None) -> None:
        self.context = Context()
        # domain_id None: ROS_DOMAIN_ID of the environment (the test session's claim).
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = Node(node_name, context=self.context)
        self.group = ReentrantCallbackGroup()
        self._clients: Dict[Any, Any] = {}
        self._clients_lock = threading.Lock()
        # Single-threaded on purpose: the callbacks here only record messages and complete
        # futures, and rclpy's multi-threaded executor can spin hot in Python while its tasks
        # are in flight, starving the virtual devices that share this process of the GIL.
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._closing = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        # One wait at a time: an error of a wait (rclpy raises one for an entity destroyed
        # while the executor waited on it, "cannot use Destroyable because destruction was
        # requested") costs that wait, and is said on stderr. Spun by executor.spin(), it ended
        # this thread unseen, and every later call of the harness timed out (the likely cause
        # of campaign s13a runs 7 and 8: a publisher destroyed just before).
        while not self._closing and self.context.ok():
            try:
                self.executor.spin_once()
            except Exception:  # noqa: BLE001 - this thread is every call's; it goes on
                if self._closing or not self.context.ok():
                    return
                print(f'RosHarness executor: {traceback.format_exc()}', file=sys.stderr,
                      flush=True)

    def subscribe(self, msg_type: Any, topic: str, latched: bool = False,
                  reliable: bool = True, depth: int = 100) -> MessageLog:
        """Record every message of `topic`; `latched` matches transient-local publishers."""
        qos = QoSProfile(depth=depth)
        qos.reliability = ReliabilityPolicy.RELIABLE if reliable else \
            ReliabilityPolicy.BEST_EFFORT
        if latched:
            qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
        log = MessageLog()
        self.node.create_subscription(msg_type, topic, log.append, qos,
                                      callback_group=self.group)
        return log

    def publisher(self, msg_type: Any, topic: str, wait_subscribers: int = 1,
                  timeout: float = 10.0) -> Any:
        """Create a publisher and wait until `wait_subscribers` subscribers match it."""
        pub = self.node.create_publisher(msg_type, topic, 10)
        if wait_subscribers:
            wait_for(lambda: pub.get_subscription_count() >= wait_subscribers, timeout,
                     what=f'a subscriber on {topic}')
        return pub

    def call(self, srv_type: Any, name: str, request: Any = None, timeout: float = 10.0) -> Any:
        """Call a service and return its response; fail the test on timeout (x `wait_scale()`).

        The request is sent once (a call may act on a device), when this client has matched
        the server both ways (``wait_for_service``: its request writer and its response
        reader). Whether the server has matched this client's response reader no client API
        tells; a server under test/conftest.py waits for it (test/fastdds_profiles.xml), where
        rmw_fastrtps's default drops the response of a client it discovers 100 ms too late.
        """
        timeout *= wait_scale()
        client = self.client(srv_type, name)
        if not client.wait_for_service(timeout_sec=timeout):
            raise AssertionError(f'service {name} not available after {timeout:.0f} s')
        future = client.call_async(request if request is not None else srv_type.Request())
        done = threading.Event()
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(timeout):
            client.remove_pending_request(future)
            raise AssertionError(
                f'service {name} did not answer within {timeout:.0f} s (a response the server '
                'dropped shows in its stderr: "failed to send response (timeout)")')
        return future.result()

    def client(self, srv_type: Any, name: str) -> Any:
        """Return the client of one service, created once and kept.

        Creating a client creates DDS entities while holding the GIL; doing it on every call
        stalls every other thread of the test process (the in-process virtual devices) for
        up to seconds.
        """
        key = (srv_type, name)
        with self._clients_lock:
            client = self._clients.get(key)
            if client is None:
                client = self.node.create_client(srv_type, name, callback_group=self.group)
                self._clients[key] = client
            return client

    def wait_for_service(self, name: str, timeout: float = 15.0) -> None:
        """Wait until a service of that (fully qualified) name exists."""
        wait_for(lambda: any(n == name for n, _ in self.node.get_service_names_and_types()),
                 timeout, interval=0.05, what=f'service {name}')

    def wait_for_topic(self, name: str, timeout: float = 15.0) -> None:
        """Wait until a publisher of that (fully qualified) topic exists."""
        wait_for(lambda: self.node.count_publishers(name) > 0, timeout, interval=0.05,
                 what=f'a publisher on {name}')

    def close(self) -> None:
        """Stop spinning and shut the context down."""
        self._closing = True
        try:
            self.executor.shutdown(timeout_sec=2.0)
        finally:
            self.node.destroy_node()
            if self.context.ok():
                rclpy.shutdown(context=self.context)
            self._thread.join(timeout=2.0)
