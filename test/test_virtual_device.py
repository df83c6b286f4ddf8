"""The virtual-device runner: a model behind a pty, with wire timing and wire faults."""

import threading
import time

import pytest
import serial

from uav_serial_common.process import wait_for, wait_scale
from uav_serial_common.pty_port import wire_time
from uav_serial_common.virtual_device import VirtualDeviceRunner


def echo_model(data, now):
    # Each request byte is answered by a 3-byte frame whose last byte is a checksum.
    return [bytes([0xAA, b, (0xAA + b) & 0xFF]) for b in data]


@pytest.fixture
def device(tmp_path):
    runner = VirtualDeviceRunner(str(tmp_path / 'dev'), echo_model, baud=115200).start()
    driver = serial.serial_for_url(runner.path, baudrate=115200, timeout=0.2)
    yield runner, driver
    driver.close()
    runner.stop()


def read_n(driver, n, timeout=2.0):
    data = b''
    deadline = time.monotonic() + timeout * wait_scale()
    while len(data) < n and time.monotonic() < deadline:
        data += driver.read(n - len(data))
    return data


def test_the_model_answers_each_request(device):
    runner, driver = device
    driver.write(b'\x01\x02')
    assert read_n(driver, 6) == bytes([0xAA, 1, 0xAB, 0xAA, 2, 0xAC])
    wait_for(lambda: (runner.bytes_in, runner.bytes_out) == (2, 6), 2, what='byte counters')


def test_dropped_and_corrupted_replies(device):
    runner, driver = device
    runner.faults.drop_next = 1
    runner.faults.corrupt_next = 1
    driver.write(b'\x01')
    driver.write(b'\x02')
    driver.write(b'\x03')
    got = read_n(driver, 6)
    # The first reply is lost, the second's checksum is wrong, the third is intact.
    assert got[:2] == b'\xaa\x02' and got[2] != 0xAC
    assert got[3:] == bytes([0xAA, 3, 0xAD])
    assert (runner.replies_dropped, runner.replies_corrupted) == (1, 1)


def test_garbage_goes_out_before_the_next_output(device):
    runner, driver = device
    runner.inject_garbage(b'\x00\xff\x13')
    assert read_n(driver, 3) == b'\x00\xff\x13'


def test_round2_22_6_output_goes_at_the_speed_the_driver_set_as_it_goes(tmp_path):
    # Found beside a busy loop: the device read the line's speed at the start of a tick, the
    # driver opened the port (setting its speed) and garbage was injected before the tick sent
    # it, and the device sent it reframed at the pty's default speed: 3 bytes reached the
    # driver as 1. Here the driver opens during the tick, in the model's own tick callback.
    opened = []
    go = threading.Event()

    def on_tick(now):
        if go.is_set() and not opened:
            opened.append(serial.serial_for_url(runner.path, baudrate=115200, timeout=0.2))
            runner.inject_garbage(b'\x00\xff\x13')
        return None

    runner = VirtualDeviceRunner(str(tmp_path / 'dev'), echo_model, on_tick=on_tick,
                                 baud=115200).start()
    try:
        wait_for(lambda: runner.driver_baud is not None, 5, what="the device's first tick")
        assert runner.driver_baud != 115200  # nobody set the speed yet
        go.set()
        wait_for(lambda: opened, 5, what='the driver opened in a tick')
        assert read_n(opened[0], 3) == b'\x00\xff\x13'
        assert runner.garbled_chunks == 0
    finally:
        for driver in opened:
            driver.close()
        runner.stop()


def test_a_reply_comes_no_sooner_than_request_and_reply_take_on_the_wire(tmp_path):
    with VirtualDeviceRunner(str(tmp_path / 'dev'), echo_model, baud=9600) as runner:
        with serial.serial_for_url(runner.path, baudrate=9600, timeout=0.5) as driver:
            start = time.monotonic()
            driver.write(bytes(8))
            assert len(read_n(driver, 24)) == 24
            assert time.monotonic() - start >= wire_time(8 + 24, 9600) * 0.95


