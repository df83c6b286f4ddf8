"""The latency-timer decisions, on a fake /dev and /sys tree (issue: faster on real adapters)."""

import os

import pytest

from uav_serial_common.usb_latency import inspect_latency_timer

# A real kernel file that holds a number and refuses every write, root's included: the latency
# timer of an adapter whose driver will not let us lower it.
READ_ONLY_NUMBER = '/proc/sys/kernel/random/poolsize'


@pytest.fixture
def tree(tmp_path):
    dev = tmp_path / 'dev'
    sysfs = tmp_path / 'sys'
    (dev / 'pts').mkdir(parents=True)
    (dev / 'ttyUSB3').write_text('')
    (dev / 'pts' / '7').write_text('')
    (dev / 'ttyACM0').write_text('')
    (dev / 'ttyS1').write_text('')
    os.symlink(dev / 'ttyUSB3', dev / 'servobus')
    timer_dir = sysfs / 'bus' / 'usb-serial' / 'devices' / 'ttyUSB3'
    timer_dir.mkdir(parents=True)
    (timer_dir / 'latency_timer').write_text('16\n')
    return dev, sysfs, timer_dir / 'latency_timer'


def inspect(tree, port, **kwargs):
    dev, sysfs, _ = tree
    return inspect_latency_timer(str(dev / port), sysfs_root=str(sysfs), dev_root=str(dev),
                                 **kwargs)


def test_a_16_ms_adapter_is_lowered_through_low_latency_mode_and_gets_a_short_margin(tree):
    timer = tree[2]
    # What the FTDI kernel driver does when pyserial asks for ASYNC_LOW_LATENCY.
    report = inspect(tree, 'servobus', request_low_latency=lambda: timer.write_text('1\n'))
    assert (report.tty, report.kind, report.before_ms, report.after_ms) == \
        ('ttyUSB3', 'ftdi', 16, 1)
    assert report.changed and report.ok
    assert report.reply_margin_s() == pytest.approx(0.004)
    assert 'lowered from 16 to 1 ms (low-latency mode)' in report.summary()
    assert 'udev' not in report.summary()
    assert report.device.endswith('ttyUSB3') and '->' in report.summary()


def test_when_low_latency_mode_is_refused_the_sysfs_file_is_written(tree):
    def refuse():
        raise PermissionError(1, 'Operation not permitted')
    report = inspect(tree, 'ttyUSB3', request_low_latency=refuse)
    assert report.after_ms == 1 and report.changed
    assert 'low-latency mode refused (Operation not permitted), sysfs write' in report.action
    assert tree[2].read_text().strip() == '1'


def test_a_timer_that_cannot_be_lowered_keeps_two_periods_and_names_the_udev_rule(tree):
    timer = tree[2]
    timer.unlink()
    os.symlink(READ_ONLY_NUMBER, timer)
    period = int(open(READ_ONLY_NUMBER).read())
    report = inspect(tree, 'ttyUSB3')
    assert not report.changed and not report.ok
    assert report.reply_margin_s() == pytest.approx(2 * period / 1000 + 0.002)
    assert 'could not be lowered' in report.summary() and 'sysfs write refused' in report.action
    assert 'ATTR{latency_timer}="1"' in report.summary()


def test_turned_off_by_parameter_nothing_is_touched_and_the_margin_follows_the_timer(tree):
    report = inspect(tree, 'ttyUSB3', allow_change=False,
                     request_low_latency=lambda: pytest.fail('must not be asked'))
    assert tree[2].read_text().strip() == '16'
    assert report.reply_margin_s() == pytest.approx(0.034)
    assert 'turned off by a parameter' in report.summary() and 'udev rule' in report.summary()


def test_an_adapter_already_at_1_ms_is_left_alone(tree):
    tree[2].write_text('1\n')
    report = inspect(tree, 'servobus', request_low_latency=lambda: pytest.fail('not needed'))
    assert report.ok and not report.changed and report.reply_margin_s() == pytest.approx(0.004)


def test_ports_without_a_timer(tree):
    assert inspect(tree, 'pts/7').kind == 'pty'
    assert inspect(tree, 'pts/7').reply_margin_s() == pytest.approx(0.002)
    assert inspect(tree, 'ttyS1').kind == 'uart'
    assert inspect(tree, 'ttyACM0').reply_margin_s() == pytest.approx(0.004)
    assert inspect_latency_timer('loop://').kind == 'url'
    # A ttyUSB adapter whose driver has no timer file (CH340, CP210x): assume the FTDI default.
    (tree[0] / 'ttyUSB4').write_text('')
    unknown = inspect(tree, 'ttyUSB4')
    assert unknown.kind == 'usb' and unknown.reply_margin_s() == pytest.approx(0.034)


def test_a_port_unplugged_while_it_is_resolved_gives_a_report_not_an_exception(tree, monkeypatch):
    # The race of a flaky connector: the udev link is there when the link opens the port and
    # gone when realpath reads it (lstat saw a symlink, readlink finds nothing).
    def vanished(path, *args, **kwargs):
        raise FileNotFoundError(2, 'No such file or directory', path)
    monkeypatch.setattr(os.path, 'realpath', vanished)
    report = inspect(tree, 'servobus')
    assert report.kind == 'gone' and 'vanished' in report.summary()
    assert report.reply_margin_s() == pytest.approx(0.002)
