"""The ROS side that every virtual device shares: the wire-fault parameters and services.

Each virtual device (``virtual_parachute``, ``virtual_servo_bus``, ``virtual_handset``,
``virtual_originman_board``) runs its model in a
:class:`~uav_serial_common.virtual_device.VirtualDeviceRunner`. The cable and the wire are the
same for all of them, and so are these, written once here:

- the parameters ``drop_probability``, ``corrupt_probability``, ``garbage_probability`` (0..1)
  and, for a device that replies, ``reply_delay_s``: :func:`wire_fault_params` declares them,
  :meth:`VirtualDeviceNode.apply_wire_faults` puts them on ``runner.faults``;
- ``~/disconnect`` (``std_srvs/SetBool``: true unplugs the cable, the pty and its symlink vanish
  as a USB adapter's device does; false plugs it back at the same path) and ``~/inject_garbage``
  (``std_srvs/Trigger``: the device's noise goes out before its next output), and on request
  ``~/drop_next_reply`` and ``~/corrupt_next_reply`` (``std_srvs/Trigger``);
- ``on_shutdown()``, which stops the runner and removes the pty and its symlink.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Optional, Tuple

from rclpy.callback_groups import CallbackGroup
from rclpy.node import Node
from std_srvs.srv import SetBool, Trigger

from uav_serial_common.params import Check, ParamSpec
from uav_serial_common.virtual_device import VirtualDeviceRunner

WIRE_FAULTS = ('drop_probability', 'corrupt_probability', 'garbage_probability',
               'reply_delay_s')
"""The wire-fault parameters, named as the fields of ``VirtualDeviceRunner.faults``."""


def _probability(name: str) -> Check:
    def check(value: Any) -> str:
        ok = isinstance(value, (int, float)) and math.isfinite(value) and 0.0 <= value <= 1.0
        return '' if ok else f'{name} is a probability 0..1, got {value!r}'
    return check


def _delay(name: str) -> Check:
    def check(value: Any) -> str:
        ok = isinstance(value, (int, float)) and math.isfinite(value) and value >= 0.0
        return '' if ok else f'{name} must be a finite number of seconds >= 0, got {value!r}'
    return check


def wire_fault_params(unit: str = 'reply', checksum: str = 'checksum',
                      reply_delay_max_s: Optional[float] = 5.0) -> Tuple[ParamSpec, ...]:
    """Return the specs of the wire-fault parameters, all 0 (no fault) by default.

    ``unit`` names what the device sends ('reply', 'frame'), ``checksum`` what a corruption
    spoils. ``reply_delay_max_s`` None leaves ``reply_delay_s`` out, for a device that never
    answers (its output is all unsolicited).
    """
    specs = (
        ParamSpec('drop_probability', 0.0, f'chance that a {unit} is lost',
                  float_range=(0.0, 1.0), check=_probability('drop_probability')),
        ParamSpec('corrupt_probability', 0.0, f'chance that a {unit} has a bad {checksum}',
                  float_range=(0.0, 1.0), check=_probability('corrupt_probability')),
        ParamSpec('garbage_probability', 0.0, f'chance of noise before a {unit}',
                  float_range=(0.0, 1.0), check=_probability('garbage_probability')),
    )
    if reply_delay_max_s is None:
        return specs
    return specs + (ParamSpec('reply_delay_s', 0.0, 'extra delay before every reply [s]',
                              float_range=(0.0, reply_delay_max_s),
                              check=_delay('reply_delay_s')),)


class VirtualDeviceNode(Node):
    """A ROS node around one device model on a pty: the shared wire faults and cable.

    A subclass declares :func:`wire_fault_params` among its parameters, calls
    :meth:`apply_wire_faults` from its parameter ``apply`` and :meth:`serve_wire` once its runner
    exists. ``garbage`` is its noise for ``~/inject_garbage`` (stray bytes and broken headers of
    its own protocol); ``unplugged_message`` and ``replugged_message`` are the ``~/disconnect``
    answers.
    """

    garbage: bytes = b'\x00\xff'
    unplugged_message = 'unplugged'
    replugged_message = 'plugged back in'

    wire_runner: Optional[VirtualDeviceRunner] = None

    def serve_wire(self, runner: VirtualDeviceRunner,
                   callback_group: Optional[CallbackGroup] = None,
                   next_reply_services: bool = False) -> None:
        """Serve ``~/disconnect`` and ``~/inject_garbage`` (and next-reply faults) on `runner`.

        ``next_reply_services`` adds ``~/drop_next_reply`` and ``~/corrupt_next_reply``.
        """
        self.wire_runner = runner
        self.create_service(SetBool, '~/disconnect', self._srv_disconnect,
                            callback_group=callback_group)
        self.create_service(Trigger, '~/inject_garbage', self._srv_inject_garbage,
                            callback_group=callback_group)
        if next_reply_services:
            self.create_service(Trigger, '~/drop_next_reply', self._srv_drop_next,
                                callback_group=callback_group)
            self.create_service(Trigger, '~/corrupt_next_reply', self._srv_corrupt_next,
                                callback_group=callback_group)

    def apply_wire_faults(self, changes: Mapping[str, Any],
                          runner: Optional[VirtualDeviceRunner] = None) -> None:
        """Put the wire-fault parameters among `changes` on the runner's faults."""
        runner = runner or self.wire_runner
        with runner.locked():
            for name, value in changes.items():
                if name in WIRE_FAULTS:
                    setattr(runner.faults, name, float(value))

    def on_shutdown(self) -> None:
        """Stop the device and remove the pty and its symlink."""
        if self.wire_runner is not None:
            self.wire_runner.stop()

    # -- services -------------------------------------------------------------------------------

    def _srv_disconnect(self, request: SetBool.Request,
                        response: SetBool.Response) -> SetBool.Response:
        try:
            if request.data:
                self.wire_runner.unplug()
                response.message = self.unplugged_message
            else:
                self.wire_runner.replug()
                response.message = self.replugged_message
            response.success = True
        except Exception as exc:  # noqa: BLE001 - a failure, never an exception in rclpy
            response.success, response.message = False, f'the virtual cable failed: {exc!r}'
        return response

    def _srv_inject_garbage(self, request: Trigger.Request,
                            response: Trigger.Response) -> Trigger.Response:
        self.wire_runner.inject_garbage(self.garbage)
        response.success = True
        response.message = f'{len(self.garbage)} bytes of noise queued'
        return response

    def _srv_drop_next(self, request: Trigger.Request,
                       response: Trigger.Response) -> Trigger.Response:
        with self.wire_runner.locked():
            self.wire_runner.faults.drop_next += 1
        response.success, response.message = True, 'the next reply will be lost'
        return response

    def _srv_corrupt_next(self, request: Trigger.Request,
                          response: Trigger.Response) -> Trigger.Response:
        with self.wire_runner.locked():
            self.wire_runner.faults.corrupt_next += 1
        response.success, response.message = True, 'the next reply will have a bad checksum'
        return response
