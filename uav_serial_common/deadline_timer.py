"""One thread that runs a driver's time-based duty when it is next due (issue 22 item 2).

A driver's timer (the handset's failsafe, the OriginMan motor watchdog, the parachute's
online judgement) is the same loop: do what is due now, learn when the next thing is due, sleep
until then or until something changed. `DeadlineTimer` is that loop, once. The rules stay in
the driver: the duty is a small method that steps them and returns the next deadline.

The duty returns an absolute time on the timer's clock (``clock``), or None when nothing is due
(the timer then sleeps ``idle_s``: the longest sleep in any case, so a change nobody signals is
seen within it). A driver whose deadlines run on another clock converts them in its duty
(``now + (due - other_now)``). Waits are real seconds: with a test's fake clock the timer sleeps
``due - clock()`` of real time, as the drivers' own loops did.

`wake()` says "something changed: run the duty now" (a deadline moved earlier). The flag is
cleared before the duty runs, so a wake that comes while it runs (even from the duty itself)
makes the next sleep end at once; none is lost. `wake(by=deadline)` says "an event set this
deadline": the timer runs the duty by then, and only a sleep that would end later is cut
short (to the deadline, not to now), so an event that moves nothing earlier costs nothing; one
that comes while the duty runs bounds the sleep that follows. The timer holds only its own
condition, never a driver's lock, and never while the duty runs.
"""

from __future__ import annotations

import threading
import time
from typing import Callable, Optional


class DeadlineTimer:
    """A daemon thread that runs ``duty()`` at the deadline it returns, or at once on `wake`.

    ``on_error(exc)`` is called inside the ``except`` block when the duty raises (so
    ``logger.exception`` and ``traceback.format_exc()`` see the traceback); the thread goes on
    after ``retry_s``. An exception of ``on_error`` itself is swallowed: the thread outlives any
    bug.
    """

    def __init__(self, duty: Callable[[], Optional[float]], *, name: str,
                 on_error: Callable[[BaseException], None], idle_s: float,
                 min_sleep_s: float = 0.001, retry_s: float = 0.01,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._duty = duty
        self._name = name
        self._on_error = on_error
        self._idle_s = idle_s
        self._min_sleep_s = min_sleep_s
        self._retry_s = retry_s
        self._clock = clock
        self._cond = threading.Condition()
        self._woken = False
        self._sleep_until: Optional[float] = None
        """When the current sleep ends (clock time); None while the duty runs."""
        self._wake_by: Optional[float] = None
        """The earliest deadline `wake(by=...)` asked for since the duty last ran."""
        # A run's token: a thread ends when the current token is no longer its own, so a stop
        # that timed out followed by a start never leaves two threads running duties.
        self._token: Optional[object] = None
        self._thread: Optional[threading.Thread] = None

    def start(self) -> None:
        """Start the thread (the duty runs at once); nothing if it is running."""
        with self._cond:
            if self._token is not None:
                return
            token = self._token = object()
            self._thread = threading.Thread(target=self._run, args=(token,), name=self._name,
                                            daemon=True)
        self._thread.start()

    def wake(self, by: Optional[float] = None) -> None:
        """Something changed: run the duty now (it recomputes the deadline).

        With ``by`` (a time on the timer's clock: a deadline an event set), run it no later
        than then: a sleep that ends later ends then, one that ends earlier is left alone.
        """
        with self._cond:
            if by is None:
                self._woken = True
            elif self._sleep_until is None or by < self._sleep_until:
                self._wake_by = by if self._wake_by is None else min(self._wake_by, by)
            else:
                return
            self._cond.notify()

    def stop(self, timeout: Optional[float] = 2.0) -> bool:
        """Stop the thread and join it (not from the duty itself); idempotent.

        Returns True when the thread has ended (or, called from the duty, will end when the
        duty returns).
        """
        with self._cond:
            self._token = None
            thread, self._thread = self._thread, None
            self._cond.notify()
        if thread is None or thread is threading.current_thread():
            return True
        thread.join(timeout)
        return not thread.is_alive()

    def is_alive(self) -> bool:
        """Whether the thread runs (started and not stopped)."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    def _run(self, token: object) -> None:
        while True:
            with self._cond:
                if self._token is not token:
                    return
                self._woken = False  # before the duty: a wake during it is kept
                self._sleep_until = self._wake_by = None
            try:
                due = self._duty()
                wait = self._idle_s if due is None else due - self._clock()
                wait = min(self._idle_s, max(self._min_sleep_s, wait))
            except Exception as exc:  # noqa: BLE001 - a timer's thread must outlive any bug
                try:
                    self._on_error(exc)
                except Exception:  # noqa: BLE001 - nor may reporting the bug end it
                    pass
                wait = self._retry_s
            with self._cond:
                until = self._clock() + wait
                while not self._woken and self._token is token:
                    if self._wake_by is not None:
                        until, self._wake_by = min(until, self._wake_by), None
                    self._sleep_until = until
                    left = until - self._clock()
                    # A timeout ends the sleep whatever a test's fake clock says; only a wake
                    # with a deadline sleeps again, to the earlier end.
                    if left <= 0 or not self._cond.wait(left):
                        break
