"""The ``~/command`` hot path: coalesced targets, handed to the read chain or sent by a thread.

A mixin of :class:`~desheng_servo_ros.core.ServoBusCore`. The rules (the newest target of each
servo wins, the commands' share of the bus) are the schedule's
(:class:`~desheng_servo_ros.schedule.CommandQueue`); this runs them on the caller's thread (a
due command is handed to the running read chain and goes out at the next READ boundary) and on
the command thread (``_commander_main``), with ``_commands`` guarded by ``_cmd_cond``.
"""

from __future__ import annotations

import time
import traceback
from typing import Dict, List, Optional, Sequence, Tuple

from desheng_servo_ros.link import LinkError, PRIORITY_SERVICE
from desheng_servo_ros.schedule import sync_write_frames
from desheng_servo_ros.state import Result
from desheng_servo_ros.units import resolve_targets, Target
from uav_serial_common.text import clip


class CommandPath:
    """``command()`` and the command thread of a ServoBusCore (a mixin)."""

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
        """Pending targets by id (``_cmd_cond`` held)."""
        return self._commands.pending

    def command(self, names: Sequence[str], ids: Sequence[int], positions: Sequence[float],
                move_time_ms: int) -> Result:
        """Queue a move; the newest target of each servo wins. Refusals send nothing."""
        try:
            targets = self._resolve(names, ids, positions, move_time_ms)
        except ValueError as exc:
            return Result.refused('bad_input', clip(str(exc)))
        except Exception as exc:  # noqa: BLE001 - no input may cost the node
            self.log_error(f'command failed:\n{traceback.format_exc()}')
            return Result.failed(f'internal error: {exc!r}', cause='internal')
        with self._cmd_cond:
            self._commands.add(targets)
            # While the read chain runs, a due command is handed to it on this thread and goes
            # out at the next READ boundary; otherwise the command thread sends it.
            if not (self._command_due() and self._post_pending()):
                self._cmd_cond.notify()
        return Result.sent(f'{len(targets)} target(s) queued')

    def _command_due(self) -> bool:
        """Whether the next command frame may go now (``_cmd_cond`` held).

        Not before the last one handed to the read chain has left the line; then as the bus
        budget allows (CommandQueue).
        """
        last = self._last_post
        if last is not None:
            if not last.settled:
                return False
            self._last_post = None
            self._charge(last.written_at, last.size)
        return time.monotonic() >= self._commands.free_at()

    def _charge(self, ended_at: float, size: int) -> None:
        """Charge a batch of `size` bytes that left the line at `ended_at` (``_cmd_cond`` held)."""
        self._commands.charge(ended_at, size, self.config.baud, self.config.publish_rate_hz)

    def _post_pending(self) -> bool:
        """Hand the pending targets to the running read chain (``_cmd_cond`` held)."""
        commands = self._commands
        frames = sync_write_frames([(i, t, ms) for i, (t, ms) in commands.pending.items()])
        posted = self.bus.post(frames)
        if posted is None:
            return False
        self._last_post = posted
        commands.pending = {}
        commands.frames_sent += len(frames)
        return True

    def _resolve(self, names: Sequence[str], ids: Sequence[int], positions: Sequence[float],
                 move_time_ms: int) -> List[Target]:
        return resolve_targets(self.servos, self.units, names, ids, positions, move_time_ms,
                               self.config.default_move_time_ms)

    def _commander_main(self) -> None:
        commands = self._commands
        while self._running:
            in_flight = None
            with self._cmd_cond:
                while self._running and not (commands.pending and self._command_due()):
                    if commands.pending and self._last_post is not None:
                        in_flight = self._last_post
                        break
                    wait = (0.5 if not commands.pending
                            else commands.free_at() - time.monotonic())
                    self._cmd_cond.wait(max(0.0005, min(0.5, wait)))
                if not self._running:
                    return
                if in_flight is None:
                    if self._post_pending():
                        continue
                    targets = commands.take()
            if in_flight is not None:
                # The frames handed to the read chain are not out yet; the reader thread
                # settles them. Waited for outside the lock: it takes the post lock meanwhile.
                in_flight.wait(0.1)
                continue
            try:
                frames = self.bus.sync_write_positions(targets, PRIORITY_SERVICE, wait=False)
                with self._cmd_cond:
                    commands.frames_sent += len(frames)
                    self._charge(time.monotonic(), sum(map(len, frames)))
            except LinkError as exc:
                self.log_warning(f'~/command not sent: {exc}', every_s=5.0, key='cmd-link')
            except Exception:  # noqa: BLE001 - the command thread must not die
                self.log_error(f'~/command failed:\n{traceback.format_exc()}', every_s=5.0,
                               key='cmd-bug')

    def _drop_pending(self, ids: Optional[Sequence[int]] = None) -> None:
        with self._cmd_cond:
            self._commands.drop(ids)
