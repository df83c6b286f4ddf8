"""What the autopilot-link tests share: a MAVLink hub on loopback UDP and the rig of processes.

`Hub` is a small mavlink-router in the test process: ``parachute_mavlink`` listens on a UDP
port (``udpin``) that the hub sends to, the virtual autopilot sends to the hub's other port
(``udpout``), and the hub forwards between them, decoding and recording every message with its
time. The test injects its own messages (a ground station's DO_PARACHUTE, a second autopilot,
garbage) towards the node through it, as any other MAVLink endpoint would.

`MavlinkRig` is the whole stack of real processes: the virtual parachute (in this process, its
wire tapped, as `parachute_rig.Rig` has it), ``parachute_node`` with its release gate pointed
at ``parachute_mavlink``, ``virtual_autopilot`` and ``parachute_mavlink``.
"""

from __future__ import annotations

import os
import select
import socket
import struct
import threading
import time
from typing import Any, Callable, List, Optional, Tuple

from diagnostic_msgs.msg import DiagnosticArray
from parachute_rig import Rig
from rcl_interfaces.msg import Parameter
from rcl_interfaces.srv import SetParameters
from std_msgs.msg import String
from uav_serial_common.process import wait_for, wait_scale

os.environ.setdefault('MAVLINK20', '1')
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from uav_serial_drivers.msg import MavlinkLink  # noqa: E402

GCS = (255, 190)
GATE = '/parachute_mavlink/release_gate'


