"""The pseudo-terminal helper: a raw byte pipe at a stable path that can be unplugged."""

import os
import time

import pytest
import serial

from uav_serial_common.process import wait_scale
from uav_serial_common.pty_port import VirtualSerialPort, wire_time

ALL_BYTES = bytes(range(256))


def read_exactly(reader, n, timeout=2.0):
    data = b''
    deadline = time.monotonic() + timeout * wait_scale()
    while len(data) < n and time.monotonic() < deadline:
        data += reader(n - len(data))
    return data


def test_every_byte_value_passes_unchanged_both_ways(tmp_path):
    link = str(tmp_path / 'dev')
    with VirtualSerialPort(link) as port:
        driver = serial.serial_for_url(link, baudrate=115200, timeout=0.5)
        try:
            # Control characters (XON/XOFF, ^C, CR/LF) are where a cooked tty would interfere.
            driver.write(ALL_BYTES)
            got = b''
            deadline = time.monotonic() + 2 * wait_scale()
            while len(got) < 256 and time.monotonic() < deadline:
                got += port.read(timeout=0.2)
            assert got == ALL_BYTES
            port.write(ALL_BYTES)
            assert read_exactly(driver.read, 256) == ALL_BYTES
        finally:
            driver.close()


def test_the_link_path_points_at_the_pty_and_vanishes_on_unplug(tmp_path):
    link = str(tmp_path / 'dev')
    port = VirtualSerialPort(link).open()
    try:
        assert os.path.realpath(link) == port.device_name
        port.unplug()
        assert not os.path.exists(link)
        port.replug()
        assert os.path.exists(link)
    finally:
        port.close()
    assert not os.path.lexists(link)


def test_an_open_driver_port_fails_on_unplug_and_the_path_works_again_after_replug(tmp_path):
    link = str(tmp_path / 'dev')
    port = VirtualSerialPort(link).open()
    driver = serial.serial_for_url(link, baudrate=115200, timeout=0.2)
    try:
        port.unplug()
        with pytest.raises(serial.SerialException):
            # A vanished USB adapter reports readiness with no data, like a closed pty.
            for _ in range(5):
                driver.read(1)
        driver.close()
        port.replug()
        driver = serial.serial_for_url(link, baudrate=115200, timeout=0.5)
        port.write(b'\x41\x75')
        assert read_exactly(driver.read, 2) == b'\x41\x75'
    finally:
        driver.close()
        port.close()


def test_paced_writes_take_at_least_their_wire_time(tmp_path):
    with VirtualSerialPort(str(tmp_path / 'dev')) as port:
        driver = serial.serial_for_url(port.path, baudrate=9600, timeout=0.5)
        try:
            start = time.monotonic()
            port.write(bytes(48), baud=9600)
            elapsed = time.monotonic() - start
            # A lower bound only: a loaded machine may be slower, never faster than the wire.
            assert elapsed >= wire_time(48, 9600) * 0.95
            assert read_exactly(driver.read, 48) == bytes(48)
        finally:
            driver.close()


def test_wire_time_is_ten_bits_per_byte():
    assert wire_time(12, 115200) == pytest.approx(12 * 10 / 115200)
    assert wire_time(12, 0) == 0.0


@pytest.mark.parametrize('baud', [9600, 115200, 1000000, 250000])
def test_line_baud_is_the_speed_the_driver_set_on_its_end(tmp_path, baud):
    # 250000 has no Bxxx code: pyserial sets it as a custom rate (BOTHER, termios2).
    with VirtualSerialPort(str(tmp_path / 'dev')) as port:
        driver = serial.serial_for_url(port.path, baudrate=baud, timeout=0.1)
        try:
            assert port.line_baud() == baud
            driver.baudrate = 19200
            assert port.line_baud() == 19200
        finally:
            driver.close()
    assert port.line_baud() is None  # unplugged: nobody's settings to read
