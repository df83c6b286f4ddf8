"""The USB serial adapter's latency timer: find it, lower it where allowed, say what was done.

FTDI adapters hold received bytes for up to their latency timer (16 ms by default) before
passing them to the host. On a half-duplex bus every reply pays that, so a bus that could carry
hundreds of transactions a second carries a few dozen, and a reply wait tuned for a 1 ms adapter
times out on a 16 ms one. Users of every bus-servo SDK meet this and fix it by hand; a driver can
do it itself on open:

1. resolve the port (a udev symlink such as ``/dev/servobus``) to its tty; only ``ttyUSB*``
   adapters have the timer, at ``/sys/bus/usb-serial/devices/<tty>/latency_timer``;
2. read it; if it is above 1 ms and the user allows it, ask for low-latency mode (pyserial's
   ``set_low_latency_mode``, which the FTDI kernel driver turns into a 1 ms timer), and failing
   that write ``1`` to the sysfs file;
3. read it again, and derive the reply margin from what the port really does: two timer periods
   plus 2 ms (ROBOTIS DynamixelSDK's rule), a few ms for a pty, an on-board UART or a 1 ms adapter.

The result is a `LatencyReport` that the driver logs once and shows in its diagnostics, with the
udev rule that makes the setting permanent when the driver could not change it. No ROS here;
the sysfs root is a parameter so the decisions are tested on a fake tree.
"""

from __future__ import annotations

from dataclasses import dataclass
import os
from pathlib import Path
from typing import Callable, Optional

DEFAULT_FTDI_LATENCY_MS = 16
"""What an FTDI adapter's timer is set to by its driver unless told otherwise."""
CDC_ACM_LATENCY_MS = 1
"""USB CDC-ACM devices (ttyACM*) pass data on every 1 ms USB frame: no timer to lower."""
BASE_MARGIN_S = 0.002
"""The margin of a port with no latency timer (the host's own scheduling)."""
WANTED_MS = 1


@dataclass(frozen=True)
class LatencyReport:
    """What the latency timer of one port was, what the driver did, what it is now."""

    port: str
    device: str
    tty: Optional[str]
    kind: str
    """'pty', 'uart', 'url', 'ftdi', 'usb' (a ttyUSB without a timer file), 'cdc-acm', 'gone'."""
    before_ms: Optional[int]
    after_ms: Optional[int]
    action: str
    changed: bool = False

    @property
    def effective_ms(self) -> float:
        """The delay the adapter adds to a reply [ms] (assumed when it cannot be read)."""
        if self.kind == 'ftdi':
            return float(self.after_ms if self.after_ms is not None else DEFAULT_FTDI_LATENCY_MS)
        if self.kind == 'usb':
            return float(DEFAULT_FTDI_LATENCY_MS)
        if self.kind == 'cdc-acm':
            return float(CDC_ACM_LATENCY_MS)
        return 0.0

    @property
    def ok(self) -> bool:
        """Whether the port adds at most 1 ms to a reply."""
        return self.effective_ms <= WANTED_MS

    def reply_margin_s(self) -> float:
        """Return the wait for a reply beyond its wire time: two timer periods plus 2 ms."""
        return 2.0 * self.effective_ms / 1000.0 + BASE_MARGIN_S

    def udev_rule(self) -> str:
        """Return the udev rule that sets the timer to 1 ms at every plug-in ('' when moot)."""
        if self.kind != 'ftdi' or self.ok:
            return ''
        return ('ACTION=="add", SUBSYSTEM=="usb-serial", DRIVER=="ftdi_sio", '
                'ATTR{latency_timer}="1"  (e.g. in /etc/udev/rules.d/99-ftdi-latency.rules)')

    def summary(self) -> str:
        """One line for the log and the diagnostics."""
        where = self.device if self.device == self.port else f'{self.port} -> {self.device}'
        text = (f'{where}: {self.action}; reply margin {self.reply_margin_s() * 1000:.0f} ms')
        rule = self.udev_rule()
        return f'{text}. To make 1 ms permanent add the udev rule: {rule}' if rule else text


def inspect_latency_timer(port: str, allow_change: bool = True,
                          request_low_latency: Optional[Callable[[], None]] = None,
                          sysfs_root: str = '/sys', dev_root: str = '/dev') -> LatencyReport:
    """Read (and, when allowed, lower) the latency timer of `port`; see the module docstring.

    `request_low_latency` asks the open port for low-latency mode (``port.set_low_latency_mode``
    of pyserial); it may raise (not every driver supports it, or the user may not).
    """
    if '://' in port:
        return LatencyReport(port, port, None, 'url', None, None, 'a pyserial URL: no adapter')
    try:
        device = os.path.realpath(port)
    except OSError as exc:
        # Unplugged between the open and here (a udev link that went away mid-resolution):
        # the port fails its next read and the driver reopens it and asks again.
        return LatencyReport(port, port, None, 'gone', None, None,
                             f'the port vanished while its latency timer was looked up '
                             f'({_reason(exc)})')
    tty = os.path.basename(device)
    if tty.startswith('ttyACM'):
        return LatencyReport(port, device, tty, 'cdc-acm', None, None,
                             'USB CDC-ACM device: no latency timer (1 ms USB frames)')
    if not tty.startswith('ttyUSB'):
        kind = 'pty' if device.startswith(os.path.join(dev_root, 'pts')) else 'uart'
        what = 'a pseudo-terminal' if kind == 'pty' else 'not a USB serial adapter'
        return LatencyReport(port, device, tty, kind, None, None, f'{what}: no latency timer')
    timer = Path(sysfs_root, 'bus', 'usb-serial', 'devices', tty, 'latency_timer')
    before = _read_ms(timer)
    if before is None:
        return LatencyReport(port, device, tty, 'usb', None, None,
                             f'USB adapter without a readable latency timer ({timer}); '
                             f'assuming {DEFAULT_FTDI_LATENCY_MS} ms')
    if before <= WANTED_MS:
        return LatencyReport(port, device, tty, 'ftdi', before, before,
                             f'latency timer {before} ms: nothing to do')
    if not allow_change:
        return LatencyReport(port, device, tty, 'ftdi', before, before,
                             f'latency timer {before} ms, left as it is (the attempt is turned '
                             'off by a parameter)')
    tried = []
    if request_low_latency is not None:
        try:
            request_low_latency()
            tried.append('low-latency mode')
        except Exception as exc:  # noqa: BLE001 - any driver or permission failure
            tried.append(f'low-latency mode refused ({_reason(exc)})')
    after = _read_ms(timer)
    if after is None or after > WANTED_MS:
        try:
            timer.write_text(f'{WANTED_MS}\n')
            tried.append('sysfs write')
        except OSError as exc:
            tried.append(f'sysfs write refused ({_reason(exc)})')
        after = _read_ms(timer)
    if after is not None and after <= WANTED_MS:
        return LatencyReport(port, device, tty, 'ftdi', before, after,
                             f'latency timer lowered from {before} to {after} ms '
                             f'({", ".join(tried)})', changed=True)
    now = 'unreadable' if after is None else f'{after} ms'
    return LatencyReport(port, device, tty, 'ftdi', before, after,
                         f'latency timer {before} ms could not be lowered '
                         f'({", ".join(tried) or "nothing to try"}); now {now}')


def _read_ms(path: Path) -> Optional[int]:
    try:
        return int(path.read_text().strip())
    except (OSError, ValueError):
        return None


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__
