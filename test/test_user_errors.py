"""Errors a user meets are explained in /diagnostics with what to do: wrong baud, missing port."""

import random
import threading

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import pytest

from uav_serial_common.pty_port import VirtualSerialPort

# What a device sends when the baud rate is wrong looks like noise. Leaving out the first byte of
# every frame header (0x41/0x42 for the DPS-S, 0xFF for the servos) keeps it from ever forming one.
NOISE = bytes(b for b in range(256) if b not in (0x41, 0x42, 0xFF))


class NoisyDevice:
    """A pty whose device answers everything with noise, and chatters on its own too."""

    def __init__(self, path):
        self.port = VirtualSerialPort(path).open()
        self.rng = random.Random(7)
        self.running = True
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        while self.running:
            self.port.read(timeout=0.05)
            self.port.write(bytes(self.rng.choice(NOISE) for _ in range(24)))

    def close(self):
        self.running = False
        self.thread.join(2)
        self.port.close()


@pytest.fixture
def noisy(tmp_path):
    device = NoisyDevice(str(tmp_path / 'noisy'))
    yield device
    device.close()


def wait_diag(diags, name, words, timeout=15.0):
    def ok(msg):
        return any(s.name == name and s.level == DiagnosticStatus.ERROR and
                   all(w in s.message for w in words) for s in msg.status)
    msg = diags.wait(ok, timeout, what=f'ERROR {name} mentioning {words}')
    return next(s for s in msg.status if s.name == name)


def test_parachute_on_a_wrong_baud_says_to_check_the_baud_parameter(
        ros, launch, noisy, tmp_path):
    diags = ros.subscribe(DiagnosticArray, '/diagnostics')
    launch.start('parachute_node', {'port': noisy.port.path,
                                    'blackbox_dir': str(tmp_path / 'bb')},
                 ros=ros, wait_service='/parachute/deploy')
    status = wait_diag(diags, '/parachute: link', ['wrong baud rate', '`baud` parameter'])
    assert 'valid DPS-S frame' in status.message


def test_parachute_with_a_missing_port_says_so(ros, launch, tmp_path):
    diags = ros.subscribe(DiagnosticArray, '/diagnostics')
    missing = str(tmp_path / 'ttyUSB9')
    launch.start('parachute_node', {'port': missing, 'blackbox_dir': str(tmp_path / 'bb')},
                 ros=ros, wait_service='/parachute/deploy')
    wait_diag(diags, '/parachute: link', ['no such device', missing])


def test_servo_bus_on_a_wrong_baud_says_to_check_the_baud_parameter(ros, launch, noisy):
    diags = ros.subscribe(DiagnosticArray, '/diagnostics')
    launch.start('servo_bus_node', {'port': noisy.port.path, 'servo_ids': [1, 2]},
                 ros=ros, wait_service='/servo_bus/emergency_stop')
    wait_diag(diags, 'servo_bus: bus', ['not one valid reply', 'check the baud'])


def test_servo_bus_with_a_missing_port_says_so(ros, launch, tmp_path):
    diags = ros.subscribe(DiagnosticArray, '/diagnostics')
    missing = str(tmp_path / 'ttyUSB8')
    launch.start('servo_bus_node', {'port': missing, 'servo_ids': [1]},
                 ros=ros, wait_service='/servo_bus/emergency_stop')
    wait_diag(diags, 'servo_bus: bus', ['no such device', missing])


def test_handset_link_on_a_wrong_baud_says_to_check_the_baud_parameter(ros, launch, noisy):
    diags = ros.subscribe(DiagnosticArray, '/diagnostics')
    launch.start('handset_link_node', {'port': noisy.port.path, 'link_timeout_s': 0.5},
                 ros=ros, wait_topic='/handset_link/failsafe')
    status = wait_diag(diags, '/handset_link: link', ['wrong baud rate', '`baud` parameter'])
    assert status.message.startswith('link lost')


def test_handset_link_with_a_missing_port_says_so(ros, launch, tmp_path):
    diags = ros.subscribe(DiagnosticArray, '/diagnostics')
    missing = str(tmp_path / 'ttyUSB7')
    launch.start('handset_link_node', {'port': missing, 'link_timeout_s': 0.5},
                 ros=ros, wait_topic='/handset_link/failsafe')
    wait_diag(diags, '/handset_link: link', ['link lost', 'no such device', missing])
