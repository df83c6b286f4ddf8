"""Log lines at a level given by name, and throttled per key.

`log_at` logs on an rclpy logger (or anything with its methods); `Throttle` holds lines back.

rclpy refuses a call site whose severity changes ("Logger severity cannot be changed between
calls"), so one shared ``logger.log(text, severity)`` site raises after the first level it saw.
Here each severity has its own call site. No rclpy import: a device core may use it with the
logger its node hands it.
"""

from __future__ import annotations

from typing import Any, Dict, Hashable, Optional


def log_at(logger: Any, level: str, text: str) -> None:
    """Log `text` at `level`: 'debug', 'info', 'warn' or 'warning', 'error' (any case)."""
    name = level.lower()
    if name == 'error':
        logger.error(text)
    elif name in ('warn', 'warning'):
        logger.warning(text)
    elif name == 'debug':
        logger.debug(text)
    else:
        logger.info(text)


class Throttle:
    """Let a log line of each key through at most once per period, counting what it holds back.

    Not locked: the caller holds its own lock, or accepts that two threads racing on one key
    may both get a line through.
    """

    def __init__(self) -> None:
        self._last: Dict[Hashable, float] = {}
        self._held: Dict[Hashable, int] = {}

    def admit(self, key: Hashable, now: float, every_s: float) -> Optional[str]:
        """Return None to hold this line back, else the note to append to it.

        The note says how many lines of `key` were held back since the last one let through
        ('' when none were).
        """
        last = self._last.get(key)
        if last is not None and now - last < every_s:
            self._held[key] = self._held.get(key, 0) + 1
            return None
        self._last[key] = now
        held = self._held.pop(key, 0)
        return f' ({held} more like it since the last report)' if held else ''
