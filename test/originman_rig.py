"""The OriginMan board model behind a real pty in this process, for link and core tests.

:class:`VirtualBoard` is the virtual board of ``virtual_originman_board``
(:class:`~originman_board_ros.virtual_node.VirtualOriginManBoard`: the model on a
:class:`uav_serial_common.virtual_device.VirtualDeviceRunner`, wire timing at 1 Mbaud, wire
faults) with a fixed seed, wire faults on direct answers only, and a tap on every byte of the
wire, decoded the way the board's parser (or the host's decoder) sees it.
"""

from __future__ import annotations

import threading
from typing import List, Optional, Tuple

from originman_board_ros import protocol as p
from originman_board_ros.virtual_node import VirtualOriginManBoard


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
