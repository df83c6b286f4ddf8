"""The resynchronising stream decoder every driver's protocol builds on.

A serial line delivers bytes cut at arbitrary points, with noise, truncated and corrupted
frames. :class:`StreamDecoder` holds the buffer and runs the one loop all four protocols share:
find the next header, let the device decide what the candidate starting there is, and either
wait for more bytes, abandon the candidate one byte after its start (so a real frame that
begins inside a false one is still found), or take the frame. Everything outside frames is
counted as garbage; nothing raises on input.

A subclass gives its header(s) and one method, :meth:`StreamDecoder._candidate`, which holds
what is device-specific: the length rules, the checksum or CRC, the typing of the frame. One
call per candidate keeps the loop as fast as the hand-written ones it replaced
(``bench/decoders.py``).

The counters have the same names in every driver: ``frames_decoded``, ``checksum_errors``,
``bytes_discarded``; ``pending`` is the number of bytes held back.
"""

from __future__ import annotations

from typing import Tuple, Union

WAIT = -1
"""`_candidate`: the candidate may still be a frame; wait for more bytes (a drop under flush)."""
DROP = 0
"""`_candidate`: no frame starts here; abandon the candidate one byte after its start."""
BAD_CHECKSUM = -2
"""`_candidate`: the candidate is complete but its checksum (CRC) fails; counted, then DROP."""


class StreamDecoder:
    """Incremental frame decoder for a byte stream cut at arbitrary points; never raises.

    Subclasses set ``headers`` (one or two byte strings; two for a line that carries frames of
    both directions) and implement :meth:`_candidate`. ``feed(data)`` returns the frames that
    ``data`` completes, in wire order; ``flush()`` settles held bytes because the line went
    idle (a candidate still waiting is abandoned, so frames hidden inside it are found).
    """

    headers: Tuple[bytes, ...] = ()

    def __init__(self) -> None:
        if len(self.headers) not in (1, 2) or not all(self.headers):
            raise ValueError(f'a stream decoder needs one or two headers, got {self.headers!r}')
        self._buf = bytearray()
        # A trailing byte that could be the first half of a header is kept for the next chunk.
        self._first_bytes = bytes({h[0] for h in self.headers if len(h) > 1})
        # The loop, chosen once: _run(final) takes every frame the buffer holds and, with
        # final, abandons what still waits.
        self._run = self._scan_one if len(self.headers) == 1 else self._scan_two
        self.frames_decoded = 0
        """Frames delivered (accepted by ``_candidate``)."""
        self.checksum_errors = 0
        """Complete candidates whose checksum (or CRC) did not match."""
        self.bytes_discarded = 0
        """Bytes thrown away: outside frames, and the first byte of every abandoned candidate."""

    @property
    def pending(self) -> int:
        """Bytes held back because they may be the start of a frame."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes (e.g. after a reconnect); counters are kept."""
        self._buf.clear()

    def feed(self, data: Union[bytes, bytearray]) -> list:
        """Add received bytes and return every frame now complete, in wire order."""
        try:
            self._buf += data
        except TypeError:
            return []
        return self._run(False)

    def flush(self) -> list:
        """Settle buffered bytes because the line went idle; incomplete candidates are dropped."""
        return self._run(True)

    def _candidate(self, buf: bytearray, pos: int, n: int, final: bool, out: list) -> int:
        """Judge the candidate whose header starts at ``buf[pos]`` (``n`` bytes are buffered).

        Return the frame's length after appending the frame (whatever the driver delivers) to
        ``out``; or :data:`WAIT`, :data:`DROP` or :data:`BAD_CHECKSUM`. ``final`` is True under
        ``flush()``: a WAIT then abandons the candidate. A subclass may append other results
        to ``out`` (the handset reports each rejected candidate) before it returns DROP.
        A subclass may instead set ``self._candidate`` in ``__init__`` to a plain function of
        the same arguments, a closure over its tables: the hot loop then reads no attributes.
        """
        raise NotImplementedError

    def _scan_one(self, final: bool) -> list:
        buf = self._buf
        n = len(buf)
        out: list = []
        pos = 0
        discarded = 0
        decoded = 0
        candidate = self._candidate
        find = buf.find
        header = self.headers[0]
        while True:
            start = find(header, pos)
            if start < 0:
                # No header from pos on: all garbage but a last byte that may be the first
                # half of a header arriving in the next chunk.
                end = n - 1 if not final and n > pos and buf[n - 1] in self._first_bytes else n
                discarded += end - pos
                pos = end
                break
            discarded += start - pos
            length = candidate(buf, start, n, final, out)
            if length > 0:
                pos = start + length
                decoded += 1
                continue
            if length == WAIT and not final:
                pos = start
                break
            if length == BAD_CHECKSUM:
                self.checksum_errors += 1
            discarded += 1
            pos = start + 1
        if pos:
            del buf[:pos]
        self.bytes_discarded += discarded
        self.frames_decoded += decoded
        return out

    def _scan_two(self, final: bool) -> list:
        # The next position of each header is cached, so a stream of one kind of frame does
        # not search the rest of the buffer for the other at every frame.
        buf = self._buf
        n = len(buf)
        out: list = []
        pos = 0
        discarded = 0
        decoded = 0
        candidate = self._candidate
        find = buf.find
        first, second = self.headers
        next_a = find(first)
        next_b = find(second)
        while True:
            if next_a != -1 and next_a < pos:
                next_a = find(first, pos)
            if next_b != -1 and next_b < pos:
                next_b = find(second, pos)
            if next_a == -1:
                start = next_b
                if start == -1:
                    end = n - 1 if not final and n > pos and buf[n - 1] in self._first_bytes \
                        else n
                    discarded += end - pos
                    pos = end
                    break
            elif next_b == -1 or next_a < next_b:
                start = next_a
            else:
                start = next_b
            discarded += start - pos
            length = candidate(buf, start, n, final, out)
            if length > 0:
                pos = start + length
                decoded += 1
                continue
            if length == WAIT and not final:
                pos = start
                break
            if length == BAD_CHECKSUM:
                self.checksum_errors += 1
            discarded += 1
            pos = start + 1
        if pos:
            del buf[:pos]
        self.bytes_discarded += discarded
        self.frames_decoded += decoded
        return out
