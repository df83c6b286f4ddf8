"""Request chains on a :class:`~uav_serial_common.serial_link.SerialLink`.

A chain sends requests one after the other, each the moment the previous one is settled; the
link's reader thread sends the next one itself. Split out of ``serial_link``, which re-exports
:class:`RequestChain` and :data:`Match`.
"""

from __future__ import annotations

import threading
import time
import traceback
from typing import Any, Callable, Optional, Protocol, Tuple, TYPE_CHECKING

from uav_serial_common.serial_errors import LinkError

if TYPE_CHECKING:  # pragma: no cover - annotations only
    from uav_serial_common.serial_link import SerialLink

Match = Callable[[Any], bool]


class RequestChain(Protocol):
    """Requests sent one after the other, each the moment the previous one is settled."""

    def next_request(self) -> Optional[Tuple[bytes, Optional[Match], float]]:
        """Return the next (data, match, timeout), or None to end the chain.

        `match` None: a frame that gets no reply; the chain holds the line for `timeout` (its
        wire time and a guard), then goes on without a result (``on_result`` is not called).
        """

    def on_result(self, frame: Any) -> None:
        """Take the reply of the request before (None: it timed out)."""


class RunningChain:
    """A running :class:`RequestChain`: the reader thread sends each next request itself.

    On a reply the next request goes out first and ``on_result`` runs while it is on the wire,
    so the bus never waits for the handling of a reply; on a timeout (detected by the caller's
    thread) ``on_result(None)`` comes first, so the chain can retry that request at once.
    """

    def __init__(self, link: 'SerialLink', chain: RequestChain, flush: bool) -> None:
        self.link = link
        self.chain = chain
        self.flush = flush
        self.lock = threading.Lock()
        self.event = threading.Event()
        self.match: Match = match_nothing
        self.no_reply = False
        self.deadline = 0.0
        self.timeout = 0.0
        self.sent = 0
        self.done = False
        self.error: Optional[LinkError] = None

    def offer(self, frame: Any) -> bool:
        """Take `frame` if it answers the current request, and send the next (reader thread)."""
        with self.lock:
            if self.done or not self.match(frame):
                return False
            # The reader thread has just taken in everything the port had: no stale reply can
            # be waiting there, and flushing a pty costs a slow ioctl per request.
            self.send_next(flush_port=False)
            self._deliver(frame)
            return True

    def expire(self) -> None:
        """Report the current request as timed out and go on (caller's thread, lock held)."""
        if self.no_reply:
            # A frame without a reply has had its time on the line: nothing timed out.
            self.send_next()
            return
        self.link.stats.timeouts += 1
        self._deliver(None)
        self.send_next()

    def send_next(self, flush_port: bool = True) -> None:
        """Send the chain's next request, or finish (lock held).

        With `flush` set, input is discarded first: the port's (when `flush_port`; a late reply
        may be on its way after a timeout) and the decoder's partial frame.
        """
        try:
            item = self.chain.next_request()
        except Exception:  # noqa: BLE001 - a planner bug ends the chain, not the reader
            self.link._log.error(f'request chain failed:\n{traceback.format_exc()}')
            item = None
        if item is None:
            self.finish()
            return
        data, match, timeout = item
        self.no_reply = match is None
        self.match = match_nothing if match is None else match
        try:
            if self.flush:
                self.link.flush_input(port=flush_port)
            self.link.write(data)
        except LinkError as exc:
            self.error = exc
            self.finish()
            return
        self.sent += 1
        self.timeout = timeout
        self.deadline = time.monotonic() + timeout
        if self.no_reply:
            self.link._hold(self)

    def end_hold(self) -> None:
        """End a hold that is over and send on (reader thread)."""
        with self.lock:
            if self.done or not self.no_reply:
                return
            if time.monotonic() >= self.deadline:
                self.expire()
            else:
                self.link._hold(self)  # a newer hold began meanwhile: watch that one

    def _deliver(self, frame: Any) -> None:
        try:
            self.chain.on_result(frame)
        except Exception:  # noqa: BLE001 - a handler bug must not kill the reader
            self.link._log.error(f'request chain handler failed:\n{traceback.format_exc()}')

    def finish(self) -> None:
        """Wake the caller (lock held)."""
        self.done = True
        self.match = match_nothing
        self.event.set()


def match_nothing(frame: Any) -> bool:
    """Match no frame: the matcher of a request that expects no reply."""
    return False
