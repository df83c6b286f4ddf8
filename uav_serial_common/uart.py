"""What a UART receiver makes of a serial line, bit by bit: wrong speeds and colliding senders.

A byte-level device model cannot say what a real line does when the two ends disagree on the
speed (the driver's ``baud`` is wrong: the receiver sees garbage, usually more or fewer bytes than
were sent), or when two devices answer at once on a half-duplex bus (two servos sharing one id:
the receiver mostly sees one garbled frame). This module models the line itself, in pure Python:

- 8N1 framing: a start bit (0), 8 data bits least significant first, a stop bit (1); idle is 1.
- Several senders on one wire make the AND of their levels (a 0 from anyone wins, as on an
  open-drain or half-duplex bus line).
- The receiver waits for a falling edge, samples the middle of each of its own bit times, and
  delivers the byte; a missing stop bit is a framing error, which Linux delivers as 0x00 on a raw
  tty (IGNPAR and PARMRK clear), after which the receiver waits for the line to go idle again.

Times are in any unit as long as all agree: seconds with ``1 / baud`` bit times, or bit times.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from typing import Iterable, List, Sequence

BITS_PER_FRAME = 10  # start + 8 data + stop


@dataclass(frozen=True)
class Transmission:
    """One sender putting `data` on the line from `start`, back to back at `bit_time` per bit."""

    start: float
    bit_time: float
    data: bytes

    @property
    def end(self) -> float:
        """Return when the last stop bit ends."""
        return self.start + len(self.data) * BITS_PER_FRAME * self.bit_time

    def level(self, t: float) -> int:
        """Return the level this sender drives at time `t` (1 when idle)."""
        if t < self.start:
            return 1
        # A boundary belongs to the bit it starts; the epsilon keeps k * bit_time / bit_time
        # from rounding down to k - 1.
        index = int((t - self.start) / self.bit_time + 1e-9)
        byte, bit = divmod(index, BITS_PER_FRAME)
        if byte >= len(self.data):
            return 1
        if bit == 0:
            return 0
        if bit == BITS_PER_FRAME - 1:
            return 1
        return (self.data[byte] >> (bit - 1)) & 1

    def boundaries(self) -> Iterable[float]:
        """Yield the times at which this sender's level may change."""
        for k in range(len(self.data) * BITS_PER_FRAME + 1):
            yield self.start + k * self.bit_time


def receive(line: Sequence[Transmission], bit_time: float) -> bytes:
    """Return the bytes a receiver at `bit_time` per bit reads from the senders on `line`."""
    senders = [tx for tx in line if tx.data]
    if not senders:
        return b''

    def level(t: float) -> int:
        return min(tx.level(t) for tx in senders)

    edges: List[float] = sorted({t for tx in senders for t in tx.boundaries()})
    out = bytearray()
    armed = True  # the line was idle (1) since the last byte: a falling edge starts a byte
    i = 0
    while i < len(edges):
        t = edges[i]
        i += 1
        if level(t):
            armed = True
            continue
        if not armed:
            continue
        # A falling edge: sample the middle of the start bit, the 8 data bits and the stop bit.
        if level(t + 0.5 * bit_time):
            continue  # a glitch shorter than half a bit is no start bit
        value = 0
        for bit in range(8):
            value |= level(t + (bit + 1.5) * bit_time) << bit
        stop_at = t + (BITS_PER_FRAME - 0.5) * bit_time
        stop = level(stop_at)
        out.append(value if stop else 0x00)
        armed = bool(stop)
        i = bisect.bisect_right(edges, stop_at, i)
    return bytes(out)


def reframe(data: bytes, tx_baud: float, rx_baud: float) -> bytes:
    """Return what a UART at `rx_baud` reads when `data` is sent back to back at `tx_baud`."""
    if not data or tx_baud == rx_baud:
        return bytes(data)
    return receive([Transmission(0.0, 1.0 / tx_baud, bytes(data))], 1.0 / rx_baud)


def collide(frames: Sequence[bytes], offsets_bits: Sequence[float]) -> bytes:
    """Return what a receiver reads when `frames` go out at once, each `offsets_bits` late.

    All at one speed (times in bit times); the wire carries the AND of the senders.
    """
    line = [Transmission(float(offset), 1.0, bytes(frame))
            for frame, offset in zip(frames, offsets_bits)]
    return receive(line, 1.0)
