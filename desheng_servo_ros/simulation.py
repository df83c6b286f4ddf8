"""Plain-Python model of a bus of Desheng servos: request bytes in, reply bytes out.

No I/O, no threads, no ROS and no clock: every call that lets time pass takes ``now`` (seconds,
any monotonic origin) from the caller, so runs are deterministic. Faults of the wire (lost,
corrupted, late replies, noise) are the runner's
(:class:`uav_serial_common.virtual_device.WireFaults`), the same for every device.

Behaviour where the vendor document is silent is listed as decisions S13.. in
``docs/protocols.md``.
"""

from __future__ import annotations

import math
import random
from typing import Iterable, Optional, Union

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.protocol import Instruction, Request, StreamDecoder
from desheng_servo_ros.registers import by_name, decode_value, Register, REGISTERS, registers_in
from uav_serial_common.uart import collide

# S20: run time 0 means "as fast as possible": 60 degrees (4096 / 6 ticks) in 0.2 s.
MAX_SPEED_TICKS_PER_S = 4096 / 6 / 0.2
# Current model (mA). Unpowered logic draws a little; moving costs more the faster it goes.
IDLE_CURRENT_MA = 5
HOLD_CURRENT_MA = 40
MOVE_CURRENT_MA = 120
MOVE_CURRENT_MA_PER_TICK_S = 0.12
STALL_CURRENT_MA = 1500
# Thermal model: first order towards ambient + HEATING_C_PER_MA * current.
AMBIENT_C = 25.0
HEATING_C_PER_MA = 0.02
THERMAL_TIME_CONSTANT_S = 60.0
OVER_TEMPERATURE_LIMIT_C = 70.0
DEFAULT_FIRMWARE = (1, 28)
START_POSITION = 2048
# S24: servos sharing an id answer together; each reply after the first starts up to this many
# bit times late (firmware latency jitter), and the wire carries the AND of them.
COLLISION_JITTER_BITS = 2.0

_POSITION_BLOCK_END = proto.TARGET_POSITION_ADDRESS + proto.POSITION_PAYLOAD_LENGTH
_PRESET_STORE = {0x16: 'preset_position_1', 0x18: 'preset_position_2', 0x1A: 'preset_position_3'}
_PRESET_RUN = {0x3C: 'preset_position_1', 0x3D: 'preset_position_2', 0x3E: 'preset_position_3'}
# Values the servo computes itself; host writes to them are ignored (S14).
_LIVE = {'firmware_version', 'current', 'present_position', 'present_speed', 'temperature',
         'reg_write_flag'}
_STORED = [r for r in REGISTERS if r.size > 0 and r.name not in _LIVE]
_PERSISTED = {r.name for r in _STORED if r.persisted}


def factory_values(position_ticks: int = START_POSITION) -> dict[str, int]:
    """Return the stored register values of a servo fresh from the factory (S16)."""
    values = {r.name: (r.default if r.default is not None else 0) for r in _STORED}
    values['target_position'] = position_ticks
    return values


