"""The OriginMan core's services: reads and settings of the servos, each answered with the truth.

Part of :class:`~originman_board_ros.core.OriginManCore` (``originman_board_ros.core``
assembles it; the shared state, ``_lock`` and the other threads are described there).
Threads:

* **caller threads** (a node's service threads) call the service methods: they validate and
  check the board is online (``_service``), then write, or read through the link (a lock per
  FUNCTION keeps one read outstanding; a read blocks for at most a few read timeouts).

Shares, under ``_lock``: ``_servos`` (with the poll), ``_poll_ids`` (renamed by
``set_bus_servo_id``), ``_expected_offsets`` (with the worker's settings check).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Callable, Dict, List, Sequence, Tuple

from originman_board_ros import protocol as p
from originman_board_ros.core_bus_poll import _with_values
from originman_board_ros.core_commands import _distinct, _int, _ints
from originman_board_ros.core_types import BusServoStatus, PwmServoStates, Refused
from originman_board_ros.link import BusServoFailure, LinkError
from uav_serial_common.result import Result


def _not_seen(message: str, exc: LinkError) -> Result:
    """Answer a write whose read-back failed: FAILED on the servo's failure answer (O14).

    Any other error leaves whether the write took unseen: UNKNOWN.
    """
    if isinstance(exc, BusServoFailure):
        return Result.failed(message, cause='servo_failure')
    return Result.unknown(message, cause='no_reply')


class Services:
    """The service methods of :class:`~originman_board_ros.core.OriginManCore`."""

    # -- services -------------------------------------------------------------------------------

    def _service(self, validate: Callable[[], Any]) -> Any:
        """Run ``validate`` and the online check; return its value or raise Refused."""
        value = validate()
        self._require_online()
        return value

    def _bus_ids(self, ids: Sequence[int], allow_empty: bool = False) -> List[int]:
        servo_ids = _ints('ids', list(ids), 0, p.BUS_ID_MAX)
        if not servo_ids and not allow_empty:
            raise Refused('empty', 'no bus servo given')
        _distinct('ids', servo_ids)
        return servo_ids

    def get_bus_servo_state(self, ids: Sequence[int]) -> Result[Tuple[BusServoStatus, ...]]:
        """Read every field of each servo afresh (empty ``ids``: every polled servo).

        The value holds each servo; one with a failed read has ``online`` False, and the
        message names it (O14).
        """
        try:
            servo_ids = self._service(lambda: self._bus_ids(ids, allow_empty=True)) \
                or self.bus_servo_ids
        except Refused as exc:
            return self._refuse(exc)
        states, problems = [], []
        for servo_id in servo_ids:
            values: Dict[int, p.BusValue] = {}
            error = ''
            for sub in p.BUS_READ_FORMATS:
                if sub == p.BusSub.READ_ID:
                    continue
                try:
                    values[sub] = self.link.bus_read(sub, servo_id)
                except (LinkError, p.ProtocolError) as exc:
                    error = str(exc)
                    break
            status = _with_values(BusServoStatus(servo_id, online=not error,
                                                 last_error=error), values)
            if error:
                problems.append(f'servo {servo_id}: {error}')
            states.append(status)
            with self._lock:
                if servo_id in self._servos:
                    old = self._servos[servo_id]
                    self._servos[servo_id] = replace(
                        status, failed_reads=old.failed_reads + 1 if error else 0,
                        online=old.online if error else True)
        if problems:
            return Result.failed('; '.join(problems), value=tuple(states))
        return Result.done(f'read {len(states)} servo(s)', value=tuple(states))

    def set_bus_servo_torque(self, ids: Sequence[int], enable: bool) -> Result:
        """Torque on (0x0C) or off (0x0B) for each servo (O6), checked by reading 0x0D."""
        try:
            servo_ids = self._service(lambda: self._bus_ids(ids))
        except Refused as exc:
            return self._refuse(exc)
        done, problems, unseen = [], [], False
        for servo_id in servo_ids:
            try:
                self._write(p.encode_bus_torque(servo_id, bool(enable)),
                            cancels=() if enable else (servo_id,))
                loaded = self.link.bus_read(p.BusSub.READ_LOAD, servo_id)
            except LinkError as exc:
                unseen = unseen or not isinstance(exc, BusServoFailure)
                problems.append(f'servo {servo_id}: {exc}')
                continue
            if loaded != bool(enable):
                problems.append(f'servo {servo_id}: torque reads {"on" if loaded else "off"}')
            else:
                done.append(servo_id)
        state = 'on' if enable else 'off'
        if problems:
            message = f'torque {state} for {done or "none"}; failed: ' + '; '.join(problems)
            return Result.unknown(message, 'no_reply') if unseen else Result.failed(message)
        return Result.done(f'torque {state} for {done} (read back)')

    def stop_bus_servos(self, ids: Sequence[int]) -> Result:
        """Stop servos where they are (0x03)."""
        try:
            servo_ids = self._service(lambda: self._bus_ids(ids))
        except Refused as exc:
            return self._refuse(exc)
        # Queued targets of these servos are dropped: a stop is not followed by an old move.
        return self._send_all([p.encode_bus_stop(servo_ids)], f'stop bus servos {servo_ids}',
                              cancels=servo_ids)

    def set_bus_servo_id(self, servo_id: int, new_id: int) -> Result:
        """Give a servo a new id; refused if ``new_id`` answers. Renamed in the poll list too."""
        def validate() -> Tuple[int, int]:
            old = _int('id', servo_id, 0, p.BUS_ID_MAX)
            new = _int('new_id', new_id, 0, p.BUS_ID_MAX)
            if old == new:
                raise Refused('out_of_range', f'servo {old} already has id {new}')
            return old, new
        try:
            old, new = self._service(validate)
            if self._answers(new):
                raise Refused('id_taken', f'id {new} is taken: a servo answers at it')
        except Refused as exc:
            return self._refuse(exc)
        except LinkError as exc:
            return Result.failed(f'could not check whether id {new} is free: {exc}',
                                 cause='no_reply')
        try:
            if not self._answers(old):
                return Result.refused('no_servo', f'servo {old} does not answer; nothing '
                                      'written')
            self._write(p.encode_bus_write_id(old, new), cancels=(old,))
            if not self._answers(new):
                return Result.failed(f'id {new} written to servo {old}, but nothing answers at '
                                     f'{new}')
        except LinkError as exc:
            return _not_seen(f'set id {old} -> {new}: {exc}', exc)
        with self._lock:
            if old in self._poll_ids:
                self._poll_ids[self._poll_ids.index(old)] = new
                self._servos[new] = replace(self._servos.pop(old, BusServoStatus(new)), id=new)
        return Result.done(f'servo {old} now answers at id {new}')

    def _answers(self, servo_id: int) -> bool:
        """Whether a servo answers at ``servo_id`` (raises LinkError when the board is silent)."""
        try:
            self.link.bus_read(p.BusSub.READ_POSITION, servo_id)
        except BusServoFailure:
            return False
        return True

    def set_bus_servo_offset(self, servo_id: int, offset: int, save: bool) -> Result:
        """Set a servo's deviation (-125..125), optionally saved to its flash; read back."""
        def validate() -> Tuple[int, int]:
            return (_int('id', servo_id, 0, p.BUS_ID_MAX),
                    _int('offset', offset, -p.BUS_OFFSET_MAX, p.BUS_OFFSET_MAX))
        try:
            sid, value = self._service(validate)
        except Refused as exc:
            return self._refuse(exc)
        try:
            self._write(p.encode_bus_set_offset(sid, value))
            if save:
                self._write(p.encode_bus_save_offset(sid))
            got = self.link.bus_read(p.BusSub.READ_OFFSET, sid)
        except LinkError as exc:
            return _not_seen(f'servo {sid} offset {value}: {exc}', exc)
        if got != value:
            return Result.failed(f'servo {sid} offset reads {got}, not {value}')
        return Result.done(f'servo {sid} offset {value}' + (' saved' if save else '')
                           + ' (read back)')

    def set_bus_servo_limits(self, servo_id: int, min_position: int, max_position: int,
                             min_voltage_mv: int, max_voltage_mv: int,
                             max_temperature_c: int) -> Result:
        """Set a servo's limits; a pair of zeros (or temperature 0) is left as it is (O24)."""
        def validate() -> Tuple[int, list]:
            sid = _int('id', servo_id, 0, p.BUS_ID_MAX)
            jobs = []
            lo, hi = (_int(n, v, 0, p.U16_MAX) for n, v in
                      (('min_position', min_position), ('max_position', max_position)))
            if (lo, hi) != (0, 0):
                if not 0 <= lo <= hi <= p.BUS_POSITION_MAX:
                    raise Refused('out_of_range', f'position limits need 0 <= min <= max <= '
                                                  f'{p.BUS_POSITION_MAX}, got {lo}..{hi}')
                jobs.append((p.encode_bus_set_angle_limits(sid, lo, hi),
                             p.BusSub.READ_ANGLE_LIMITS, (lo, hi), 'position limits'))
            vlo, vhi = (_int(n, v, 0, p.U16_MAX) for n, v in
                        (('min_voltage_mv', min_voltage_mv), ('max_voltage_mv', max_voltage_mv)))
            if (vlo, vhi) != (0, 0):
                if not p.BUS_VOLTAGE_MIN_MV <= vlo <= vhi <= p.BUS_VOLTAGE_MAX_MV:
                    raise Refused('out_of_range', f'voltage limits need {p.BUS_VOLTAGE_MIN_MV} '
                                                  f'<= min <= max <= {p.BUS_VOLTAGE_MAX_MV} '
                                                  f'mV, got {vlo}..{vhi}')
                jobs.append((p.encode_bus_set_voltage_limits(sid, vlo, vhi),
                             p.BusSub.READ_VOLTAGE_LIMITS, (vlo, vhi), 'voltage limits'))
            temp = _int('max_temperature_c', max_temperature_c, 0, 255)
            if temp:
                if temp > p.BUS_TEMPERATURE_LIMIT_MAX_C:
                    raise Refused('out_of_range', f'max_temperature_c must be 1..'
                                                  f'{p.BUS_TEMPERATURE_LIMIT_MAX_C}, got {temp}')
                jobs.append((p.encode_bus_set_temperature_limit(sid, temp),
                             p.BusSub.READ_TEMPERATURE_LIMIT, temp, 'temperature limit'))
            return sid, jobs
        try:
            sid, jobs = self._service(validate)
        except Refused as exc:
            return self._refuse(exc)
        if not jobs:
            return Result.done(f'servo {sid}: nothing to change (every limit is 0)')
        done = []
        for frame, sub, wanted, what in jobs:
            try:
                self._write(frame)
                got = self.link.bus_read(sub, sid)
            except LinkError as exc:
                return _not_seen(f'servo {sid} {what}: {exc}'
                                 + (f' (set before: {", ".join(done)})' if done else ''), exc)
            if got != wanted:
                return Result.failed(f'servo {sid} {what} read {got}, not {wanted}')
            done.append(what)
        return Result.done(f'servo {sid}: {", ".join(done)} set (read back)')

    def get_pwm_servo_state(self, ids: Sequence[int]) -> Result[PwmServoStates]:
        """Read pulse and offset of PWM servos 1..4 (empty ``ids``: all four)."""
        def validate() -> List[int]:
            servo_ids = _ints('ids', list(ids), 1, p.PWM_SERVO_COUNT)
            _distinct('ids', servo_ids)
            return servo_ids or list(range(1, p.PWM_SERVO_COUNT + 1))
        try:
            servo_ids = self._service(validate)
        except Refused as exc:
            return self._refuse(exc)
        pulses, offsets, problems = [], [], []
        for servo_id in servo_ids:
            try:
                pulses.append(self.link.read_pwm_pulse(servo_id))
                offsets.append(self.link.read_pwm_offset(servo_id))
            except LinkError as exc:
                pulses += [0] * (len(offsets) + 1 - len(pulses))
                offsets.append(0)
                problems.append(f'PWM servo {servo_id}: {exc}')
        states = PwmServoStates(tuple(pulses), tuple(offsets))
        if problems:
            return Result.failed('; '.join(problems), value=states)
        return Result.done(f'read PWM servos {servo_ids}', value=states)

    def set_pwm_servo_offset(self, servo_id: int, offset_us: int) -> Result:
        """Set a PWM servo's offset (-100..100 us), read back; until the next (re)connect."""
        def validate() -> Tuple[int, int]:
            return (_int('id', servo_id, 1, p.PWM_SERVO_COUNT),
                    _int('offset_us', offset_us, -p.PWM_OFFSET_MAX_US, p.PWM_OFFSET_MAX_US))
        try:
            sid, value = self._service(validate)
        except Refused as exc:
            return self._refuse(exc)
        try:
            self._write(p.encode_pwm_set_offset(sid, value))
            got = self.link.read_pwm_offset(sid)
        except LinkError as exc:
            return _not_seen(f'PWM servo {sid} offset {value} us: {exc}', exc)
        with self._lock:
            # What the board should now hold; a reset is what makes it differ (O37).
            self._expected_offsets[sid] = value
        if got != value:
            return Result.failed(f'PWM servo {sid} offset reads {got} us, not {value}')
        return Result.done(f'PWM servo {sid} offset {value} us (read back)')
