"""The servo bus's services (``~/write_positions``, ``~/set_torque``, ``~/set_id``, ...).

A mixin of :class:`~desheng_servo_ros.core.ServoBusCore`: each service is a call on the node's
executor thread that returns a :class:`Result`, refuses bad input before anything is sent, and
says UNKNOWN when a frame left and its outcome was not seen. Services that need a quiet bus
(a scan, an id change, a reset) hold the read loop meanwhile (``_loop_paused``).
"""

from __future__ import annotations

import functools
import time
import traceback
from typing import Any, Callable, Sequence, Tuple

from desheng_servo_ros import id_change as idc
from desheng_servo_ros import protocol as proto
from desheng_servo_ros.link import LinkDown, LinkError, LinkTimeout
from desheng_servo_ros.registers import (by_address, by_name, decode_block, decode_value,
                                         encode_value, RegisterError)
from desheng_servo_ros.schedule import patient_wait, renamed, set_id_refusal
from desheng_servo_ros.state import FIRMWARE, ID, Outcome, Result, RUN_PRESETS, TORQUE
from desheng_servo_ros.units import select
from uav_serial_common.text import clip, few

# Services that change nothing on a servo: a request of theirs that went unanswered leaves no
# outcome to find out.
_READS_ONLY = frozenset({'read_register', 'scan'})


def _service(method: Callable[..., Result]) -> Callable[..., Result]:
    """One error path for every service: refusals, link errors and bugs become a Result."""
    @functools.wraps(method)
    def call(self: Any, *args: Any, **kwargs: Any) -> Result:
        try:
            result = method(self, *args, **kwargs)
        except (ValueError, RegisterError) as exc:
            result = Result.refused('bad_input', f'refused: {exc}')
        except LinkError as exc:
            if not exc.sent and isinstance(exc, LinkDown):
                result = Result.refused('offline', f'port not open: {exc}; nothing sent')
            elif exc.sent and method.__name__ not in _READS_ONLY:
                # The servo may have acted on a frame whose answer never came.
                result = Result.unknown(f'bus error: {exc}; the request had left, so whether '
                                        'the servo acted on it is UNKNOWN (read it back)',
                                        cause='no_reply')
            else:
                result = Result.failed(f'bus error: {exc}', cause='bus_error')
        except Exception as exc:  # noqa: BLE001 - a bug must not cost the node
            self.log_error(f'{method.__name__} failed:\n{traceback.format_exc()}')
            result = Result.failed(f'internal error: {exc!r}', cause='internal')
        return result.with_message(clip(result.message))
    return call


