"""Serialized ROS messages (CDR, little endian) built with ``struct``, for the hot paths.

rclpy publishes ``bytes`` as a message already serialized. Building a message object field by
field and converting it for the middleware costs tens of microseconds of Python per message; on
the paths that run for every frame (the parachute's status stream, the handset's setpoints) the
constant parts are serialized once and each message is a few joins. The layout is XCDR1 as
rclpy's ``serialize_message`` makes it: a 4-byte encapsulation header, then each field aligned
to its own size counted from the end of that header, strings as a uint32 length (with the NUL)
and the bytes and a NUL, sequences as a uint32 count and the elements. Padding bytes are zero
(rclpy's own are whatever was in memory: compare messages, never bytes). Tests deserialize
what the packers make with ``rclpy.serialization`` and compare it with the message builders'.
"""

from __future__ import annotations

import struct
from typing import Iterable, Tuple

ENCAPSULATION = b'\x00\x01\x00\x00'
"""CDR, little endian, no options."""
STAMP = struct.Struct('<iI')
"""``builtin_interfaces/Time`` at offset 0 (the start of a ``std_msgs/Header``)."""
_U32 = struct.Struct('<I')


def string(text: str, offset: int) -> Tuple[bytes, int]:
    """Return a string field starting at `offset` (its alignment included) and the end offset."""
    data = text.encode('utf-8') + b'\x00'
    out = bytes(-offset % 4) + _U32.pack(len(data)) + data
    return out, offset + len(out)


def string_sequence(items: Iterable[str], offset: int) -> Tuple[bytes, int]:
    """Return a ``string[]`` field starting at `offset` and the end offset."""
    items = list(items)
    pad = bytes(-offset % 4)
    parts = [pad, _U32.pack(len(items))]
    offset += len(pad) + 4
    for item in items:
        data, offset = string(item, offset)
        parts.append(data)
    return b''.join(parts), offset


def fields(codes: str, offset: int) -> Tuple[struct.Struct, int]:
    """Return a packer of fixed-size values, ``struct`` `codes`, starting at `offset`.

    Each field is aligned to its own size, as CDR does; returns the Struct and the end offset.
    """
    fmt = '<'
    for code in codes:
        size = struct.calcsize(code)
        pad = -offset % size
        fmt += 'x' * pad + code
        offset += pad + size
    return struct.Struct(fmt), offset


def header(frame_id: str) -> Tuple[bytes, int]:
    """Return a ``std_msgs/Header``'s frame_id field (it follows the 8-byte stamp), end offset."""
    return string(frame_id, STAMP.size)


class FramedPacker:
    """A message packer whose constant parts follow ``header.frame_id``.

    A subclass lays out what it needs after the header in `_layout`; `set_frame_id` swaps the
    parts in one assignment, so a thread packing meanwhile uses the old parts or the new ones.
    """

    def __init__(self, frame_id: str) -> None:
        self.frame_id = ''
        self._parts: tuple = ()
        self.set_frame_id(frame_id)

    def set_frame_id(self, frame_id: str) -> None:
        """Change ``header.frame_id`` (any thread: the parts change as one)."""
        frame, offset = header(frame_id)
        self._parts = self._layout(frame, offset)
        self.frame_id = frame_id

    def _layout(self, frame: bytes, offset: int) -> tuple:
        """Return the parts after a frame id field `frame` that ends at `offset`."""
        raise NotImplementedError
