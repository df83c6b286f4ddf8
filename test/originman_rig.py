"""The OriginMan board model behind a real pty, for link and core tests.

:class:`VirtualBoard` is the virtual board of ``virtual_originman_board``
(:class:`~originman_board_ros.virtual_node.VirtualOriginManBoard`: the model on a
:class:`uav_serial_common.virtual_device.VirtualDeviceRunner`, wire timing at 1 Mbaud, wire
faults) with a fixed seed, wire faults on direct answers only, and a tap on every byte of the
wire, decoded the way the board's parser (or the host's decoder) sees it.

:class:`BoardProcess` runs one in a process of its own, as a real board has a CPU of its own:
in the test's process its thread waits on the GIL behind the driver's threads, and a starved
host then hands it the driver's bytes late, all at once. The model stamps them with that late
time and queues them behind each other: a backlog the driver never sent, which no real board
has. The tests that judge the board's own timing (how long a command waited in its queue) use
it. It is also this module's entry point: ``python originman_rig.py ADDRESS KWARGS_JSON``.
"""

from __future__ import annotations

import json
from multiprocessing.connection import Client, Listener
import os
import subprocess
import sys
import threading
import time
from typing import Any, List, Optional, Tuple

from originman_board_ros import protocol as p
from originman_board_ros.virtual_node import VirtualOriginManBoard
from uav_serial_common.process import device_process, wait_scale


class VirtualBoard(VirtualOriginManBoard):
    """A board model on a pty: ``start()``, ``stop()``, ``path``, ``model``, ``runner``."""

    def __init__(self, link_path: Optional[str], baud: int = p.BAUD, seed: int = 1,
                 **model_kwargs) -> None:
        super().__init__(link_path, baud=baud, seed=seed, fault_unsolicited=False,
                         **model_kwargs)
        self._chunks: List[Tuple[str, bytes]] = []  # (direction, bytes), in wire order
        self._tap_lock = threading.Lock()
        self.runner.add_tap(self._tap)

    def _tap(self, direction: str, data: bytes, t: float) -> None:
        with self._tap_lock:
            self._chunks.append((direction, bytes(data)))

    def mark(self) -> int:
        """Return a position in the wire log; the views below decode what came after it."""
        with self._tap_lock:
            return len(self._chunks)

    def written(self, mark: int = 0) -> bytes:
        """Every byte the driver wrote since ``mark``."""
        with self._tap_lock:
            return b''.join(d for direction, d in self._chunks[mark:] if direction == 'rx')

    def commands(self, mark: int = 0) -> list:
        """Return the commands sent since ``mark``, as the board's handlers read them."""
        return [p.decode_host_command(f) for f in p.BoardParser().feed(self.written(mark))]

    def wire_log(self, mark: int = 0) -> list:
        """('host', command) and ('board', message) since ``mark``, in wire order."""
        with self._tap_lock:
            chunks = list(self._chunks[mark:])
        parser, decoder, out = p.BoardParser(), p.StreamDecoder(), []
        for direction, data in chunks:
            if direction == 'rx':
                out += [('host', p.decode_host_command(f)) for f in parser.feed(data)]
            else:
                out += [('board', p.decode_board_frame(f)) for f in decoder.feed(data)]
        return out


AUTHKEY = b'originman-rig'
SWITCH_INTERVAL_S = 0.0005
"""As ``virtual_originman_board``: reports are paced on the device thread."""


class BoardProcess:
    """A :class:`VirtualBoard` in a child process, driven by calls (``call(name, *args)``).

    ``path`` is the pty the driver opens; the calls are :class:`_BoardServer`'s methods.
    """

    def __init__(self, link_path: str, timeout_s: float = 30.0, **model_kwargs: Any) -> None:
        self.path = link_path
        self._address = link_path + '.sock'
        self._log_path = link_path + '.log'
        self._log = open(self._log_path, 'wb')
        self._proc = subprocess.Popen(
            [sys.executable, os.path.abspath(__file__), self._address,
             json.dumps(model_kwargs)], stdout=self._log, stderr=subprocess.STDOUT,
            preexec_fn=device_process)
        self._lock = threading.Lock()
        self._conn = None
        deadline = time.monotonic() + timeout_s * wait_scale()
        try:
            while True:
                try:  # the socket's file exists from its bind, a moment before it listens
                    self._conn = Client(self._address, authkey=AUTHKEY)
                    break
                except (FileNotFoundError, ConnectionRefusedError):
                    if self._proc.poll() is not None or time.monotonic() > deadline:
                        raise RuntimeError(
                            f'the board process did not start:\n{self.output()}') from None
                    time.sleep(0.01)
        except BaseException:
            self.stop()  # never leave the child waiting for a caller that is gone
            raise

    def call(self, name: str, *args: Any) -> Any:
        """Run the board process's ``name(*args)`` and return its result."""
        with self._lock:
            self._conn.send((name, args))
            ok, value = self._conn.recv()
        if not ok:
            raise RuntimeError(f'board process: {name}{args} failed: {value}')
        return value

    def output(self) -> str:
        """Return what the board process wrote (its log, tracebacks)."""
        with open(self._log_path, 'rb') as f:
            return f.read().decode(errors='replace')

    def stop(self) -> None:
        """Stop the board and its process."""
        conn = self._conn
        if conn is not None:
            try:
                self.call('stop')
            except (OSError, EOFError, RuntimeError):
                pass
            conn.close()
            self._conn = None
        else:
            self._proc.kill()  # not started, or waiting for a caller that never came
        try:
            self._proc.wait(10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(5)
        self._log.close()


class _BoardServer:
    """What a test can ask of the board in the child process."""

    def __init__(self, board: VirtualBoard) -> None:
        self.board = board
        self.model = board.model

    def queue_log(self) -> list:
        """Return (arrival, handled, command) of each command handled, oldest first."""
        with self.board.locked():
            return list(self.model.queue_log)

    def motor_set_points(self) -> list:
        """Return the motors' set-points (wire ids 0..3)."""
        with self.board.locked():
            return list(self.model.motor_set_points)

    def bus_targets(self, ids: list) -> dict:
        """Return the target of each of these bus servos."""
        with self.board.locked():
            return {i: self.model.bus_servo(i).target for i in ids}

    def set_answer_reads(self, answer: bool) -> None:
        """Set whether reads are answered (False: handled, no reply; reports go on)."""
        with self.board.locked():
            self.model.answer_reads = answer

    def commands(self, mark: int = 0) -> list:
        """Return the commands the driver sent since ``mark``."""
        return self.board.commands(mark)

    def unplug(self) -> None:
        """Pull the cable."""
        self.board.runner.unplug()

    def replug(self) -> None:
        """Plug the cable back in."""
        self.board.runner.replug()


def _serve(address: str, model_kwargs: dict) -> None:
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    board = VirtualBoard(address[:-len('.sock')], **model_kwargs)
    board.start()
    server = _BoardServer(board)
    listener = Listener(address, authkey=AUTHKEY)
    try:
        conn = listener.accept()
        while True:
            try:
                name, args = conn.recv()
            except EOFError:
                return
            if name == 'stop':
                conn.send((True, None))
                return
            try:
                conn.send((True, getattr(server, name)(*args)))
            except Exception as exc:  # noqa: BLE001 - the test gets the error, the board lives
                conn.send((False, f'{type(exc).__name__}: {exc}'))
    finally:
        listener.close()
        board.stop()


if __name__ == '__main__':
    _serve(sys.argv[1], json.loads(sys.argv[2]))
