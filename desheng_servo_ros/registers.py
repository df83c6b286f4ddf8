"""Register table of the Desheng bus servo (section 三 of the vendor document) as data.

Where the document leaves a range as "?", the range is the raw range of the register's data type
(decision S16 in ``docs/protocols.md``); angle limits use the position range 0..4095.
"""

from __future__ import annotations

from dataclasses import dataclass
import difflib
from typing import Optional, Union

from desheng_servo_ros.protocol import POSITION_MAX, POSITION_MIN, ProtocolError


class RegisterError(ProtocolError):
    """A register name, address or value the table does not allow."""


class UnknownRegisterError(RegisterError, KeyError):
    """No register has this name or address."""

    def __str__(self) -> str:
        # KeyError would print the message wrapped in quotes.
        return str(self.args[0]) if self.args else ''


@dataclass(frozen=True)
class Register:
    """One entry of the register table.

    ``kind`` is ``uint``/``int`` (plain numbers), ``version`` (two bytes shown as ``vA.B``) or
    ``command`` (no data: writing the address alone triggers an action). ``address_only`` marks
    registers whose WRITE carries no data; ``preset_position_N`` can still be read as a number.
    """

    address: int
    name: str
    size: int
    signed: bool
    access: str
    minimum: Optional[int]
    maximum: Optional[int]
    unit: str
    default: Optional[int]
    persisted: bool
    description: str
    kind: str = 'uint'
    address_only: bool = False

    @property
    def readable(self) -> bool:
        """Whether a READ of this register returns its value."""
        return 'r' in self.access and self.size > 0

    @property
    def writable(self) -> bool:
        """Whether the host may write this register."""
        return 'w' in self.access

    @property
    def end(self) -> int:
        """First address after this register."""
        return self.address + self.size


def _u(address: int, name: str, size: int, access: str, default: Optional[int],
       description: str, *, unit: str = '', lo: int = 0, hi: Optional[int] = None,
       persisted: bool = False, address_only: bool = False) -> Register:
    top = (1 << (8 * size)) - 1 if hi is None else hi
    return Register(address, name, size, False, access, lo, top, unit, default, persisted,
                    description, 'uint', address_only)


def _command(address: int, name: str, description: str) -> Register:
    return Register(address, name, size=0, signed=False, access='w', minimum=None, maximum=None,
                    unit='', default=None, persisted=False, description=description,
                    kind='command', address_only=True)


REGISTERS: tuple[Register, ...] = (
    Register(0x03, 'firmware_version', 2, False, 'r', None, None, '', None, True,
             'Firmware version vA.B: byte 0x03 = A, byte 0x04 = B (v1.28 = 0x01 0x1C).',
             'version'),
    _u(0x05, 'id', 1, 'rw', 1, 'Servo id on the bus (254 is broadcast, never a servo id).',
       lo=1, hi=250, persisted=True),
    _u(0x06, 'stall_protection_time', 1, 'rw', 3,
       'Stall time after which the servo protects itself (releases torque, sets overload).',
       unit='s', persisted=True),
    _u(0x09, 'min_angle_limit', 2, 'rw', 0, 'Lowest target position accepted (S16).',
       unit='ticks', hi=POSITION_MAX, persisted=True),
    _u(0x0B, 'max_angle_limit', 2, 'rw', 4095, 'Highest target position accepted (S16).',
       unit='ticks', hi=POSITION_MAX, persisted=True),
    _u(0x10, 'max_torque', 2, 'rw', 800, 'Torque limit; unit not documented (raw).',
       persisted=True),
    _u(0x12, 'speed_adjust', 1, 'rw', 30, 'Speed tuning; meaning not documented (raw).',
       persisted=True),
    _u(0x13, 'unload_condition', 1, 'rw', 0,
       'Conditions that release torque; meaning not documented (raw).', persisted=True),
    Register(0x14, 'center_offset', 2, True, 'rw', -32768, 32767, 'ticks', 0, True,
             'Centre trim: positive shifts towards 4095, negative towards 0 (raw Int16 range).'),
    _u(0x16, 'preset_position_1', 2, 'rw', 2048,
       'User preset 1. Writing the address alone stores the present position.',
       unit='ticks', hi=POSITION_MAX, persisted=True, address_only=True),
    _u(0x18, 'preset_position_2', 2, 'rw', 2048,
       'User preset 2. Writing the address alone stores the present position.',
       unit='ticks', hi=POSITION_MAX, persisted=True, address_only=True),
    _u(0x1A, 'preset_position_3', 2, 'rw', 2048,
       'User preset 3. Writing the address alone stores the present position.',
       unit='ticks', hi=POSITION_MAX, persisted=True, address_only=True),
    _u(0x1C, 'motor_mode', 1, 'rw', None, 'Motor mode; values not documented (raw).',
       persisted=True),
    _u(0x1D, 'motor_direction', 1, 'rw', None, 'Motor direction; values not documented (raw).',
       persisted=True),
    _u(0x28, 'torque_enable', 1, 'rw', 0, 'Torque switch: 0 off, any other value on.'),
    _u(0x2A, 'target_position', 2, 'rw', None,
       'Target position; the servo clamps out-of-range values, we refuse them.',
       unit='ticks', lo=POSITION_MIN, hi=POSITION_MAX),
    _u(0x2C, 'run_time', 2, 'rw', 0, 'Time to reach the target; 0 = as fast as possible.',
       unit='ms'),
    _u(0x2E, 'current', 2, 'r', None, 'Motor current.', unit='mA'),
    _u(0x30, 'lock_flag', 1, 'rw', 0, 'Lock / emergency-stop flag; values not documented (raw).'),
    _u(0x38, 'present_position', 2, 'r', None, 'Present position.', unit='ticks',
       lo=POSITION_MIN, hi=POSITION_MAX),
    _u(0x3A, 'present_speed', 2, 'r', None, 'Present speed; unit not documented (raw).'),
    _command(0x3C, 'run_preset_1', 'Command: move to preset position 1 (address only).'),
    _command(0x3D, 'run_preset_2', 'Command: move to preset position 2 (address only).'),
    _command(0x3E, 'run_preset_3', 'Command: move to preset position 3 (address only).'),
    _u(0x3F, 'temperature', 1, 'r', None, 'Servo temperature.', unit='degC'),
    _u(0x40, 'reg_write_flag', 1, 'r', None,
       'REG WRITE flag; values not documented (raw; nonzero = write staged, S16).'),
    _u(0x41, 'speed_adjust_2', 2, 'rw', None,
       'Second "speed adjust" register (16 bit); meaning not documented (raw).'),
)

