"""DPS-S serial link: SerialLink + the DPS stream decoder, typed requests, unsolicited frames.

Requests are matched to replies by what answers them (the typed reply class, so a 6-byte
0x34/0x35 frame answers the cell-voltage query while a 16-byte 0x35 frame is a trigger record,
P3). Requests that wait for the same kind of reply are serialized; different kinds may be in
flight at once, so a deploy never waits behind a poll that is timing out. Everything no request
waits for (status stream, heartbeats, trigger requests with either header) goes to
``on_message`` straight from the reader thread. No ROS here.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable, Optional, Tuple, Type

from dps_parachute_ros import protocol as p
from dps_parachute_ros.blackbox import BlackBox
from uav_serial_common.serial_link import LinkDown, LinkError, LinkTimeout, SerialLink

__all__ = ['LinkDown', 'LinkError', 'LinkTimeout', 'ParachuteLink', 'LinkBusy',
           'REQUEST_TIMEOUT_S', 'EXPECTED_REPLY']

REQUEST_TIMEOUT_S = 1.0
"""P12: no reply within 1 s of a request means the module is offline."""
RECORDS_QUIET_S = 0.2
"""The trigger-record reply is complete when no further record came for this long."""
UNREAD_POLL_S = 0.01
"""How often the record query looks again while the reader has bytes still to hand on."""
READ_TIMEOUT_S = 0.5
"""The reader's longest sleep on a quiet line (SerialLink wakes it 5 ms after the last byte when
the decoder holds a frame that could still grow, P3); every wake-up costs CPU."""

EXPECTED_REPLY: dict[int, Tuple[Type, ...]] = {
    p.CMD_HEARTBEAT: (p.Heartbeat,),
    p.CMD_ARM: (p.ArmReply,),
    p.CMD_DEPLOY: (p.DeployAck,),
    p.CMD_SHUTDOWN: (p.ShutdownAck,),
    p.CMD_STREAMING: (p.StreamingReply,),
    p.CMD_LIGHT_LEVEL: (p.LightLevel,),
    p.CMD_LIGHT_THRESHOLD: (p.LightThreshold,),
    p.CMD_ATTITUDE_TRIGGER: (p.AutoTriggerFlags,),
    p.CMD_FREEFALL_TRIGGER: (p.AutoTriggerFlags,),
    p.CMD_ATTITUDE_THRESHOLD: (p.AttitudeThreshold,),
    p.CMD_FREEFALL_THRESHOLD: (p.FreefallThreshold,),
    p.CMD_FREEFALL_TIME: (p.FreefallTime,),
    p.CMD_BOOT_COUNT: (p.BootCount,),
    p.CMD_BAUD_RATE: (p.BaudRate,),
    p.CMD_SENSOR_ZERO: (p.ZeroAck,),
    p.CMD_ARMED: (p.ArmedState,),
    p.CMD_TRIGGERED: (p.TriggeredState,),
    p.CMD_STATUS: (p.Status,),
    p.CMD_CHARGING: (p.Charging,),
    p.CMD_CELL_VOLTAGE: (p.CellVoltage,),
}
"""Host command code to the typed reply that answers it."""


class LinkBusy(LinkError):
    """Another request waiting for the same kind of reply did not finish in time."""


class _Decoder:
    """The DPS stream decoder, plus a record of every frame and the time of the last one."""

    def __init__(self, blackbox: Optional[BlackBox], clock: Callable[[], float]) -> None:
        self.inner = p.StreamDecoder('from_module')
        self.blackbox = blackbox
        self.clock = clock
        # (valid module frames so far, clock time of the last one): one tuple, so a reader on
        # another thread always sees a matching pair.
        self.last_frame: Tuple[int, Optional[float]] = (0, None)

    @property
    def last_frame_time(self) -> Optional[float]:
        return self.last_frame[1]

    @property
    def pending(self) -> int:
        return self.inner.pending

    def feed(self, data: bytes) -> list:
        return self._seen(self.inner.feed(data))

    def flush(self) -> list:
        return self._seen(self.inner.flush())

    def reset(self) -> None:
        self.inner.reset()

    def _seen(self, frames: list) -> list:
        if frames:
            # Our own echoed frames (host header) are no sign of life, a trigger request is.
            if any(f.header == p.MODULE_HEADER or f.code == p.CMD_TRIGGER_REQUEST
                   for f in frames):
                self.last_frame = (self.last_frame[0] + 1, self.clock())
            if self.blackbox is not None:
                for f in frames:
                    self.blackbox.frame('rx', f.raw)
        return frames


class ParachuteLink:
    """One DPS-S module on one serial port."""

    def __init__(self, url: str, baud: int,
                 on_message: Callable[[p.ModuleMessage], None],
                 on_connection: Optional[Callable[[bool, str], None]] = None,
                 blackbox: Optional[BlackBox] = None,
                 logger: Optional[Any] = None,
                 layout: p.FlagLayout = 'table',
                 clock: Callable[[], float] = time.monotonic,
                 on_tx: Optional[Callable[[bytes], None]] = None) -> None:
        """`clock` stamps `last_frame_time`; `on_tx(frame)` hears every frame that left."""
        self.layout: p.FlagLayout = layout
        self.blackbox = blackbox
        self._on_message = on_message
        self._on_tx_hook = on_tx
        self._decoder = _Decoder(blackbox, clock)
        self._locks: dict[Tuple[Type, ...], threading.Lock] = {}
        self._locks_guard = threading.Lock()
        self._collector: Optional[list] = None
        self._collector_cond = threading.Condition()
        # When the reader received the bytes of the last record frame (monotonic).
        self._record_rx_at = 0.0
        self._tail_owed = 0  # frames of the last records answer that had not come when it ended
        self._tail_until = 0.0
        self._power_ups = 0  # reboots told (void_answers): an answer across one never ends
        self.timeouts = 0
        self.serial = SerialLink(
            url, baud, self._decoder, on_frame=self._on_frame, on_connection=on_connection,
            on_tx=self._on_tx, logger=logger, read_timeout_s=READ_TIMEOUT_S,
            idle_flush_s=0.005)

    # -- lifecycle and state --------------------------------------------------------------------

    def start(self) -> None:
        """Open the port (in the reader thread, with reconnects)."""
        self.serial.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Close the port and stop the reader thread."""
        self.serial.stop(timeout)

    @property
    def port_open(self) -> bool:
        """Whether the port is open."""
        return self.serial.port_open

    @property
    def last_frame_time(self) -> Optional[float]:
        """Clock time of the last valid frame from the module, None if none yet."""
        return self._decoder.last_frame[1]

    @property
    def last_frame(self) -> Tuple[int, Optional[float]]:
        """(valid module frames received so far, clock time of the last one)."""
        return self._decoder.last_frame

    @property
    def decoder(self) -> p.StreamDecoder:
        """Return the DPS stream decoder, whose counters the diagnostics show."""
        return self._decoder.inner

    # -- I/O ------------------------------------------------------------------------------------

    def write(self, frame: bytes) -> None:
        """Send one frame now, without waiting for anything (raises LinkDown)."""
        self.serial.write(frame)

    def request(self, frame: bytes, timeout: float = REQUEST_TIMEOUT_S, retries: int = 0,
                expect: Optional[Tuple[Type, ...]] = None) -> p.ModuleMessage:
        """Send a host frame, return the typed reply (LinkTimeout, LinkDown, LinkBusy)."""
        expect = expect or EXPECTED_REPLY[frame[2]]
        lock = self._lock_for(expect)
        wait = timeout * (retries + 1) + 0.5
        if not lock.acquire(timeout=wait):
            raise LinkBusy(f'another request for {expect[0].__name__} is still running')
        try:
            layout = self.layout
            found: list = []

            def match(f: p.Frame) -> bool:
                if f.header != p.MODULE_HEADER:
                    return False
                msg = p.decode_module_frame(f, layout)
                if isinstance(msg, expect):
                    found.append(msg)
                    return True
                return False

            if self.blackbox is not None:
                self.blackbox.record('request', hex=frame.hex(' '), expect=expect[0].__name__)
            try:
                self.serial.request(frame, match, timeout, retries)
            except LinkTimeout:
                self.timeouts += 1
                raise
            return found[-1]
        finally:
            lock.release()

    def query_records(self, timeout: float = REQUEST_TIMEOUT_S,
                      quiet_s: float = RECORDS_QUIET_S,
                      max_records: int = p.RECORD_SLOTS) -> p.TriggerRecords:
        """Ask for the trigger history and collect every 16-byte record of the answer.

        The module answers with one frame per slot of its ring (P15): collect until
        ``max_records`` or until none came for ``quiet_s``; the answer is `complete` only with
        every slot's frame. Raises LinkTimeout when none came at all. A query after an answer
        cut short first lets that answer's late frames pass (up to ``timeout``): a list never
        holds frames of two answers.

        The gap is the line's, not this thread's: measured from the time the reader received
        the last record, and only once the reader has handed on every byte that came in. A
        caller or a reader late on a loaded machine does not end the list early; a reader
        that stays behind for ``timeout`` more does.
        """
        lock = self._lock_for((p.TriggerRecord,))
        if not lock.acquire(timeout=timeout + 1.0):
            raise LinkBusy('another trigger-record query is still running')
        try:
            records: list = []
            with self._collector_cond:
                # The rest of an earlier answer cut short (its frames owed) may still be
                # coming: let it pass, or this list would begin with it.
                while self._tail_owed and time.monotonic() < self._tail_until:
                    self._collector_cond.wait(self._tail_until - time.monotonic())
                self._tail_owed = 0
                self._collector = records
                power_ups = self._power_ups
            try:
                if self.blackbox is not None:
                    self.blackbox.record('request', hex=p.encode_trigger_records_query().hex(' '),
                                         expect='TriggerRecord')
                self.write(p.encode_trigger_records_query())
                deadline = time.monotonic() + timeout
                with self._collector_cond:
                    while len(records) < max_records and self.port_open:
                        now = time.monotonic()
                        if records:
                            quiet_at = self._record_rx_at + quiet_s
                            if now >= quiet_at and (not self.serial.unread_input()
                                                    or now >= quiet_at + timeout):
                                break
                            wait = max(quiet_at - now, UNREAD_POLL_S)
                        else:
                            wait = deadline - now
                            if wait <= 0:
                                break
                        self._collector_cond.wait(wait)
            finally:
                with self._collector_cond:
                    self._collector = None
                    # Frames still to come (P15), for at most one more timeout; none when the
                    # module rebooted meanwhile.
                    self._tail_owed = max_records - len(records) \
                        if power_ups == self._power_ups else 0
                    self._tail_until = time.monotonic() + timeout
            if not records:
                if not self.port_open:
                    raise LinkDown('port closed while waiting for trigger records')
                self.timeouts += 1
                raise LinkTimeout(f'no trigger record within {timeout * 1000:.0f} ms')
            return p.TriggerRecords(records)
        finally:
            lock.release()

    def void_answers(self) -> None:
        """Take it that the module rebooted: the rest of a records answer will not come.

        A power-up does not go on with the answer of the power-up before (P5, P15): the next
        query does not wait for that answer's tail, nor does the one in progress leave one owed.
        """
        with self._collector_cond:
            self._power_ups += 1
            self._tail_owed = 0
            self._collector_cond.notify_all()

    # -- reader thread ----------------------------------------------------------------------------

    def _lock_for(self, key: Tuple[Type, ...]) -> threading.Lock:
        with self._locks_guard:
            lock = self._locks.get(key)
            if lock is None:
                lock = self._locks[key] = threading.Lock()
            return lock

    def _on_frame(self, frame: p.Frame) -> None:
        msg = p.decode_module_frame(frame, self.layout)
        if isinstance(msg, p.TriggerRecord):
            with self._collector_cond:
                # Also when no query collects it: the tail of an answer cut short, which the
                # next query lets pass first.
                self._record_rx_at = self.serial.last_rx_time or time.monotonic()
                self._collector_cond.notify_all()
                if self._collector is not None:
                    self._collector.append(msg)
                    return
                self._tail_owed = max(0, self._tail_owed - 1)
        self._on_message(msg)

    def _on_tx(self, data: bytes) -> None:
        # Called by SerialLink right after the bytes were written, in the writing thread.
        if self.blackbox is not None:
            self.blackbox.frame('tx', data)
        if self._on_tx_hook is not None:
            self._on_tx_hook(data)
