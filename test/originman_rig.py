"""The OriginMan board model behind a real pty in this process, for link and core tests.

:class:`VirtualBoard` joins :class:`VirtualOriginManBoardModel` to a
:class:`uav_serial_common.virtual_device.VirtualDeviceRunner` (wire timing at 1 Mbaud, wire
faults) and taps every byte the driver writes, decoded the way the board's parser sees it.
"""

from __future__ import annotations

import threading
from typing import List, Optional, Tuple

from originman_board_ros import protocol as p
from originman_board_ros.simulation import VirtualOriginManBoardModel
from uav_serial_common.virtual_device import VirtualDeviceRunner


class VirtualBoard:
    """A board model on a pty: ``start()``, ``stop()``, ``path``, ``model``, ``runner``."""

    def __init__(self, link_path: Optional[str], baud: int = p.BAUD, seed: int = 1,
                 **model_kwargs) -> None:
        self.runner = VirtualDeviceRunner(link_path, self._on_input, on_tick=self._on_tick,
                                          next_event=self._next_event, baud=baud, seed=seed)
        self.model = VirtualOriginManBoardModel(self.runner.now(), **model_kwargs)
        self._chunks: List[Tuple[str, bytes]] = []  # (direction, bytes), in wire order
        self._tap_lock = threading.Lock()
        self.runner.add_tap(self._tap)

    @property
    def path(self) -> str:
        """Path the driver opens."""
        return self.runner.path

    def start(self) -> 'VirtualBoard':
        """Open the pty and start the device thread."""
        self.runner.start()
        return self

    def stop(self) -> None:
        """Stop the device thread and remove the pty."""
        self.runner.stop()

    def locked(self):
        """Hold the model lock (change the model from a test)."""
        return self.runner.locked()

    def _on_input(self, data: bytes, now: float) -> bytes:
        return self.model.receive(data, now)

    def _on_tick(self, now: float) -> bytes:
        return self.model.step(now)

    def _next_event(self) -> Optional[float]:
        return self.model.next_event_time()

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
