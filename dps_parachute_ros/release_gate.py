"""The release gate: one call to a helper just before a release leaves, that never holds it back.

``release_gate`` names a ``std_srvs/Trigger`` service, by default the autopilot link's
``parachute_mavlink/release_gate``. When it is there, the parachute node calls it before the
deploy frame of ``~/deploy`` and before the confirmation of the module's own trigger request,
after every refusal has been decided: only for a release that will be attempted. The helper
stops the motors there. Whatever it answers, or if it does not answer by the deadline, the
release goes out: the outcome is logged and written to the black box. While no such service has
ever been seen (``parachute_mavlink`` is not running), nothing is called, written or logged: the
driver works exactly as before. One that was there and is gone is said (log, black box). Empty:
no gate at all.

A core without I/O asks for the gate with `PassGate` and is told with `GateDone` (the deploy and
the trigger-request cores: one pair of names for both).
"""

from __future__ import annotations

from dataclasses import dataclass
import time
from typing import Callable, Optional, Tuple

from dps_parachute_ros.state import MODULE_WINDOW_S

GateCall = Callable[[float], Tuple[Optional[bool], str]]
"""Call the gate with a timeout [s]; return (success, message), success None when no answer."""

WINDOW_MARGIN_S = 0.25
"""A trigger request's confirmation leaves at the latest this long before the module's 1-s
window closes, whatever the gate does (room for a loaded host and the wire)."""


@dataclass(frozen=True)
class PassGate:
    """A core's action: pass the gate for the release by `what`, then feed back `GateDone`.

    Every refusal was decided before it. `token` tells the gates of one core apart (0: it has
    one at a time); `t_request`: a trigger request's arrival (``before_release``).
    """

    what: str
    token: int = 0
    t_request: Optional[float] = None


@dataclass(frozen=True)
class GateDone:
    """The event: the gate asked for by the `PassGate` of `token` was passed."""

    now: float
    token: int = 0


class ReleaseGate:
    """Ask the gate before a release; record what it said; never refuse the release."""

    def __init__(self, name: str, call: GateCall, timeout_s: float,
                 record: Callable[..., None], log: Callable[[str, str], None],
                 clock: Callable[[], float] = time.monotonic,
                 ready: Callable[[], bool] = lambda: True) -> None:
        self.name = name
        self.timeout_s = timeout_s
        self._call = call
        self._record = record
        self._log = log
        self._clock = clock
        self._ready = ready
        self._seen = False

    def available(self, route: str) -> bool:
        """Return whether the gate is there to be called; say so if it was and is gone."""
        try:
            if self._ready():
                self._seen = True
                return True
            if self._seen:
                self._record('decision', what='release gate', route=route, called=False,
                             reason=f'{self.name} is gone')
                self._log('error', f'release gate {self.name} is gone (it was there before): '
                                   f'releasing without it ({route})')
        except Exception as exc:  # noqa: BLE001 - the gate never stops a release
            try:
                self._log('error', f'release gate check failed ({exc!r}): releasing')
            except Exception:  # noqa: BLE001 - not even a log line may stop it
                pass
        return False

    def before_release(self, route: str, t_request: Optional[float] = None) -> None:
        """Call the gate for a release by `route`; `t_request`: a trigger request's arrival.

        Never raises: whatever goes wrong here, the release that follows must still go out.
        """
        try:
            self._before_release(route, t_request)
        except Exception as exc:  # noqa: BLE001 - the gate never stops a release
            try:
                self._log('error', f'release gate failed ({exc!r}): releasing anyway')
            except Exception:  # noqa: BLE001 - not even a log line may stop it
                pass

    def _before_release(self, route: str, t_request: Optional[float]) -> None:
        if not self.available(route):
            return
        timeout = self.timeout_s
        if t_request is not None:
            timeout = min(timeout, t_request + MODULE_WINDOW_S - WINDOW_MARGIN_S - self._clock())
        if timeout <= 0.0:
            self._record('decision', what='release gate', route=route, called=False,
                         reason="no time left in the module's window")
            self._log('error', f'release gate {self.name} not called for the {route}: no time '
                               "left in the module's 1 s window; releasing")
            return
        t0 = self._clock()
        try:
            ok, message = self._call(timeout)
        except Exception as exc:  # noqa: BLE001 - the gate never stops a release
            ok, message = None, f'gate call failed: {exc!r}'
        wait_ms = (self._clock() - t0) * 1000.0
        self._record('decision', what='release gate', route=route, called=True,
                     answered=ok is not None, success=ok, message=message, wait_ms=wait_ms,
                     timeout_ms=timeout * 1000.0)
        if ok:
            self._log('warn', f'release gate for the {route}: {message} ({wait_ms:.0f} ms); '
                              'releasing')
        else:
            state = 'did not answer' if ok is None else 'answered false'
            self._log('error', f'release gate {self.name} {state} for the {route} '
                               f'({message}, {wait_ms:.0f} ms): releasing anyway')
