"""What a deploy decides on: the knowledge half of `DeployCore` (``deploy_core``), no I/O.

Whether the port is open and the module answers, whether its armed and triggered states were
read since it last could have changed unseen (D15), its boot count and whether it was read since
the last reboot seen, the deploy frames of this power-up without a successful acknowledgement
(P11, and how many left since the boot count was last read: a reboot found later may have come
before them), a deploy whose outcome is unknown. Taken from the module's frames and the link's
events, or told by a caller that keeps them (``mirror``: the session).
"""

from __future__ import annotations

from typing import Any, List, Optional, Set, Tuple, Union

from dps_parachute_ros import protocol as p
from dps_parachute_ros.deploy_events import (Action, Event, LinkDown, LinkUp, Log, PassGate,
                                             Rebooted, Record, Report, Request,
                                             REQUEST_TIMEOUT_S, SaveAttempts, SYNC_WAIT, Timeout)

POWER_UP_HEARTBEATS_S = 0.2
"""Unsolicited heartbeats closer together than this belong to one power-up (P5, D3)."""

LATE_HEARTBEAT_S = 2.0
"""A power-up's second heartbeat taken up to this long after its first, but beyond
`POWER_UP_HEARTBEATS_S` (a reader that stalled between the two), may still be that power-up's."""

SAME_POWER_UP, REBOOT, MAYBE_REBOOT = 'same power-up', 'reboot', 'maybe reboot'
"""What `PowerUpHeartbeats.take` makes of an unsolicited heartbeat."""


class PowerUpHeartbeats:
    """Which unsolicited heartbeats tell a reboot (P5, D3): one rule for the session and the core.

    A power-up sends two heartbeats 50 ms apart. The second of a pair taken more than
    `POWER_UP_HEARTBEATS_S` after the first (the reader stalled in between) cannot be told from
    another reboot: it is a `MAYBE_REBOOT`, which the driver handles as a reboot (the armed state
    unknown, the module read afresh) but does not record as one: the boot count read next tells.

    Heartbeats taken close together are one power-up's where that is the one reading: the
    second right after a first that is surely a first (taken after a pair, or long after the
    heartbeat before), or one after a whole pair (the module's answer to the driver's heartbeat
    is the same frame). One close after a heartbeat that may be a late second (a
    `MAYBE_REBOOT`, or a `REBOOT` taken within `LATE_HEARTBEAT_S` of one) may be the first of
    another power-up, whose request of the power-up before, taken in between, is void: a
    `MAYBE_REBOOT` too.
    """

    _FIRST, _PAIR, _UNSURE = 'first', 'pair', 'unsure'

    def __init__(self) -> None:
        """Start with no heartbeat seen."""
        self._last = -1e9
        self._newest = self._PAIR  # what the last heartbeat taken was

    def take(self, now: float) -> str:
        """Take a heartbeat at `now`; return `SAME_POWER_UP`, `REBOOT` or `MAYBE_REBOOT`."""
        gap = now - self._last
        self._last = now
        newest = self._newest
        if gap <= POWER_UP_HEARTBEATS_S:
            if newest == self._FIRST:
                self._newest = self._PAIR
                return SAME_POWER_UP
            if newest == self._UNSURE:
                return MAYBE_REBOOT
            # After a pair: the module's answer to the driver's heartbeat taken as unsolicited
            # (the same frame), or a power-up the reader held with it: not told apart here.
            return SAME_POWER_UP
        if gap <= LATE_HEARTBEAT_S and newest != self._PAIR:
            # A late second, or another power-up's first: either way not surely a first.
            self._newest = self._UNSURE
            return MAYBE_REBOOT if newest == self._FIRST else REBOOT
        self._newest = self._FIRST
        return REBOOT

    def handled(self, now: float) -> None:
        """Run the window from `now`: handling the first heartbeat took until then."""
        self._last = max(self._last, now)


LATE_HEARTBEAT_EVENT = 'unsolicited heartbeat late: the power-up\'s second, or another reboot'
"""The black-box ``state`` event of a `MAYBE_REBOOT` (not counted as a reboot: the boot count
read after it is)."""


def heartbeat_actions(verdict: str) -> List[Action]:
    """Return the log line and black-box record of a `REBOOT` or `MAYBE_REBOOT` heartbeat."""
    if verdict == REBOOT:
        return [Log('warn', 'unsolicited heartbeat: the module has (re)booted'),
                Record.of('state', event='module reboot (unsolicited heartbeat)')]
    return [Log('warn', 'unsolicited heartbeat that may be a late one of the power-up before '
                        f'(more than {POWER_UP_HEARTBEATS_S:g} s after its first, or taken with '
                        'such a one), or another reboot; the module is read afresh and its boot '
                        'count tells'),
            Record.of('state', event=LATE_HEARTBEAT_EVENT)]