class SimServo:
    """One simulated servo: its register file and a simple motion/electrical/thermal model.

    Read its state through the properties or :meth:`register`; change it through the bus
    (:meth:`ServoBusSim.feed`) or the fault hooks of :class:`ServoBusSim`.
    """

    def __init__(self, servo_id: int, now: float, *, position_ticks: int = START_POSITION,
                 firmware_version: tuple[int, int] = DEFAULT_FIRMWARE,
                 ambient_c: float = AMBIENT_C) -> None:
        self.values = factory_values(position_ticks)
        self.values['id'] = servo_id
        self.firmware_version = firmware_version
        self.ambient_c = ambient_c
        self.position = float(position_ticks)
        self.temperature_c = ambient_c
        self.stalled = False
        self.stall_elapsed_s = 0.0
        self.overload = False
        self.voltage_fault = False
        self.extra_heat_c = 0.0
        self.over_temperature_limit_c = OVER_TEMPERATURE_LIMIT_C
        self.pending: Optional[tuple[int, bytes]] = None
        self._speed = 0.0
        self._time = now

    # ----- state as the host would see it ---------------------------------------------------

    @property
    def servo_id(self) -> int:
        """Present bus id."""
        return self.values['id']

    @property
    def torque_enabled(self) -> bool:
        """Whether the motor is driven."""
        return self.values['torque_enable'] != 0

    @property
    def locked(self) -> bool:
        """Whether the lock (emergency stop) flag is set (S19)."""
        return self.values['lock_flag'] != 0

    @property
    def position_ticks(self) -> int:
        """Present position as reported (rounded, 0..4095)."""
        return min(proto.POSITION_MAX, max(proto.POSITION_MIN, int(round(self.position))))

    @property
    def moving(self) -> bool:
        """Whether the horn is turning right now."""
        return (self.torque_enabled and not self.stalled and self._speed > 0
                and self.position != self.values['target_position'])

    @property
    def speed_ticks_per_s(self) -> float:
        """Present speed magnitude in ticks per second (what register 0x3A reports, S20)."""
        return self._speed if self.moving else 0.0

    @property
    def current_ma(self) -> float:
        """Present motor current in mA."""
        if not self.torque_enabled:
            return IDLE_CURRENT_MA
        if self.stalled:
            return STALL_CURRENT_MA
        if self.moving:
            return MOVE_CURRENT_MA + MOVE_CURRENT_MA_PER_TICK_S * self._speed
        return HOLD_CURRENT_MA

    @property
    def over_temperature(self) -> bool:
        """Whether the temperature is above the limit (status bit 2)."""
        return self.temperature_c > self.over_temperature_limit_c

    @property
    def status(self) -> int:
        """Status byte sent in every reply (S4)."""
        return ((proto.STATUS_OVERLOAD if self.overload else 0)
                | (proto.STATUS_OVER_TEMPERATURE if self.over_temperature else 0)
                | (proto.STATUS_VOLTAGE_FAULT if self.voltage_fault else 0))

    def read(self, address: int, length: int) -> bytes:
        """Return ``length`` bytes of the register file from ``address`` (gaps read 0, S14)."""
        image = bytearray(256)
        live = {
            'current': int(round(self.current_ma)),
            'present_position': self.position_ticks,
            'present_speed': int(round(self.speed_ticks_per_s)),
            'temperature': min(255, max(0, int(round(self.temperature_c)))),
            'reg_write_flag': 1 if self.pending else 0,
        }
        for reg in REGISTERS:
            if reg.size == 0:
                continue
            if reg.kind == 'version':
                image[reg.address:reg.end] = bytes(self.firmware_version)
                continue
            value = live[reg.name] if reg.name in live else self.values[reg.name]
            image[reg.address:reg.end] = value.to_bytes(reg.size, 'big', signed=reg.signed)
        return bytes(image[address:address + length])

    def register(self, name: str) -> Union[int, str]:
        """Return a register's value exactly as a READ of it would decode."""
        reg = by_name(name)
        return decode_value(reg, self.read(reg.address, reg.size))

    # ----- host commands --------------------------------------------------------------------

    def write(self, address: int, data: bytes) -> None:
        """Apply a WRITE (or an executed REG WRITE / SYNC WRITE entry) at the present time."""
        if address in _PRESET_STORE:
            # S12: the servo stores where it is; any data bytes are ignored.
            self.values[_PRESET_STORE[address]] = self.position_ticks
            return
        if address in _PRESET_RUN:
            self._set_target(self.values[_PRESET_RUN[address]])
            return
        target: Optional[int] = None
        for reg in registers_in(address, len(data)):
            if reg.name in _LIVE or reg.address_only or reg.kind == 'version':
                continue
            raw = data[reg.address - address:reg.end - address]
            value = int.from_bytes(raw, 'big', signed=reg.signed)
            if reg.name == 'target_position':
                target = value
            else:
                self._set_value(reg, value)
        if target is not None:
            self._set_target(target)

    def reg_write(self, address: int, data: bytes) -> None:
        """Stage a write until ACTION; only the position block 0x2A..0x2D is honoured (S18)."""
        if address == proto.TARGET_POSITION_ADDRESS and address + len(data) <= _POSITION_BLOCK_END:
            self.pending = (address, bytes(data))

    def action(self) -> None:
        """Execute the staged REG WRITE, if any."""
        if self.pending is not None:
            address, data = self.pending
            self.pending = None
            self.write(address, data)

    def factory_reset(self, keep_id: bool) -> None:
        """RESET: every stored register back to its factory value (S23)."""
        servo_id = self.servo_id
        self.values = factory_values(self.position_ticks)
        if keep_id:
            self.values['id'] = servo_id
        self._clear_runtime()

    def power_cycle(self) -> None:
        """Lose the RAM registers, keep the persisted ones."""
        kept = {k: v for k, v in self.values.items() if k in _PERSISTED}
        self.values = factory_values(self.position_ticks)
        self.values.update(kept)
        self._clear_runtime()

    def _clear_runtime(self) -> None:
        self.pending = None
        self.overload = False
        self.stall_elapsed_s = 0.0
        self._speed = 0.0

    def _set_value(self, reg: Register, value: int) -> None:
        name = reg.name
        if name == 'id':
            if not proto.is_servo_id(value):
                return
        elif name in ('min_angle_limit', 'max_angle_limit'):
            value = min(value, proto.POSITION_MAX)
        elif name == 'torque_enable':
            self._set_torque(value)
            return
        elif name == 'lock_flag' and value and not self.locked:
            # S19: emergency stop holds where it is.
            self.values['target_position'] = self.position_ticks
            self._speed = 0.0
        self.values[name] = value

    def _set_torque(self, value: int) -> None:
        was_on = self.torque_enabled
        self.values['torque_enable'] = value
        if value:
            # S21: re-enabling torque is how the host acknowledges an overload.
            self.overload = False
            self.stall_elapsed_s = 0.0
            if not was_on:
                # S19: hold where it is rather than jump to a stale target.
                self.values['target_position'] = self.position_ticks
                self._speed = 0.0
        else:
            self.stall_elapsed_s = 0.0

    def _set_target(self, value: int) -> None:
        if self.locked:
            return
        lo, hi = sorted((self.values['min_angle_limit'], self.values['max_angle_limit']))
        target = min(hi, max(lo, value))
        self.values['target_position'] = target
        distance = abs(target - self.position)
        run_time_s = self.values['run_time'] / 1000.0
        if run_time_s <= 0 or distance == 0:
            self._speed = MAX_SPEED_TICKS_PER_S
        else:
            self._speed = min(MAX_SPEED_TICKS_PER_S, distance / run_time_s)

    def set_position(self, position_ticks: float) -> None:
        """Force the horn to ``position_ticks`` (an external hand); torque on drives it back."""
        self.position = float(min(proto.POSITION_MAX, max(proto.POSITION_MIN, position_ticks)))
        if self.torque_enabled:
            self._speed = MAX_SPEED_TICKS_PER_S

    # ----- physics --------------------------------------------------------------------------

    def advance(self, now: float) -> None:
        """Integrate motion, stall protection and temperature up to ``now`` (exactly, no steps)."""
        t = self._time
        while t < now:
            end = now
            moving = self.moving
            target = self.values['target_position']
            arrive = trip = math.inf
            if moving:
                arrive = t + abs(target - self.position) / self._speed
                end = min(end, arrive)
            stalling = self.stalled and self.torque_enabled
            if stalling:
                protect_s = float(self.values['stall_protection_time'])
                trip = t + max(0.0, protect_s - self.stall_elapsed_s)
                end = min(end, trip)
            dt = end - t
            self._heat(dt)
            # Events are decided by time, not by accumulated floats, so the loop always ends.
            if moving:
                if end >= arrive:
                    self.position = float(target)
                else:
                    step = min(self._speed * dt, abs(target - self.position))
                    self.position += math.copysign(step, target - self.position)
            if stalling:
                self.stall_elapsed_s += dt
                if end >= trip:
                    self._trip()
            t = end
        self._time = max(self._time, now)
        if self.stalled and self.torque_enabled and (
                self.stall_elapsed_s >= self.values['stall_protection_time']):
            # A protection time of 0 trips without any time passing.
            self._trip()

    def _trip(self) -> None:
        # S21: protection trips: torque released, overload latched.
        self.values['torque_enable'] = 0
        self.overload = True
        self.stall_elapsed_s = 0.0

    def _heat(self, dt: float) -> None:
        if dt <= 0:
            return
        equilibrium = self.ambient_c + self.extra_heat_c + HEATING_C_PER_MA * self.current_ma
        decay = math.exp(-dt / THERMAL_TIME_CONSTANT_S)
        self.temperature_c = equilibrium + (self.temperature_c - equilibrium) * decay


