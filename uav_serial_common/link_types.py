"""What a serial link's owner sees of it: the decoder it is given and the counters it keeps."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable, Protocol


class Decoder(Protocol):
    """What the link needs of a streaming decoder (``stream_decoder.StreamDecoder`` is one).

    A decoder that can hold back a frame which could still grow also has ``pending`` (bytes
    held) and ``flush()`` (settle them, returning frames as ``feed`` does): with ``idle_flush_s``
    the link calls ``flush()`` once the line has been idle that long. The link looks both up
    with getattr, so a decoder (or an owner's adapter around one) may leave them out.
    """

    def feed(self, data: bytes) -> Iterable[Any]:
        """Consume bytes, return the complete frames found."""

    def reset(self) -> None:
        """Forget any partial frame."""


@dataclass
class LinkStats:
    """Counters of one link, since it was created."""

    bytes_in: int = 0
    bytes_out: int = 0
    frames_in: int = 0
    frames_out: int = 0
    timeouts: int = 0
    retries: int = 0
    reconnects: int = 0
    open_failures: int = 0
