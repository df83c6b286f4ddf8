"""The OriginMan core's bus servo poll: blocking reads, one servo at a time, on the worker.

Part of :class:`~originman_board_ros.core.OriginManCore` (``originman_board_ros.core``
assembles it; the shared state, ``_lock`` and the other threads are described there).
Threads:

* **worker thread** (from ``poll``): ``_poll_servos`` reads the polled servos (position every
  cycle, telemetry every ``bus_servo_telemetry_period_s``; an offline servo is re-probed every
  ``SERVO_REPROBE_S``) and calls ``on_bus_servo_states``. It owns the poll schedule
  (``_next_poll``, ``_telemetry_at``, ``_reprobe_at``: worker only, no lock).

Shares, under ``_lock``: ``_servos`` (with the read services), ``_poll_ids``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Dict, Optional

from originman_board_ros import protocol as p
from originman_board_ros.core_types import bus_position_to_rad, BusServoStatus
from originman_board_ros.link import LinkError

SERVO_OFFLINE_AFTER = 3
"""Consecutive failed reads after which a polled bus servo is offline."""
SERVO_REPROBE_S = 1.0
"""An offline bus servo is read once per this period, without retries."""


class BusServoPoll:
    """The bus servo poll of :class:`~originman_board_ros.core.OriginManCore`."""

    def _poll_servos(self, now: float, online: bool) -> None:
        cfg = self.config
        if not self._poll_ids or cfg.bus_servo_poll_hz <= 0 or not online:
            return
        if self._next_poll is None or now < self._next_poll:
            return
        period = 1.0 / cfg.bus_servo_poll_hz
        # Catch up without bursts: a late cycle does not cause several quick ones.
        self._next_poll = max(self._next_poll + period, now)
        with self._lock:
            ids = list(self._poll_ids)
        for servo_id in ids:
            # A pass of unanswered reads takes seconds: the board's silence is judged between
            # them, not only after the pass.
            if self._stop.is_set() or not self._tick(self._clock()):
                break
            self._poll_one(servo_id, now)
        with self._lock:
            states = [self._servos[i] for i in self._poll_ids if i in self._servos]
        self._call('states', states)

    def _poll_one(self, servo_id: int, now: float) -> None:
        with self._lock:
            status = self._servos.setdefault(servo_id, BusServoStatus(servo_id))
        if not status.online and status.failed_reads >= SERVO_OFFLINE_AFTER:
            if now < self._reprobe_at.get(servo_id, 0.0):
                return
            self._reprobe_at[servo_id] = now + SERVO_REPROBE_S
            retries: Optional[int] = 0
        else:
            retries = None
        telemetry = now >= self._telemetry_at.get(servo_id, 0.0)
        reads = [p.BusSub.READ_POSITION]
        if telemetry:
            reads += [p.BusSub.READ_VOLTAGE, p.BusSub.READ_TEMPERATURE, p.BusSub.READ_LOAD]
        values: Dict[int, p.BusValue] = {}
        error = ''
        for sub in reads:
            try:
                values[sub] = self.link.bus_read(sub, servo_id, retries=retries)
            except (LinkError, p.ProtocolError) as exc:
                error = str(exc)
                break
        if telemetry and not error:
            self._telemetry_at[servo_id] = now + self.config.bus_servo_telemetry_period_s
        with self._lock:
            status = self._servos.get(servo_id, BusServoStatus(servo_id))
            if error:
                failed = status.failed_reads + 1
                if failed == SERVO_OFFLINE_AFTER:
                    self._log.warning(f'bus servo {servo_id} offline after {failed} failed '
                                      f'reads: {error}')
                    self._reprobe_at[servo_id] = now + SERVO_REPROBE_S
                status = replace(status, failed_reads=failed, last_error=error,
                                 online=status.online and failed < SERVO_OFFLINE_AFTER)
            else:
                if not status.online:
                    self._log.info(f'bus servo {servo_id} online')
                status = _with_values(replace(status, online=True, failed_reads=0,
                                              last_error=''), values)
            self._servos[servo_id] = status

    def _mark_servos_offline(self, why: str) -> None:
        with self._lock:
            for servo_id, status in self._servos.items():
                self._servos[servo_id] = replace(status, online=False, last_error=why)
            states = [self._servos[i] for i in self._poll_ids if i in self._servos]
        self._telemetry_at.clear()
        if states:
            self._call('states', states)


def _with_values(status: BusServoStatus, values: Dict[int, p.BusValue]) -> BusServoStatus:
    """Fold read values into a status (units: V, degrees C, rad)."""
    changes: Dict[str, Any] = {}
    s = p.BusSub
    if s.READ_POSITION in values:
        raw = int(values[s.READ_POSITION])  # type: ignore[arg-type]
        changes.update(position=raw, position_rad=bus_position_to_rad(raw))
    if s.READ_VOLTAGE in values:
        changes['voltage_v'] = values[s.READ_VOLTAGE] / 1000.0  # type: ignore[operator]
    if s.READ_TEMPERATURE in values:
        changes['temperature_c'] = float(values[s.READ_TEMPERATURE])  # type: ignore[arg-type]
    if s.READ_LOAD in values:
        changes['torque_enabled'] = bool(values[s.READ_LOAD])
    if s.READ_OFFSET in values:
        changes['offset'] = int(values[s.READ_OFFSET])  # type: ignore[arg-type]
    if s.READ_ANGLE_LIMITS in values:
        lo, hi = values[s.READ_ANGLE_LIMITS]  # type: ignore[misc]
        changes.update(min_position=lo, max_position=hi)
    if s.READ_VOLTAGE_LIMITS in values:
        lo, hi = values[s.READ_VOLTAGE_LIMITS]  # type: ignore[misc]
        changes.update(min_voltage_v=lo / 1000.0, max_voltage_v=hi / 1000.0)
    if s.READ_TEMPERATURE_LIMIT in values:
        changes['max_temperature_c'] = float(values[s.READ_TEMPERATURE_LIMIT])  # type: ignore
    return replace(status, **changes)
