"""Desheng bus servo driver: wire protocol, register table, bus simulator and ROS nodes."""
