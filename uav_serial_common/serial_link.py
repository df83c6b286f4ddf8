"""A serial link: one reader thread, request/response matching, timeouts, retries, reconnect.

The link knows nothing of a device's protocol. It is given a streaming decoder (``feed(bytes) ->
frames``) and a frame handler. Frames that answer an outstanding request (decided by the
request's own ``match`` predicate) are handed to the waiting caller; every other frame goes to
``on_frame`` straight from the reader thread, so unsolicited frames never wait behind anything.

The port is opened with ``serial.serial_for_url``, so device paths, ``loop://`` and ``spy://``
URLs all work. When the port errors or disappears the reader thread closes it and reopens it with
exponential backoff until `stop()`.
"""

from __future__ import annotations

import logging
import os
import select
import threading
import time
import traceback
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Optional, Tuple

import serial

try:
    from serial.serialposix import Serial as _PosixSerial
except ImportError:  # pragma: no cover - not a POSIX system
    _PosixSerial = None

from uav_serial_common.link_types import Decoder, LinkStats
from uav_serial_common.serial_errors import (
    describe_open_error, LinkDown, LinkError, LinkTimeout, PORT_ERRORS,
)

__all__ = [
    'Decoder', 'describe_open_error', 'LinkDown', 'LinkError', 'LinkStats', 'LinkTimeout',
    'Match', 'PORT_ERRORS', 'SerialLink',
]

Match = Callable[[Any], bool]
"""Whether a frame is the reply a request waits for."""


@dataclass
class _Waiter:
    match: Match
    event: threading.Event = field(default_factory=threading.Event)
    frame: Any = None

    def offer(self, frame: Any) -> bool:
        """Take `frame` if it is the awaited reply (reader thread)."""
        if self.event.is_set() or not self.match(frame):
            return False
        self.frame = frame
        self.event.set()
        return True


