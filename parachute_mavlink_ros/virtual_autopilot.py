"""``virtual_autopilot``: a small pymavlink flight controller for the demo, the launch and tests.

It heartbeats as a PX4 quadrotor (MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, armed: flying) from
(``system_id``, ``component_id``), acknowledges the motor stops (MAV_CMD_COMPONENT_ARM_DISARM,
MAV_CMD_DO_FLIGHTTERMINATION: it disarms) and MAV_CMD_NAV_RETURN_TO_LAUNCH, logs what it
receives and publishes it on ``~/received`` (``std_msgs/String``, one line per message).

Parameters (runtime): ``answer`` ``accept`` | ``refuse`` (DENIED) | ``late`` (ACCEPTED after
``ack_delay_s``) | ``ignore`` (no ACK); ``silent`` true: no heartbeat and no answer at all (a
vanished autopilot). Services (``std_srvs/Trigger``): ``~/parachute_release``,
``~/parachute_enable``, ``~/parachute_disable`` send MAV_CMD_DO_PARACHUTE to the parachute
(resent with ``confirmation`` + 1 until acknowledged, as the command protocol says) and reply
with the final COMMAND_ACK; ``~/rearm`` arms the virtual vehicle again.
"""

from __future__ import annotations

import os
import threading
import time
from typing import Any, Dict, List, Optional

from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger

from parachute_mavlink_ros import core as c
from uav_serial_common.node_main import run_node
from uav_serial_common.params import declare_and_check, ParameterBinding, ParamSpec

os.environ.setdefault('MAVLINK20', '1')
from pymavlink import mavutil  # noqa: E402

MAV_TYPE_QUADROTOR = 2
MAV_AUTOPILOT_PX4 = 12
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_STATE_ACTIVE = 4
MAV_STATE_STANDBY = 3
ANSWERS = ('accept', 'refuse', 'late', 'ignore')
MOTOR_STOPS = (c.MAV_CMD_COMPONENT_ARM_DISARM, c.MAV_CMD_DO_FLIGHTTERMINATION)
ANSWERED = MOTOR_STOPS + (c.MAV_CMD_NAV_RETURN_TO_LAUNCH,)

PARAMS = (
    ParamSpec('mavlink_url', 'udpin:127.0.0.1:14550', 'pymavlink connection string',
              read_only=True),
    ParamSpec('system_id', 1, 'system id of the virtual vehicle', int_range=(1, 255),
              read_only=True),
    ParamSpec('component_id', 1, 'component id (MAV_COMP_ID_AUTOPILOT1)', int_range=(1, 255),
              read_only=True),
    ParamSpec('parachute_component_id', 161, 'component the DO_PARACHUTE services address',
              int_range=(0, 255)),
    ParamSpec('answer', 'accept', 'answer to motor stops and RETURN_TO_LAUNCH',
              choices=ANSWERS),
    ParamSpec('ack_delay_s', 0.5, 'under answer late: delay of the ACK [s]',
              float_range=(0.0, 10.0)),
    ParamSpec('silent', False, 'no heartbeat and no answer at all (a vanished autopilot)'),
    ParamSpec('command_timeout_s', 10.0, 'how long the DO_PARACHUTE services wait for the '
              'final ACK [s]', float_range=(0.5, 60.0)),
)


