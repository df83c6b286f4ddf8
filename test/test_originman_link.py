"""OriginManLink on a real pty against the board model: reports, matched reads, timeouts."""

import threading

from originman_board_ros import protocol as p
from originman_board_ros.link import (BusServoFailure, LinkDown, LinkTimeout, OriginManLink,
                                      READ_TIMEOUT_S)
from originman_board_ros.protocol import BusSub
from originman_rig import VirtualBoard
import pytest
from uav_serial_common.process import wait_for, wait_scale

# The board model shares this process (and its GIL) with the test: a wide reply window keeps
# a scheduling hiccup from looking like a lost reply. Timeout tests set their own.
RIG_TIMEOUT_S = 0.25


@pytest.fixture
def rig(tmp_path):
    board = VirtualBoard(str(tmp_path / 'board'), battery_period_s=0.2).start()
    reports = []
    link = OriginManLink(board.path, on_report=lambda m: reports.append(
        (threading.current_thread().name, m)), timeout_s=RIG_TIMEOUT_S)
    link.start()
    try:
        assert link.wait_port_open(5 * wait_scale())
        yield board, link, reports
    finally:
        link.stop()
        board.stop()


def quiet(board):
    """No IMU stream and no battery reports: the replies are alone on the wire."""
    with board.locked():
        board.model.set_imu(rate_hz=0)
        board.model.set_battery_period(1000.0)


def test_o20_the_link_defaults_to_1_mbaud_and_a_50_ms_read_timeout(tmp_path):
    link = OriginManLink(str(tmp_path / 'none'))
    assert (link.baud, link.timeout_s, READ_TIMEOUT_S) == (1_000_000, 0.1, 0.1)


def test_reports_reach_the_callback_from_the_reader_thread(rig):
    board, link, reports = rig
    with board.locked():
        board.model.press_key(2, 'click')
        board.model.set_sbus([1000] * 16)
        board.model.send_asr()
    kinds = {p.ImuReport, p.BatteryReport, p.KeyReport, p.SbusReport, p.AsrReport}
    wait_for(lambda: kinds <= {type(m) for _, m in list(reports)}, 5,
             what='IMU, battery, key, SBUS and ASR reports')

    def keys():
        return [m.event for _, m in list(reports) if isinstance(m, p.KeyReport)]
    wait_for(lambda: len(keys()) == 3, 5, what='the three events of a click')
    assert keys() == [p.KeyEvent.PRESSED, p.KeyEvent.RELEASE_FROM_SHORT_PRESS, p.KeyEvent.CLICK]
    assert {name for name, _ in list(reports)} == {f'serial-reader {board.path}'}
    assert link.last_frame_time is not None and link.decoder.checksum_errors == 0


def test_bus_reads_return_the_addressed_servos_values(rig):
    board, link, _ = rig
    with board.locked():
        board.model.bus_servo(2).set_by_hand(-20, board.model.now)
        board.model.bus_servo(3).temperature_c = 51
    assert link.bus_read(BusSub.READ_POSITION, 2) == -20
    assert link.bus_read(BusSub.READ_TEMPERATURE, 3) == 51
    assert link.bus_read(BusSub.READ_ANGLE_LIMITS, 1) == (0, 1000)
    assert link.bus_read(BusSub.READ_LOAD, 1) is False


def test_o14_o41_a_failed_read_raises_at_once_and_never_gives_a_value(rig):
    board, link, _ = rig
    mark = board.mark()
    with pytest.raises(BusServoFailure) as info:
        link.bus_read(BusSub.READ_POSITION, 9)
    # The board's answer is final: not retried like a missing reply.
    wait_for(lambda: board.commands(mark), 5, what='the request on the wire')
    assert board.commands(mark) == [p.BusRead(BusSub.READ_POSITION, 9)]
    assert (info.value.servo_id, info.value.sub, info.value.success) == (9, 5, -1)
    assert 'no valid answer' in info.value.reason
    assert link.read_failures == 1 and link.read_timeouts == 0


def test_pwm_reads_return_pulse_and_offset(rig):
    board, link, _ = rig
    link.send(p.encode_pwm_set_offset(4, -30))
    link.send(p.encode_pwm_move(20, [(4, 700)]))
    assert link.read_pwm_offset(4) == -30
    wait_for(lambda: link.read_pwm_pulse(4) == 700, 5, what='the PWM servo at 700 us')


