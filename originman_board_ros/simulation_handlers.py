"""The OriginMan firmware model's handlers: each host command, run as the firmware runs it.

Part of :class:`~originman_board_ros.simulation.VirtualOriginManBoardModel`
(``originman_board_ros.simulation`` assembles it; the board's state and its clock are described
there). ``_handle`` runs one command at its time, one at a time in arrival order, and returns
how long the receive task is busy with it: motors (set-points, type, stop mask; wire ids >= 4
ignored and counted, O3), PWM servos, the LEDs, buzzer, OLED and RGB, the settings, and the bus
of LX servos, whose commands take the servo bus's time (115200 baud) and whose reads wait for
the servo's answer or the 5 ms timeout (§6, O14, O24).
"""

from __future__ import annotations

from typing import List, Optional

from originman_board_ros import protocol as p
from originman_board_ros.simulation_parts import Pattern, PwmServo, SimBusServo

SERVO_BUS_BAUD = 115200
SERVO_ANSWER_S = 0.001
"""The servo's answer to a read, its frame included (§6)."""
SERVO_TIMEOUT_S = 0.005
"""The firmware's read timeout (``proc_timeout = 5`` ticks)."""


def _servo_bus_time(nbytes: int) -> float:
    return nbytes * 10 / SERVO_BUS_BAUD


