"""The radio modem's serial port: SerialLink with the handset stream decoder, read only (H11).

SerialLink's reader thread reads the port, decodes at once and hands each read's results to
``on_received`` as one ``Received`` batch, so frames that arrived together can be delivered
together and nothing waits for a timer (H7). A partial frame is settled as malformed after 0.1 s
of silence (H3): SerialLink calls the decoder's ``flush()`` once the line has been idle that long,
and ``poll()`` does the same for an owner that keeps its own clock; ``on_held(deadline)`` tells
that owner, after each read that leaves a partial frame held, when to poll (its timer sleeps
until then, whatever reads the port). The port vanishing and
coming back is SerialLink's business. Nothing is ever written. No ROS here.
"""

from __future__ import annotations

from dataclasses import dataclass
import threading
import time
from typing import Any, Callable, Optional

from handset_link_ros import protocol as p
from uav_serial_common.serial_link import SerialLink

READ_TIMEOUT_S = 0.5
"""The reader's longest sleep on a quiet line. A held partial frame wakes it once the line has
been idle for the idle timeout (SerialLink's idle flush), so the idle rule still settles it
then; a shorter timeout only costs CPU (one wake-up each)."""


@dataclass(frozen=True, slots=True)
class Received:
    """The results settled by one read (or by the line going quiet), and when that was."""

    results: tuple[p.Decoded, ...]
    time: float


class _DecoderAdapter:
    """What SerialLink calls: ``feed`` and ``flush`` return one ``Received`` batch, or none."""

    def __init__(self, link: 'ModemLink') -> None:
        self._link = link

    @property
    def pending(self) -> int:
        return self._link.decoder.pending

    def feed(self, data: bytes) -> list:
        return self._link._decode(data)

    def flush(self) -> list:
        # SerialLink has measured the silence itself (idle_flush_s).
        return self._link._settle(None)

    def reset(self) -> None:
        self._link._reset()


class ModemLink:
    """One radio modem on one serial port, read only."""

    def __init__(self, url: str, baud: int, on_received: Callable[[Received], None],
                 on_connection: Optional[Callable[[bool, str], None]] = None,
                 clock: Callable[[], float] = time.monotonic,
                 logger: Optional[Any] = None,
                 idle_timeout_s: float = p.IDLE_TIMEOUT_S,
                 on_held: Optional[Callable[[float], None]] = None) -> None:
        self.decoder = p.StreamDecoder(idle_timeout_s)
        self._on_received = on_received
        self._on_held = on_held
        self._clock = clock
        self._lock = threading.Lock()  # the decoder: reader thread, poll() and tests
        self.serial = SerialLink(
            url, baud, _DecoderAdapter(self), on_frame=on_received,
            on_connection=on_connection, logger=logger, read_timeout_s=READ_TIMEOUT_S,
            idle_flush_s=idle_timeout_s)

    # -- lifecycle and state --------------------------------------------------------------------

    def start(self) -> None:
        """Open the port in the reader thread (with reconnects)."""
        self.serial.start()

    def stop(self) -> None:
        """Stop the reader thread and close the port."""
        self.serial.stop()

    @property
    def port_open(self) -> bool:
        """Whether the serial port is open."""
        return self.serial.port_open

    # -- bytes in -------------------------------------------------------------------------------

    def feed(self, data: bytes) -> None:
        """Decode bytes read from the modem and deliver the results (the reader's path; tests)."""
        for batch in self._decode(data):
            self._on_received(batch)

    def poll(self) -> None:
        """Settle a partial frame once the line has been quiet for the idle timeout (H3)."""
        for batch in self._settle(self._clock()):
            self._on_received(batch)

    def idle_deadline(self) -> Optional[float]:
        """When ``poll()`` would settle held bytes (clock time), None if nothing is held."""
        with self._lock:
            return self.decoder.idle_deadline()

    def _decode(self, data: bytes) -> list:
        with self._lock:
            now = self._clock()
            results = self.decoder.feed(data, now)
            held = self.decoder.idle_deadline()
        if held is not None and self._on_held is not None:
            self._on_held(held)  # before the results are handed on: they may take a while
        return [Received(tuple(results), now)] if results else []

    def _settle(self, now: Optional[float]) -> list:
        with self._lock:
            results = self.decoder.flush(now)
            when = self._clock() if now is None else now
        return [Received(tuple(results), when)] if results else []

    def _reset(self) -> None:
        with self._lock:
            self.decoder.reset()
