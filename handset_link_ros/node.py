"""``handset_link_node``: the drone end of the handset's radio link, as a thin ROS adapter.

The device is ``core.HandsetCore`` (no ROS): it reads the radio modem's port, decodes, validates,
keeps the link health and the failsafe rules. This node turns parameters into its config, the
battery topic into ``on_battery()``, its callbacks into messages (``messages.py``) and its
snapshots into ``/diagnostics``. Nothing is ever written to the port (H11).

Threads: setpoints and auxiliary changes arrive on the link's reader thread and are published
from right there (rclpy's publish is thread-safe), so a setpoint leaves within the read that
completed its frame (H7); a lost link arrives on the core's timer thread; the battery, the 1 Hz
``~/link`` and the diagnostics run on the executor. Decisions: ``docs/protocols.md`` (Handset
link, H1-H25).
"""

from __future__ import annotations

import math
import threading
import time
import traceback
from typing import Any, Dict, Optional, Tuple

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from rclpy.validate_topic_name import validate_topic_name
from sensor_msgs.msg import BatteryState
from uav_serial_drivers.msg import Failsafe, HandsetAuxiliary, HandsetLink, HandsetSetpoint

from handset_link_ros import messages
from handset_link_ros.core import HandsetConfig, HandsetCore
from uav_serial_common.diagnostics import DiagnosticsUpdater, ERROR, OK, Status, WARN
from uav_serial_common.logs import log_at
from uav_serial_common.node_main import run_node
from uav_serial_common.params import declare_and_check, ParameterBinding, ParamSpec

LOW_RATE_FRACTION = 0.8
"""A measured command rate below this share of ``expected_rate_hz`` is a warning."""
LINK_PERIOD_S = 1.0
RUNTIME = ('link_timeout_s', 'expected_rate_hz', 'low_battery_fraction', 'battery_timeout_s')
"""Parameters the core takes while running (``HandsetCore.reconfigure``)."""


def _topic_problem(name: str) -> str:
    if not name:
        return ''
    try:
        validate_topic_name(name)
    except Exception as exc:  # noqa: BLE001 - rclpy's own wording of what is wrong
        return f'battery_topic {name!r} is not a valid topic name: ' \
            f'{str(exc).splitlines()[0]}'
    return ''


SPECS = (
    ParamSpec('port', '/dev/ttyUSB2', 'serial device or pyserial URL of the radio modem',
              read_only=True),
    ParamSpec('baud', 115200, 'baud rate of the radio modem', read_only=True,
              int_range=(1, 4_000_000)),
    ParamSpec('frame_id', 'handset', 'header.frame_id of published messages'),
    ParamSpec('link_timeout_s', 5.0, 'a stick setpoint (yaw, pitch, roll, altitude) not '
              'refreshed by a valid frame for this long = link lost (H8); auxiliary frames do '
              'not count [s]', float_range=(0.1, 3600.0)),
    ParamSpec('expected_rate_hz', 50.0, "the handset's frame rate; a measured command rate "
              'below 80 % of it is a diagnostics warning [Hz]', float_range=(0.1, 1000.0)),
    ParamSpec('battery_topic', 'battery', 'sensor_msgs/BatteryState of the aircraft (H9); '
              'empty = no battery check', startup_only=True, check=_topic_problem),
    ParamSpec('low_battery_fraction', 0.20, 'battery below this fraction is low (H9); it '
              'clears 0.05 above', float_range=(0.0, 0.95)),
    ParamSpec('battery_timeout_s', 10.0, 'a battery reading older than this is stale: the '
              'battery is unknown (diagnostics WARN; no return to home by itself, a low battery '
              'stays low) [s]', float_range=(0.1, 3600.0)),
)


EXECUTOR_THREADS = 2
"""Threads of the executor's pool (``main()``; the tests' in-process driver reads it)."""


