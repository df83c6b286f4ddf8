"""What goes wrong on a serial link: the port's exceptions, the link's errors, an open failure.

Split out of :mod:`uav_serial_common.serial_link`, which re-exports every name here.
"""

from __future__ import annotations

import errno
import os
import termios
from typing import Optional

import serial

# What a port can raise besides SerialException and OSError: termios.error (tcflush/tcgetattr on a
# vanished device; not an OSError), and TypeError/AttributeError/ValueError when its descriptor
# was closed under a concurrent close. None of them may escape the link or stop its reader.
PORT_ERRORS = (serial.SerialException, OSError, termios.error, TypeError, AttributeError,
               ValueError)


class LinkError(Exception):
    """Base class of link errors.

    `sent` says whether the request's frame had left when the error ended it (set by
    `SerialLink.request`): then the device may have acted on it, and only asking it tells.
    """

    sent: bool = False


class LinkDown(LinkError):
    """The port is not open (missing, unplugged or failing)."""


class LinkTimeout(LinkError):
    """No matching reply arrived in time, after every retry."""


def _errno_of(exc: BaseException) -> Optional[int]:
    """Return the errno behind `exc`: its own, or that of the error it was raised from."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        number = getattr(exc, 'errno', None)
        if isinstance(number, int):
            return number
        if isinstance(exc, termios.error) and exc.args and isinstance(exc.args[0], int):
            return exc.args[0]
        exc = exc.__cause__ or exc.__context__
    return None


def describe_open_error(url: str, exc: BaseException) -> str:
    """Turn an open failure into a message that tells the user what to do (by its errno)."""
    number = _errno_of(exc)
    if number in (errno.EACCES, errno.EPERM):
        return (f'cannot open {url}: permission denied. Add your user to the dialout group '
                f'(sudo usermod -aG dialout $USER, then log in again) or fix the udev rule.')
    if number == errno.EISDIR or (number is None and os.path.isdir(url)):
        return (f'cannot open {url}: {url} is a directory, not a serial device. Check the port '
                f'parameter (e.g. /dev/ttyUSB0 or a /dev/serial/by-id/ name); retrying.')
    if number == errno.ENOTTY:
        return (f'cannot open {url}: it is not a serial device (a regular file or another '
                f'kind of device?). Check the port parameter; retrying.')
    if number == errno.ENOTDIR:
        return (f'cannot open {url}: a part of the path is not a directory. Check the port '
                f'parameter; retrying.')
    if number in (errno.ENOENT, errno.ENODEV, errno.ENXIO):
        return (f'cannot open {url}: no such device. Is it plugged in? Check `ls -l {url}` '
                f'and the port parameter; retrying.')
    if number in (errno.EBUSY, errno.EAGAIN):
        return f'cannot open {url}: the port is in use by another program; retrying.'
    return f'cannot open {url}: {exc}; retrying.'
