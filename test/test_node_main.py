"""The signal handling of `run_node`: a flag and a wake-up pipe, no lock taken in the handler."""

import os
import signal
import threading

import pytest

from uav_serial_common.node_main import _Signals


@pytest.fixture
def signals():
    handlers = _Signals()
    try:
        yield handlers
    finally:
        for sig, previous in handlers.previous.items():
            signal.signal(sig, previous)
        handlers.close()


def test_issue22_the_first_signal_wakes_the_main_thread_and_later_ones_are_only_noted(
        signals, capfd):
    assert not signals.wait(0.0)
    os.kill(os.getpid(), signal.SIGTERM)
    assert signals.wait(30.0)
    os.kill(os.getpid(), signal.SIGINT)
    os.kill(os.getpid(), signal.SIGINT)
    assert signals.count == 3
    err = capfd.readouterr().err
    assert err.count('again: shutdown in progress') == 2, err


def test_issue22_the_executor_ending_wakes_the_main_thread_from_another_thread(signals):
    waker = threading.Thread(target=signals.wake)
    waker.start()
    assert signals.wait(30.0)
    waker.join(5.0)


def test_issue22_a_wake_after_close_writes_nowhere(signals):
    signals.close()
    signals.wake()  # the executor thread ending late, after the shutdown closed the pipe
    assert signals.requested