class ServoBusSim:
    """A half-duplex bus of simulated servos driven by the host's request bytes.

    ``feed(data, now)`` decodes requests (any split, any garbage) and returns the reply frames
    the servos put on the wire. Servos that share an id answer at once and their replies collide
    (S24): what comes out is what the host's UART reads from the mix, mostly a garbled frame.
    ``collisions=False`` returns each reply whole instead, in bus order (a bus that keeps them
    apart); ``seed`` makes the collisions' timing repeatable.
    """

    def __init__(self, ids: Iterable[int] = (1, 2, 3), *, now: float = 0.0,
                 firmware_version: tuple[int, int] = DEFAULT_FIRMWARE,
                 ambient_c: float = AMBIENT_C,
                 over_temperature_limit_c: float = OVER_TEMPERATURE_LIMIT_C,
                 reset_keeps_id: bool = False, collisions: bool = True,
                 seed: Optional[int] = 0) -> None:
        self.decoder = StreamDecoder('request')
        self.firmware_version = firmware_version
        self.ambient_c = ambient_c
        self.over_temperature_limit_c = over_temperature_limit_c
        self.reset_keeps_id = reset_keeps_id
        self.collisions = collisions
        self._rng = random.Random(seed)
        self.requests_handled = 0
        self.resets = 0  # RESETs a servo heard and carried out (each servo of an id counts)
        self.requests_ignored = 0
        self.replies_sent = 0
        self.replies_collided = 0
        self._now = now
        self.servos: list[SimServo] = []
        for servo_id in ids:
            self.add_servo(servo_id)

    # ----- bus ------------------------------------------------------------------------------

    @property
    def now(self) -> float:
        """Time of the latest advance."""
        return self._now

    @property
    def ids(self) -> list[int]:
        """Ids of the servos on the bus, in bus order (duplicates possible after an id clash)."""
        return [s.servo_id for s in self.servos]

    def servo(self, servo_id: int) -> SimServo:
        """Return the (first) servo with ``servo_id``."""
        for s in self.servos:
            if s.servo_id == servo_id:
                return s
        raise KeyError(f'no servo {servo_id} on the bus (present: {self.ids})')

    def advance(self, now: float) -> None:
        """Let time pass up to ``now``; an earlier ``now`` than before is ignored."""
        if now <= self._now:
            return
        for s in self.servos:
            s.advance(now)
        self._now = now

    def feed(self, data: bytes, now: float) -> list[bytes]:
        """Advance to ``now``, then handle every request completed by ``data``; return replies."""
        self.advance(now)
        replies: list[bytes] = []
        for request in self.decoder.feed(data):
            for reply in self._handle(request):
                self.replies_sent += 1
                replies.append(reply)
        return replies

    def _handle(self, req: Request) -> list[bytes]:
        instr, params, broadcast = req.instruction, req.params, req.is_broadcast
        if broadcast:
            targets = list(self.servos)
        else:
            targets = [s for s in self.servos if s.servo_id == req.servo_id]
        answer = not broadcast
        if instr in (Instruction.PING, Instruction.READ, Instruction.REG_WRITE) and broadcast:
            return self._ignore()
        if instr in (Instruction.ACTION, Instruction.SYNC_WRITE) and not broadcast:
            return self._ignore()
        data = b''
        if instr == Instruction.READ:
            address, length = params[0], params[1]
            if not 1 <= length <= proto.MAX_READ_LENGTH or address + length > 256:
                return self._ignore()
        elif instr == Instruction.WRITE:
            for s in targets:
                s.write(params[0], params[1:])
        elif instr == Instruction.REG_WRITE:
            for s in targets:
                s.reg_write(params[0], params[1:])
        elif instr == Instruction.ACTION:
            for s in targets:
                s.action()
        elif instr == Instruction.RESET:
            for s in targets:
                s.factory_reset(self.reset_keeps_id)
                self.resets += 1
        elif instr == Instruction.SYNC_WRITE:
            try:
                address, length, items = proto.parse_sync_write(params)
            except proto.ProtocolError:
                return self._ignore()
            if address != proto.TARGET_POSITION_ADDRESS or address + length > _POSITION_BLOCK_END:
                return self._ignore()
            for servo_id, item in items:
                for s in self.servos:
                    if s.servo_id == servo_id:
                        s.write(address, item)
        self.requests_handled += 1
        if not answer:
            return []
        replies = []
        for s in targets:
            s.advance(self._now)  # settle instantaneous events (a stall trip) before answering
            if instr == Instruction.READ:
                data = s.read(params[0], params[1])
            # S15: the reply carries the id the request was addressed to.
            replies.append(proto.encode_reply(req.servo_id, s.status, data))
        if len(replies) > 1 and self.collisions:
            # S24: two servos answering one id drive the wire at once.
            self.replies_collided += len(replies)
            offsets = [0.0] + [self._rng.uniform(0.0, COLLISION_JITTER_BITS)
                               for _ in replies[1:]]
            return [collide(replies, offsets)]
        return replies

    def _ignore(self) -> list[bytes]:
        self.requests_ignored += 1
        return []

    # ----- scenario and fault hooks (they act at the time of the latest advance) -----------

    def add_servo(self, servo_id: int, *, position_ticks: int = START_POSITION,
                  allow_duplicate: bool = False) -> SimServo:
        """Connect a factory-fresh servo with ``servo_id`` (torque off) to the bus."""
        if not proto.is_servo_id(servo_id):
            raise ValueError(f'servo id must be 1..250, got {servo_id!r}')
        if not allow_duplicate and servo_id in self.ids:
            raise ValueError(f'servo {servo_id} is already on the bus')
        s = SimServo(servo_id, self._now, position_ticks=position_ticks,
                     firmware_version=self.firmware_version, ambient_c=self.ambient_c)
        s.over_temperature_limit_c = self.over_temperature_limit_c
        self.servos.append(s)
        return s

    def remove_servo(self, servo_id: int) -> None:
        """Disconnect every servo answering to ``servo_id``; it falls silent."""
        if servo_id not in self.ids:
            raise KeyError(f'no servo {servo_id} on the bus (present: {self.ids})')
        self.servos = [s for s in self.servos if s.servo_id != servo_id]

    def stall(self, servo_id: int, active: bool = True) -> None:
        """Block (or free) a servo's horn: high current, then protection after the stall time."""
        s = self.servo(servo_id)
        s.stalled = active
        if not active:
            s.stall_elapsed_s = 0.0
        # Protection time 0 trips at once, not at the next advance.
        s.advance(self._now)

    def overheat(self, servo_id: int, temperature_c: float = 80.0) -> None:
        """Heat a servo to ``temperature_c`` and keep it at least that hot until :meth:`cool`."""
        s = self.servo(servo_id)
        s.extra_heat_c = temperature_c - s.ambient_c
        s.temperature_c = float(temperature_c)

    def cool(self, servo_id: int) -> None:
        """Remove the heat added by :meth:`overheat`; the servo cools with its time constant."""
        self.servo(servo_id).extra_heat_c = 0.0

    def set_over_temperature_limit(self, limit_c: float, servo_id: Optional[int] = None) -> None:
        """Change the temperature above which status bit 2 is set (all servos by default)."""
        for s in self._select(servo_id):
            s.over_temperature_limit_c = limit_c
        if servo_id is None:
            self.over_temperature_limit_c = limit_c

    def set_voltage_fault(self, active: bool = True, servo_id: Optional[int] = None) -> None:
        """Set or clear the voltage fault (status bit 0); all servos by default (shared supply)."""
        for s in self._select(servo_id):
            s.voltage_fault = active

    def move_by_hand(self, servo_id: int, position_ticks: float) -> None:
        """Turn a servo's horn from outside, e.g. before storing a preset position."""
        self.servo(servo_id).set_position(position_ticks)

    def power_cycle(self, servo_id: Optional[int] = None) -> None:
        """Power-cycle servos: RAM registers reset, persisted ones kept, torque off."""
        for s in self._select(servo_id):
            s.power_cycle()

    def _select(self, servo_id: Optional[int]) -> list[SimServo]:
        if servo_id is None:
            return list(self.servos)
        return [s for s in self.servos if s.servo_id == servo_id] or [self.servo(servo_id)]