class FirmwareHandlers:
    """The command handlers of the board model (``VirtualOriginManBoardModel``)."""

    def _handle(self, frame: p.HostFrame, t: float) -> float:
        """Run one command at ``t``; return how long the receive task is busy with it."""
        cmd = p.decode_host_command(frame)
        self.frames_handled += 1
        self.command_log.append((t, cmd))
        if isinstance(cmd, p.IgnoredCommand):
            self.commands_ignored += 1
            return 0.0
        if isinstance(cmd, p.SetBatteryLimit):
            self.battery_limit_mv = cmd.limit_mv
            self._check_battery()
        elif isinstance(cmd, p.SetLed):
            if cmd.led_id in self.leds:  # O25
                self.leds[cmd.led_id] = Pattern(cmd.on_ms, cmd.off_ms, cmd.repeat, t)
            else:
                self.commands_ignored += 1
        elif isinstance(cmd, p.SetBuzzer):
            self._beep(t, cmd.frequency_hz, cmd.on_ms, cmd.off_ms, cmd.repeat, 'host')
        elif isinstance(cmd, (p.SetMotorSpeeds, p.StopMotors, p.SetMotorType)):
            self._motor(cmd)
        elif isinstance(cmd, (p.PwmMove, p.PwmRead, p.PwmSetOffset)):
            self._pwm(cmd, t)
        elif isinstance(cmd, p.SetOledText):
            if cmd.line in self.oled_lines:
                # O19: the real board overflows its 24-byte buffer; the model keeps 23 bytes.
                self.oled_lines[cmd.line] = cmd.text[:p.OLED_TEXT_MAX_BYTES]
            else:
                self.commands_ignored += 1
        elif isinstance(cmd, p.SetRgb):
            for index, r, g, b in cmd.pixels:
                if index < p.RGB_PIXEL_COUNT:  # O18
                    self.rgb[index] = (r, g, b)
                else:
                    self.commands_ignored += 1
        else:
            return self._bus(cmd, t)
        return 0.0

    def _motor(self, cmd: p.HostCommand) -> None:
        self.motors_initialized = True
        if isinstance(cmd, p.SetMotorSpeeds):
            for wire_id, speed in cmd.items:
                if wire_id < p.MOTOR_COUNT:
                    self.motor_set_points[wire_id] = speed
                else:
                    # O3: an out-of-bounds write in the firmware; the model ignores it.
                    self.bad_motor_ids += 1
        elif isinstance(cmd, p.StopMotors):
            for wire_id in cmd.wire_ids:
                if wire_id < p.MOTOR_COUNT:
                    self.motor_set_points[wire_id] = 0.0
                else:
                    self.bad_motor_ids += 1
        else:
            # O5: anything but 0..3 selects JGB520.
            self.motor_type = cmd.type_code if cmd.type_code < len(p.MotorType) else 0

    def _pwm(self, cmd: p.HostCommand, t: float) -> None:
        if isinstance(cmd, p.PwmMove):
            for servo_id, pulse in cmd.items:
                servo = self._pwm_servo(servo_id)
                if servo is not None:
                    servo.move(pulse, cmd.duration_ms, t)
            return
        servo = self._pwm_servo(cmd.servo_id)
        if servo is None:
            return  # no reply for id 0 or > 4
        if isinstance(cmd, p.PwmSetOffset):
            servo.set_offset(cmd.offset_us)
        elif cmd.sub == p.PwmSub.READ_PULSE:
            self._reply(t, p.encode_pwm_pulse_reply(cmd.servo_id, servo.pulse_at(t)))
        else:
            self._reply(t, p.encode_pwm_offset_reply(cmd.servo_id, servo.offset_us))

    def _pwm_servo(self, servo_id: int) -> Optional[PwmServo]:
        servo = self.pwm_servos.get(servo_id)
        if servo is None:
            # O30: id 0 indexes out of bounds in the firmware, > 4 is skipped; both ignored.
            self.bad_pwm_ids += 1
        return servo

    def _targets(self, servo_id: int) -> List[SimBusServo]:
        if servo_id == p.BUS_BROADCAST_ID:
            return list(self.bus_servos)
        return [s for s in self.bus_servos if s.servo_id == servo_id]

    def _bus(self, cmd: p.HostCommand, t: float) -> float:
        if isinstance(cmd, p.BusMove):
            position_items = [(sid, min(pos, p.BUS_POSITION_MAX)) for sid, pos in cmd.items]
            for servo_id, position in position_items:  # O23: > 1000 clamped to 1000
                for servo in self._targets(servo_id):
                    servo.move(position, cmd.duration_ms, t)
            return len(cmd.items) * _servo_bus_time(10)
        if isinstance(cmd, p.BusStop):
            for servo_id in cmd.ids:
                for servo in self._targets(servo_id):
                    servo.hold(t)
            return len(cmd.ids) * _servo_bus_time(6)
        if isinstance(cmd, p.BusRead):
            return self._bus_read(cmd, t)
        servos = self._targets(cmd.servo_id)
        for servo in servos:
            if isinstance(cmd, p.BusTorque):
                servo.loaded = cmd.enable
                servo.hold(t)
            elif isinstance(cmd, p.BusWriteId):
                servo.servo_id = cmd.new_id
            elif isinstance(cmd, p.BusSetOffset):
                if -p.BUS_OFFSET_MAX <= cmd.offset <= p.BUS_OFFSET_MAX:  # O35
                    servo.offset = cmd.offset
            elif isinstance(cmd, p.BusSaveOffset):
                servo.saved_offset = servo.offset
            elif isinstance(cmd, p.BusSetLimits):
                servo_limits(servo, cmd.sub, cmd.low, cmd.high)
            elif isinstance(cmd, p.BusSetTemperatureLimit):
                servo.temperature_limit_c = min(cmd.max_c, p.BUS_TEMPERATURE_LIMIT_MAX_C)
        params = 4 if isinstance(cmd, p.BusSetLimits) else 1
        return _servo_bus_time(6 + params)

    def _bus_read(self, cmd: p.BusRead, t: float) -> float:
        self.bus_reads += 1
        servos = self._targets(cmd.servo_id)
        # Two answers at once collide on the half-duplex bus: the board sees a bad frame.
        servo = servos[0] if len(servos) == 1 else None
        duration = _servo_bus_time(6) + (SERVO_ANSWER_S if servo else SERVO_TIMEOUT_S)
        done = t + duration
        if servo is None:
            self.bus_read_failures += 1
            # O14: the model sends zeros with a failure (the firmware sometimes garbage).
            reply = p.encode_bus_reply(cmd.servo_id, cmd.sub, None, p.BUS_FAILURE)
        else:
            reply = p.encode_bus_reply(cmd.servo_id, cmd.sub, self._bus_value(servo, cmd.sub,
                                                                              done))
        self._reply(done, reply)
        return duration

    def _bus_value(self, servo: SimBusServo, sub: int, t: float) -> p.BusValue:
        if sub == p.BusSub.READ_POSITION:
            return servo.read_position(t)
        if sub == p.BusSub.READ_VOLTAGE:
            mv = servo.voltage_mv if servo.voltage_mv is not None else self.battery_mv
            return max(0, min(p.U16_MAX, mv))
        if sub == p.BusSub.READ_TEMPERATURE:
            return max(0, min(255, int(servo.temperature_c)))
        if sub == p.BusSub.READ_LOAD:
            return int(servo.loaded)
        if sub == p.BusSub.READ_ID:
            return servo.servo_id
        if sub == p.BusSub.READ_OFFSET:
            return servo.offset
        if sub == p.BusSub.READ_ANGLE_LIMITS:
            return servo.angle_limits
        if sub == p.BusSub.READ_VOLTAGE_LIMITS:
            return servo.voltage_limits
        return servo.temperature_limit_c


def servo_limits(servo: SimBusServo, sub: int, low: int, high: int) -> None:
    """Apply a limit command with the firmware's clamps, then its swap (O24)."""
    if sub == p.BusSub.SET_ANGLE_LIMITS:
        low, high = min(low, p.BUS_POSITION_MAX), min(high, p.BUS_POSITION_MAX)
        servo.angle_limits = (min(low, high), max(low, high))
    else:
        low, high = max(low, p.BUS_VOLTAGE_MIN_MV), min(high, p.BUS_VOLTAGE_MAX_MV)
        servo.voltage_limits = (min(low, high), max(low, high))
