"""The shared serial link: reader thread, request matching, timeouts, retries, reconnect."""

import contextlib
import os
import random
import tempfile
import threading
import time

import pytest

from uav_serial_common.process import wait_for, wait_scale
from uav_serial_common.pty_port import PortUnplugged, VirtualSerialPort
from uav_serial_common.serial_link import LinkDown, LinkError, LinkTimeout, SerialLink


class LineDecoder:
    """A toy protocol for these tests: frames are newline-terminated lines."""

    def __init__(self):
        self.buffer = b''

    def feed(self, data):
        self.buffer += data
        *lines, self.buffer = self.buffer.split(b'\n')
        return lines

    def reset(self):
        self.buffer = b''


class Echo:
    """A device on a pty that answers `ask X` with `re X` and can be made silent."""

    def __init__(self, port):
        self.port = port
        self.silent = False
        self.mute = set()
        self.received = []
        self.arrivals = []
        self.running = True
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self):
        pending = b''
        while self.running:
            pending += self.port.read(timeout=0.02)
            *lines, pending = pending.split(b'\n')
            for line in lines:
                self.received.append(line)
                self.arrivals.append(time.monotonic())
                if line.startswith(b'ask ') and not self.silent and line[4:] not in self.mute:
                    try:
                        self.port.write(b're ' + line[4:] + b'\n')
                    except PortUnplugged:
                        pass  # the cable was pulled as it answered: the reply is lost

    def stop(self):
        self.running = False
        self.thread.join(2)


@pytest.fixture
def device(tmp_path):
    port = VirtualSerialPort(str(tmp_path / 'dev')).open()
    echo = Echo(port)
    yield echo
    echo.stop()
    port.close()


def make_link(path, **kwargs):
    unsolicited = []
    states = []
    link = SerialLink(path, 115200, LineDecoder(), on_frame=unsolicited.append,
                      on_connection=lambda up, why: states.append(up), **kwargs)
    link.start()
    return link, unsolicited, states


@contextlib.contextmanager
def open_link(path, **kwargs):
    """Yield (link, unsolicited frames, connection states) once the port is open; stop after."""
    link, unsolicited, states = make_link(path, **kwargs)
    try:
        assert link.wait_port_open(2)
        yield link, unsolicited, states
    finally:
        link.stop()


def test_a_reply_is_matched_to_its_request_and_others_go_to_the_handler(device):
    with open_link(device.port.path) as (link, unsolicited, _):
        device.port.write(b'hello\n')
        reply = link.request(b'ask 7\n', lambda f: f == b're 7', timeout=1.0)
        assert reply == b're 7'
        wait_for(lambda: b'hello' in unsolicited, 2, what='the unsolicited frame')
        assert b're 7' not in unsolicited
        assert link.stats.frames_in >= 2 and link.stats.bytes_out == len(b'ask 7\n')


def test_no_reply_times_out_after_the_retries_and_counts_them(device):
    with open_link(device.port.path) as (link, _, _):
        device.silent = True
        with pytest.raises(LinkTimeout):
            link.request(b'ask 1\n', lambda f: f == b're 1', timeout=0.05, retries=2)
        wait_for(lambda: device.received.count(b'ask 1') == 3, 2, what='three attempts')
        assert link.stats.timeouts == 1 and link.stats.retries == 2


def test_writing_while_the_port_is_missing_fails_at_once(tmp_path):
    link, _, _ = make_link(str(tmp_path / 'missing'))
    try:
        with pytest.raises(LinkDown):
            link.write(b'x')
        wait_for(lambda: 'no such device' in link.last_error, 2,
                 what='an open error that tells the user what is wrong')
    finally:
        link.stop()


def test_a_port_the_user_may_not_open_is_reported_with_the_dialout_hint():
    # A device node of another group, as /dev/ttyUSB0 (root:dialout, 660) is for a new user.
    # Root may open anything, so as root the attempt is made by a child that became nobody.
    directory = tempfile.mkdtemp(prefix='uav-perm-')
    os.chmod(directory, 0o755)
    port = VirtualSerialPort(os.path.join(directory, 'ttyUSB0')).open()
    os.chmod(port.device_name, 0)
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child reports through the pipe
        code = 1
        try:
            if os.geteuid() == 0:
                os.setgroups([])
                os.setgid(65534)
                os.setuid(65534)
            link, _, _ = make_link(port.path)
            try:
                wait_for(lambda: link.last_error, 5, what='an open error')
                os.write(write_end, f'{link.port_open}|{link.last_error}'.encode())
                code = 0
            finally:
                link.stop()
        finally:
            os._exit(code)
    try:
        os.close(write_end)
        with os.fdopen(read_end, 'rb') as pipe:
            report = pipe.read().decode()
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0, report
    finally:
        port.close()
        os.rmdir(directory)
    connected, message = report.split('|', 1)
    assert connected == 'False'
    assert 'permission denied' in message and 'dialout' in message and port.path in message


