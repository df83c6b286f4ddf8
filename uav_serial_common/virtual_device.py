"""Run a device model behind a pseudo-terminal, with wire timing and fault injection.

The device models (``dps_parachute_ros.simulation``, ``desheng_servo_ros.simulation``) are plain
Python and clocked by their caller. `VirtualDeviceRunner` is that caller for real time: one thread
reads what the driver wrote, hands it to the model once it would have finished arriving on a real
wire, and sends the model's output back paced at the configured baud. Faults that concern the wire
rather than the device (garbage, lost or late replies, bad checksums, an unplugged cable) are
applied here, the same way for every device.

The runner also honours the line settings the driver put on the pty: when the driver's speed
differs from the device's ``baud``, what each side receives is what a UART at its own speed makes
of the other's bits (``uav_serial_common.uart``): garbage both ways, as on a real wire, so a
driver's "wrong baud?" diagnostics can be exercised.
"""

from __future__ import annotations

import logging
import os
import random
import threading
import time
from dataclasses import dataclass
from typing import Callable, Iterable, Optional, Union

from uav_serial_common.pty_port import PortUnplugged, sleep_until, VirtualSerialPort, wire_time
from uav_serial_common.uart import reframe

Output = Union[bytes, Iterable[bytes], None]


@dataclass
class WireFaults:
    """Faults applied to the device's output. Counts are consumed as replies go out."""

    drop_next: int = 0                 # replies to drop entirely
    corrupt_next: int = 0              # replies whose last (checksum) byte is flipped
    reply_delay_s: float = 0.0         # extra delay before every reply
    drop_probability: float = 0.0      # random loss, for soak tests
    corrupt_probability: float = 0.0   # random corruption, for soak tests
    garbage_probability: float = 0.0   # chance of a burst of noise before a reply


