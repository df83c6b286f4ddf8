"""The servo bus schedule's transactions and service calls (``bus_schedule.BusSchedule``).

:class:`_Tx` is one request that waits for its reply (a READ of the read loop, or a service's);
:class:`_Service` is a service call as a sequence of transactions and frames without a reply,
which the schedule runs one step at a time (a generator: no thread, no clock). Kept apart from
``bus_schedule.py`` so that each stays under 600 lines.
"""

from __future__ import annotations

from typing import Any, Hashable, Optional, Tuple

from desheng_servo_ros import id_change as idc
from desheng_servo_ros import protocol as proto
from desheng_servo_ros.bus_events import Answer, QUIET_CALLS
from desheng_servo_ros.schedule import (LATE_REPLY_WINDOW_S, OWED_REPLY_S, own_read,
                                        patient_wait, renamed, sync_write_frames, trimmed)
from desheng_servo_ros.state import TORQUE


WAIT = object()
"""What a service's step is when it waits off the bus until its ``ready_at``."""


class _Tx:
    """One transaction of a service or of the read loop that waits for a reply."""

    __slots__ = ('frame', 'reply_id', 'nparams', 'retries', 'owner', 'tag', 'attempts', 'mark',
                 'wait', 'flush')

    def __init__(self, frame: bytes, reply_id: int, nparams: int, retries: int, owner: Any,
                 tag: Any = None, wait: Optional[float] = None) -> None:
        self.frame = frame
        self.reply_id = reply_id
        self.nparams = nparams
        self.retries = retries
        self.owner = owner
        self.tag = tag
        self.attempts = 0
        self.mark = (0, 0)  # (bytes, frames) received when it was first sent
        self.wait = wait  # how long an attempt waits for its reply (None: wire time + margin)
        self.flush = True  # stale input is discarded before it is sent (Send.flush)