def test_o41_a_lost_or_corrupted_reply_is_retried(rig):
    board, link, _ = rig
    quiet(board)
    retries = link.serial.stats.retries
    board.runner.faults.drop_next = 1
    assert link.read_pwm_pulse(1) == 1500
    board.runner.faults.corrupt_next = 1
    assert link.read_pwm_pulse(2) == 1500
    assert link.serial.stats.retries == retries + 2
    assert link.decoder.checksum_errors == 1


def test_a_silent_board_times_out_after_every_retry(rig):
    board, link, _ = rig
    with board.locked():
        board.model.power_off()
    mark = board.mark()
    with pytest.raises(LinkTimeout):
        link.bus_read(BusSub.READ_VOLTAGE, 1, timeout=0.05, retries=2)
    # The last retry's frame is on its way when its wait ends: a board thread that a loaded
    # host starves logs it later (campaign s14c, run 4: two of three seen at once).
    wait_for(lambda: len(board.commands(mark)) >= 3, 5, what='the three frames at the board')
    assert board.commands(mark) == [p.BusRead(BusSub.READ_VOLTAGE, 1)] * 3
    assert link.read_timeouts == 1


def test_o41_a_late_reply_is_counted_not_taken(rig):
    board, link, _ = rig
    quiet(board)
    board.runner.faults.reply_delay_s = 0.15
    try:
        with pytest.raises(LinkTimeout):
            link.read_pwm_pulse(1, timeout=0.05, retries=0)
        wait_for(lambda: link.unexpected_replies == 1, 5, what='the late reply')
    finally:
        board.runner.faults.reply_delay_s = 0.0
    assert link.read_pwm_pulse(1) == 1500


def test_o41_one_read_outstanding_per_function_matched_by_sub_and_id(rig):
    board, link, _ = rig
    mark = board.mark()
    retries = link.serial.stats.retries
    results = {}

    def reader(servo_id):
        values = []
        for _ in range(8):
            try:
                values.append(link.bus_read(BusSub.READ_POSITION, servo_id))
            except BusServoFailure:
                values.append(None)
        results[servo_id] = values

    threads = [threading.Thread(target=reader, args=(i,)) for i in (1, 2, 3, 9)]
    pwm = threading.Thread(target=lambda: results.update(
        pwm=[link.read_pwm_pulse(1) for _ in range(8)]))
    for t in threads + [pwm]:
        t.start()
    for t in threads + [pwm]:
        t.join(10)
    assert results == {1: [500] * 8, 2: [500] * 8, 3: [500] * 8, 9: [None] * 8,
                       'pwm': [1500] * 8}
    # On the wire, a bus-servo request is followed by its reply before the next one, but where
    # an attempt's wait ran out on a loaded host (campaign s15a, run 3): its retry goes before
    # the reply, and the request after it before the retry's own reply (two per retry).

    def outstanding() -> tuple:
        count = early = 0
        for side, msg in board.wire_log(mark):
            if side == 'host' and isinstance(msg, p.BusRead):
                early += count > 0
                count += 1
            elif side == 'board' and isinstance(msg, p.BusServoReply):
                count -= 1
        return count, early
    # The board's tap logs a reply once written: the host may have had it a moment before.
    wait_for(lambda: outstanding()[0] == 0, 2, what='the last reply in the wire log')
    assert outstanding()[1] <= 2 * (link.serial.stats.retries - retries)


def test_o22_frames_from_many_threads_reach_the_board_whole(rig):
    board, link, _ = rig
    mark = board.mark()

    def sender(k):
        for i in range(50):
            link.send(p.encode_led(1 + k % 2, i, 100 + k, 1))

    threads = [threading.Thread(target=sender, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    wait_for(lambda: len(board.commands(mark)) == 200, 5, what='200 LED commands')
    assert sorted((c.on_ms, c.off_ms) for c in board.commands(mark)) == \
        sorted((i, 100 + k) for k in range(4) for i in range(50))
    assert board.model.parser.checksum_errors == 0 and board.model.parser.bytes_discarded == 0


def test_write_only_commands_change_the_board(rig):
    board, link, _ = rig
    link.send(p.encode_motor_speeds([(0, 1.25), (2, -0.5)]))
    wait_for(lambda: board.model.motor_set_points == [1.25, 0.0, -0.5, 0.0], 5,
             what='the motor set-points')


def test_writing_while_the_port_is_missing_fails_at_once(tmp_path):
    link = OriginManLink(str(tmp_path / 'missing'))
    link.start()
    try:
        with pytest.raises(LinkDown):
            link.send(p.encode_motor_stop_mask(0x0F))
        with pytest.raises(LinkDown):
            link.read_pwm_pulse(1)
    finally:
        link.stop()