class VirtualDeviceRunner:
    """Drive a device model from a pty in real time."""

    def __init__(
        self,
        link_path: Optional[str],
        on_input: Callable[[bytes, float], Output],
        on_tick: Optional[Callable[[float], Output]] = None,
        next_event: Optional[Callable[[], Optional[float]]] = None,
        baud: int = 115200,
        tick_period_s: float = 0.005,
        response_delay_s: float = 0.0,
        seed: Optional[int] = None,
        logger: Optional[logging.Logger] = None,
        fault_unsolicited: bool = False,
        checksum_from_end: int = 1,
    ) -> None:
        self.port = VirtualSerialPort(link_path)
        self.baud = baud
        self.faults = WireFaults()
        self.response_delay_s = response_delay_s
        self.bytes_in = 0
        self.bytes_out = 0
        self.replies_dropped = 0
        self.replies_corrupted = 0
        # Chunks that crossed the wire at mismatched speeds (the driver's baud was not ours).
        self.garbled_chunks = 0
        self.chunks_handled = 0
        """Chunks of input the model has taken (a test waits for one its tap saw)."""
        self.driver_baud: Optional[int] = None
        self._on_input = on_input
        self._on_tick = on_tick
        self._next_event = next_event
        self._tick_period = tick_period_s
        self._rng = random.Random(seed)
        self._log = logger or logging.getLogger('virtual_device')
        self._lock = threading.RLock()  # the model is not thread-safe: one caller at a time
        self._running = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._pending_garbage = b''
        self._replug_at: Optional[float] = None
        self._taps: list = []
        self._last_tick = 0.0
        self._tick_due = 0.0
        # Devices whose output is mostly unsolicited (a board's reports, a handset's frames, a
        # bus servo reply that the model emits on a tick) are faulted on every frame they send.
        self._fault_unsolicited = fault_unsolicited
        # Where the checksum sits, counted from the end (1: last byte; 2: before an end byte).
        self._checksum_from_end = checksum_from_end

    # -- lifecycle ------------------------------------------------------------------------------

    @property
    def path(self) -> str:
        """Return the path the driver opens."""
        return self.port.path

    def start(self) -> 'VirtualDeviceRunner':
        """Open the pty and start the device thread; returns self."""
        self.port.open()
        self._running.set()
        self._thread = threading.Thread(target=self._run, name='virtual-device', daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and remove the pty."""
        self._running.clear()
        self.port.halt()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        self.port.close()

    def __enter__(self) -> 'VirtualDeviceRunner':
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def locked(self) -> threading.RLock:
        """Return the model lock: hold it to change the model from another thread."""
        return self._lock

    def now(self) -> float:
        """Return the runner's clock (the time the model is given)."""
        return time.monotonic()

    # -- faults ---------------------------------------------------------------------------------

    def inject_garbage(self, data: bytes) -> None:
        """Send noise to the driver before the next output (or at the next tick)."""
        with self._lock:
            self._pending_garbage += data

    def unplug(self, duration_s: Optional[float] = None) -> None:
        """Pull the cable; plug it back after `duration_s` if given."""
        with self._lock:
            self.port.unplug()
            self._replug_at = None if duration_s is None else time.monotonic() + duration_s

    def replug(self) -> None:
        """Plug the cable back in at the same path."""
        with self._lock:
            self._replug_at = None
            self.port.replug()

    def add_tap(self, tap: Callable[[str, bytes, float], None]) -> None:
        """Call `tap(direction, data, time)` for every chunk in ('rx') and out ('tx')."""
        self._taps.append(tap)

    # -- the device thread ----------------------------------------------------------------------

    def _run(self) -> None:
        # A device has a CPU of its own: under the test harness (UAV_DEVICE_NICE), this thread
        # runs at that priority even inside a test's process, so a busy host does not starve it.
        nice = os.environ.get('UAV_DEVICE_NICE')
        if nice:
            try:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), int(nice))
            except (OSError, ValueError):
                pass
        rx_busy_until = 0.0
        while self._running.is_set():
            try:
                rx_busy_until = self._run_once(rx_busy_until)
            except Exception:  # noqa: BLE001 - the device must outlive any fault of its pty
                self._log.exception('virtual device: unexpected failure; going on')
                time.sleep(0.005)

    def _run_once(self, rx_busy_until: float) -> float:
        """Serve one read (or an unplugged pause) and the tick if due; return rx_busy_until."""
        if not self.port.plugged:
            if self._replug_at is not None and time.monotonic() >= self._replug_at:
                self.replug()
            else:
                time.sleep(0.005)
                self._tick()
                return rx_busy_until
        data = self.port.read(timeout=self._poll_timeout())
        if data:
            now = time.monotonic()
            sender = self._check_line()
            # The bytes reached the pty at once; on a wire the last one arrives only after all
            # of them were clocked out, and a half-duplex device answers after that.
            arrival = max(now, rx_busy_until) + wire_time(len(data), sender)
            rx_busy_until = arrival
            if sender != self.baud:
                # Our UART samples the driver's bits at our own speed.
                data = reframe(data, sender, self.baud)
                self.garbled_chunks += 1
            sleep_until(arrival)
            self.bytes_in += len(data)
            for tap in self._taps:
                tap('rx', data, arrival)
            with self._lock:
                try:
                    output = self._on_input(data, arrival)
                except Exception:  # noqa: BLE001 - a model bug must not kill the device
                    self._log.exception('device model failed on input %s', data.hex(' '))
                    output = None
                self.chunks_handled += 1
            self._send(output, reply=True, ready_at=arrival)
        if time.monotonic() >= self._tick_due:
            self._tick()
        return rx_busy_until

    def _poll_timeout(self) -> float:
        """Return how long to wait for input before the model's next tick is due."""
        due = self._last_tick + self._tick_period
        if self._next_event is not None:
            with self._lock:
                when = self._next_event()
            if when is not None:
                due = min(due, when)
        self._tick_due = due
        return max(0.0, due - time.monotonic())

    def _check_line(self) -> int:
        """Return the speed the driver's bytes travel at: its own setting, else ours."""
        baud = self.port.line_baud()
        self.driver_baud = baud
        if baud is None or self.baud <= 0:
            return self.baud
        return baud

    def _tick(self) -> None:
        # Only when due, not after every request: the model advances on input anyway, and the
        # device must be back listening as soon as its reply is out.
        self._last_tick = time.monotonic()
        self._check_line()
        if self._on_tick is None:
            output = None
        else:
            with self._lock:
                try:
                    output = self._on_tick(time.monotonic())
                except Exception:  # noqa: BLE001 - a model bug must not kill the device
                    self._log.exception('device model failed on tick')
                    output = None
        self._send(output, reply=False)

    def _send(self, output: Output, reply: bool, ready_at: Optional[float] = None) -> None:
        frames = _frames(output)
        with self._lock:
            garbage, self._pending_garbage = self._pending_garbage, b''
        start = None
        if reply and frames:
            # A reply leaves the device its response delay after the request fully arrived; the
            # model's own computing time is hidden in that and the reply's wire time, so the
            # timing on the wire is the device's, not this Python process's.
            start = (ready_at if ready_at is not None else time.monotonic()) + \
                self.response_delay_s + self.faults.reply_delay_s
        if garbage:
            start = self._write(garbage, start)
        for frame in frames:
            frame = self._apply_faults(frame) if reply or self._fault_unsolicited else frame
            if frame:
                start = self._write(frame, start)

    def _apply_faults(self, frame: bytes) -> bytes:
        faults = self.faults
        if faults.drop_next > 0:
            faults.drop_next -= 1
            self.replies_dropped += 1
            return b''
        if faults.drop_probability and self._rng.random() < faults.drop_probability:
            self.replies_dropped += 1
            return b''
        corrupt = False
        if faults.corrupt_next > 0:
            faults.corrupt_next -= 1
            corrupt = True
        elif faults.corrupt_probability and self._rng.random() < faults.corrupt_probability:
            corrupt = True
        if corrupt:
            # Flipping the checksum is an error the driver can detect.
            at = len(frame) - min(self._checksum_from_end, len(frame))
            frame = frame[:at] + bytes([frame[at] ^ 0x5A]) + frame[at + 1:]
            self.replies_corrupted += 1
        if faults.garbage_probability and self._rng.random() < faults.garbage_probability:
            noise = bytes(self._rng.randrange(256) for _ in range(self._rng.randrange(1, 9)))
            frame = noise + frame
        return frame

    def _write(self, data: bytes, start: Optional[float] = None) -> Optional[float]:
        """Pace `data` out from `start`; return when its last byte arrived (None: unplugged)."""
        # The driver's speed as the bytes go out, not as of the last tick: a driver that opened
        # the port (and set its speed) since then reads them at its new speed.
        self._check_line()
        receiver = self.driver_baud
        try:
            if receiver is None or self.baud <= 0 or receiver == self.baud:
                end = self.port.write(data, self.baud, start)
            else:
                # The driver's UART samples our bits at its own speed: it gets what it makes of
                # them, once they have been on the wire for their time at our speed.
                end = max(time.monotonic(), start or 0.0) + wire_time(len(data), self.baud)
                sleep_until(end)
                self.port.write(reframe(data, self.baud, receiver))
                self.garbled_chunks += 1
        except PortUnplugged:
            return None
        self.bytes_out += len(data)
        for tap in self._taps:
            tap('tx', data, end)
        return end


def _frames(output: Output) -> list:
    if not output:
        return []
    if isinstance(output, (bytes, bytearray)):
        return [bytes(output)]
    return [bytes(f) for f in output if f]