class ServoServices:
    """The services of a ServoBusCore (a mixin: it uses the core's bus, servos and loop)."""

    @_service
    def write_positions(self, names: Sequence[str], ids: Sequence[int],
                        positions: Sequence[float], move_time_ms: int,
                        staged: bool) -> Result:
        """Move servos now: one SYNC WRITE, or REG WRITE each then ACTION (staged)."""
        targets = self._resolve(names, ids, positions, move_time_ms)
        if not staged:
            # The schedule drops a queued ~/command for these servos: it is older than this.
            self.bus.call('write_positions', tuple(targets))
            return Result.sent(f'SYNC WRITE sent to {len(targets)} servo(s)')
        self._drop_pending([t[0] for t in targets])
        for servo_id, ticks, ms in targets:
            try:
                self.bus.reg_write(servo_id, proto.TARGET_POSITION_ADDRESS,
                                   proto.encode_position_payload(ticks, ms))
            except LinkTimeout:
                return Result.failed(f'servo {servo_id} did not acknowledge its REG WRITE; '
                                     'ACTION not sent, nothing moved', cause='no_reply')
        self.bus.action()  # a broadcast: no servo answers it
        return Result.sent(f'REG WRITE to {len(targets)} servo(s), then ACTION')

    @_service
    def set_torque(self, ids: Sequence[int], enable: bool) -> Result:
        """Switch torque of `ids` (empty = all), each verified by reading it back."""
        chosen = select(self.servos, ids)
        # One call of the schedule for all: it records each servo's torque as read back.
        read_back = dict(self.bus.torque([j.id for j in chosen], enable))
        failed, read_other = [], False
        for joint in chosen:
            who = f'{joint.name} (id {joint.id})'
            reply = read_back.get(joint.id)
            if reply is None:
                failed.append(f'{who} did not answer')
                continue
            back = reply.params[0] != 0
            if back != enable:
                read_other = True
                failed.append(f'{who} reads back torque {"on" if back else "off"}')
        state = 'on' if enable else 'off'
        if failed:
            # A servo that reads back the other state did not do it; one that did not answer
            # may have.
            message = f'torque {state}: ' + few(failed, 3)
            return Result.failed(message) if read_other else Result.unknown(message, 'no_reply')
        return Result.done(f'torque {state} for {len(chosen)} servo(s), verified by read-back')

    @_service
    def emergency_stop(self) -> Result:
        """Torque off, every servo at once (one broadcast); queued commands are dropped."""
        # The schedule's: ahead of everything queued, the queued commands dropped, every
        # servo's torque recorded off.
        self.bus.call('emergency_stop')
        self.log_warning('emergency stop: torque off broadcast to every servo')
        return Result.sent('torque off broadcast to every servo (id 254)')

    @_service
    def read_register(self, servo_id: int, register_name: str, address: int,
                      length: int) -> Result:
        """Read a register by name, or `length` bytes at `address`."""
        if not proto.is_servo_id(servo_id):
            raise ValueError(f'id must be 1..250 (READ cannot be broadcast), got {servo_id}')
        if register_name:
            reg = by_name(register_name)
            if not reg.readable:
                raise ValueError(f'{reg.name} is a command register (write only); '
                                 'nothing to read')
            address, length = reg.address, reg.size
        else:
            if not 1 <= length <= proto.MAX_READ_LENGTH or address + length > 256:
                raise ValueError(f'length must be 1..{proto.MAX_READ_LENGTH} and address + '
                                 f'length <= 256, got address 0x{address:02X} length {length}')
            try:
                reg = by_address(address)
                if reg.size != length or not reg.readable:
                    reg = None
            except RegisterError:
                reg = None
        reply = self.bus.read(servo_id, address, length)
        data = bytes(reply.params)
        if reg is not None:
            value = decode_value(reg, data)
            number = int.from_bytes(data, 'big', signed=reg.signed)
            text = value if isinstance(value, str) else f'{value} {reg.unit}'.strip()
            label = reg.name
        else:
            number = int.from_bytes(data, 'big') if length <= 8 else 0
            block = decode_block(address, data)
            text = ', '.join(f'{k}={v}' for k, v in block.items()) or data.hex(' ')
            label = f'{length} byte(s) at 0x{address:02X}'
        faults = proto.describe_status(reply.status)
        message = f'servo {servo_id} {label}: {text}' + (
            f' (status: {", ".join(faults)})' if faults else '')
        return Result.done(message, {'value': number, 'text': text, 'data': list(data),
                                     'status': reply.status})

    @_service
    def write_register(self, servo_id: int, register_name: str, value: int) -> Result:
        """Write a register by name (typed, range-checked); a unicast write is read back."""
        if not (proto.is_servo_id(servo_id) or servo_id == proto.BROADCAST_ID):
            raise ValueError(f'id must be 1..250 or 254 (broadcast), got {servo_id}')
        reg = by_name(register_name)
        if reg.name == ID.name:
            raise ValueError('change ids with ~/set_id (it checks the new id is free)')
        data = encode_value(reg, None if reg.address_only else int(value))
        self.bus.write(servo_id, reg.address, data)
        if servo_id == proto.BROADCAST_ID:
            return Result.sent(f'{reg.name} written to every servo (broadcast, no reply)')
        if reg.address_only or not reg.readable:
            return Result.done(f'servo {servo_id} acknowledged {reg.name}')
        back = decode_value(reg, bytes(self.bus.read(servo_id, reg.address, reg.size).params))
        if reg is TORQUE:
            for s in self._servos:
                if s.id == servo_id:
                    s.set_torque(bool(back))
        ok = back == value
        return Result.checked(ok, f'servo {servo_id} {reg.name} = {back} {reg.unit}'.strip() + (
            '' if ok else f' after writing {value} (the servo did not take it)'))

    @_service
    def scan(self, first_id: int, last_id: int) -> Result:
        """PING ids `first_id`..`last_id`; report who answers, firmware, and shared ids."""
        if not (proto.is_servo_id(first_id) and proto.is_servo_id(last_id)
                and first_id <= last_id):
            raise ValueError(f'need 1 <= first_id <= last_id <= 250, got {first_id}..{last_id}')
        with self._loop_paused():
            found = self.bus.scan(range(first_id, last_id + 1))
            shared = [i for i in found
                      if self._how_many_answer(i, values_differ=False)[0] == 'several']
            versions = []
            for servo_id in found:
                try:
                    data = bytes(self.bus.read(servo_id, FIRMWARE.address, FIRMWARE.size,
                                               retries=0 if servo_id in shared else None).params)
                    versions.append(str(decode_value(FIRMWARE, data)))
                except LinkTimeout:
                    versions.append('')
        message = (f'found {len(found)} servo(s) in {first_id}..{last_id}: '
                   + few((f'{i} ({v or "?"})' for i, v in zip(found, versions)), 20))
        if shared:
            message += (f'; more than one servo answers to id(s) {few(shared)}: connect them '
                        'one at a time and give each its own id')
        slow = [i for i in found if self.bus.margin_for(i) > self.bus.margin_s]
        if slow:
            message += (f'; id(s) {few(slow)} answer late: the driver waits up to '
                        f'{max(self.bus.margin_for(i) for i in slow) * 1000:.0f} ms for them')
        return Result.done(message, {'ids': found, 'firmware_versions': versions})

    @_service
    def go_to_preset(self, ids: Sequence[int], preset: int) -> Result:
        """Run servos to their stored preset position 1..3 (address-only WRITE)."""
        if not 1 <= preset <= len(RUN_PRESETS):
            raise ValueError(f'preset must be 1..3, got {preset}')
        chosen = select(self.servos, ids)
        failed = []
        for joint in chosen:
            try:
                self.bus.write(joint.id, RUN_PRESETS[preset - 1].address)
            except LinkTimeout:
                failed.append(f'{joint.name} (id {joint.id})')
        if failed:
            # Sent, and not acknowledged: whether they run is not known.
            return Result.unknown(f'no acknowledgement from {few(failed)}', 'no_reply')
        return Result.done(f'{len(chosen)} servo(s) running to preset {preset}')

    # -- the probes and ~/set_id: id_change's procedures, each step a call on the bus ----------

    def _carry(self, step: Any) -> Any:
        """Carry out one step of an id_change procedure on the bus (this service's thread)."""
        if isinstance(step, idc.Ask):
            wait = None
            if step.patient:
                wait = patient_wait(len(step.frame), step.nparams, self.bus.baud,
                                    self.bus.timeout_for(len(step.frame), step.nparams,
                                                         step.servo_id))
            garbled = self.bus.garbled_by_id[step.servo_id]
            try:
                return idc.Heard(self.bus.transact(step.frame, step.servo_id, step.nparams,
                                                   retries=step.retries, timeout=wait,
                                                   flush=step.flush))
            except LinkTimeout as exc:
                return idc.Heard(None, str(exc),
                                 garbled=self.bus.garbled_by_id[step.servo_id] > garbled)
            except LinkError as exc:
                return idc.Heard(None, str(exc), lost=True, left=exc.sent)
        if isinstance(step, idc.Quiet):
            time.sleep(step.seconds)  # off the bus: commands may go meanwhile
            return None
        if isinstance(step, idc.Unsolicited):
            return self.bus.unsolicited_replies(step.servo_id, step.size)
        if isinstance(step, idc.Servos):
            return self._servos
        if isinstance(step, idc.PortBack):
            return self.bus.wait_port_open(step.seconds)
        if isinstance(step, idc.Rename):
            self._set_servos(renamed(self._servos, step.old, step.new))
            return None
        raise TypeError(f'not a step of an id change: {step!r}')

    def _probe(self, steps: Any) -> Any:
        """Run a probe of id_change; a link that went down raises its LinkError here."""
        try:
            return idc.run_to_end(steps, self._carry)
        except idc.LinkLost as exc:
            error = LinkDown(str(exc))
            error.sent = exc.heard.left
            raise error from None

    def _how_many_answer(self, servo_id: int, values_differ: bool = True) -> Tuple[str, str]:
        """Return ('none' | 'one' | 'unsure' | 'several', why): id_change.how_many_answer."""
        return self._probe(idc.how_many_answer(servo_id, self.config.baud, values_differ))

    @_service
    def set_id(self, old: int, new: int) -> Result:
        """Give the servo at `old` the id `new`, if exactly one servo answers at `old`.

        The procedure is id_change.set_id, the one the bus model searches.
        """
        refusal = set_id_refusal(self._servos, old, new)
        if refusal is not None:
            raise ValueError(refusal)
        with self._loop_paused():
            result = idc.run_to_end(idc.set_id(old, new, self._servos, self.config.baud),
                                    self._carry)
        if result.cause == 'shared_id' and result.outcome == Outcome.FAILED:
            self.log_error(result.message)
        elif result.ok:
            self.log_info(result.message)
        return result

    @_service
    def factory_reset(self, servo_id: int, confirm: str) -> Result:
        """RESET one servo to its factory registers (`confirm` must be ``RESET``).

        The procedure is id_change.factory_reset, the one the bus model searches.
        """
        if confirm != 'RESET':
            raise ValueError('confirm must be exactly "RESET"; nothing sent')
        if not proto.is_servo_id(servo_id):
            raise ValueError(f'id must be 1..250 (RESET is never broadcast), got {servo_id}')
        with self._loop_paused():
            result = idc.run_to_end(idc.factory_reset(servo_id, self._configured_ids,
                                                      self.config.baud), self._carry)
        if result.cause == 'shared_id':  # done, and the factory id now has two servos
            self.log_warning(result.message)
        return result