class VirtualAutopilot(Node):
    """A pymavlink flight controller that heartbeats and answers motor stops."""

    def __init__(self) -> None:
        super().__init__('virtual_autopilot')
        self.values: Dict[str, Any] = declare_and_check(self, PARAMS)
        ParameterBinding(self, PARAMS, apply=self.values.update)
        self.armed = True
        url = self.values['mavlink_url']
        try:
            self.conn = mavutil.mavlink_connection(
                url, source_system=self.values['system_id'],
                source_component=self.values['component_id'], autoreconnect=False)
        except Exception as exc:  # noqa: BLE001 - pymavlink raises what its transport does
            raise OSError(f'cannot open mavlink_url {url!r}: {exc}') from None
        self._lock = threading.Lock()   # guards writes to the connection and _acks
        self._acks: List[Any] = []
        self._acks_cond = threading.Condition(self._lock)
        self._stop = threading.Event()
        self.received_pub = self.create_publisher(String, '~/received', 50)
        group = ReentrantCallbackGroup()
        for name, action in (('parachute_release', c.PARACHUTE_RELEASE),
                             ('parachute_enable', c.PARACHUTE_ENABLE),
                             ('parachute_disable', c.PARACHUTE_DISABLE)):
            self.create_service(Trigger, f'~/{name}',
                                lambda q, r, a=action: self._do_parachute(a, r),
                                callback_group=group)
        self.create_service(Trigger, '~/rearm', self._rearm, callback_group=group)
        for target, name in ((self._heartbeats, 'va-heartbeat'), (self._read, 'va-reader')):
            threading.Thread(target=target, name=name, daemon=True).start()
        self.get_logger().info(
            f'virtual autopilot {self.values["system_id"]}/{self.values["component_id"]} on '
            f'{self.values["mavlink_url"]}; motor stops: {self.values["answer"]}')

    def _write(self, kind: str, **fields: Any) -> None:
        with self._lock:
            try:
                getattr(self.conn.mav, kind + '_send')(**fields)
            except Exception as exc:  # noqa: BLE001 - a virtual device never dies of a write
                self.get_logger().warning(f'write failed: {exc!r}', throttle_duration_sec=5.0)

    def _heartbeats(self) -> None:
        while not self._stop.wait(1.0 if self._heartbeat() else 0.2):
            pass

    def _heartbeat(self) -> bool:
        if self.values['silent']:
            return False
        mode = MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (MAV_MODE_FLAG_SAFETY_ARMED
                                                    if self.armed else 0)
        self._write('heartbeat', type=MAV_TYPE_QUADROTOR, autopilot=MAV_AUTOPILOT_PX4,
                    base_mode=mode, custom_mode=0,
                    system_status=MAV_STATE_ACTIVE if self.armed else MAV_STATE_STANDBY)
        return True

    def _publish(self, text: str) -> None:
        self.get_logger().info(text)
        self.received_pub.publish(String(data=text))

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.conn.recv_match(blocking=True, timeout=0.2)
            except Exception as exc:  # noqa: BLE001 - keep reading
                self.get_logger().warning(f'read failed: {exc!r}', throttle_duration_sec=5.0)
                time.sleep(0.1)
                continue
            if msg is None or self.values['silent']:
                continue
            try:
                self._on_message(msg)
            except Exception as exc:  # noqa: BLE001 - keep reading
                self.get_logger().error(f'handling {msg}: {exc!r}')

    def _on_message(self, msg: Any) -> None:
        kind = msg.get_type()
        src = f'{msg.get_srcSystem()}/{msg.get_srcComponent()}'
        if kind == 'HEARTBEAT':
            if msg.type == c.MAV_TYPE_PARACHUTE:
                return  # once a second: not worth a line
            self._publish(f'HEARTBEAT from {src} type {msg.type}')
        elif kind == 'STATUSTEXT':
            text = msg.text if isinstance(msg.text, str) else msg.text.decode('utf-8', 'replace')
            self._publish(f'STATUSTEXT from {src} severity {msg.severity}: {text}')
        elif kind == 'COMMAND_ACK':
            self._publish(f'COMMAND_ACK from {src} command {msg.command} result '
                          f'{c.RESULT_NAMES.get(msg.result, msg.result)} reason '
                          f'{msg.result_param2}')
            with self._acks_cond:
                self._acks.append(msg)
                self._acks_cond.notify_all()
        elif kind in ('COMMAND_LONG', 'COMMAND_INT'):
            if msg.target_system not in (0, self.values['system_id']) or \
                    msg.target_component not in (0, self.values['component_id']):
                return
            self._publish(f'{kind} from {src} command {msg.command} param1 {msg.param1} '
                          f'param2 {msg.param2} confirmation {getattr(msg, "confirmation", 0)}')
            if msg.command in ANSWERED:
                self._answer(msg)

    def _answer(self, msg: Any) -> None:
        answer = self.values['answer']
        if answer == 'ignore':
            return
        result = c.MAV_RESULT_DENIED if answer == 'refuse' else c.MAV_RESULT_ACCEPTED
        if result == c.MAV_RESULT_ACCEPTED and msg.command in MOTOR_STOPS:
            self.armed = False
        to = dict(command=msg.command, result=result, progress=0, result_param2=0,
                  target_system=msg.get_srcSystem(), target_component=msg.get_srcComponent())
        if answer == 'late':
            timer = threading.Timer(self.values['ack_delay_s'],
                                    lambda: self._write('command_ack', **to))
            timer.daemon = True
            timer.start()
        else:
            self._write('command_ack', **to)

    def _do_parachute(self, action: int, response: Trigger.Response) -> Any:
        target = self.values['system_id'], self.values['parachute_component_id']
        with self._lock:
            start = len(self._acks)
        t0 = time.monotonic()
        deadline = t0 + self.values['command_timeout_s']
        confirmation = 0
        final: Optional[Any] = None
        in_progress = False
        while final is None and time.monotonic() < deadline:
            if not in_progress:
                self._write('command_long', target_system=target[0], target_component=target[1],
                            command=c.MAV_CMD_DO_PARACHUTE, confirmation=confirmation,
                            param1=float(action), param2=0, param3=0, param4=0, param5=0,
                            param6=0, param7=0)
                confirmation = min(confirmation + 1, 255)
            wait_until = min(deadline, time.monotonic() + (5.0 if in_progress else 1.5))
            with self._acks_cond:
                while final is None and time.monotonic() < wait_until:
                    for ack in self._acks[start:]:
                        if ack.command != c.MAV_CMD_DO_PARACHUTE:
                            continue
                        if ack.result == c.MAV_RESULT_IN_PROGRESS:
                            in_progress = True
                        else:
                            final = ack
                    start = len(self._acks)
                    if final is None:
                        self._acks_cond.wait(max(0.0, wait_until - time.monotonic()))
        ms = (time.monotonic() - t0) * 1000.0
        if final is None:
            response.success = False
            response.message = f'no final COMMAND_ACK within {ms:.0f} ms'
        else:
            name = c.RESULT_NAMES.get(final.result, str(final.result))
            response.success = final.result == c.MAV_RESULT_ACCEPTED
            response.message = (f'{name} (result_param2 {final.result_param2}: '
                                f'{c.REASON_NAMES.get(final.result_param2, "?")}) in '
                                f'{ms:.0f} ms')
        return response

    def _rearm(self, request: Any, response: Trigger.Response) -> Any:
        self.armed = True
        response.success, response.message = True, 'armed (flying)'
        return response

    def on_shutdown(self) -> None:
        """Stop the threads and close the socket."""
        self._stop.set()
        time.sleep(0.25)
        try:
            self.conn.close()
        except Exception:  # noqa: BLE001 - closing anyway
            pass


def main(args: Optional[list] = None) -> int:
    """Run the virtual autopilot until Ctrl-C."""
    return run_node(VirtualAutopilot, args, threads=4)


if __name__ == '__main__':
    import sys
    sys.exit(main())