def test_unplug_is_noticed_and_the_link_reopens_the_same_path_after_replug(device):
    with open_link(device.port.path) as (link, _, states):
        device.port.unplug()
        wait_for(lambda: states[-1] is False, 2, what='the link to notice the unplug')
        assert not link.port_open
        device.port.replug()
        wait_for(lambda: link.port_open, 3, what='the link to reconnect')
        assert link.request(b'ask 2\n', lambda f: f == b're 2', timeout=1.0) == b're 2'
        assert states == [True, False, True]
        assert link.stats.reconnects == 1


def test_the_on_open_hook_sees_every_open_before_the_port_is_used(device):
    opened = []
    states = []

    def on_open(port):
        # Before the link reports the port open and before anything is written to it.
        opened.append((port.is_open, list(states), len(device.received)))
    link = SerialLink(device.port.path, 115200, LineDecoder(), on_frame=lambda frame: None,
                      on_connection=lambda up, why: states.append(up), on_open=on_open)
    link.start()
    try:
        assert link.wait_port_open(2)
        assert opened == [(True, [], 0)]
        device.port.unplug()
        wait_for(lambda: not link.port_open, 2, what='the unplug noticed')
        device.port.replug()
        wait_for(lambda: link.port_open, 3, what='the link to reconnect')
        assert len(opened) == 2
    finally:
        link.stop()


def test_a_failing_on_open_hook_costs_the_port_nothing(device):
    def on_open(port):
        raise OSError('no such ioctl')
    with open_link(device.port.path, on_open=on_open) as (link, _, _):
        assert link.request(b'ask 5\n', lambda f: f == b're 5', timeout=1.0) == b're 5'


def test_a_request_in_flight_fails_fast_when_the_port_goes_away(device):
    with open_link(device.port.path) as (link, _, _):
        device.silent = True
        threading.Timer(0.1, device.port.unplug).start()
        start = time.monotonic()
        with pytest.raises(LinkDown):
            link.request(b'ask 3\n', lambda f: f == b're 3', timeout=5.0)
        assert time.monotonic() - start < 4.0


def test_a_write_from_the_reader_thread_to_a_vanished_port_fails_fast_and_the_link_recovers(
        device):
    # A runtime writes its next request from the reader thread, on the reply before it (the
    # servo bus's READs). The cable pulled in between, the write finds the port gone: it fails
    # at once (the reader used to deadlock on its own lock), and the link reopens after replug.
    outcome = []

    def on_frame(frame):
        if frame == b're 1':
            device.stop()  # its select would hold the pty open a little longer
            device.port.unplug()
            try:
                link.write(b'ask 2\n')
                outcome.append('written')
            except LinkError as exc:
                outcome.append(exc)
    link = SerialLink(device.port.path, 115200, LineDecoder(), on_frame=on_frame)
    link.start()
    try:
        assert link.wait_port_open(2)
        link.write(b'ask 1\n')
        wait_for(lambda: outcome, 5, what='the write from the reader thread to end')
        assert isinstance(outcome[0], LinkDown), outcome
        assert device.received[-1] == b'ask 1'
        assert 'write failed' in link.last_error or 'cannot open' in link.last_error
        device.port.replug()
        echo = Echo(device.port)
        wait_for(lambda: link.port_open, 3, what='the link to reconnect')
        assert link.request(b'ask 4\n', lambda f: f == b're 4', timeout=1.0) == b're 4'
        echo.stop()
    finally:
        link.stop()


def test_flushing_while_bytes_arrive_is_not_taken_for_a_disconnect(tmp_path):
    # A request flushes stale input while a late reply may be coming in. When the flush empties
    # the port between the reader's select and its read, the empty read is not a lost device.
    port = VirtualSerialPort(str(tmp_path / 'dev')).open()
    link, unsolicited, states = make_link(port.path)
    streaming = threading.Event()
    streaming.set()

    def stream():
        while streaming.is_set():
            port.write(b'tick\n')
    writer = threading.Thread(target=stream, daemon=True)
    try:
        assert link.wait_port_open(2)
        writer.start()
        wait_for(lambda: unsolicited, 2, what='the stream')
        # Many flushes, however long a loaded host takes for them (a count, not a second).
        for _ in range(50_000):
            link.flush_input()
        assert states == [True] and link.port_open and link.stats.reconnects == 0, \
            link.last_error
    finally:
        streaming.clear()
        writer.join(2)
        link.stop()
        port.close()


def test_loop_url_works_for_plain_python_use():
    with open_link('loop://') as (link, unsolicited, _):
        assert link.request(b'ping\n', lambda f: f == b'ping', timeout=1.0) == b'ping'


def test_a_failing_frame_handler_does_not_stop_the_reader(device):
    def boom(frame):
        raise RuntimeError('handler bug')
    link = SerialLink(device.port.path, 115200, LineDecoder(), on_frame=boom)
    link.start()
    try:
        assert link.wait_port_open(2)
        device.port.write(b'first\n')
        assert link.request(b'ask 4\n', lambda f: f == b're 4', timeout=1.0) == b're 4'
    finally:
        link.stop()