def test_unplug_for_a_while_replugs_at_the_same_path(device):
    runner, driver = device
    runner.unplug(duration_s=0.2)
    with pytest.raises(serial.SerialException):
        for _ in range(5):
            driver.read(1)
    driver.close()
    wait_for(lambda: runner.port.plugged, 3, what='the automatic replug')
    with serial.serial_for_url(runner.path, baudrate=115200, timeout=0.2) as again:
        again.write(b'\x05')
        assert read_n(again, 3) == bytes([0xAA, 5, 0xAF])


def test_safety_20_a_driver_at_another_baud_sends_and_receives_garbage(tmp_path):
    # As a real UART: the device samples the driver's bits at its own speed and the driver
    # samples the device's at its own. Nothing valid gets through either way.
    heard = []

    def model(data, now):
        heard.append(bytes(data))
        return [bytes([0xAA, b, (0xAA + b) & 0xFF]) for b in data]
    with VirtualDeviceRunner(str(tmp_path / 'dev'), model, baud=9600) as runner:
        with serial.serial_for_url(runner.path, baudrate=115200, timeout=0.2) as driver:
            request = bytes.fromhex('FF FF 01 04 02 38 04 BA')
            driver.write(request)
            wait_for(lambda: heard, 2, what='the device to receive something')
            assert b''.join(heard) != request and runner.driver_baud == 115200
            expected = b''.join(bytes([0xAA, b, (0xAA + b) & 0xFF]) for b in b''.join(heard))
            got = read_n(driver, len(expected), timeout=1.0)
            assert got and got != expected
            # Counted once the chunk is written: the driver may have read it a moment before.
            wait_for(lambda: runner.garbled_chunks >= 2, 2, what='a chunk garbled each way')
            while driver.read(256):  # the rest of the garbage (timeout 0.2 s: line idle)
                pass
            # The driver sets the device's speed: from now on everything gets through.
            driver.baudrate = 9600
            heard.clear()
            driver.write(b'\x01')
            assert read_n(driver, 3) == bytes([0xAA, 1, 0xAB]) and heard == [b'\x01']


def test_a_device_without_wire_timing_ignores_the_drivers_baud(tmp_path):
    with VirtualDeviceRunner(str(tmp_path / 'dev'), echo_model, baud=0) as runner:
        with serial.serial_for_url(runner.path, baudrate=9600, timeout=0.2) as driver:
            driver.write(b'\x07')
            assert read_n(driver, 3) == bytes([0xAA, 7, 0xB1])


def test_unsolicited_output_is_faulted_when_asked_and_the_checksum_position_is_honoured(
        tmp_path):
    # A device that only talks on its own (a handset): frames AA n CHK 55, checksum before the
    # end byte.
    frames = iter([bytes([0xAA, n, 0xAA ^ n, 0x55]) for n in range(3)])
    listening = threading.Event()

    def tick(now):
        return next(frames, None) if listening.is_set() else None

    runner = VirtualDeviceRunner(str(tmp_path / 'dev'), lambda data, now: None, on_tick=tick,
                                 tick_period_s=0.05, fault_unsolicited=True,
                                 checksum_from_end=2)
    runner.faults.drop_next = 1
    runner.faults.corrupt_next = 1
    with runner:
        driver = serial.serial_for_url(runner.path, baudrate=115200, timeout=0.2)
        listening.set()
        try:
            got = read_n(driver, 8)
        finally:
            driver.close()
    # Frame 0 dropped; frame 1's checksum flipped, its end byte intact; frame 2 as sent.
    assert got[:2] == b'\xaa\x01' and got[2] != 0xAA ^ 1 and got[3] == 0x55
    assert got[4:] == bytes([0xAA, 2, 0xAA ^ 2, 0x55])
    assert (runner.replies_dropped, runner.replies_corrupted) == (1, 1)
