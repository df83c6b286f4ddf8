"""Pseudo-terminal ports with a stable path, for virtual devices and tests.

A `VirtualSerialPort` is the device end of a pty pair. The other end (the slave, which a driver
opens with pyserial) is published at a stable symlink, like a udev name in ``/dev/serial/by-id``.
`unplug()` makes the port vanish the way a USB adapter does (the open file starts failing and the
path disappears); `replug()` brings a new pty back at the same path. `line_baud()` tells the speed
the driver set on its end (termios of the slave, which the device side keeps open), so a virtual
device can behave as a real one does at the wrong speed.
"""

from __future__ import annotations

import array
import errno
import fcntl
import os
import re
import select
import sys
import termios
import threading
import time
import tty
from typing import Optional

BITS_PER_BYTE = 10  # 8N1: start bit, 8 data bits, stop bit
WRITE_STALL_DROP_S = 0.2
PACING_BURST_S = 0.002

# termios speed codes (B9600 ...) to bit/s.
_SPEEDS = {getattr(termios, name): int(name[1:]) for name in dir(termios)
           if re.fullmatch(r'B[0-9]+', name)}
_BOTHER = getattr(termios, 'BOTHER', 0o010000)
# Linux TCGETS2 = _IOR('T', 0x2A, struct termios2): the numeric speeds behind BOTHER (a rate
# without a Bxxx code, which pyserial sets that way). struct termios2 is 4 flags, c_line,
# 19 control characters, then c_ispeed and c_ospeed: 44 bytes, the speeds at int 9 and 10.
_TCGETS2 = 0x802C542A


def wire_time(nbytes: int, baud: int) -> float:
    """Return the seconds that `nbytes` take on a UART at `baud` (8N1); 0 when baud is 0."""
    if baud <= 0:
        return 0.0
    return nbytes * BITS_PER_BYTE / float(baud)


def sleep_until(deadline: float) -> None:
    """Sleep until ``time.monotonic()`` reaches `deadline`, with sub-millisecond accuracy."""
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return
        # The kernel's sleep overshoots by ~50-100 us; spin the last stretch so paced bytes
        # stay close to the wire rate even for short frames.
        if remaining > 0.0005:
            time.sleep(remaining - 0.0003)


class PortUnplugged(OSError):
    """Raised when the virtual port is used while unplugged."""


