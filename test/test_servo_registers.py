"""Register table of the Desheng bus servo: contents, lookups, typed encoding and decoding."""

import pytest

from desheng_servo_ros import protocol as p
from desheng_servo_ros import registers as r
from desheng_servo_ros.registers import RegisterError, UnknownRegisterError

# (address, name, size, access, default, persisted) from section 三 of the vendor document.
DOCUMENT_TABLE = [
    (0x03, 'firmware_version', 2, 'r', None, True),
    (0x05, 'id', 1, 'rw', 1, True),
    (0x06, 'stall_protection_time', 1, 'rw', 3, True),
    (0x09, 'min_angle_limit', 2, 'rw', 0, True),
    (0x0B, 'max_angle_limit', 2, 'rw', 4095, True),
    (0x10, 'max_torque', 2, 'rw', 800, True),
    (0x12, 'speed_adjust', 1, 'rw', 30, True),
    (0x13, 'unload_condition', 1, 'rw', 0, True),
    (0x14, 'center_offset', 2, 'rw', 0, True),
    (0x16, 'preset_position_1', 2, 'rw', 2048, True),
    (0x18, 'preset_position_2', 2, 'rw', 2048, True),
    (0x1A, 'preset_position_3', 2, 'rw', 2048, True),
    (0x1C, 'motor_mode', 1, 'rw', None, True),
    (0x1D, 'motor_direction', 1, 'rw', None, True),
    (0x28, 'torque_enable', 1, 'rw', 0, False),
    (0x2A, 'target_position', 2, 'rw', None, False),
    (0x2C, 'run_time', 2, 'rw', 0, False),
    (0x2E, 'current', 2, 'r', None, False),
    (0x30, 'lock_flag', 1, 'rw', 0, False),
    (0x38, 'present_position', 2, 'r', None, False),
    (0x3A, 'present_speed', 2, 'r', None, False),
    (0x3C, 'run_preset_1', 0, 'w', None, False),
    (0x3D, 'run_preset_2', 0, 'w', None, False),
    (0x3E, 'run_preset_3', 0, 'w', None, False),
    (0x3F, 'temperature', 1, 'r', None, False),
    (0x40, 'reg_write_flag', 1, 'r', None, False),
    (0x41, 'speed_adjust_2', 2, 'rw', None, False),
]


def test_table_matches_the_document():
    got = [(x.address, x.name, x.size, x.access, x.default, x.persisted) for x in r.REGISTERS]
    assert got == DOCUMENT_TABLE


def test_registers_do_not_overlap_and_fit_one_read():
    ordered = sorted(r.REGISTERS, key=lambda x: x.address)
    for a, b in zip(ordered, ordered[1:]):
        assert a.end <= b.address, (a.name, b.name)
    # S10: the whole table is readable with one READ of MAX_READ_LENGTH bytes.
    assert ordered[-1].end - ordered[0].address == p.MAX_READ_LENGTH


def test_every_register_is_described_and_value_registers_have_ranges():
    for reg in r.REGISTERS:
        assert reg.description
        if reg.kind in ('uint', 'int') and reg.size:
            assert reg.minimum is not None and reg.maximum is not None, reg.name
            assert reg.minimum <= (reg.default if reg.default is not None else reg.minimum)
            assert (reg.default if reg.default is not None else reg.maximum) <= reg.maximum


def test_lookups():
    assert r.by_name('present_position').address == 0x38
    assert r.by_address(0x2A).name == 'target_position'


def test_unknown_name_lists_close_matches():
    with pytest.raises(UnknownRegisterError, match='did you mean present_position'):
        r.by_name('present_postion')
    with pytest.raises(KeyError):
        r.by_name('nonsense_register_xyz')


def test_address_inside_a_register_is_explained():
    with pytest.raises(UnknownRegisterError, match='byte 2 of target_position'):
        r.by_address(0x2B)
    with pytest.raises(UnknownRegisterError, match='no register at address 0x07'):
        r.by_address(0x07)


@pytest.mark.parametrize('name, value, data', [
    ('id', 1, b'\x01'),
    ('id', 250, b'\xfa'),
    ('target_position', 2000, b'\x07\xd0'),
    ('run_time', 1000, b'\x03\xe8'),
    ('center_offset', -1, b'\xff\xff'),
    ('center_offset', 300, b'\x01\x2c'),
    ('torque_enable', True, b'\x01'),
    ('max_torque', 800, b'\x03\x20'),
])
def test_encode_value(name, value, data):
    assert r.encode_value(name, value) == data
    assert r.encode_value(r.by_name(name), value) == data


@pytest.mark.parametrize('name, value', [
    ('id', 0), ('id', 251), ('id', 254),
    ('target_position', 4096), ('target_position', -1),
    ('min_angle_limit', 5000), ('run_time', 65536),
    ('center_offset', 40000), ('stall_protection_time', 256),
    ('torque_enable', 1.0), ('run_time', '100'), ('run_time', None),
])
def test_encode_value_refuses_out_of_range_or_wrong_type(name, value):
    with pytest.raises(RegisterError, match=name):
        r.encode_value(name, value)


@pytest.mark.parametrize('name', ['firmware_version', 'current', 'present_position',
                                  'present_speed', 'temperature', 'reg_write_flag'])
def test_read_only_registers_refuse_writes(name):
    with pytest.raises(RegisterError, match='read-only'):
        r.encode_value(name, 0)


@pytest.mark.parametrize('name', ['preset_position_1', 'preset_position_3', 'run_preset_2'])
def test_address_only_registers_encode_to_nothing_and_refuse_a_value(name):
    assert r.encode_value(name) == b''
    with pytest.raises(RegisterError, match='address only'):
        r.encode_value(name, 1000)


def test_address_only_write_frame_for_preset():
    reg = r.by_name('run_preset_1')
    assert p.encode_write(1, reg.address, r.encode_value(reg)) == bytes.fromhex('FFFF0103033CBC')


def test_decode_firmware_version_as_string():
    assert r.decode_value('firmware_version', b'\x01\x1c') == 'v1.28'
    assert r.decode_value('firmware_version', b'\x02\x05') == 'v2.5'


def test_decode_values():
    assert r.decode_value('present_position', b'\x07\xff') == 0x07FF
    assert r.decode_value('center_offset', b'\xff\x9c') == -100
    assert r.decode_value('preset_position_2', b'\x08\x00') == 2048


def test_decode_refuses_wrong_length_and_write_only():
    with pytest.raises(RegisterError, match='2 bytes'):
        r.decode_value('present_position', b'\x07')
    with pytest.raises(RegisterError, match='cannot be read'):
        r.decode_value('run_preset_1', b'')


def test_decode_block_of_telemetry_read():
    # One READ of 0x2E..0x3F: current, lock flag, position, speed, temperature; gaps skipped.
    data = bytearray(0x40 - 0x2E)
    data[0:2] = (120).to_bytes(2, 'big')
    data[0x38 - 0x2E:0x3A - 0x2E] = (1234).to_bytes(2, 'big')
    data[0x3F - 0x2E] = 41
    block = r.decode_block(0x2E, bytes(data))
    assert block == {'current': 120, 'lock_flag': 0, 'present_position': 1234,
                     'present_speed': 0, 'temperature': 41}


def test_register_error_is_a_protocol_error():
    with pytest.raises(p.ProtocolError):
        r.encode_value('id', 0)
