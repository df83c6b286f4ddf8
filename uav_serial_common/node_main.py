"""The Jazzy `main()` pattern, shared by every executable of the package."""

from __future__ import annotations

import sys
from typing import Callable, List, Optional

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node


def run_node(factory: Callable[[], Node], args: Optional[List[str]] = None,
             threads: int = 4) -> int:
    """Create the node, spin it on a multi-threaded executor, shut down cleanly on Ctrl-C.

    A node may define ``on_shutdown()``: it runs after spinning stops and before the node is
    destroyed, so a driver can still talk to its device (torque off, lock) as its last act.
    Returns the process exit code.
    """
    node = None
    code = 0
    try:
        rclpy.init(args=args)
        node = factory()
        executor = MultiThreadedExecutor(num_threads=threads)
        executor.add_node(node)
        try:
            executor.spin()
        finally:
            executor.shutdown(timeout_sec=1.0)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:  # noqa: BLE001 - report a startup failure as one clear line
        print(f'fatal: {exc}', file=sys.stderr)
        code = 1
    finally:
        if node is not None:
            hook = getattr(node, 'on_shutdown', None)
            if hook is not None:
                try:
                    hook()
                except Exception as exc:  # noqa: BLE001 - shutting down regardless
                    print(f'shutdown hook failed: {exc}', file=sys.stderr)
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return code
