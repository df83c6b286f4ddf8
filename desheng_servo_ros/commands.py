"""The ``~/command`` hot path: coalesced targets, stepped into the bus's schedule.

A mixin of :class:`~desheng_servo_ros.core.ServoBusCore`. The rules (the newest target of each
servo wins, the commands' share of the bus, a due batch goes out at the next READ boundary) are
the schedule's (``bus_schedule.BusSchedule`` and its ``schedule.CommandQueue``); ``command()``
steps the targets in on the caller's thread and returns: the batch leaves from whichever thread
steps the schedule at that boundary (the reader thread, the runtime's timer, this caller).
"""

from __future__ import annotations

import traceback
from typing import Dict, List, Optional, Sequence, Tuple

from desheng_servo_ros.state import Result
from desheng_servo_ros.units import resolve_targets, Target
from uav_serial_common.text import clip


class CommandPath:
    """``command()`` of a ServoBusCore (a mixin)."""

    @property
    def commands_received(self) -> int:
        """``~/command`` messages taken (each with at least one target)."""
        return self._commands.received

    @property
    def commands_superseded(self) -> int:
        """Targets replaced by a newer one before they were sent."""
        return self._commands.superseded

    @property
    def command_frames_sent(self) -> int:
        """SYNC WRITE frames the commands became."""
        return self._commands.frames_sent

    @property
    def _pending(self) -> Dict[int, Tuple[int, int]]:
        """Pending targets by id, (ticks, ms) each (the runtime's lock held to read it whole)."""
        return self._commands.pending

    def command(self, names: Sequence[str], ids: Sequence[int], positions: Sequence[float],
                move_time_ms: int) -> Result:
        """Queue a move; the newest target of each servo wins. Refusals send nothing."""
        try:
            targets = self._resolve(names, ids, positions, move_time_ms)
            self.runtime.command(targets)
        except ValueError as exc:
            return Result.refused('bad_input', clip(str(exc)))
        except Exception as exc:  # noqa: BLE001 - no input may cost the node
            self.log_error(f'command failed:\n{traceback.format_exc()}')
            return Result.failed(f'internal error: {exc!r}', cause='internal')
        return Result.sent(f'{len(targets)} target(s) queued')

    def _resolve(self, names: Sequence[str], ids: Sequence[int], positions: Sequence[float],
                 move_time_ms: int) -> List[Target]:
        return resolve_targets(self.servos, self.units, names, ids, positions, move_time_ms,
                               self.config.default_move_time_ms)

    def _drop_pending(self, ids: Optional[Sequence[int]] = None) -> None:
        with self.runtime.locked():
            self._commands.drop(ids)
