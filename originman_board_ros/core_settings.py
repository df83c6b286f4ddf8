"""The OriginMan core's settings: written whenever the board (re)appears, then checked.

Part of :class:`~originman_board_ros.core.OriginManCore` (``originman_board_ros.core``
assembles it; the shared state, ``_lock`` and the other threads are described there).
Threads:

* **worker thread** (from ``poll``): ``_apply_settings`` writes the desired settings when they
  are due (at connect and after every return: a reboot loses them, §4), retrying every
  ``SETTINGS_RETRY_S``; ``_check_settings`` reads the PWM offsets back every
  ``settings_check_period_s`` and has them all written again when they differ (O37). It owns
  ``_check_at`` (worker only, no lock).

Owns, under ``_lock``: ``_settings_due``, ``_settings_ok``, ``_settings_message``,
``_settings_asked`` (each request counts: a write that a newer request overtook does not settle
it); reads ``_expected_offsets`` (and resets it to the desired offsets when the check finds them
lost).
"""

from __future__ import annotations

from typing import Dict

from originman_board_ros import protocol as p
from originman_board_ros.link import LinkError

SETTINGS_RETRY_S = 1.0


class SettingsAtConnect:
    """The settings duties of :class:`~originman_board_ros.core.OriginManCore`."""

    def _ask_settings(self, now: float) -> None:
        """Have the desired settings written (again) from ``now`` (``_lock`` held)."""
        self._settings_due = now
        self._settings_ok = False
        self._settings_message = 'writing'
        self._settings_asked += 1

    def _apply_settings(self, now: float) -> None:
        with self._lock:
            if self._settings_due is None or now < self._settings_due:
                return
            cfg = self.config
            expected = dict(self._expected_offsets)
            asked = self._settings_asked
        problems = []
        try:
            if cfg.low_battery_mv != -1:
                self._write(p.encode_battery_limit(cfg.low_battery_mv))
            if cfg.motor_type != 'keep':
                self._write(p.encode_motor_type(p.MotorType[cfg.motor_type]))
            for servo_id, offset in sorted(expected.items()):
                self._write(p.encode_pwm_set_offset(servo_id, offset))
            for servo_id, offset in sorted(expected.items()):
                got = self.link.read_pwm_offset(servo_id)
                if got != offset:
                    problems.append(f'PWM servo {servo_id} offset reads {got} us, '
                                    f'wanted {offset} us')
        except LinkError as exc:
            problems.append(f'could not write the settings: {exc}')
        with self._lock:
            if self._settings_asked != asked:
                # Asked for again while these were written (a parameter changed, the board
                # came back): what was written may be the old; the newer request stands.
                return
            if problems:
                self._settings_ok = False
                self._settings_message = '; '.join(problems)
                self._settings_due = now + SETTINGS_RETRY_S
            else:
                self._settings_due = None
                self._settings_ok = True
                self._settings_message = self._describe_settings(expected)
        if problems:
            self._log.warning(f'originman board settings: {self._settings_message}; retrying')
            return
        period = cfg.settings_check_period_s
        self._check_at = now + period if period > 0 and expected else None

    def _describe_settings(self, offsets: Dict[int, int]) -> str:
        cfg = self.config
        parts = []
        if cfg.low_battery_mv != -1:
            parts.append(f'low battery alarm {cfg.low_battery_mv} mV')
        if cfg.motor_type != 'keep':
            parts.append(f'motor type {cfg.motor_type}')
        if offsets:
            parts.append('PWM offsets ' + ', '.join(
                f'{i}: {v} us' for i, v in sorted(offsets.items())) + ' (read back)')
        return 'written: ' + '; '.join(parts) if parts else 'no desired settings'

    def _check_settings(self, now: float) -> None:
        # O37: a reboot shorter than offline_timeout_s leaves no other trace; offsets that no
        # longer read back as expected mean the board lost its settings: write them all again.
        if self._check_at is None or now < self._check_at or self._settings_due is not None:
            return
        self._check_at = now + self.config.settings_check_period_s
        with self._lock:
            expected = dict(self._expected_offsets)
        for servo_id, offset in sorted(expected.items()):
            try:
                got = self.link.read_pwm_offset(servo_id)
            except LinkError:
                return  # silence is the offline judgement's business
            if got != offset:
                self._log.warning(f'PWM servo {servo_id} offset reads {got} us instead of '
                                  f'{offset} us: the board was reset? writing the desired '
                                  'settings again')
                with self._lock:
                    self._ask_settings(now)
                    self._expected_offsets = {
                        i + 1: v for i, v in enumerate(self.config.pwm_servo_offsets_us)}
                return