class _Service:
    """A service call as a sequence of transactions.

    ``~/set_id`` and ``~/factory_reset`` run the driver's own procedures (``id_change``).
    """

    def __init__(self, bus: Any, token: Hashable, name: str,
                 args: Tuple[Any, ...]) -> None:
        self.bus = bus
        self.token = token
        self.name = name
        self.args = args
        # A scan, an id change and a hold stop the read loop: they need a quiet bus.
        self.quiet = name in QUIET_CALLS
        self.ok = True
        self.text = ''
        self.retry: Optional[_Tx] = None  # its transaction to send again
        self._steps = self._run()
        self._reply: Optional[proto.Reply] = None
        self._answer_reply: Optional[proto.Reply] = None
        self._garbled = False
        self._cut = False
        self._result: Any = None  # an id_change procedure's Result
        self._at = 0.0  # when its last transaction ended
        self._now = 0.0  # when its current step began
        self.ready_at = 0.0  # its next step waits until then

    def next(self, now: float) -> Any:
        """Return the next step at `now`: a transaction, a frame without a reply, or None."""
        self._now = now
        try:
            return next(self._steps)
        except StopIteration:
            return None

    def result(self, now: float, reply: Optional[proto.Reply], garbled: bool = False,
               cut: bool = False) -> None:
        """Take the reply of the step's transaction (None: none after its retries).

        `garbled`: bytes and no frame came while it was awaited; `cut`: the link went down or
        up meanwhile (the request was lost with it).
        """
        self._reply = reply
        self._garbled = garbled
        self._cut = cut
        self._at = now

    def answer(self) -> Answer:
        """Return the call's answer."""
        return Answer(self.token, self.ok, self.text, self._answer_reply, self._result)

    def _tx(self, frame: bytes, servo_id: int, nparams: int, retries: int) -> _Tx:
        return _Tx(frame, servo_id, nparams, retries, self)

    def _run(self) -> Any:
        name, args, bus = self.name, self.args, self.bus
        if name == 'write_positions':
            for frame in sync_write_frames(args[0]):
                yield frame
            self.text = 'SYNC WRITE sent'
        elif name == 'transact':
            frame, servo_id, nparams, retries = args[:4]
            tx = self._tx(frame, servo_id, nparams, retries)
            tx.wait = args[4] if len(args) > 4 else None  # a scan's long confirmation
            # False: what arrived before it is kept (a scan collects late replies by id).
            tx.flush = args[5] if len(args) > 5 else True
            yield tx
            self.ok, self._answer_reply = self._reply is not None, self._reply
            self.text = 'answered' if self.ok else 'no reply'
        elif name == 'send':
            for frame in args[0]:
                yield frame
            self.text = 'sent'
        elif name == 'hold':
            self.text = 'the read loop holds'
        elif name == 'read_register':
            servo_id, address, length = args[:3]
            retries = args[3] if len(args) > 3 and args[3] is not None else bus.max_retries
            self._answer_reply = yield from self._read(servo_id, address, length, retries)
            self.ok = self._answer_reply is not None
            self.text = 'read' if self.ok else 'no reply'
        elif name == 'set_torque':
            self._result = yield from self._torque(*args)
        elif name == 'scan':
            first, last = args
            found = []
            for servo_id in range(first, last + 1):
                yield self._tx(proto.encode_ping(servo_id), servo_id, 0, 0)
                if self._reply is not None:
                    found.append(servo_id)
            self.text = f'found {found}'
        elif name == 'set_id':
            yield from self._run_procedure(idc.set_id(*args, self.bus.servos, self.bus.baud))
        elif name == 'factory_reset':
            servo_id, configured = args
            yield from self._run_procedure(idc.factory_reset(servo_id, configured,
                                                             self.bus.baud))

    def _torque(self, ids: Tuple[int, ...], enable: bool) -> Any:
        """WRITE torque on or off to each of `ids`, each read back; return (id, reply) pairs.

        The reply is that of the READ of the torque register (None: no answer). It is read
        back even when the WRITE's acknowledgement was lost, since the servo may have done it.
        A cut link ends the call: whether the servo took the frame that had left is unknown.
        """
        bus = self.bus
        value = b'\x01' if enable else b'\x00'
        read_back = []
        for servo_id in ids:
            yield self._tx(proto.encode_write(servo_id, TORQUE.address, value), servo_id, 0,
                           bus.max_retries)
            reply = None
            if not self._cut:
                reply = yield from self._read(servo_id, TORQUE.address, 1, bus.max_retries)
            if self._cut:
                self.ok, self.text = False, 'the link went down; its request had left'
                return read_back
            if reply is not None:
                for s in bus.servos:
                    if s.id == servo_id:
                        s.set_torque(reply.params[0] != 0)
            read_back.append((servo_id, reply))
        self.text = f'torque {"on" if enable else "off"} written and read back'
        return read_back

    def _read(self, servo_id: int, address: int, length: int, retries: int) -> Any:
        """READ `length` bytes at `address` at a length of its own; return its reply or None.

        The length is ``schedule.own_read``'s: no other READ of that servo that may still be
        answered (the read loop's, one left unanswered) has it. An unanswered one, or one cut
        off by the link, is owed its reply for OWED_REPLY_S; an answered one, for a second
        servo's at its id, for LATE_REPLY_WINDOW_S.
        """
        bus = self.bus
        start, size, skip = own_read(address, length, bus.owed_lengths(servo_id, self._now))
        yield self._tx(proto.encode_read(servo_id, start, size), servo_id, size, retries)
        # Cut off by an unplug too: a reply the device gave before may still come after. And
        # answered: a second servo at the id answers after the first (S24).
        bus.owed[(servo_id, size)] = self._at + (
            OWED_REPLY_S if self._reply is None else LATE_REPLY_WINDOW_S)
        if self._reply is None:
            return None
        return trimmed(self._reply, skip, length)

    def _run_procedure(self, steps: Any) -> Any:
        """Run the driver's ~/set_id or ~/factory_reset (id_change), each step here."""
        result = yield from self._procedure(steps)
        self.ok, self.text, self._result = result.ok, result.message, result

    def _procedure(self, steps: Any) -> Any:
        """Run an id_change procedure here; return its value."""
        bus = self.bus
        heard: Any = None
        while True:
            try:
                step = steps.send(heard)
            except StopIteration as stop:
                return stop.value
            heard = None
            if isinstance(step, idc.Ask):
                tx = self._tx(step.frame, step.servo_id, step.nparams,
                              bus.max_retries if step.retries is None else step.retries)
                if step.patient:
                    tx.wait = patient_wait(len(step.frame), step.nparams, bus.baud,
                                           bus.reply_timeout(len(step.frame), step.nparams,
                                                             step.servo_id))
                tx.flush = step.flush
                yield tx
                if self._cut:
                    heard = idc.Heard(None, 'the link went down during the request', lost=True)
                else:
                    heard = idc.Heard(self._reply, f'no reply from servo {step.servo_id}',
                                      garbled=self._garbled)
            elif isinstance(step, idc.Quiet):
                # As the driver: off the bus (it sleeps off the bus lock: commands may go
                # meanwhile, the read loop is paused).
                self.ready_at = self._at + step.seconds
                yield WAIT
            elif isinstance(step, idc.Unsolicited):
                heard = bus.unsolicited.get((step.servo_id, step.size), 0)
            elif isinstance(step, idc.Servos):
                heard = bus.servos
            elif isinstance(step, idc.PortBack):
                heard = bus.port_open
            elif isinstance(step, idc.Rename):
                bus.servos = renamed(bus.servos, step.old, step.new)
            else:
                raise TypeError(f'not a step of an id change: {step!r}')