def test_spy_url_logs_the_traffic_and_still_works(device, tmp_path):
    # spy:// wraps the port to log every byte: the link must go through its read and write.
    log = tmp_path / 'spy.txt'
    with open_link(f'spy://{device.port.path}?file={log}') as (link, _, _):
        assert link.request(b'ask 9\n', lambda f: f == b're 9', timeout=1.0) == b're 9'
    text = log.read_text()
    assert 'TX   0000  61 73 6B 20 39 0A' in text  # "ask 9\n" as it went out
    assert 'e 9.' in text  # the reply as it came in (the spy logs each read)


def test_safety_14_a_port_that_fails_any_way_is_a_link_error_and_the_reader_lives_on(tmp_path):
    # A vanished pty answers tcflush with termios.error, which is no OSError: it used to escape
    # flush_input (and with it every request) and end the servo bus's read loop for good.
    port = VirtualSerialPort(str(tmp_path / 'dev')).open()
    echo = Echo(port)
    link, _, _ = make_link(port.path, backoff_max_s=0.05)
    escaped = []
    hammering = threading.Event()
    hammering.set()

    def hammer():
        n = 0
        while hammering.is_set():
            n += 1
            try:
                link.request(f'ask {n}\n'.encode(), lambda f, n=n: f == f're {n}'.encode(),
                             timeout=0.02, flush=True)
            except (LinkDown, LinkTimeout):
                time.sleep(0.001)
            except Exception as exc:  # noqa: BLE001 - what the test is looking for
                escaped.append(repr(exc))
    worker = threading.Thread(target=hammer, daemon=True)
    rng = random.Random(14)
    try:
        assert link.wait_port_open(2)
        worker.start()
        for _ in range(25):
            time.sleep(rng.uniform(0.0, 0.03))
            port.unplug()
            # Right after the cable is pulled, before the reader has noticed.
            for _ in range(3):
                try:
                    link.flush_input()
                except LinkDown:
                    pass
            time.sleep(rng.uniform(0.0, 0.03))
            port.replug()
            wait_for(lambda: link.port_open, 3, what='the link to reconnect')
        hammering.clear()
        worker.join(5)
        assert escaped == []
        assert link.reader_alive and link.reader_error == ''

        def answered() -> bool:
            # The last replug may not be noticed yet (the link still on the old pty): it is
            # a link error until the reader reopens the port, then the request is answered.
            try:
                return link.request(b'ask x\n', lambda f: f == b're x', timeout=1.0) == b're x'
            except (LinkDown, LinkTimeout):
                return False

        wait_for(answered, 5, interval=0.05, what='a request answered after the last replug')
    finally:
        hammering.clear()
        echo.stop()
        link.stop()
        port.close()


@pytest.mark.parametrize('kind', ['directory', 'regular file', 'missing'])
def test_safety_19_a_port_that_is_no_serial_device_is_named_for_what_it_is(tmp_path, kind):
    path = tmp_path / 'port'
    if kind == 'directory':
        path.mkdir()
    elif kind == 'regular file':
        path.write_text('')
    link, _, _ = make_link(str(path))
    try:
        wait_for(lambda: link.last_error, 2, what='an open error')
        expected = {'directory': f'{path} is a directory, not a serial device',
                    'regular file': 'not a serial device',
                    'missing': 'no such device'}[kind]
        assert expected in link.last_error and not link.port_open
        assert link.reader_alive
    finally:
        link.stop()


def test_issue22_a_reply_the_reader_has_read_but_not_handed_on_is_no_timeout(device):
    """A loaded host holds the reader between reading the reply and handing it on, past the
    request's deadline: the reply came in time, so the request gets it (no timeout, no resend
    on a half-duplex line), and the wait ends as soon as the reader hands it on."""
    held = threading.Event()
    release = threading.Event()

    def slow_reader(data):
        if b're 5' in data:
            held.set()
            release.wait(5)  # the reader, descheduled with the reply in hand

    link, _, _ = make_link(device.port.path, on_rx=slow_reader)
    try:
        assert link.wait_port_open(2)
        answered = []
        sent = time.monotonic()
        asking = threading.Thread(target=lambda: answered.append(
            link.request(b'ask 5\n', lambda f: f == b're 5', timeout=1.0)))
        asking.start()
        assert held.wait(5 * wait_scale())
        # Past the request's 1-s deadline, the reader still holding the reply (a wait of
        # one more timeout at most is what a late reader is given).
        time.sleep(max(0.0, sent + 1.2 - time.monotonic()))
        assert not answered
        release.set()
        asking.join(5)
        assert answered == [b're 5']
        assert device.received.count(b'ask 5') == 1 and link.stats.timeouts == 0
    finally:
        release.set()
        link.stop()