class DeployKnowledge:
    """What the deploy procedure knows of the module, and how each event changes it."""

    def __init__(self, stored: Optional[Any] = None, port_open: bool = False,
                 request_timeout_s: float = REQUEST_TIMEOUT_S, mirror: bool = False) -> None:
        """Start knowing nothing; see `DeployCore`."""
        self.mirror = mirror
        self._stale = False               # the core's own verdict: read again before acting
        self._told_fresh = False
        self.timeout_s = request_timeout_s
        self.port_open = port_open
        self.online = False
        self.offline_reason = ('no valid frame from the module since the port opened'
                               if port_open else 'not connected yet')
        self.fresh = False
        self.armed: Optional[bool] = None
        self.triggered: Optional[bool] = None
        self.boot_count: Optional[int] = None
        # P11: an earlier run's frames count until a boot count read says another power-up.
        self._stored = stored if stored is not None and stored.failed > 0 else None
        self.failed = self._stored.failed if self._stored else 0
        self.unacked = self._stored.unacked if self._stored else 0
        self.outcome_unknown = False
        self._unknown_boot: Optional[int] = None
        self.reboots = 0                  # reboots seen (heartbeat or a changed boot count)
        self.boot_reads = 0               # boot counts read
        self._boot_read_reboots = -1      # reboots seen when the boot count was last read
        self._sent_since_read = 0         # deploy frames since the boot count was last read
        self._told_boot_current = False
        self._power_ups = PowerUpHeartbeats()
        self._triggered_seen: Optional[Tuple[float, str]] = None
        self._frame_at: Optional[float] = None
        self._reported: Set[Optional[int]] = set()
        self._out: List[Action] = []
        self._waiting: Optional[Union[Request, PassGate]] = None
        self._now = 0.0

    # -- what the driver knows ------------------------------------------------------------------

    def know(self, *, port_open: bool, online: bool, offline_reason: str, fresh: bool,
             armed: Optional[bool], triggered: Optional[bool], boot_count: Optional[int],
             failed: int, unacked: int, outcome_unknown: bool, unknown_boot: Optional[int],
             triggered_seen: Optional[Tuple[float, str]], frame_at: Optional[float],
             reboots: int, boot_current: bool, deployed_boots: Set[Optional[int]]) -> None:
        """Take what the caller knows of the module (a `mirror` core, before each step)."""
        self.port_open, self.online, self.offline_reason = port_open, online, offline_reason
        self._told_fresh = fresh
        self.fresh = fresh and not self._stale  # (a silence it saw: read again first)
        self.armed, self.triggered, self.boot_count = armed, triggered, boot_count
        self.failed, self.unacked = failed, unacked
        self.outcome_unknown, self._unknown_boot = outcome_unknown, unknown_boot
        self._triggered_seen, self._frame_at, self.reboots = triggered_seen, frame_at, reboots
        self._told_boot_current = boot_current
        self._reported = deployed_boots

    @property
    def boot_current(self) -> bool:
        """Whether the boot count was read since the last reboot seen."""
        if self.mirror:
            return self._told_boot_current
        return self.boot_count is not None and self._boot_read_reboots == self.reboots

    def _know(self, action: Action) -> None:
        """Emit an action about the module's state, unless the caller keeps that (mirror)."""
        if not self.mirror:
            self._out.append(action)

    def _link_event(self, event: Event) -> None:
        if isinstance(event, LinkUp):
            self.port_open = True
            self._offline('no valid frame from the module since the port opened')
        elif isinstance(event, LinkDown):
            self.port_open = False
            self._offline(event.reason)
        elif isinstance(event, Timeout):
            wait = self._waiting
            if not (isinstance(wait, Request) and wait.silence_ok):
                self._offline(f'no reply within {self.timeout_s:.1f} s of a request')
        elif isinstance(event, Rebooted):
            if event.boot_count is None:
                self._heartbeat()
            else:
                self._boot_count(event.boot_count)

    def _offline(self, reason: str) -> None:
        self.fresh = False
        self._stale = True
        if not self.mirror:  # (a mirror core's caller judges online: D2)
            self.online = False
            self.offline_reason = reason

    def _take(self, msg: Any, solicited: bool) -> None:
        """Take a frame from the module: it answers (online), and what it tells."""
        if self.mirror:
            # The caller took it already (or refused it: read before a reboot), and told.
            if isinstance(msg, p.BootCount):
                self.boot_reads += 1
            elif isinstance(msg, p.Status):
                self._reread_done(msg.armed)
            return
        if self.port_open and not self.online:
            # Back: it may have changed while silent, re-read before acting on it (D15).
            self.online, self.offline_reason, self.fresh = True, '', False
        if isinstance(msg, p.Heartbeat) and not solicited:
            self._heartbeat()
        elif isinstance(msg, p.BootCount):
            self._boot_count(msg.count)
        elif isinstance(msg, p.Status):
            self._set_triggered(msg.triggered, 'status' if not solicited else 'query',
                                armed=msg.armed)
        elif isinstance(msg, p.ArmedState):
            self.armed = msg.armed
        elif isinstance(msg, p.TriggeredState):
            self._set_triggered(msg.triggered, 'query')
        elif isinstance(msg, p.DeployAck) and not solicited:
            self._deploy_reply(msg, late=True)

    def _heartbeat(self) -> None:
        verdict = self._power_ups.take(self._now)
        if verdict == SAME_POWER_UP:
            return
        # P5: nobody asked, so it may have just (re)booted: its armed state is unknown (D15).
        self.reboots += 1
        self.fresh, self.armed, self.triggered = False, None, None
        for action in heartbeat_actions(verdict):
            self._know(action)

    def _boot_count(self, count: int) -> None:
        previous, self.boot_count = self.boot_count, count
        self.boot_reads += 1
        if previous is None and self._stored is not None:
            stored, self._stored = self._stored, None
            if stored.boot_count == count:
                self._know(Log('warn', f'{stored.failed} deploy frame(s) without a successful '
                               f'acknowledgement in this power-up (boot {count}), sent by an '
                               'earlier run of the driver: they count (P11)'))
                self._know(Record.of('state', event='deploy attempts of an earlier run',
                                     boot_count=count, failed_deploys=stored.failed,
                                     unacked_deploys=stored.unacked))
            else:
                # Another power-up: the module forgot them (P19), but not those sent after the
                # earlier run last read the boot count (they may have gone to this one).
                since = getattr(stored, 'since_read', 0)
                self.failed = max(0, self.failed - stored.failed) + min(stored.failed, since)
                self.unacked = max(0, self.unacked - stored.unacked) + min(stored.unacked, since)
        if previous is not None and previous != count:
            self.reboots += 1
            # A new power-up forgets the attempts (P19), but not those that may have come
            # after the reboot: the frames sent since the boot count was last read.
            self.failed = min(self.failed, self._sent_since_read)
            self.unacked = min(self.unacked, self._sent_since_read)
            self.fresh, self.armed, self.triggered = False, None, None
            self._know(Log('warn', f'module boot count {previous} -> {count}: it rebooted'))
        self._sent_since_read = 0
        self._boot_read_reboots = self.reboots

    def _set_triggered(self, triggered: bool, via: str, armed: Optional[bool] = None) -> None:
        if armed is not None:
            self.armed = armed
            self.fresh = True
            self._stale = False
        if triggered and not self.triggered:
            self._triggered_seen = (self._now, via)
        changed = triggered != self.triggered
        self.triggered = triggered
        if changed:
            self._know(Record.of('state', triggered=triggered, via=via))
            if triggered:
                self._know(Log('error', f'the module reports TRIGGERED (via {via})'))
                self._report(via)
        if self.outcome_unknown and self._unknown_boot == self.boot_count:
            self._resolve_unknown(triggered, 'read after the deploy')

    def _report(self, via: str) -> None:
        if self.boot_count not in self._reported:
            self._reported.add(self.boot_count)
            self._know(Report(via, self.boot_count))

    def _resolve_unknown(self, triggered: bool, how: str) -> None:
        self.outcome_unknown = False
        outcome = 'deployed' if triggered else 'not deployed'
        self._know(Record.of('decision', SYNC_WAIT, what='deploy', outcome=outcome, resolved=how))
        self._know(Log('error' if triggered else 'warn', 'the earlier deploy whose outcome was '
                       f'unknown: {outcome} ({how})'))

    def _save(self, leaving: bool = False) -> None:
        action = SaveAttempts(self.boot_count, self.failed, self.unacked, self._sent_since_read)
        if leaving:
            self._out.append(action)  # before the frame: the procedure's own
        else:
            self._know(action)

    def _deploy_reply(self, ack: p.DeployAck, late: bool) -> None:
        self.unacked = 0
        if ack.success:
            self.failed = 0
        self._save()
        if not ack.success:
            return
        if late:
            self._know(Log('warn', 'late deploy acknowledgement: the module deployed'))
        self.armed = False
        self._set_triggered(True, 'deploy ack')
        if self.outcome_unknown:
            self._resolve_unknown(True, 'late acknowledgement')

    def _seen_triggered(self) -> str:
        if not self.triggered or self._triggered_seen is None:
            return ''
        at, via = self._triggered_seen
        text = f'the module reported TRIGGERED (via {via}'
        if self._frame_at is not None and at >= self._frame_at:
            text += f', {(at - self._frame_at) * 1000:.0f} ms after the deploy frame left'
        return text + ')'

    def _reread_done(self, armed: bool) -> None:
        """Take a re-read: armed and triggered are this power-up's (D15)."""
        self._stale = False
        if self.mirror:
            self.fresh = self._told_fresh  # as the caller took the reply
        else:
            self.armed, self.fresh = armed, True
