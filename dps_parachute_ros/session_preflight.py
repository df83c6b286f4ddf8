"""``~/preflight_check`` (D17): go / no-go from the module read afresh, one check per entry.

Part of `ParachuteSession` (``dps_parachute_ros.session`` assembles it; the shared state and the
lock are described there). Runs on a caller's thread (the node's service thread); its queries
update the shared state through the session's helpers. Owns no state.
"""

from __future__ import annotations

from typing import Callable, List, Optional, Tuple

from dps_parachute_ros import protocol as p
from dps_parachute_ros.deploy_events import guard_text, MAX_FAILED_DEPLOYS
from dps_parachute_ros.link import LinkDown, LinkError, LinkTimeout
from dps_parachute_ros.session_deploy import SAFETY_SYNC_S
from dps_parachute_ros.session_online import LINK_ERROR_COUNTERS
from dps_parachute_ros.session_worker import STREAM_GRACE
from dps_parachute_ros.settings_rule import conditions
from dps_parachute_ros.state import FLAG_SETTINGS, Result, SessionConfig, SETTINGS

LOW_BATTERY_V = 3.5
"""On battery, a cell below this is a warning (a 1S Li-ion cell is near empty there), D9."""
LINK_QUIET_S = 10.0
"""Preflight: a link error (checksum, lost reply, reconnect) this recent fails."""
Check = Tuple[bool, str, str]
"""A preflight line: passed, name, detail."""


