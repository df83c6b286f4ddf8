"""The MAVLink port of the autopilot link: pymavlink, a reader thread, reopening, never a crash.

`MavlinkPort` opens a pymavlink connection string (``udpout:``, ``udpin:``, ``tcp:``, a serial
device with ``,BAUD``), retries every ``REOPEN_S`` while it cannot, decodes what arrives into
the core's events (`parachute_mavlink_ros.core`) and hands them to ``on_event``; `send()` writes
one message. Garbage arrives as pymavlink's BAD_DATA and becomes a `BadData` event; an
exception of the socket or the device closes the port and it is reopened.
"""

from __future__ import annotations

import os
import threading
from typing import Any, Callable, Optional

from parachute_mavlink_ros import core as c

os.environ.setdefault('MAVLINK20', '1')  # MAVLink 2 (STATUSTEXT chunks), before pymavlink loads
from pymavlink import mavutil  # noqa: E402

REOPEN_S = 2.0
READ_WAIT_S = 0.2


def to_event(msg: Any) -> Optional[c.Event]:
    """Return the core's event for one pymavlink message (None: not one the core uses)."""
    kind = msg.get_type()
    if kind == 'BAD_DATA':
        return c.BadData(str(getattr(msg, 'reason', 'bad data')))
    if kind == 'HEARTBEAT':
        return c.Heartbeat(msg.get_srcSystem(), msg.get_srcComponent(), msg.type,
                           msg.autopilot, msg.base_mode)
    if kind in ('COMMAND_LONG', 'COMMAND_INT'):
        params = (msg.param1, msg.param2, msg.param3, msg.param4,
                  float(msg.x if kind == 'COMMAND_INT' else msg.param5),
                  float(msg.y if kind == 'COMMAND_INT' else msg.param6),
                  msg.z if kind == 'COMMAND_INT' else msg.param7)
        return c.Command(msg.get_srcSystem(), msg.get_srcComponent(), msg.target_system,
                         msg.target_component, msg.command, params,
                         getattr(msg, 'confirmation', 0), kind)
    if kind == 'COMMAND_ACK':
        return c.Ack(msg.get_srcSystem(), msg.get_srcComponent(), msg.command, msg.result,
                     getattr(msg, 'target_system', 0), getattr(msg, 'target_component', 0))
    return None


class MavlinkPort:
    """One MAVLink connection with its reader thread."""

    def __init__(self, url: str, component_id: int,
                 on_event: Callable[[c.Event], None],
                 on_error: Callable[[str], None]) -> None:
        self.url = url
        self.component_id = component_id
        self._on_event = on_event
        self._on_error = on_error
        self._conn: Any = None
        self._lock = threading.Lock()  # guards _conn and writes
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='mavlink-reader', daemon=True)
        self.sysid = 0

    def start(self) -> 'MavlinkPort':
        """Start the reader (it opens the port, with retries)."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the reader and close the port (bounded)."""
        self._stop.set()
        self._thread.join(2.0)
        self._close()

    def send(self, kind: str, fields: dict, sysid: int) -> bool:
        """Send one message from system `sysid`; False when the port is not open or failed."""
        with self._lock:
            conn = self._conn
            if conn is None:
                return False
            try:
                conn.mav.srcSystem = sysid
                conn.mav.srcComponent = self.component_id
                if kind == 'statustext':
                    fields = dict(fields, text=fields['text'].encode('utf-8', 'replace')[:50])
                getattr(conn.mav, kind + '_send')(**fields)
                return True
            except Exception as exc:  # noqa: BLE001 - a write error is a link fault, not a crash
                self._on_error(f'write failed: {exc!r}')
                return False

    def _close(self) -> None:
        with self._lock:
            conn, self._conn = self._conn, None
        if conn is not None:
            try:
                conn.close()
            except Exception:  # noqa: BLE001 - closing a broken port
                pass

    def _open(self) -> Any:
        return mavutil.mavlink_connection(self.url, source_system=max(self.sysid, 1),
                                          source_component=self.component_id,
                                          autoreconnect=False)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn = self._open()
            except Exception as exc:  # noqa: BLE001 - a port that cannot be opened is reported
                self._on_event(c.LinkState(False, f'cannot open {self.url}: {exc}'))
                self._stop.wait(REOPEN_S)
                continue
            with self._lock:
                self._conn = conn
            self._on_event(c.LinkState(True))
            try:
                while not self._stop.is_set():
                    msg = conn.recv_match(blocking=True, timeout=READ_WAIT_S)
                    if msg is None:
                        continue
                    try:
                        event = to_event(msg)
                    except Exception as exc:  # noqa: BLE001 - a message we cannot read
                        event = c.BadData(f'undecodable {msg.get_type()}: {exc!r}')
                    if event is not None:
                        self._on_event(event)
            except Exception as exc:  # noqa: BLE001 - the port broke: reopen it
                if not self._stop.is_set():
                    self._on_event(c.LinkState(False, f'{self.url}: {exc!r}'))
                self._close()
                self._stop.wait(REOPEN_S)