class HandsetLinkNode(Node):
    """The handset link driver."""

    def __init__(self, **node_options: Any) -> None:
        super().__init__('handset_link', **node_options)
        values = declare_and_check(self, SPECS)
        self.frame_id: str = values['frame_id']
        self._setpoint = messages.SetpointPacker(self.frame_id)
        self.battery_topic: str = values['battery_topic']
        config = HandsetConfig(port=values['port'], baud=values['baud'],
                               **{name: values[name] for name in RUNTIME})
        self._battery_lock = threading.Lock()
        self._battery_msgs = 0

        reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._setpoint_pub = self.create_publisher(HandsetSetpoint, '~/setpoint', reliable)
        self._auxiliary_pub = self.create_publisher(HandsetAuxiliary, '~/auxiliary', latched)
        self._link_pub = self.create_publisher(HandsetLink, '~/link', reliable)
        self._failsafe_pub = self.create_publisher(Failsafe, '~/failsafe', latched)
        self.diagnostics = DiagnosticsUpdater(self, config.port)
        self.diagnostics.add('link', self._diagnose_link)
        self.diagnostics.add('battery', self._diagnose_battery)

        self.core = HandsetCore(config, on_setpoint=self._on_setpoint,
                                on_auxiliary=self._on_auxiliary, on_link=self._on_link,
                                on_failsafe=self._on_failsafe, on_log=self._on_log)
        if self.battery_topic:
            # Best effort matches reliable and best-effort publishers alike (flight-controller
            # bridges publish BatteryState either way); the battery repeats, so a lost one is
            # replaced by the next.
            self.create_subscription(BatteryState, self.battery_topic, self._on_battery,
                                     qos_profile_sensor_data)
        ParameterBinding(self, SPECS, apply=self._apply, commit=self._commit)
        self.create_timer(LINK_PERIOD_S, self._publish_link)
        self.core.start()
        battery = self.resolve_topic_name(self.battery_topic) if self.battery_topic else 'off'
        self.get_logger().info(
            f'handset link on {config.port} at {config.baud} baud (read only, H11); link lost '
            f'when a stick setpoint is {config.link_timeout_s:g} s old; battery: {battery} '
            f'(unknown after {config.battery_timeout_s:g} s without a reading)')

    # -- core callbacks (reader, timer or executor thread) -------------------------------------

    def _stamp(self, stamp: float = math.nan) -> Any:
        return messages.ros_stamp(stamp, time.monotonic(), self.get_clock().now().nanoseconds)

    def _on_setpoint(self, setpoint: Any) -> None:
        # The per-frame path: serialized bytes (SetpointPacker), and the ROS clock read only
        # on simulated time (else it is the wall clock).
        clock = self.get_clock()
        now_ns = clock.now().nanoseconds if clock.ros_time_is_active else time.time_ns()
        self._setpoint_pub.publish(self._setpoint.pack(
            setpoint, *messages.ros_time_ns(setpoint.stamp, time.monotonic(), now_ns)))

    def _on_auxiliary(self, auxiliary: Any) -> None:
        self._auxiliary_pub.publish(
            messages.auxiliary_msg(auxiliary, self.frame_id, self._stamp(auxiliary.stamp)))

    def _on_link(self, state: Any) -> None:
        self._link_pub.publish(messages.link_msg(state, self.frame_id, self._stamp()))
        self.diagnostics.force_update()

    def _on_failsafe(self, state: Any) -> None:
        self._failsafe_pub.publish(messages.failsafe_msg(state, self.frame_id, self._stamp()))
        self.diagnostics.force_update()

    def _on_log(self, level: str, text: str) -> None:
        log_at(self.get_logger(), level, text)

    # -- executor callbacks --------------------------------------------------------------------

    def _on_battery(self, msg: BatteryState) -> None:
        try:
            with self._battery_lock:
                self._battery_msgs += 1
            self.core.on_battery(msg.percentage)
        except Exception:  # noqa: BLE001 - no input ends the process
            self.get_logger().error(f'battery message not taken:\n{traceback.format_exc()}')

    def _publish_link(self) -> None:
        try:
            self._link_pub.publish(
                messages.link_msg(self.core.link_state(), self.frame_id, self._stamp()))
        except Exception:  # noqa: BLE001 - the next period tries again
            self.get_logger().error(f'~/link not published:\n{traceback.format_exc()}')

    def _commit(self, changes: Dict[str, Any]) -> Tuple[bool, str]:
        core_changes = {k: v for k, v in changes.items() if k in RUNTIME}
        if core_changes:
            try:
                self.core.reconfigure(**core_changes)
            except ValueError as exc:
                return False, str(exc)
        return True, ''

    def _apply(self, changes: Dict[str, Any]) -> None:
        if 'frame_id' in changes:
            self.frame_id = changes['frame_id']
            self._setpoint.set_frame_id(self.frame_id)
        self.diagnostics.force_update()

    # -- diagnostics ---------------------------------------------------------------------------

    def _diagnose_link(self, stat: Status) -> None:
        state, failsafe, config = self.core.link_state(), self.core.failsafe(), self.core.config
        port_error = self.core.link.serial.last_error
        for key, value in (('connected', state.connected), ('port_open', state.port_open),
                           ('frame_rate_hz', f'{state.frame_rate_hz:.1f}'),
                           ('command_rate_hz', f'{state.command_rate_hz:.1f}'),
                           ('expected_rate_hz', f'{config.expected_rate_hz:g}'),
                           ('frames_accepted', state.frames_accepted),
                           ('frames_malformed', state.frames_malformed),
                           ('frames_out_of_range', state.frames_out_of_range),
                           ('frames_unknown_type', state.frames_unknown_type),
                           ('frames_rejected_last_second', state.frames_rejected_recently),
                           ('last_frame_age_s', f'{state.last_frame_age_s:.3f}'),
                           ('stick_age_s', f'{state.stick_age_s:.3f}'),
                           ('link_timeout_s', f'{config.link_timeout_s:g}'),
                           ('port_error', port_error)):
            stat.add(key, value)
        port = '' if state.port_open else \
            f'; modem port not open ({port_error or "opening"}), retrying'
        if state.port_open and not state.frames_accepted and state.frames_malformed:
            port = '; bytes arrive but not one valid handset frame: wrong baud rate? check the ' \
                '`baud` parameter against the modem'
        # Said in every state: frames refused while the link waits or is lost may be why.
        rejected = '' if not state.frames_rejected_recently else \
            f'; {state.frames_rejected_recently} frame(s) rejected in the last second ' \
            '(malformed, out of range or unknown type)'
        if failsafe.link_lost:
            stat.summary(ERROR, f'link lost: a stick setpoint not refreshed by a valid handset '
                                f'frame for {config.link_timeout_s:g} s; requesting return to '
                                f'home{port}{rejected}')
            return
        if not state.connected:
            stat.summary(WARN, f'waiting for the four stick setpoints of the handset (link lost '
                               f'after {config.link_timeout_s:g} s){port}{rejected}')
            return
        stat.summary(OK, f'receiving {state.command_rate_hz:.1f} commands/s')
        if not state.port_open:
            stat.merge_summary(WARN, port.lstrip('; '))
        floor = LOW_RATE_FRACTION * config.expected_rate_hz
        if state.command_rate_hz < floor:
            stat.merge_summary(WARN, f'below {LOW_RATE_FRACTION * 100:.0f} % of the expected '
                                     f'{config.expected_rate_hz:g} Hz')
        if rejected:
            stat.merge_summary(WARN, rejected[2:])

    def _diagnose_battery(self, stat: Status) -> None:
        failsafe = self.core.failsafe()
        low = self.core.config.low_battery_fraction
        with self._battery_lock:
            received = self._battery_msgs
        stat.add('battery_topic', self.battery_topic)
        stat.add('battery_fraction', f'{failsafe.battery_fraction:.3f}')
        stat.add('low_battery_fraction', f'{low:g}')
        stat.add('messages_received', received)
        stat.add('percentages_outside_0_1', self.core.battery_out_of_range)
        last, age = self.core.battery_last()
        timeout = self.core.config.battery_timeout_s
        stat.add('battery_age_s', f'{age:.3f}')
        stat.add('battery_timeout_s', f'{timeout:g}')
        stat.add('battery_stale', failsafe.battery_stale)
        if not self.battery_topic:
            stat.summary(OK, 'no battery check (battery_topic is empty)')
        elif failsafe.battery_low:
            stale = f' (no reading for {age:.1f} s)' if failsafe.battery_stale else ''
            stat.summary(WARN, f'battery low: {last * 100:.1f} % < {low * 100:.0f} %{stale}; '
                               f'requesting return to home')
        elif failsafe.battery_stale:
            topic = self.resolve_topic_name(self.battery_topic)
            stat.summary(WARN, f'battery unknown: no usable BatteryState on {topic} for '
                               f'{age:.1f} s (> {timeout:g} s; last {last * 100:.1f} %): the '
                               f'low-battery failsafe cannot act')
        elif math.isnan(failsafe.battery_fraction):
            topic = self.resolve_topic_name(self.battery_topic)
            what = 'no BatteryState received' if not received else \
                f'{received} BatteryState message(s) without a usable percentage'
            stat.summary(WARN, f'{what} on {topic}: the low-battery failsafe cannot act')
        else:
            stat.summary(OK, f'battery {failsafe.battery_fraction * 100:.1f} %')

    def on_shutdown(self) -> None:
        """Stop the core (timer thread, reader thread, port) before the node goes away."""
        self.core.stop()


def main(args: Optional[list] = None) -> int:
    """Run ``handset_link_node`` until Ctrl-C."""
    return run_node(HandsetLinkNode, args, threads=EXECUTOR_THREADS)


if __name__ == '__main__':
    import sys
    sys.exit(main())
