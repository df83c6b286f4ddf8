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
from typing import Any, Callable, Optional, Sequence, Tuple

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.link import LinkDown, LinkError, LinkTimeout
from desheng_servo_ros.registers import (by_address, by_name, decode_block, decode_value,
                                         encode_value, RegisterError)
from desheng_servo_ros.schedule import (judge_probe, patient_wait, PROBE_READS, probe_quiet_s,
                                        renamed, set_id_refusal)
from desheng_servo_ros.state import FACTORY_ID, FIRMWARE, ID, POSITION, Result, RUN_PRESETS, TORQUE
from desheng_servo_ros.units import select
from uav_serial_common.text import clip, few

# An id change or RESET whose frame left without an acknowledgement (lost, or the link dropped)
# is settled by asking the bus; a link that went down gets this long to come back for that.
SETTLE_WAIT_S = 2.0

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


def _unknown(what: str, error: LinkError, then: str) -> Result:
    """Answer an outcome the bus did not tell: never a success or refusal not seen."""
    return Result.unknown(f'UNKNOWN whether {what}: its frame left, then {error}; {then}',
                          cause='no_reply')


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
        by_id = {s.id: s for s in self._servos}
        value = b'\x01' if enable else b'\x00'
        failed, read_other = [], False
        for joint in chosen:
            who = f'{joint.name} (id {joint.id})'
            try:
                self.bus.write(joint.id, TORQUE.address, value)
                back = self.bus.read(joint.id, TORQUE.address, TORQUE.size).params[0] != 0
            except LinkTimeout:
                failed.append(f'{who} did not answer')
                continue
            if joint.id in by_id:
                by_id[joint.id].set_torque(back)
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

    def _answers(self, servo_id: int) -> str:
        """PING up to twice: 'yes', 'garbled' (something answers, not cleanly) or 'no'.

        Each waits patiently (schedule.patient_wait): its silence becomes the answer.
        """
        garbled = False
        frame = proto.encode_ping(servo_id)
        wait = patient_wait(len(frame), 0, self.bus.baud,
                            self.bus.timeout_for(len(frame), 0, servo_id))
        for _ in range(2):
            reply, mangled = self.bus.probe(frame, servo_id, 0, timeout=wait)
            if reply is not None:
                return 'yes'
            garbled = garbled or mangled
        return 'garbled' if garbled else 'no'

    def _how_many_answer(self, servo_id: int, values_differ: bool = True) -> Tuple[str, str]:
        """Return ('none' | 'one' | 'several', why): READs the present position a few times.

        The judgement is schedule.judge_probe's (BusSchedule's set_id probe uses it too).
        """
        # Replies that no READ waited for, of the READs' size only: a late reply to an earlier
        # request (a PING of the scan when the device stalled) is one reply to one request.
        unsolicited = self.bus.unsolicited_replies(servo_id, POSITION.size)
        frame = proto.encode_read(servo_id, POSITION.address, POSITION.size)
        # A second whole reply follows the first at once: the next READ waits for it to end
        # (it would collide with it on the bus). Only the first READ flushes the input: a
        # second reply later than that (the device or the reader fell behind) is then taken by
        # the next READ or counted unsolicited, never thrown away (thrown away, beside a busy
        # loop, it let set_id rename two servos at one id).
        quiet = probe_quiet_s(self.config.baud)
        values, garbled = [], 0
        for k in range(PROBE_READS):
            reply, mangled = self.bus.probe(frame, servo_id, POSITION.size, flush=k == 0)
            if reply is not None:
                values.append(int.from_bytes(reply.params, 'big'))
                time.sleep(quiet)
            elif mangled:
                garbled += 1
        return judge_probe(values, garbled,
                           self.bus.unsolicited_replies(servo_id, POSITION.size) - unsolicited,
                           values_differ)

    @_service
    def set_id(self, old: int, new: int) -> Result:
        """Give the servo at `old` the id `new`, if exactly one servo answers at `old`."""
        refusal = set_id_refusal(self._servos, old, new)
        if refusal is not None:
            raise ValueError(refusal)
        with self._loop_paused():
            taken = self._answers(new)
            if taken != 'no':
                how = '' if taken == 'yes' else ' (with a garbled reply: more than one servo?)'
                raise ValueError(f'id {new} already answers on the bus{how}; pick a free id '
                                 '(~/scan)')
            count, why = self._how_many_answer(old)
            if count == 'none':
                return Result.refused('no_servo', f'servo {old} does not answer; nothing '
                                      'changed')
            if count == 'several':
                return Result.refused('shared_id', (
                    f'more than one servo answers at id {old} ({why}): a new id would go to '
                    'all of them. Disconnect or power off all but one, then try again; nothing '
                    'changed'))
            if count == 'unsure':
                return Result.refused('lossy_bus', (
                    f'servo {old} answers, but {why}: whether it is alone at id {old} and id '
                    f'{new} is free cannot be told; nothing changed. Try again'))
            what = f'servo {old} now has id {new}'
            lost = self._send_unacknowledged(
                lambda: self.bus.write(old, ID.address, encode_value(ID, new)))
            try:
                if lost is not None and not self.bus.wait_port_open(SETTLE_WAIT_S):
                    return _unknown(what, lost, f'~/scan tells (id {new} answers if it did)')
                if self._answers(new) != 'yes':
                    if lost is None:
                        return Result.failed(f'servo {old} acknowledged but does not answer '
                                             f'at id {new}; check with ~/scan')
                    if self._answers(old) == 'yes':
                        return Result.failed(f'servo {old} did not take id {new} ({lost}): it '
                                             f'still answers at id {old}; nothing changed')
                    return _unknown(what, lost, f'neither id {old} nor {new} answers now; '
                                                'check with ~/scan')
                # Done only if it is alone there: a servo at the new id whose PING replies
                # were lost would now share it (the same probe as before the change).
                after, why = self._how_many_answer(new)
            except LinkError as exc:
                return _unknown(what, exc, f'~/scan tells (id {new} answers if it did)')
            self._rename(old, new)
            if after == 'several':
                message = (f'servo {old} took id {new}, and more than one servo answers there '
                           f'now ({why}): id {new} was taken by a servo the probe did not hear. '
                           'Connect them one at a time and give each its own id')
                self.log_error(message)
                return Result.failed(message, 'shared_id')
            if after != 'one':
                return Result.unknown(f'servo {old} answers at id {new}, but whether it is alone '
                                      f'there was not seen ({why or "no reply"}); check with '
                                      '~/scan', 'lossy_bus')
        message = f'servo {old} now answers at id {new}' + (
            '' if lost is None else f' (its acknowledgement was lost: {lost})')
        self.log_info(message)
        return Result.done(message)

    def _send_unacknowledged(self, send: Callable[[], Any]) -> Optional[LinkError]:
        """Run `send`; return None if acknowledged, the error if its frame left without one.

        An error before the frame left (the port not open) is raised: nothing was sent.
        """
        try:
            send()
        except LinkError as exc:
            if not exc.sent:
                raise
            return exc
        return None

    def _rename(self, old: int, new: int) -> None:
        self._set_servos(renamed(self._servos, old, new))

    @_service
    def factory_reset(self, servo_id: int, confirm: str) -> Result:
        """RESET one servo to its factory registers (`confirm` must be ``RESET``)."""
        if confirm != 'RESET':
            raise ValueError('confirm must be exactly "RESET"; nothing sent')
        if not proto.is_servo_id(servo_id):
            raise ValueError(f'id must be 1..250 (RESET is never broadcast), got {servo_id}')
        what = f'servo {servo_id} reset to factory settings'
        with self._loop_paused():
            taken = servo_id != FACTORY_ID and self._answers(FACTORY_ID) != 'no'
            lost = self._send_unacknowledged(lambda: self.bus.reset(servo_id))
            try:
                if lost is not None and not self.bus.wait_port_open(SETTLE_WAIT_S):
                    return _unknown(what, lost, f'~/scan tells (a reset servo answers at the '
                                                f'factory id {FACTORY_ID})')
                at_own = self._answers(servo_id) == 'yes'
                at_factory = 'no' if at_own else self._how_many_answer(FACTORY_ID)[0]
            except LinkError as exc:
                return _unknown(what, exc, '~/scan tells')
        if lost is not None:
            if at_own:
                # A servo that keeps its id on RESET (S23) or one that never got it: the bus
                # cannot tell them apart.
                return _unknown(what, lost, f'it still answers at id {servo_id}; read its '
                                            'registers with ~/read_register')
            if at_factory == 'none':
                return _unknown(what, lost, f'neither id {servo_id} nor the factory id '
                                            f'{FACTORY_ID} answers now; check with ~/scan')
            note = f' (its acknowledgement was lost: {lost})'
        else:
            note = ''
        if at_own:
            return Result.done(f'servo {servo_id} reset to factory settings (torque off)')
        give_back = (f'give it its id back with ~/set_id {FACTORY_ID} -> {servo_id}'
                     + (f' (this driver refuses that while servo_ids lists {servo_id}: run it '
                        f'without {servo_id} for the change)'
                        if servo_id in self._configured_ids else ''))
        if taken:
            owner = next((s.name for s in self._servos if s.id == FACTORY_ID), 'another servo')
            message = (f'servo {servo_id} reset to factory settings. WARNING: it now has the '
                       f'factory id {FACTORY_ID}, which {owner} already had: '
                       + ('more than one servo answers there' if at_factory == 'several' else
                          'check with ~/scan')
                       + f', and ~/set_id refuses an id more than one servo answers to. '
                       f'Disconnect {owner} (or power it off), then {give_back}')
            self.log_warning(message)
            return Result.done(message + note)
        if at_factory != 'none':
            return Result.done(f'servo {servo_id} reset to factory settings and now answers at '
                               f'the factory id {FACTORY_ID}; {give_back}{note}')
        return Result.done(f'servo {servo_id} acknowledged RESET but no longer answers')