class SerialLink:
    """One serial port owned by one reader thread."""

    def __init__(
        self,
        url: str,
        baud: int,
        decoder: Decoder,
        on_frame: Optional[Callable[[Any], None]] = None,
        on_connection: Optional[Callable[[bool, str], None]] = None,
        on_tx: Optional[Callable[[bytes], None]] = None,
        on_rx: Optional[Callable[[bytes], None]] = None,
        logger: Optional[Any] = None,
        backoff_initial_s: float = 0.05,
        backoff_max_s: float = 1.0,
        read_timeout_s: float = 0.05,
        idle_flush_s: Optional[float] = None,
        on_open: Optional[Callable[[serial.SerialBase], None]] = None,
    ) -> None:
        self.url = url
        self.baud = baud
        self.stats = LinkStats()
        self._opened_before = False
        self.last_error = ''
        # The reader thread's last unexpected failure (a bug or a port error nobody foresaw):
        # it is logged, the port is reopened, and owners show it in their diagnostics.
        self.reader_error = ''
        self.reader_errors = 0
        self.last_rx_time: Optional[float] = None
        """When the reader thread received the last bytes (monotonic clock)."""
        # Bytes read and not yet handed on (the reader decodes and dispatches them).
        self._rx_busy = False
        self._decoder = decoder
        self._on_frame = on_frame
        self._on_connection = on_connection
        self._on_tx = on_tx
        self._on_rx = on_rx
        # Called on the reader thread with the port each time it is (re)opened, before anyone
        # may use it: port settings that the owner derives from the device (a USB adapter's
        # latency timer). A failure is logged and the port used as it is.
        self._on_open = on_open
        self._log = logger or logging.getLogger('serial_link')
        self._backoff_initial = backoff_initial_s
        self._backoff_max = backoff_max_s
        self._read_timeout = read_timeout_s
        # Decoders that hold back a frame which could still grow (DPS-S 0x35) settle it through
        # their flush() once the line has been idle this long; None = never.
        self._idle_flush_s = idle_flush_s
        self._serial: Optional[serial.SerialBase] = None
        self._fast_fd: Optional[int] = None
        self._write_lock = threading.Lock()
        self._rx_lock = threading.Lock()
        self._rx_handed_on = threading.Condition()  # the reader handed on what it read
        # _Waiter objects. Copy-on-write under the lock: the reader thread reads
        # it without the lock, so a waiter may close the port (a failed write) while it is offered.
        self._waiters: Tuple[Any, ...] = ()
        self._waiters_lock = threading.Lock()
        self._stop = threading.Event()
        self._port_open = threading.Event()
        self._thread: Optional[threading.Thread] = None

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        """Start the reader thread; it opens the port and keeps it open."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._run, name=f'serial-reader {self.url}', daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop the reader thread and close the port."""
        self._stop.set()
        port = self._serial
        if port is not None:
            try:
                # Wake a blocking read at once instead of waiting for its timeout.
                port.cancel_read()
            except Exception:  # noqa: BLE001 - not every URL handler can cancel
                pass
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        self._close('stopped')

    @property
    def port_open(self) -> bool:
        """Return True while the port is open."""
        return self._port_open.is_set()

    def on_reader_thread(self) -> bool:
        """Whether the caller is the link's reader thread (it has taken in what the port had)."""
        return threading.current_thread() is self._thread

    def wait_port_open(self, timeout: float) -> bool:
        """Wait until the port is open; returns whether it is."""
        return self._port_open.wait(timeout)

    def unread_input(self) -> bool:
        """Whether bytes have come in that the reader has not handed on yet.

        Bytes wait in the port, are being decoded and dispatched, or are held by the decoder:
        frames may still come of them. A caller waiting for the line to go quiet asks this, so
        that a reader late on a loaded machine is not taken for a quiet line.
        """
        with self._rx_lock:
            if self._rx_busy or getattr(self._decoder, 'pending', 0):
                return True
            port = self._serial
            try:
                return port is not None and port.in_waiting > 0
            except PORT_ERRORS:
                return False

    @property
    def reader_alive(self) -> bool:
        """Whether the reader thread runs (False before start() and after stop())."""
        return self._thread is not None and self._thread.is_alive()

    # -- I/O ------------------------------------------------------------------------------------

    def write(self, data: bytes) -> None:
        """Send bytes now; raises LinkDown when the port is not open."""
        with self._write_lock:
            port = self._serial
            if port is None or not self._port_open.is_set():
                raise LinkDown(f'{self.url} is not open: {self.last_error or "not connected"}')
            try:
                self._write_port(port, data)
            except PORT_ERRORS as exc:
                self._fail(f'write failed: {exc}', port)
                raise LinkDown(f'{self.url}: write failed: {exc}') from exc
            self.stats.bytes_out += len(data)
            self.stats.frames_out += 1
        if self._on_tx is not None:
            self._on_tx(data)

    def request(
        self,
        data: bytes,
        match: Match,
        timeout: float,
        retries: int = 0,
        flush: bool = False,
    ) -> Any:
        """Send `data` and return the first frame that `match` accepts.

        The frame is awaited for `timeout` seconds after each send; the request is sent again up
        to `retries` more times. Raises LinkTimeout when nothing matched, LinkDown when the port
        is not open. `flush` discards input (and any partial frame) first, for half-duplex buses
        where a late reply to an earlier request must not be taken for this one.
        """
        waiter = _Waiter(match)
        self._add_waiter(waiter)
        sent = False
        try:
            for attempt in range(retries + 1):
                if attempt:
                    self.stats.retries += 1
                if flush:
                    self.flush_input()
                self.write(data)
                sent = True
                if waiter.event.wait(timeout) and waiter.frame is not None:
                    return waiter.frame
                if self._reader_behind(waiter, timeout):
                    return waiter.frame
                if not self._port_open.is_set():
                    raise LinkDown(f'{self.url} closed while waiting for a reply')
            self.stats.timeouts += 1
            raise LinkTimeout(f'no reply within {timeout * 1000:.0f} ms '
                              f'after {retries + 1} attempt(s)')
        except LinkError as exc:
            exc.sent = sent
            raise
        finally:
            self._remove_waiter(waiter)

    def _reader_behind(self, waiter: '_Waiter', timeout: float) -> bool:
        """At a reply deadline, wait (up to `timeout` more) while the reader is behind.

        Bytes that came in and were not handed on yet may be the reply: on a loaded host the
        reader thread can be late by more than a short deadline, and calling that a timeout
        (and sending again on a half-duplex line) would report a silence nobody saw. Returns
        whether the reply came meanwhile.
        """
        self.wait_handed_on(timeout, waiter.event.is_set)
        return waiter.event.is_set() and waiter.frame is not None

    def wait_handed_on(self, timeout: float, done: Callable[[], bool] = lambda: False) -> None:
        """Wait up to `timeout` s while the reader holds unread bytes (and `done()` is false).

        Woken by the reader each time it has handed on what it read (no poll): a caller whose
        deadline passed while bytes were still coming in looks again as soon as they are taken.
        """
        end = time.monotonic() + timeout
        with self._rx_handed_on:
            while not done() and self.unread_input():
                remaining = end - time.monotonic()
                if remaining <= 0:
                    return
                self._rx_handed_on.wait(remaining)

    def flush_input(self, port: bool = True) -> None:
        """Discard unread input (unless `port` is False) and any partial frame.

        Raises LinkDown when the port fails the flush (a vanished device answers tcflush with
        termios.error): the port is closed and reopened as after a failed read.
        """
        failure = None
        with self._rx_lock:
            serial_port = self._serial if port else None
            if serial_port is not None:
                try:
                    serial_port.reset_input_buffer()
                except PORT_ERRORS as exc:
                    failure = exc
            self._decoder.reset()
        if failure is not None:
            # Outside the lock: closing notifies the owner, which must not run under it.
            self._fail(f'flush failed: {failure}', serial_port)
            raise LinkDown(f'{self.url}: flush failed: {failure}') from failure

    # -- reader thread --------------------------------------------------------------------------

    def _run(self) -> None:
        backoff = self._backoff_initial
        try:
            while not self._stop.is_set():
                try:
                    backoff = self._run_once(backoff)
                except Exception as exc:  # noqa: BLE001 - the reader must never die
                    # Not a port error (those are handled below): a bug in a handler or an
                    # error nobody foresaw. Say so once per kind, reopen the port, go on.
                    self.reader_errors += 1
                    text = f'{type(exc).__name__}: {exc}'
                    if text != self.reader_error:
                        self._log.error(f'{self.url}: reader failed ({text}); reopening the '
                                        f'port:\n{traceback.format_exc()}')
                    self.reader_error = text
                    self._fail(f'reader failed: {text}')
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, self._backoff_max)
        finally:
            if not self._stop.is_set():  # pragma: no cover - only a BaseException gets here
                self._log.error(f'{self.url}: reader thread stopped unexpectedly')

    def _run_once(self, backoff: float) -> float:
        """Open the port if needed, read once and hand the bytes on; return the next backoff."""
        if self._serial is None:
            if self._open():
                return self._backoff_initial
            self._stop.wait(backoff)
            return min(backoff * 2, self._backoff_max)
        port = self._serial
        try:
            data = self._read_port(port)
        except PORT_ERRORS as exc:
            if not self._stop.is_set():
                self._fail(f'read failed: {exc}', port)
            return backoff
        if data:
            self._receive(data)
        elif self._idle_flush_s is not None:
            self._flush_idle()
        return backoff

    def _read_port(self, port: serial.SerialBase) -> bytes:
        fd = self._fast_fd
        if fd is None:
            data = port.read(1)
            if data and port.in_waiting:
                data += port.read(port.in_waiting)
            self._rx_busy = bool(data)
            return data
        # The same as pyserial's read, minus a second select and an ioctl per wake-up: on a
        # half-duplex bus every reply pays for them, so they show in the bus rate.
        abort = port.pipe_abort_read_r
        ready, _, _ = select.select([fd, abort], [], [], self._select_timeout())
        if not ready:
            return b''
        if abort in ready:
            os.read(abort, 1000)
            return b''
        # Under the lock that flush_input takes: another thread may have flushed the input
        # between select and here (a request flushes stale bytes while a late reply comes in),
        # and only a port that still says "readable" and has nothing to give is gone.
        with self._rx_lock:
            try:
                data = os.read(fd, 4096)
                if not data:
                    ready, _, _ = select.select([fd], [], [], 0)
                    if not ready:
                        return b''
                    data = os.read(fd, 4096)
            except BlockingIOError:
                return b''
            # Stamped in the read's own lock: unread_input() sees the bytes in the port or here.
            self._rx_busy = bool(data)
            if data:
                self.last_rx_time = time.monotonic()
        if not data:
            raise serial.SerialException('device reports readiness to read but returned no data '
                                         '(device disconnected?)')
        return data

    def _select_timeout(self) -> float:
        # A wake-up costs tens of microseconds of CPU (more on a VM): a quiet line waits the
        # whole read timeout, and only a decoder holding a partial frame wakes the reader when
        # the line has been idle for idle_flush_s, to settle it.
        timeout = self._read_timeout
        if self._idle_flush_s is not None and getattr(self._decoder, 'pending', 0):
            last = self.last_rx_time
            due = self._idle_flush_s if last is None else \
                last + self._idle_flush_s - time.monotonic()
            timeout = min(timeout, max(due, 0.0005))
        return timeout

    def _write_port(self, port: serial.SerialBase, data: bytes) -> None:
        fd = self._fast_fd
        if fd is not None:
            try:
                written = os.write(fd, data)
            except BlockingIOError:
                written = 0
            if written == len(data):
                return
            data = data[written:]
        port.write(data)

    def _flush_idle(self) -> None:
        flush = getattr(self._decoder, 'flush', None)
        if flush is None or not getattr(self._decoder, 'pending', 0):
            return
        if self.last_rx_time is not None and \
                time.monotonic() - self.last_rx_time < self._idle_flush_s:
            return
        with self._rx_lock:
            frames = flush()
        self._dispatch(frames)
        self._handed_on()

    def _handed_on(self) -> None:
        with self._rx_handed_on:
            self._rx_handed_on.notify_all()

    def _receive(self, data: bytes) -> None:
        if self._fast_fd is None:
            self.last_rx_time = time.monotonic()
        try:
            self.stats.bytes_in += len(data)
            if self._on_rx is not None:
                self._on_rx(data)
            with self._rx_lock:
                frames = self._decoder.feed(data)
            self._dispatch(frames)
        finally:
            self._rx_busy = False
            self._handed_on()

    def _dispatch(self, frames: Iterable[Any]) -> None:
        for frame in frames:
            self.stats.frames_in += 1
            if not self._deliver_to_waiter(frame) and self._on_frame is not None:
                try:
                    self._on_frame(frame)
                except Exception:  # noqa: BLE001 - a handler bug must not kill the reader
                    self._log.error(f'frame handler failed on {frame!r}:\n'
                                    f'{traceback.format_exc()}')

    def _deliver_to_waiter(self, frame: Any) -> bool:
        for waiter in self._waiters:
            if waiter.offer(frame):
                return True
        return False

    def _add_waiter(self, waiter: Any) -> None:
        with self._waiters_lock:
            self._waiters = self._waiters + (waiter,)

    def _remove_waiter(self, waiter: Any) -> None:
        with self._waiters_lock:
            self._waiters = tuple(w for w in self._waiters if w is not waiter)

    def _open(self) -> bool:
        port = None
        try:
            port = serial.serial_for_url(
                self.url, baudrate=self.baud, timeout=self._read_timeout, write_timeout=1.0,
                do_not_open=True)
            if hasattr(port, 'exclusive'):
                try:
                    port.exclusive = True
                except (ValueError, serial.SerialException):
                    pass
            port.open()
            port.reset_input_buffer()
        except Exception as exc:  # noqa: BLE001 - any failure to open is a failure to open
            # Not only SerialException: a device that vanishes between open and flush answers
            # tcflush with termios.error, which is no OSError.
            if port is not None:
                try:
                    port.close()
                except Exception:  # noqa: BLE001 - it is being given up anyway
                    pass
            self.stats.open_failures += 1
            message = describe_open_error(self.url, exc)
            if message != self.last_error:
                self._log.error(message)
            self.last_error = message
            return False
        if self._on_open is not None:
            try:
                self._on_open(port)
            except Exception:  # noqa: BLE001 - a settings problem must not cost the port
                self._log.error(f'{self.url}: on-open handler failed:\n{traceback.format_exc()}')
        with self._rx_lock:
            self._decoder.reset()
        self._serial = port
        # A plain POSIX port (not loop://, spy:// and the like, which add their own behaviour to
        # read and write) is read and written through its file descriptor directly.
        plain = _PosixSerial is not None and type(port).read is _PosixSerial.read and \
            type(port).write is _PosixSerial.write and isinstance(getattr(port, 'fd', None), int)
        self._fast_fd = port.fd if plain else None
        # Any open after the first is a reconnect, whether or not an attempt failed between
        # (a cable plugged back before the reader's first try is one too).
        if self._opened_before or self.stats.open_failures:
            self.stats.reconnects += 1
        self._opened_before = True
        self.last_error = ''
        self._port_open.set()
        self._log.info(f'opened {self.url} at {self.baud} baud')
        self._notify(True, 'port open')
        return True

    def _fail(self, reason: str, port: Optional[serial.SerialBase] = None) -> None:
        """Close the port after a failure of `port` (default: the open one) and reconnect."""
        if port is not None and port is not self._serial:
            return  # that port is closed already; the first failure's reason stands
        if self._port_open.is_set():
            self._log.error(f'{self.url}: {reason}; reconnecting')
            self.last_error = reason
        elif not self.last_error:
            self.last_error = reason
        self._close(reason)

    def _close(self, reason: str) -> None:
        was_open = self._port_open.is_set()
        self._port_open.clear()
        port, self._serial = self._serial, None
        self._fast_fd = None
        if port is not None:
            try:
                port.close()
            except Exception:  # noqa: BLE001 - closing a vanished device may fail any way
                pass
        # Wake every waiter: their request fails at once rather than at its timeout.
        for waiter in self._waiters:
            waiter.event.set()
        self._handed_on()
        if was_open:
            self._notify(False, reason)

    def _notify(self, up: bool, reason: str) -> None:
        if self._on_connection is not None:
            try:
                self._on_connection(up, reason)
            except Exception:  # noqa: BLE001 - a handler bug must not kill the reader
                self._log.error(f'connection handler failed ({reason})')
