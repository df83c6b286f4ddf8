"""The OriginMan board on a serial port: whole frames out, reports and matched replies in.

No ROS here. :class:`OriginManLink` puts the board's protocol on the shared
:class:`uav_serial_common.serial_link.SerialLink` (one reader thread, reconnects):

* every frame is written whole by one ``write`` under the link's write lock, never byte by byte
  or interleaved with another thread's frame: the board's parser has no timeout and loses
  frames around a broken one (O22);
* unsolicited reports (IMU, battery, keys, SBUS, gamepad, ASR) go to ``on_report`` straight
  from the reader thread, typed (:mod:`originman_board_ros.protocol`);
* reads (PWM 0x05/0x09, the nine bus-servo reads) are matched by FUNCTION, sub-command and
  servo id, at most one outstanding per FUNCTION (§5: replies carry no sequence number), with a
  timeout and retries for a missing reply. A bus-servo reply with success != 0 raises
  :class:`BusServoFailure` and never yields a value (O14);
* commands without a reply are just written.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable, Dict, Optional

from originman_board_ros import protocol as p
from uav_serial_common.serial_link import LinkDown, LinkError, LinkTimeout, SerialLink

__all__ = ['BusServoFailure', 'LinkBusy', 'LinkDown', 'LinkError', 'LinkTimeout',
           'OriginManLink', 'READ_TIMEOUT_S', 'REPORT_TYPES']

READ_TIMEOUT_S = 0.1
"""§5: the firmware answers within ~5 ms (servo timeout) plus queued frames; 100 ms also covers
a companion computer whose CPU is busy for a while (50 ms failed reads on a loaded host)."""
LOCK_MARGIN_S = 0.5
"""How much longer than its own worst case a read waits for the read before it to finish."""

REPORT_TYPES = (p.ImuReport, p.BatteryReport, p.KeyReport, p.SbusReport, p.GamepadReport,
                p.AsrReport)
"""Messages the board sends on its own."""


class LinkBusy(LinkError):
    """The read before this one, of the same FUNCTION, did not finish in time."""


class BusServoFailure(LinkError):
    """The board answered a bus-servo read with success != 0: the servo gave no valid answer.

    The reply's arguments are never used (O14). ``servo_id``, ``sub`` and ``success`` say
    which read failed; ``reason`` says it in words.
    """

    def __init__(self, servo_id: int, sub: int, success: int) -> None:
        self.servo_id = servo_id
        self.sub = sub
        self.success = success
        self.reason = (f'bus servo {servo_id} gave no valid answer to read 0x{sub:02X} '
                       f'(board reports success {success}: no reply within 5 ms, '
                       'bad checksum or two servos answering)')
        super().__init__(self.reason)


class _Decoder:
    """The host stream decoder, typing frames and noting when the board last sent one."""

    def __init__(self, clock: Callable[[], float],
                 on_frames: Optional[Callable[[float], None]] = None) -> None:
        self.inner = p.StreamDecoder()
        self.clock = clock
        self.on_frames = on_frames
        self.last_frame_time: Optional[float] = None
        self.unknown_frames = 0

    def feed(self, data: bytes) -> list:
        frames = self.inner.feed(data)
        if not frames:
            return []
        self.last_frame_time = self.clock()
        if self.on_frames is not None:
            # Before the frames are handed out: whoever sees a report sees the board online.
            self.on_frames(self.last_frame_time)
        out = []
        for frame in frames:
            msg = p.decode_board_frame(frame)
            if isinstance(msg, p.UnknownFrame):
                self.unknown_frames += 1
            out.append(msg)
        return out

    def reset(self) -> None:
        self.inner.reset()


class OriginManLink:
    """One OriginMan board on one serial port.

    ``on_report(msg)`` gets every report (``REPORT_TYPES``) from the reader thread; it must not
    block and must not start a read. ``on_connection(up, reason)`` is called from the reader
    thread when the port opens or closes; ``on_frames(time)`` from the reader thread when valid
    frames arrived, before they are handed out; ``on_tx(frame)`` after every write (from the
    writing thread). ``clock`` stamps ``last_frame_time`` (default
    ``time.monotonic``).
    """

    def __init__(self, port: str, baud: int = p.BAUD, *,
                 on_report: Optional[Callable[[Any], None]] = None,
                 on_connection: Optional[Callable[[bool, str], None]] = None,
                 on_frames: Optional[Callable[[float], None]] = None,
                 on_tx: Optional[Callable[[bytes], None]] = None,
                 clock: Callable[[], float] = time.monotonic,
                 timeout_s: float = READ_TIMEOUT_S, retries: int = 1,
                 logger: Optional[Any] = None, backoff_max_s: float = 1.0) -> None:
        self.port = port
        self.baud = baud
        self.timeout_s = timeout_s
        self.retries = retries
        self.reads = 0
        self.read_timeouts = 0
        self.read_failures = 0
        self.unexpected_replies = 0
        self._on_report = on_report
        self._decoder = _Decoder(clock, on_frames)
        self._locks: Dict[int, threading.Lock] = {
            p.Function.PWM_SERVO: threading.Lock(), p.Function.BUS_SERVO: threading.Lock()}
        self.serial = SerialLink(port, baud, self._decoder, on_frame=self._on_frame,
                                 on_connection=on_connection, on_tx=on_tx, logger=logger,
                                 backoff_max_s=backoff_max_s, read_timeout_s=0.02)

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        """Open the port (the reader thread keeps it open and reconnects)."""
        self.serial.start()

    def stop(self) -> None:
        """Close the port and stop the reader thread."""
        self.serial.stop()

    @property
    def port_open(self) -> bool:
        """Whether the port is open."""
        return self.serial.port_open

    def wait_port_open(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for the port to be open."""
        return self.serial.wait_port_open(timeout)

    @property
    def last_frame_time(self) -> Optional[float]:
        """Clock time of the last valid frame from the board, None if none yet."""
        return self._decoder.last_frame_time

    @property
    def decoder(self) -> p.StreamDecoder:
        """The stream decoder, whose counters (CRC errors ...) diagnostics show."""
        return self._decoder.inner

    @property
    def unknown_frames(self) -> int:
        """CRC-valid frames that could not be typed (unknown sub-command or LENGTH)."""
        return self._decoder.unknown_frames

    # -- commands -------------------------------------------------------------------------------

    def send(self, frame: bytes) -> None:
        """Write one whole frame now (raises LinkDown); for commands the board never answers."""
        self.serial.write(frame)

    def read_pwm_pulse(self, servo_id: int, timeout: Optional[float] = None,
                       retries: Optional[int] = None) -> int:
        """Return PWM servo ``servo_id``'s current pulse in us (offset not included)."""
        reply = self._read(p.encode_pwm_read_pulse(servo_id), p.Function.PWM_SERVO,
                           p.PwmPulseReply, p.PwmSub.READ_PULSE, servo_id, timeout, retries)
        return reply.pulse_us

    def read_pwm_offset(self, servo_id: int, timeout: Optional[float] = None,
                        retries: Optional[int] = None) -> int:
        """Return PWM servo ``servo_id``'s offset in us (reply sub-command 0x09, O11)."""
        reply = self._read(p.encode_pwm_read_offset(servo_id), p.Function.PWM_SERVO,
                           p.PwmOffsetReply, p.PwmSub.READ_OFFSET, servo_id, timeout, retries)
        return reply.offset_us

    def bus_read(self, sub: int, servo_id: int, timeout: Optional[float] = None,
                 retries: Optional[int] = None) -> p.BusValue:
        """Run one of the nine bus-servo reads and return its value.

        Raises :class:`BusServoFailure` when the board answers with success != 0 (O14),
        LinkTimeout when it does not answer at all, LinkDown, LinkBusy.
        """
        reply = self._read(p.encode_bus_read(sub, servo_id), p.Function.BUS_SERVO,
                           p.BusServoReply, sub, servo_id, timeout, retries)
        if not reply.ok:
            self.read_failures += 1
            raise BusServoFailure(reply.servo_id, reply.sub, reply.success)
        return reply.value

    def _read(self, frame: bytes, function: int, reply_type: type, sub: int, servo_id: int,
              timeout: Optional[float], retries: Optional[int]) -> Any:
        timeout = self.timeout_s if timeout is None else timeout
        retries = self.retries if retries is None else retries
        lock = self._locks[function]
        if not lock.acquire(timeout=timeout * (retries + 1) + LOCK_MARGIN_S):
            raise LinkBusy(f'the previous FUNCTION {function} read is still waiting')
        try:
            self.reads += 1

            def match(msg: Any) -> bool:
                # §5: no sequence number; FUNCTION (by type), sub-command and the echoed id.
                return type(msg) is reply_type and msg.servo_id == servo_id and \
                    getattr(msg, 'sub', sub) == sub
            try:
                return self.serial.request(frame, match, timeout, retries)
            except LinkTimeout:
                self.read_timeouts += 1
                raise
        finally:
            lock.release()

    # -- reader thread --------------------------------------------------------------------------

    def _on_frame(self, msg: Any) -> None:
        if isinstance(msg, REPORT_TYPES):
            if self._on_report is not None:
                self._on_report(msg)
        elif isinstance(msg, (p.BusServoReply, p.PwmPulseReply, p.PwmOffsetReply)):
            # A reply nobody waits for: late (after its timeout) or from another program.
            self.unexpected_replies += 1