class Preflight:
    """The preflight checks of `ParachuteSession` (a mixin: it uses the session's state)."""

    def _preflight_steps(self) -> List[Tuple[Tuple[str, ...], bool, Callable[[], List[Check]]]]:
        """Return the checks of ``~/preflight_check`` in the order of its lines.

        Each is (the names of its lines, whether it queries the module, the check). A check that
        queries raises LinkError when the module does not answer: its lines and those of every
        later querying check say "not checked"; the others are judged from what the driver
        knows. One more check is one more entry here.
        """
        return [
            (('online',), True, self._pf_online),
            (('armed',), True, self._pf_armed),
            (('not triggered',), True, self._pf_triggered),
            (('not in protection',), False, lambda: [self._protection_check()]),
            (('settings as desired', 'auto triggers as desired'), True, self._pf_settings),
            (('auto triggers on',), False, self._pf_auto_triggers_on),
            (('trigger requests confirmed',), False, self._pf_policy),
            (('no trigger condition met',), True, self._pf_conditions),
            (('bay closed',), True, self._pf_bay),
            (('battery',), True, self._pf_battery),
            (('link clean',), False, self._pf_link),
            (('status stream',), False, lambda: [self._stream_check(self.config)]),
            (('black box writable',), False, lambda: [self._blackbox_check()]),
        ]

    def preflight_check(self) -> Result:
        """`~/preflight_check`: go / no-go from the module read afresh, queries only (D17)."""
        checks: List[Check] = []
        silent: Optional[LinkError] = None
        if not self.snapshot.port_open:
            silent = LinkDown(self.link.serial.last_error or 'port not open')
        for names, queries, check in self._preflight_steps():
            if queries and silent is not None:
                checks += [(False, name, f'no answer: {silent}' if name == 'online' else
                            'not checked: the module did not answer') for name in names]
                continue
            try:
                checks += check()
            except LinkError as exc:
                silent = exc
                checks += [(False, name, f'no answer: {exc}' if name == 'online' else
                            'not checked: the module did not answer') for name in names]
        ok = all(passed for passed, _, _ in checks)
        lines = [f'{"OK  " if passed else "FAIL"} {name}: {detail}'
                 for passed, name, detail in sorted(checks, key=lambda c: c[0])]
        self.blackbox.record('decision', what='preflight', ok=ok, checks=lines)
        return Result.checked(ok, '\n'.join(lines))

    def _pf_online(self) -> List[Check]:
        self._note_boot_count(self._req(p.encode_boot_count_query(), retries=1).count)
        return [(True, 'online', f'answers (boot count {self.snapshot.boot_count})')]

    def _pf_armed(self) -> List[Check]:
        epoch, arms = self._asked()
        armed = self._req(p.encode_armed_query(), retries=1).armed
        self._update_if(epoch, arms, armed=armed)
        return [(armed, 'armed', 'armed' if armed else 'LOCKED: arm it with ~/arm')]

    def _pf_triggered(self) -> List[Check]:
        triggered = self._query_triggered()
        if triggered is None:
            raise LinkTimeout('no reply to the triggered query')
        return [(not triggered, 'not triggered', 'not triggered' if not triggered
                 else 'TRIGGERED: the parachute has deployed')]

    def _pf_settings(self) -> List[Check]:
        for setting in SETTINGS.values():
            self._update(**{setting.field: self._req(setting.encode_query(), retries=1).value})
        if self._flags_query_answered:
            self._query_flags()
        self._update_mismatch(log=False)
        return self._settings_checks(self.config)

    def _pf_auto_triggers_on(self) -> List[Check]:
        # Both off: the module never deploys on its own detection, only on ~/deploy.
        snap = self.snapshot
        flags = (snap.attitude_trigger_enabled, snap.freefall_trigger_enabled)
        if None in flags:
            return [(True, 'auto triggers on', 'not known (the module never reported them, '
                     'P14)')]
        text = (f'attitude {"on" if flags[0] else "OFF"}, free fall '
                f'{"on" if flags[1] else "OFF"}')
        if not any(flags):
            return [(False, 'auto triggers on', f'{text}: the module never deploys on its own '
                     'crash detection, only on ~/deploy')]
        return [(True, 'auto triggers on', text)]

    def _pf_policy(self) -> List[Check]:
        config = self.config
        policy = config.trigger_request_policy
        if policy == 'deny':
            return [(False, 'trigger requests confirmed', 'trigger_request_policy deny: a '
                     "request of the module (its own crash detection, on external power) is "
                     'never confirmed, so it does not deploy on its own')]
        if policy == 'defer':
            return [(True, 'trigger requests confirmed', 'trigger_request_policy defer: '
                     'confirmed only if ~/answer_trigger_request answers true within '
                     f'{config.defer_timeout_s:.2f} s, else denied')]
        return [(True, 'trigger requests confirmed', 'trigger_request_policy confirm')]

    def _pf_conditions(self) -> List[Check]:
        epoch, arms = self._asked()
        status = self._req(p.encode_status_query(), retries=1)
        self._on_status(status, via='query', epoch=epoch, arms=arms)
        snap = self.snapshot
        tilt, accel = float(status.tilt_deg), float(status.accel_g)
        met = conditions(self._trigger_settings(snap), tilt, accel)
        if snap.pending_request:
            return [(False, 'no trigger condition met', 'a trigger request of the module is '
                     'waiting for an answer')]
        if met:
            what = ('the module is deploying or asking to' if status.armed else
                    'arming now fires the parachute at once')
            return [(False, 'no trigger condition met', f'{"; ".join(met)}: {what} (P21)')]
        return [(True, 'no trigger condition met', f'tilt {tilt:g}°, |a| {accel:.1f} g')]

    def _pf_bay(self) -> List[Check]:
        light = self._req(p.encode_light_level_query(), retries=1).volts
        snap = self._update(light_v=light)
        threshold = snap.light_threshold_raw / 10
        if snap.bay_open:
            return [(False, 'bay closed', f'BAY OPEN: light {light:.1f} V > light threshold '
                     f'{threshold:.1f} V (lid open or the parachute out?)')]
        return [(True, 'bay closed', f'light {light:.1f} V ≤ light threshold {threshold:.1f} V')]

    def _pf_battery(self) -> List[Check]:
        charging = self._req(p.encode_charging_query(), retries=1).charging
        volts = self._req(p.encode_cell_voltage_query(), retries=1).volts
        self._update(charging=charging, voltage_v=volts)
        low = not charging and volts < LOW_BATTERY_V
        return [(not low, 'battery', f'{volts:.2f} V {"charging" if charging else "on battery"}'
                 + (f', below {LOW_BATTERY_V} V' if low else ''))]

    def _pf_link(self) -> List[Check]:
        # The counters are for the whole run: one burst long ago is no reason for a no-go, a
        # recent one is (a deploy frame would meet the same link).
        counters, changed_at = self._note_link()
        totals = ', '.join(f'{n} {c}' for n, c in zip(LINK_ERROR_COUNTERS, counters))
        ago = self.clock() - changed_at
        if ago < LINK_QUIET_S:
            return [(False, 'link clean', f'link errors {ago:.1f} s ago (run: {totals}); a '
                     f'clean link for {LINK_QUIET_S:.0f} s is a go')]
        return [(True, 'link clean', f'no link error in the last {LINK_QUIET_S:.0f} s (run: '
                 f'{totals})')]

    def _protection_check(self) -> Check:
        # The module has no query for its protection state (P19): judged from the deploy
        # frames this driver sent since the module's last power-up.
        snap = self.snapshot
        if snap.failed_deploys >= MAX_FAILED_DEPLOYS:
            text = guard_text(snap.failed_deploys, snap.unacked_deploys)
            return (False, 'not in protection', text.split(': ', 1)[1])
        if snap.deploy_outcome_unknown:
            return (False, 'not in protection', 'a deploy whose outcome is unknown')
        detail = 'no unsuccessful deploy attempt since power-up' if not snap.failed_deploys \
            else f'{snap.failed_deploys} unsuccessful deploy attempt since power-up'
        return (True, 'not in protection', detail + ' (judged by the driver: the module has '
                'no query for it)')

    def _settings_checks(self, config: SessionConfig) -> List[Check]:
        snap = self.snapshot
        numeric = [m for m in snap.mismatch if m.split(':')[0] in SETTINGS]
        flags = [m for m in snap.mismatch if m.split(':')[0] in FLAG_SETTINGS]
        desired = [n for n in SETTINGS if config.desired(n) != -1]
        wanted_flags = [n for n in FLAG_SETTINGS if config.desired(n) != 'keep']
        with self._lock:
            flags_read = self._flags_query_answered
        how = 'read afresh' if flags_read else 'as last reported by the module (P14)'
        return [
            (not numeric, 'settings as desired', '; '.join(numeric) if numeric else
             (f'{", ".join(desired)} verified' if desired else 'none desired (all -1)')),
            (not flags, 'auto triggers as desired', '; '.join(flags) if flags else
             (f'{", ".join(wanted_flags)} verified, {how}' if wanted_flags else
              'none desired (keep)')),
        ]

    def _stream_check(self, config: SessionConfig) -> Tuple[bool, str, str]:
        # The queries above are answered whether the stream flows or not: judged from it.
        if not config.stream_status:
            return (True, 'status stream', 'off (stream_status false): the status is polled')
        snap = self.snapshot
        with self._lock:
            silent = self.clock() - max(self._last_stream_time, self._stream_on_at)
        if snap.stream_problem:
            return (False, 'status stream', snap.stream_problem)
        if not snap.streaming or silent > config.offline_timeout_s * STREAM_GRACE:
            return (False, 'status stream', f'no status frame for {silent:.1f} s')
        return (True, 'status stream', 'flowing')

    def _blackbox_check(self) -> Tuple[bool, str, str]:
        synced = self.blackbox.sync(SAFETY_SYNC_S)  # also notices a file removed under it
        status = self.blackbox.status()
        problem = self.blackbox_problem(status)
        if synced and not problem:
            return (True, 'black box writable', status.path)
        return (False, 'black box writable', problem or 'fsync failed')
