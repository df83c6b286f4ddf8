"""The parachute driver's black box made readable: reading, analysis and the report.

Kept apart from ``dps_parachute_ros`` (the driver, which only WRITES its black box with
``dps_parachute_ros.blackbox``): the analysis and its plots (matplotlib) are a tool for after a
flight, not a part of the driver. It reads the wire frames with ``dps_parachute_ros.protocol``.
No ROS here.
"""