_BY_NAME = {reg.name: reg for reg in REGISTERS}
_BY_ADDRESS = {reg.address: reg for reg in REGISTERS}

RegisterRef = Union[Register, str]


def by_name(name: str) -> Register:
    """Return the register called ``name``; unknown names list the closest matches."""
    try:
        return _BY_NAME[name]
    except (KeyError, TypeError):
        pass
    close = difflib.get_close_matches(str(name), list(_BY_NAME), n=3, cutoff=0.5)
    hint = f'; did you mean {", ".join(close)}?' if close else f'; known: {", ".join(_BY_NAME)}'
    raise UnknownRegisterError(f'unknown register {name!r}{hint}')


def by_address(address: int) -> Register:
    """Return the register that starts at ``address``."""
    reg = _BY_ADDRESS.get(address)
    if reg is not None:
        return reg
    inside = [r for r in REGISTERS if r.address < address < r.end] if isinstance(
        address, int) else []
    if inside:
        raise UnknownRegisterError(
            f'address 0x{address:02X} is byte {address - inside[0].address + 1} of '
            f'{inside[0].name} (0x{inside[0].address:02X}); registers start at their first byte')
    shown = f'0x{address:02X}' if isinstance(address, int) else repr(address)
    raise UnknownRegisterError(f'no register at address {shown}')


def registers_in(address: int, length: int) -> list[Register]:
    """Return the value registers lying entirely inside ``address .. address + length - 1``."""
    return [r for r in REGISTERS
            if r.size > 0 and r.address >= address and r.end <= address + length]


def _resolve(reg: RegisterRef) -> Register:
    return by_name(reg) if isinstance(reg, str) else reg


def encode_value(reg: RegisterRef, value: Optional[int] = None) -> bytes:
    """Return the data bytes that WRITE sends for ``value`` (typed and range-checked).

    Address-only registers take no value and encode to ``b''``. Read-only registers refuse.
    """
    reg = _resolve(reg)
    if not reg.writable:
        raise RegisterError(f'{reg.name} (0x{reg.address:02X}) is read-only')
    if reg.address_only:
        if value is not None:
            raise RegisterError(f'{reg.name} is written with its address only '
                                '(the servo stores or runs its position itself); give no value')
        return b''
    if isinstance(value, bool):
        value = int(value)
    if not isinstance(value, int):
        raise RegisterError(f'{reg.name} takes an int, got {type(value).__name__} {value!r}')
    assert reg.minimum is not None and reg.maximum is not None
    if not reg.minimum <= value <= reg.maximum:
        unit = f' {reg.unit}' if reg.unit else ''
        raise RegisterError(f'{reg.name} must be in {reg.minimum}..{reg.maximum}{unit}, '
                            f'got {value}')
    return value.to_bytes(reg.size, 'big', signed=reg.signed)


def decode_value(reg: RegisterRef, data: bytes) -> Union[int, str]:
    """Decode the bytes READ returned for ``reg``: an int, or ``'vA.B'`` for the version."""
    reg = _resolve(reg)
    if not reg.readable:
        raise RegisterError(f'{reg.name} (0x{reg.address:02X}) cannot be read')
    if len(data) != reg.size:
        raise RegisterError(f'{reg.name} is {reg.size} bytes, got {len(data)}')
    if reg.kind == 'version':
        return format_version(data[0], data[1])
    return int.from_bytes(data, 'big', signed=reg.signed)


def format_version(major: int, minor: int) -> str:
    """Format the two firmware version bytes: ``(1, 28)`` -> ``'v1.28'`` (S17)."""
    return f'v{major}.{minor}'


def decode_block(address: int, data: bytes) -> dict[str, Union[int, str]]:
    """Decode every register lying entirely inside a READ of ``data`` at ``address``."""
    return {r.name: decode_value(r, data[r.address - address:r.end - address])
            for r in registers_in(address, len(data)) if r.readable}