def free_udp_port() -> int:
    """Return a UDP port of 127.0.0.1 that nothing holds right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(('127.0.0.1', 0))
        return sock.getsockname()[1]


SO_TIMESTAMPNS = 35
"""Linux: the kernel stamps each datagram with its arrival (not in Python's socket module)."""


def arrival_time(ancdata: list) -> float:
    """When a datagram reached its socket, on the monotonic clock (now, without a stamp).

    The hub runs in the test's process: a loaded host holds its thread, and the time it read a
    datagram can be later than a frame the node sent after it, seen by another thread.
    """
    for level, kind, data in ancdata:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= 16:
            sec, nsec = struct.unpack('qq', data[:16])
            return sec + nsec * 1e-9 - (time.time() - time.monotonic())
    return time.monotonic()


class Hub:
    """Forward MAVLink between the node and the autopilot; record and inject."""

    def __init__(self) -> None:
        self.node_port = free_udp_port()
        self.to_node = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.to_node.bind(('127.0.0.1', 0))
        self.from_ap = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.from_ap.bind(('127.0.0.1', 0))
        self.ap_port = self.from_ap.getsockname()[1]
        self.ap_address: Optional[Tuple[str, int]] = None
        self.records: List[Tuple[float, str, Any]] = []  # (time, 'node' | 'ap', message)
        self._cond = threading.Condition()
        self._parsers = {'node': mavlink.MAVLink(None), 'ap': mavlink.MAVLink(None)}
        for parser in self._parsers.values():
            parser.robust_parsing = True
        self.encoder = mavlink.MAVLink(None, srcSystem=GCS[0], srcComponent=GCS[1])
        self.drop_to_node = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='mavlink-hub', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        socks = [self.to_node, self.from_ap]
        for sock in socks:
            sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        while not self._stop.is_set():
            ready, _, _ = select.select(socks, [], [], 0.1)
            for sock in ready:
                try:
                    data, ancdata, _, address = sock.recvmsg(65535, socket.CMSG_SPACE(16))
                except OSError:
                    continue
                now = arrival_time(ancdata)
                side = 'node' if sock is self.to_node else 'ap'
                if side == 'ap':
                    self.ap_address = address
                    if not self.drop_to_node:
                        self._send_node(data)
                elif self.ap_address is not None:
                    try:
                        self.from_ap.sendto(data, self.ap_address)
                    except OSError:
                        pass
                try:
                    messages = self._parsers[side].parse_buffer(data) or []
                except Exception:  # noqa: BLE001 - a record of garbage is no message
                    messages = []
                with self._cond:
                    self.records += [(now, side, m) for m in messages
                                     if m.get_type() != 'BAD_DATA']
                    self._cond.notify_all()

    def _send_node(self, data: bytes) -> None:
        try:
            self.to_node.sendto(data, ('127.0.0.1', self.node_port))
        except OSError:
            pass

    def inject(self, data: bytes) -> None:
        """Send raw bytes to the node."""
        self._send_node(data)

    def send(self, msg: Any, source: Tuple[int, int] = GCS) -> float:
        """Encode `msg` from system/component `source`, send it to the node; return the time."""
        self.encoder.srcSystem, self.encoder.srcComponent = source
        data = msg.pack(self.encoder)
        t = time.monotonic()
        self._send_node(data)
        return t

    def do_parachute(self, action: float, target: Tuple[int, int] = (1, 161),
                     kind: str = 'COMMAND_LONG', confirmation: int = 0,
                     source: Tuple[int, int] = GCS) -> float:
        """Send MAV_CMD_DO_PARACHUTE `action`; return the time it left."""
        if kind == 'COMMAND_LONG':
            msg = mavlink.MAVLink_command_long_message(
                target[0], target[1], mavlink.MAV_CMD_DO_PARACHUTE, confirmation,
                float(action), 0, 0, 0, 0, 0, 0)
        else:
            msg = mavlink.MAVLink_command_int_message(
                target[0], target[1], 0, mavlink.MAV_CMD_DO_PARACHUTE, 0, 0,
                float(action), 0, 0, 0, 0, 0, 0)
        return self.send(msg, source)

    def mark(self) -> int:
        """Return a position to look from."""
        with self._cond:
            return len(self.records)

    def since(self, mark: int, side: Optional[str] = None, kind: Optional[str] = None,
              where: Callable[[Any], bool] = lambda m: True) -> List[Tuple[float, Any]]:
        """Return (time, message) recorded since `mark`, from `side`, of type `kind`."""
        with self._cond:
            records = self.records[mark:]
        return [(t, m) for t, s, m in records if (side is None or s == side)
                and (kind is None or m.get_type() == kind) and where(m)]

    def wait(self, mark: int, side: str, kind: str, where: Callable[[Any], bool] = lambda m: True,
             timeout: float = 10.0, what: str = '') -> Tuple[float, Any]:
        """Wait for a message from `side` of type `kind` matching `where`; return it.

        `timeout` is stretched by `wait_scale()`, as every wait of the suite (beside a busy
        loop a STATUSTEXT came later than an unstretched 10 s).
        """
        timeout *= wait_scale()
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for t, s, m in self.records[mark:]:
                    if s == side and m.get_type() == kind and where(m):
                        return t, m
                left = deadline - time.monotonic()
                if left <= 0:
                    last = [m for _, s, m in self.records[-5:]]
                    raise AssertionError(f'timed out after {timeout:g} s waiting for {kind} from '
                                         f'{side} {what}; last: {last}')
                self._cond.wait(left)

    def acks(self, mark: int, to: Tuple[int, int] = GCS) -> List[Any]:
        """Return the COMMAND_ACKs of DO_PARACHUTE the node sent to `to` since `mark`."""
        return [m for _, m in self.since(mark, 'node', 'COMMAND_ACK', lambda m: (
            m.command == mavlink.MAV_CMD_DO_PARACHUTE
            and (m.target_system, m.target_component) == to))]

    def final_ack(self, mark: int, to: Tuple[int, int] = GCS, timeout: float = 15.0) -> Any:
        """Wait for the final (not IN_PROGRESS) DO_PARACHUTE ACK to `to`."""
        return self.wait(mark, 'node', 'COMMAND_ACK', lambda m: (
            m.command == mavlink.MAV_CMD_DO_PARACHUTE
            and (m.target_system, m.target_component) == to
            and m.result != mavlink.MAV_RESULT_IN_PROGRESS), timeout, 'final ack')[1]

    def texts(self, mark: int) -> List[str]:
        """Return the STATUSTEXTs the node sent since `mark`."""
        return [m.text for _, m in self.since(mark, 'node', 'STATUSTEXT')]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.to_node.close()
        self.from_ap.close()


def motor_stops(hub: Hub, mark: int) -> List[Tuple[float, Any]]:
    """Return the motor stops the autopilot received since `mark` (hub: from the node)."""
    return hub.since(mark, 'node', 'COMMAND_LONG', lambda m: m.command in (
        mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_DO_FLIGHTTERMINATION))


def sent_motor_stops(hub: Hub, mark: int, timeout: float = 10.0) -> List[Tuple[float, Any]]:
    """Wait for the node's motor stops since `mark`: a held hub thread reads them late."""
    return wait_for(lambda: motor_stops(hub, mark), timeout, what='a motor stop from the node')


class MavlinkRig(Rig):
    """The parachute rig plus the hub, the virtual autopilot and parachute_mavlink."""

    def __init__(self, tmp, link: Optional[dict] = None, autopilot: Optional[dict] = None,
                 **parachute) -> None:
        parachute.setdefault('release_gate', GATE)
        super().__init__(tmp, **parachute)
        self.hub = Hub()
        sub = self.ros.subscribe
        self.link = sub(MavlinkLink, '/parachute_mavlink/link')
        self.received = sub(String, '/virtual_autopilot/received')
        self.all_diagnostics = self.diagnostics
        ap = dict(mavlink_url=f'udpout:127.0.0.1:{self.hub.ap_port}')
        ap.update(autopilot or {})
        self.autopilot = self.procs.start('virtual_autopilot', parameters=ap, ros=self.ros,
                                          wait_service='/virtual_autopilot/parachute_release')
        params = dict(mavlink_url=f'udpin:127.0.0.1:{self.hub.node_port}')
        params.update(link or {})
        self.node = self.procs.start('parachute_mavlink', parameters=params, ros=self.ros,
                                     wait_service=GATE)

    def autopilot_param(self, name: str, value: Any) -> None:
        from parachute_rig import parameter_value
        request = SetParameters.Request(parameters=[Parameter(name=name,
                                                              value=parameter_value(value))])
        result = self.ros.call(SetParameters, '/virtual_autopilot/set_parameters',
                               request).results[0]
        assert result.successful, result.reason

    def quiet_acks(self, quiet_s: float = 0.6, timeout: float = 15.0) -> None:
        """Wait until no late ACK of an earlier test is on its way (none for `quiet_s`)."""
        def quiet() -> bool:
            acks = self.hub.since(0, 'ap', 'COMMAND_ACK')
            return not acks or time.monotonic() - acks[-1][0] > quiet_s
        wait_for(quiet, timeout, what='the late ACKs of the autopilot')

    def wait_autopilot(self, timeout: float = 15.0) -> None:
        """Wait until the node hears the autopilot."""
        self.link.wait(lambda m: m.autopilot_heard, timeout, what='autopilot heard')

    def mavlink_diagnostics(self, task: str, predicate: Callable[[Any], bool],
                            timeout: float = 10.0) -> Any:
        """Wait for a /diagnostics status of parachute_mavlink's `task` matching `predicate`."""
        name = f'/parachute_mavlink: {task}'

        def match(array: DiagnosticArray) -> bool:
            return any(s.name == name and predicate(s) for s in array.status)
        array = self.diagnostics.wait(match, timeout, what=f'diagnostics {task}')
        return [s for s in array.status if s.name == name][0]

    def close(self, failed):
        if failed:
            for proc in self.procs.processes:
                print(f'--- {proc.name} output ---\n{proc.output()}')
        self.hub.close()
        super().close(False)
