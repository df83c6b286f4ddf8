"""The `main()` of every executable of the package: spin, and a shutdown that always completes.

It follows the Jazzy pattern (init, spin, shut down on Ctrl-C or an external shutdown, destroy
the node, ``try_shutdown``) with one difference that a driver of real hardware needs: Ctrl-C
under ``ros2 launch`` arrives twice (the terminal signals the whole process group and launch
forwards its own SIGINT), and with rclpy's default handlers the second one raises
``KeyboardInterrupt`` inside the node's shutdown: the servo bus never gets its torque-off, the
parachute's black box is never closed. So the executor spins in a thread and the main thread
only waits; SIGINT and SIGTERM set a flag, and once shutdown has begun further signals are
logged and ignored. ``ros2 launch`` escalates to SIGKILL only after its timeouts (5 s + 5 s).
"""

from __future__ import annotations

import os
import select
import signal
import sys
import threading
from typing import Callable, List, Optional

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from uav_serial_common.executor import DriverExecutor

_WAIT_STEP_S = 0.2
"""The main thread wakes this often, so a signal is seen promptly."""
_SPIN_EXIT_S = 2.0
"""How long the shutdown waits for the executor to leave its wait (one step, normally)."""


class _Signals:
    """SIGINT/SIGTERM as a flag: the first starts the shutdown, later ones are only noted.

    The handler runs in the main thread between two bytecodes, possibly while that thread holds
    a lock (an Event's, a buffered stream's): so it takes none. It sets a plain flag and writes
    a byte to a pipe the main thread waits on, and says "again" with one `os.write`.
    """

    def __init__(self) -> None:
        self.requested = False
        self.count = 0
        self._read, write = os.pipe()
        os.set_blocking(write, False)
        self._write: Optional[int] = write
        self.previous = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            self.previous[sig] = signal.signal(sig, self._on_signal)

    def _on_signal(self, signum: int, frame: object) -> None:
        self.count += 1
        if self.count > 1 or self.requested:
            try:
                os.write(2, f'{signal.Signals(signum).name} again: shutdown in progress, '
                            'finishing it\n'.encode())
            except OSError:
                pass
            return
        self.wake()

    def wake(self) -> None:
        """Ask the main thread to shut down (a signal, or the executor that ended)."""
        self.requested = True
        fd = self._write
        if fd is None:  # closed: nobody waits any more (and the number may be reused)
            return
        try:
            os.write(fd, b'\0')
        except OSError:  # the pipe is full: the main thread has its wake-ups already
            pass

    def wait(self, timeout: float) -> bool:
        """Wait until a shutdown is asked for, at most `timeout` s; return whether it is."""
        if not self.requested:
            select.select([self._read], [], [], timeout)
        return self.requested

    def close(self) -> None:
        """Close the pipe (signals that still come find the flag set and only write to 2)."""
        self.requested = True
        if self._write is None:
            return
        fds, self._write = (self._read, self._write), None
        for fd in fds:
            try:
                os.close(fd)
            except OSError:
                pass


class NodeSpinner:
    """A node spun by a `DriverExecutor` in a thread, and the shutdown that always completes.

    `run_node` runs one per process; the tests run drivers in their own process with it too
    (test/inproc.py). The executor takes the node's context.
    """

    def __init__(self, node: Node) -> None:
        self.node = node
        self.executor: Optional[DriverExecutor] = None
        self.thread: Optional[threading.Thread] = None
        self._stop = threading.Event()

    def start(self, threads: int = 4, ended: Callable[[], None] = lambda: None) -> None:
        """Spin the node in a thread; `ended` is called when spinning ends on its own."""
        self.executor = DriverExecutor(num_threads=threads, context=self.node.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=_spin, args=(self.executor, self._stop, ended),
                                       name='executor', daemon=True)
        self.thread.start()

    def spinning(self) -> bool:
        """Return whether the executor still spins."""
        return self.thread is not None and self.thread.is_alive() and not self._stop.is_set()

    def shutdown(self) -> None:
        """Stop spinning, run the node's shutdown hook, destroy the node (never raises)."""
        self._stop.set()
        executor, node = self.executor, self.node
        if executor is not None:
            try:
                executor.stop_spinning()  # out of its wait now: it waits without a timeout
            except Exception as exc:  # noqa: BLE001 - shutting down regardless
                print(f'waking the executor failed: {exc!r}', file=sys.stderr)
        if self.thread is not None:
            # Out of its wait before anything is destroyed: rclpy's Executor.shutdown does not
            # wait for the spin thread, and a node destroyed under a waiting executor can hang
            # the exit, or abort it when the interpreter finalizes under that thread.
            self.thread.join(_SPIN_EXIT_S)
        if executor is not None:
            try:
                executor.shutdown(timeout_sec=1.0)
            except Exception as exc:  # noqa: BLE001 - shutting down regardless
                print(f'executor shutdown failed: {exc!r}', file=sys.stderr)
        hook = getattr(node, 'on_shutdown', None)
        if hook is not None:
            try:
                hook()
            except Exception as exc:  # noqa: BLE001 - shutting down regardless
                print(f'shutdown hook failed: {exc!r}', file=sys.stderr)
        try:
            node.destroy_node()
        except Exception as exc:  # noqa: BLE001 - shutting down regardless
            print(f'destroying the node failed: {exc!r}', file=sys.stderr)


def run_node(factory: Callable[[], Node], args: Optional[List[str]] = None,
             threads: int = 4, switch_interval_s: Optional[float] = None) -> int:
    """Create the node, spin it until SIGINT/SIGTERM, then shut down completely.

    A node may define ``on_shutdown()``: it runs after spinning stops and before the node is
    destroyed, so a driver can still talk to its device (torque off, motors stopped) as its last
    act; signals arriving meanwhile do not interrupt it. ``switch_interval_s`` sets the GIL
    switch interval of the process (Python's default, 5 ms, lets a busy thread hold a service
    call or a paced frame that long). Returns the process exit code.
    """
    if switch_interval_s is not None:
        sys.setswitchinterval(switch_interval_s)
    signals = _Signals()
    spinner = None
    code = 0
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        if signals.requested:
            return 0
        spinner = NodeSpinner(factory())
        spinner.start(threads, ended=signals.wake)
        while not signals.wait(_WAIT_STEP_S):
            pass
    except Exception as exc:  # noqa: BLE001 - report a startup failure as one clear line
        print(f'fatal: {exc}', file=sys.stderr)
        code = 1
    finally:
        if spinner is not None:
            spinner.shutdown()
        rclpy.try_shutdown()
        # The shutdown is complete. While the interpreter exits Python restores the default
        # action of the signals it handled, so a late Ctrl-C would still end the process as
        # killed by SIGINT; ignored signals stay ignored.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signals.close()
    return code


def _spin(executor: DriverExecutor, stop: threading.Event, ended: Callable[[], None]) -> None:
    try:
        # No timeout: rclpy makes a timer for every timed wait, and each wake-up walks every
        # entity of the node in Python (~0.3 ms of CPU). The shutdown wakes it (wake() above;
        # an external shutdown through the context's on_shutdown, which rclpy registers).
        while not stop.is_set() and executor.context.ok():
            executor.spin_once()
    except ExternalShutdownException:
        pass
    except Exception as exc:  # noqa: BLE001 - the main thread shuts down cleanly after it
        print(f'executor failed: {exc!r}', file=sys.stderr, flush=True)
    finally:
        # An external shutdown (the context shut down elsewhere) ends the process too.
        stop.set()
        ended()
