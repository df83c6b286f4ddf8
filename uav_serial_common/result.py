"""What a driver answers to a call: one result type with an enumerated outcome, for every driver.

A caller (a node mapping a service reply, the MAVLink bridge, a test) decides on the
:class:`Outcome`, never on the wording of the message: the message is for people.

- ``DONE``: the device did it, and the driver saw it (an acknowledgement, a read-back, a reply
  that holds the value asked for);
- ``SENT``: handed to the wire (or queued for it) where the device gives no reply to see, e.g. a
  broadcast, a SYNC WRITE or a motor command;
- ``REFUSED``: the driver refused before anything was sent (bad input, the device offline,
  another call still running): the device is as it was;
- ``FAILED``: the device said no or did not do it (a negative reply, a read-back that
  differs, no reply where one proves it was not done, a write the port did not take);
- ``UNKNOWN``: sent, and whether the device did it was not seen (a reply that did not come
  where silence proves nothing): the driver says so and finds out.

No ROS, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass
import enum
from typing import Generic, Optional, TypeVar

T = TypeVar('T')


class Outcome(enum.Enum):
    """How a call ended (the module docstring says what each means)."""

    DONE = 'done'
    SENT = 'sent'
    REFUSED = 'refused'
    FAILED = 'failed'
    UNKNOWN = 'unknown'

    @property
    def ok(self) -> bool:
        """True for the outcomes a service reports as ``success``: DONE and SENT."""
        return self in (Outcome.DONE, Outcome.SENT)


@dataclass(frozen=True)
class Result(Generic[T]):
    """A driver's answer to one call.

    ``cause`` is a short key (``offline``, ``out_of_range`` ...) for counting and telling
    refusals apart; other outcomes may carry one too. ``value`` is what the call read or
    returns (trigger records, a register's value, servo states ...), typed by the call.
    ``latency_ms`` is how long the device took where the call measures it.
    """

    outcome: Outcome
    message: str
    cause: str = ''
    value: Optional[T] = None
    latency_ms: Optional[float] = None

    @property
    def ok(self) -> bool:
        """Whether the call did what was asked (the ``success`` of a service reply)."""
        return self.outcome.ok

    @classmethod
    def done(cls, message: str, value: Optional[T] = None,
             latency_ms: Optional[float] = None) -> 'Result[T]':
        """Answer that the device did it and the driver saw it."""
        return cls(Outcome.DONE, message, value=value, latency_ms=latency_ms)

    @classmethod
    def sent(cls, message: str, value: Optional[T] = None) -> 'Result[T]':
        """Answer that it was handed to the wire (or queued) with no reply to see."""
        return cls(Outcome.SENT, message, value=value)

    @classmethod
    def refused(cls, cause: str, message: str) -> 'Result[T]':
        """Answer a refusal before anything was sent; ``cause`` is a short key for counting."""
        return cls(Outcome.REFUSED, message, cause=cause)

    @classmethod
    def failed(cls, message: str, cause: str = '', value: Optional[T] = None) -> 'Result[T]':
        """Answer that the device said no or did not do it (``value``: what was read anyway)."""
        return cls(Outcome.FAILED, message, cause=cause, value=value)

    @classmethod
    def unknown(cls, message: str, cause: str = '') -> 'Result[T]':
        """Answer that it was sent and whether the device did it was not seen."""
        return cls(Outcome.UNKNOWN, message, cause=cause)

    @classmethod
    def checked(cls, ok: bool, message: str, value: Optional[T] = None) -> 'Result[T]':
        """Answer DONE when a check of the device's answer passed, else FAILED."""
        return cls(Outcome.DONE if ok else Outcome.FAILED, message, value=value)

    def with_message(self, message: str) -> 'Result[T]':
        """Return a copy with another message (the same outcome, cause and value)."""
        return Result(self.outcome, message, self.cause, self.value, self.latency_ms)