class VirtualSerialPort:
    """The device side of a pseudo-terminal whose other side is published at `link_path`."""

    def __init__(self, link_path: Optional[str] = None) -> None:
        self._link_path = link_path
        self._lock = threading.Lock()
        self._master: Optional[int] = None
        self._slave: Optional[int] = None
        self._slave_name: Optional[str] = None
        self.plugged = False
        self.dropped_bytes = 0
        self.halted = False
        """Set by `halt()`: writes stop at once (the device is being stopped)."""

    # -- lifecycle ------------------------------------------------------------------------------

    def open(self) -> 'VirtualSerialPort':
        """Create the pty pair and publish its path; returns self."""
        with self._lock:
            self.halted = False
            self._open_locked()
        return self

    def _open_locked(self) -> None:
        master, slave = os.openpty()
        # Raw on both ends: a serial line carries bytes, not a terminal's lines and signals.
        tty.setraw(master, termios.TCSANOW)
        tty.setraw(slave, termios.TCSANOW)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self._slave_name = os.ttyname(slave)
        if self._link_path:
            tmp = f'{self._link_path}.{os.getpid()}.tmp'
            try:
                os.unlink(tmp)
            except FileNotFoundError:
                pass
            try:
                os.symlink(self._slave_name, tmp)
                # rename() replaces atomically: a driver polling the path never sees it missing.
                os.replace(tmp, self._link_path)
            except OSError as exc:
                os.close(master)
                os.close(slave)
                self._master = self._slave = None
                folder = os.path.dirname(os.path.abspath(self._link_path))
                hint = '' if os.path.isdir(folder) else f' (no directory {folder})'
                error = OSError(f'cannot make the link {self._link_path} to the virtual port: '
                                f'{exc.strerror}{hint}')
                error.errno = exc.errno
                raise error from None
        self.plugged = True

    def close(self) -> None:
        """Close the pty and remove the symlink."""
        with self._lock:
            self._close_locked()

    def _close_locked(self) -> None:
        self.plugged = False
        if self._link_path:
            try:
                if os.path.islink(self._link_path) and \
                        os.readlink(self._link_path) == self._slave_name:
                    os.unlink(self._link_path)
            except OSError:
                pass
        for fd in (self._master, self._slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = None

    def halt(self) -> None:
        """Make every write in progress or to come give up (raise `PortUnplugged`).

        For stopping the device: a write to a driver that no longer reads stalls up to
        `WRITE_STALL_DROP_S` per frame, so a device thread with frames to send could outlast
        the stop's join. The descriptors stay open until `close()`, so a thread still using
        them never writes to a reused one.
        """
        self.halted = True

    def unplug(self) -> None:
        """Simulate pulling the cable: the path vanishes and the driver's open port fails."""
        self.close()

    def replug(self) -> None:
        """Simulate plugging the device back in at the same path."""
        with self._lock:
            if self.plugged:
                return
            self._open_locked()

    def __enter__(self) -> 'VirtualSerialPort':
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- properties -----------------------------------------------------------------------------

    @property
    def path(self) -> str:
        """Return the path a driver opens: the symlink if one was asked for, else the pty."""
        if self._link_path:
            return self._link_path
        if self._slave_name is None:
            raise PortUnplugged('port is not open')
        return self._slave_name

    @property
    def device_name(self) -> Optional[str]:
        """Return the /dev/pts/N name of the current pty, None while unplugged."""
        return self._slave_name if self.plugged else None

    def fileno(self) -> int:
        """Return the master file descriptor (for select)."""
        if self._master is None:
            raise PortUnplugged('port is unplugged')
        return self._master

    def line_baud(self) -> Optional[int]:
        """Return the output speed (bit/s) the driver set on its end; None if unknown.

        Termios settings belong to the terminal, not to a descriptor: the slave this port keeps
        open shows what the driver's ``tcsetattr`` (pyserial's ``baudrate``) put there.
        """
        fd = self._slave
        if fd is None:
            return None
        try:
            code = termios.tcgetattr(fd)[5]
        except (termios.error, OSError, ValueError):
            return None
        if code in _SPEEDS:
            return _SPEEDS[code]
        if code == _BOTHER and sys.platform.startswith('linux'):
            speeds = array.array('i', [0] * 11)
            try:
                fcntl.ioctl(fd, _TCGETS2, speeds)
            except OSError:
                return None
            return speeds[10] or None
        return None

    # -- I/O ------------------------------------------------------------------------------------

    def read(self, timeout: float = 0.0, max_bytes: int = 4096) -> bytes:
        """Return the bytes the driver wrote, waiting up to `timeout` s for the first one."""
        master = self._master
        if master is None:
            if timeout > 0:
                time.sleep(timeout)
            return b''
        try:
            ready, _, _ = select.select([master], [], [], timeout)
            if not ready:
                return b''
            return os.read(master, max_bytes)
        except (OSError, ValueError) as exc:
            # EIO: nobody holds the slave open; EBADF/ValueError: unplugged meanwhile; EAGAIN:
            # unplugged and replugged meanwhile, and the new pty (the same descriptor number)
            # has nothing to read yet.
            gone = (errno.EIO, errno.EBADF, errno.EAGAIN)
            if isinstance(exc, OSError) and exc.errno not in gone:
                raise
            return b''

    def write(self, data: bytes, baud: int = 0, start: Optional[float] = None) -> float:
        """Send `data` to the driver, paced at `baud` (8N1) when baud > 0.

        The first byte goes on the wire at `start` (a ``time.monotonic()`` value; default now, and
        never earlier than the previous write ended). Returns when the last byte has arrived.
        """
        if not data:
            return time.monotonic()
        if baud <= 0:
            self._write_all(data)
            return time.monotonic()
        now = time.monotonic()
        start = now if start is None else start
        per_byte = wire_time(1, baud)
        # Each burst is written when its last byte would have arrived, so nothing comes earlier
        # than on a real UART. Bursts of up to PACING_BURST_S keep a short frame in one piece,
        # as a USB adapter delivers it, instead of costing the reader a wake-up per few bytes.
        burst = max(1, int(PACING_BURST_S / per_byte))
        for offset in range(0, len(data), burst):
            chunk = data[offset:offset + burst]
            sleep_until(start + (offset + len(chunk)) * per_byte)
            self._write_all(chunk)
        return start + len(data) * per_byte

    def _write_all(self, data: bytes) -> None:
        view = memoryview(data)
        stalled_since: Optional[float] = None
        while view:
            master = self._master
            if master is None or self.halted:
                raise PortUnplugged('port is unplugged')
            try:
                written = os.write(master, view)
            except BlockingIOError:
                # Nobody drains the other end: a real UART would just lose these bytes, and
                # blocking here would freeze the device model.
                now = time.monotonic()
                stalled_since = stalled_since or now
                if now - stalled_since > WRITE_STALL_DROP_S:
                    self.dropped_bytes += len(view)
                    return
                select.select([], [master], [], 0.01)
                continue
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EBADF):
                    raise PortUnplugged(str(exc)) from exc
                raise
            stalled_since = None
            view = view[written:]
