"""The servo bus's diagnostics: the bus's health and each servo's (a mixin of the core)."""

from __future__ import annotations

from typing import Any, List, Optional, Tuple

from desheng_servo_ros.schedule import OFFLINE_AFTER_FAILURES
from desheng_servo_ros.state import ERROR, fault_names, Health, OK, STALE, WARN
from uav_serial_common.text import few

# A failed read loop is reported for this long after its last failure.
LOOP_FAILURE_HOLD_S = 10.0
# An offline servo with this share of garbled replies is said to look like a duplicate id.
GARBLE_HINT_LEVEL = 0.2


class BusHealth:
    """Diagnostics of a ServoBusCore (a mixin: it reads the core's bus, servos and loop)."""

    def bus_health(self) -> Health:
        """Return the bus's diagnostic status: level, message, values."""
        now = self.clock()
        servos = self._servos
        online = sum(1 for s in servos if s.online)
        stats = self.bus.link.stats
        bus = self.bus
        values = [
            ('port', self.config.port), ('baud', self.config.baud),
            ('link', 'open' if bus.port_open else (bus.link.last_error or 'not open')),
            ('online servos', f'{online}/{len(servos)}'),
            ('cycle rate [Hz]', f'{self.cycle_rate_hz:.1f}'),
            ('publish_rate_hz', f'{self.config.publish_rate_hz:g}'),
            ('transactions', bus.transactions), ('failed transactions', bus.failed_transactions),
            ('timeouts', stats.timeouts), ('retries', stats.retries),
            ('checksum errors', bus.checksum_errors),
            ('unexpected frames', bus.unexpected_frames),
            ('garbled replies', sum(bus.garbled_by_id)),
            ('reconnects', stats.reconnects),
            ('bytes in', stats.bytes_in), ('bytes out', stats.bytes_out),
            ('commands', self.commands_received),
            ('commands superseded', self.commands_superseded),
            ('read loop restarts', self._loop_failures)] + self._latency_values()
        level, message = self._bus_problem(now)
        if level == OK:
            duplicates = [s for s in servos if now < s.duplicate_until]
            offline = [s for s in servos if not s.online]
            if duplicates:
                level, message = ERROR, (f'more than one servo answers to id(s) '
                                         f'{few(s.id for s in duplicates)}: give each servo its '
                                         'own id (~/set_id)')
            elif offline:
                level, message = WARN, (f'{online}/{len(servos)} servos online; offline: '
                                        + few(f'{s.name} (id {s.id})' for s in offline))
            else:
                message = f'{online}/{len(servos)} servos online'
        return Health(level, message, values)

    def _latency_values(self) -> List[Tuple[str, Any]]:
        """Return the port's latency timer and the reply margin as diagnostic values."""
        bus = self.bus
        report = bus.latency
        margin = f'{bus.margin_s * 1000:.1f}'
        if self.config.response_timeout_ms > 0:
            margin += ' (response_timeout_ms)'
        if report is None:
            return [('latency timer', 'port not opened yet'), ('reply margin [ms]', margin)]

        def ms(value: Optional[int]) -> str:
            return 'none' if value is None else str(value)
        return [('latency timer before [ms]', ms(report.before_ms)),
                ('latency timer after [ms]', ms(report.after_ms)),
                ('latency timer action', report.action),
                ('reply margin [ms]', margin),
                ('udev rule', report.udev_rule() or 'not needed')]

    def _bus_problem(self, now: float) -> Tuple[int, str]:
        loop = self._loop
        if self._running and loop is not None and not loop.is_alive():
            return ERROR, f'read loop stopped: {self._loop_failure or "unknown reason"}'
        if now - self._loop_failed_at < LOOP_FAILURE_HOLD_S:
            return ERROR, (f'read loop failed ({self._loop_failure}); restarted '
                           f'{self._loop_failures} time(s)')
        link = self.bus.link
        if link.reader_error and not link.reader_alive and self._running:
            return ERROR, f'serial reader stopped: {link.reader_error}'
        if not self.bus.port_open:
            if link.last_error:
                return ERROR, link.last_error
            if not link.stats.open_failures and not link.stats.reconnects:
                return WARN, f'opening {self.config.port}'
            return ERROR, f'{self.config.port} is not open'
        if not self._startup_done and self._scan_at_start:
            return WARN, 'scanning the bus for servos'
        servos = self._servos
        if servos and not any(s.online for s in servos) and \
                self.cycle_count > OFFLINE_AFTER_FAILURES:
            return ERROR, f'no servo answers: {self._silence_hint()}'
        return OK, ''

    def servo_health(self, servo_id: int) -> Health:
        """Return one servo's diagnostic status (STALE if it is no longer configured)."""
        s = next((x for x in self._servos if x.id == servo_id), None)
        if s is None:
            return Health(STALE, f'no servo {servo_id} configured any more', [])
        r, t = s.reading, s.telemetry
        values = [('id', s.id), ('online', s.online), ('position [ticks]', r.ticks),
                  ('position [rad]', f'{r.rad:.4f}'), ('current [mA]', t.current_ma),
                  ('temperature [degC]', t.temperature_c), ('status', f'0x{r.status:02X}'),
                  ('torque', t.torque_enabled), ('error count', s.error_count),
                  ('reply margin [ms]', f'{self.bus.margin_for(s.id) * 1000:.1f}')]
        who = f'{s.name} (id {s.id})'
        if self.clock() < s.duplicate_until:
            return Health(ERROR, f'{who}: duplicate id, more than one servo answers; give '
                                 'each its own id (~/set_id)', values)
        if not s.online:
            if self.bus.garble_level[s.id] >= GARBLE_HINT_LEVEL:
                return Health(ERROR, f'{who} offline: its replies come garbled, as when more '
                                     'than one servo answers to one id (or on a noisy line)',
                              values)
            return Health(ERROR, f'{who} offline: no reply ({s.error_count} failed '
                                 'transactions); check its power, cable and id (~/scan)', values)
        faults = fault_names(r.status)
        if faults:
            return Health(WARN, f'{who}: ' + ', '.join(faults), values)
        return Health(OK, 'ok', values)
