"""The module's online judgement (D2) as a state machine without I/O, thread, lock or clock.

The session tells it what happened (the port opened or closed, a request left, a request ended
answered or not) and asks for the verdict at a time, with the link's count of valid frames and
the time of the last one. It answers online or offline with the reason, and when the verdict
could next change by the clock alone (``next_deadline``: the monitor sleeps until then).

D2: offline while the port is closed, until a valid frame came since it opened, when a request
sent after the last valid frame has gone unanswered for ``timeout_s`` (across its retries, and
after the request gave up: the module has been silent since it was sent), and while streaming
when no frame at all came for ``timeout_s``. Back online only with a valid frame received after
going offline (counted, not timed, so the rule holds for any clock).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Set, Tuple

NOT_OPEN = 'port not open'
NO_FRAME = 'no valid frame from the module since the port opened'


@dataclass(frozen=True)
class Verdict:
    """Online or not, and why not."""

    online: bool
    reason: str = ''


class OnlineRule:
    """The D2 judgement of one link; every method is called under the owner's lock."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self.verdict = Verdict(False, NOT_OPEN)
        self._frames_at_open = 0
        self._frames_at_offline = 0
        # Request token -> (sent, frames then): in flight, or given up unanswered.
        self._silent_since: Dict[int, Tuple[float, int]] = {}
        self._in_flight: Set[int] = set()

    @property
    def requests_in_flight(self) -> int:
        """Requests sent that have not ended yet."""
        return len(self._in_flight)

    def port_opened(self, frames: int) -> None:
        """Take the port's (re)opening; `frames` is the link's frame count then."""
        self._frames_at_open = frames

    def request_sent(self, token: int, now: float, frames: int) -> None:
        """Take a request that D2 counts, sent at `now` after `frames` valid frames."""
        self._silent_since[token] = (now, frames)
        self._in_flight.add(token)

    def request_ended(self, token: int, unanswered: bool) -> None:
        """End a request; one that went unanswered counts on until a frame comes."""
        self._in_flight.discard(token)
        if not unanswered:
            self._silent_since.pop(token, None)

    def judge(self, now: float, port_open: bool, frames: int, last_frame: Optional[float],
              streaming: bool, closed_reason: str = '') -> Verdict:
        """Judge at `now`; return the verdict (also kept in ``verdict``)."""
        # A frame since a request answers for the module: it is not silent since then.
        for token in [k for k, (_, n) in self._silent_since.items() if n < frames]:
            del self._silent_since[token]
        timeout = self.timeout_s
        if not port_open:
            verdict = Verdict(False, closed_reason or 'port closed')
        elif last_frame is None or frames <= self._frames_at_open:
            verdict = Verdict(False, NO_FRAME)
        elif not self.verdict.online and frames <= self._frames_at_offline:
            verdict = self.verdict  # back only with a new frame
        else:
            verdict = Verdict(True)
            sent = [t for t, _ in self._silent_since.values()]
            # (The same sums as `next_deadline`'s: at its deadline a monitor finds it offline,
            # never online by a rounding of `now - sent`; the search found that.)
            if sent and now >= min(sent) + timeout:
                verdict = Verdict(False, f'no reply within {timeout:.1f} s of a request')
            elif streaming and now >= last_frame + timeout:
                verdict = Verdict(False, f'no status frame for {timeout:.1f} s while streaming')
        if self.verdict.online and not verdict.online:
            self._frames_at_offline = frames
        self.verdict = verdict
        return verdict

    def next_deadline(self, frames: int, last_frame: Optional[float],
                      streaming: bool) -> Optional[float]:
        """When the verdict may next change with no event but the clock (None: never)."""
        if not self.verdict.online:
            return None  # back online only with a frame, which is an event
        times = [t for t, n in self._silent_since.values() if n >= frames]
        due = [min(times) + self.timeout_s] if times else []
        if streaming and last_frame is not None:
            due.append(last_frame + self.timeout_s)
        return min(due) if due else None
