"""The autopilot link of the DPS-S parachute driver: a MAVLink parachute component."""
