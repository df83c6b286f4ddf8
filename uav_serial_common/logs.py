"""A log line at a level given by name, on an rclpy logger (or anything with its methods).

rclpy refuses a call site whose severity changes ("Logger severity cannot be changed between
calls"), so one shared ``logger.log(text, severity)`` site raises after the first level it saw.
Here each severity has its own call site. No rclpy import: a device core may use it with the
logger its node hands it.
"""

from __future__ import annotations

from typing import Any


def log_at(logger: Any, level: str, text: str) -> None:
    """Log `text` at `level`: 'debug', 'info', 'warn' or 'warning', 'error' (any case)."""
    name = level.lower()
    if name == 'error':
        logger.error(text)
    elif name in ('warn', 'warning'):
        logger.warning(text)
    elif name == 'debug':
        logger.debug(text)
    else:
        logger.info(text)
