"""Benchmarks and the fault campaign of uav_serial_drivers (`make bench`)."""
