"""DPS-S protocol: the streaming decoder of either direction of the link."""

from __future__ import annotations

from uav_serial_common.stream_decoder import BAD_CHECKSUM, DROP, WAIT
from uav_serial_common.stream_decoder import StreamDecoder as BaseStreamDecoder

from dps_parachute_ros.protocol_frames import (
    CMD_STATUS, CMD_TRIGGER_RECORDS, CMD_TRIGGER_REQUEST, Direction, Frame, FRAME_LEN,
    HOST_CODES, HOST_HEADER, KNOWN_SOURCE_BITS, MODULE_CODES, MODULE_HEADER, RECORD_FRAME_LEN,
    STATUS_FRAME_LEN,
)


class StreamDecoder(BaseStreamDecoder):
    """Incremental frame decoder for either direction of the link; never raises.

    ``from_module`` accepts module frames (6, 8 and 16 bytes) and 6-byte frames with the host
    header (the trigger request of P10, or echoes). ``from_host`` accepts 6-byte host frames.
    Frames are delimited by header, the length the command code dictates and the P1
    checksum; the 0x34/0x35 collision is settled per P3/P16. Call ``flush()`` when the line
    has been idle for a few character times to settle a frame that could still grow (a 6-byte
    0x35 voltage reply waiting for a possible 16-byte record is then delivered).

    Counters: those of :class:`uav_serial_common.stream_decoder.StreamDecoder`
    (``frames_decoded`` includes unknown codes; ``checksum_errors`` counts header-started
    candidates whose checksum matched at no allowed length) and ``unknown_frames``.
    """

    def __init__(self, direction: Direction = 'from_module') -> None:
        if direction not in ('from_module', 'from_host'):
            raise ValueError(f"direction must be 'from_module' or 'from_host', got {direction!r}")
        self.direction = direction
        self._from_module = direction == 'from_module'
        self.headers = (MODULE_HEADER, HOST_HEADER) if self._from_module else (HOST_HEADER,)
        super().__init__()
        self.unknown_frames = 0
        """Delivered frames whose code (or header) this protocol does not define."""

    def _candidate(self, buf: bytearray, pos: int, n: int, final: bool, out: list) -> int:
        avail = n - pos
        if avail < 3:
            return WAIT
        code = buf[pos + 2]
        checked = False
        if buf[pos] == 0x41:  # MODULE_HEADER, only looked for from the module
            if code == CMD_STATUS:
                length = STATUS_FRAME_LEN
            elif code == CMD_TRIGGER_RECORDS:
                length = self._record_or_voltage(buf, pos, avail, final)
                if length <= 0:
                    return length
                checked = True
            else:
                length = FRAME_LEN
            known = code in MODULE_CODES
        else:
            length = FRAME_LEN
            known = code in HOST_CODES and (not self._from_module or code == CMD_TRIGGER_REQUEST)
        if avail < length:
            return WAIT
        end = pos + length
        if checked or sum(buf[pos + 2:end - 1]) & 0xFF == buf[end - 1]:
            raw = bytes(buf[pos:end])
            out.append(Frame(raw[:2], code, raw[3:-1], raw))
            if not known:
                self.unknown_frames += 1
            return length
        return BAD_CHECKSUM

    @staticmethod
    def _record_or_voltage(buf: bytearray, pos: int, avail: int, final: bool) -> int:
        """P3/P16: 0x35 is a 16-byte record or a 6-byte voltage reply, by checksum and length.

        Returns the checked length, or WAIT / BAD_CHECKSUM.
        """
        if avail < FRAME_LEN:
            return WAIT
        ok6 = sum(buf[pos + 2:pos + 5]) & 0xFF == buf[pos + 5]
        if avail >= RECORD_FRAME_LEN:
            ok16 = sum(buf[pos + 2:pos + 15]) & 0xFF == buf[pos + 15]
            if ok16 and (not ok6 or _record_plausible(buf, pos, RECORD_FRAME_LEN)):
                return RECORD_FRAME_LEN
            if ok6:
                return FRAME_LEN
            return BAD_CHECKSUM
        if ok6 and (final or not _record_plausible(buf, pos, avail)):
            return FRAME_LEN
        if final:
            return DROP
        return WAIT


def _record_plausible(buf: bytearray, pos: int, avail: int) -> bool:
    """Whether the bytes at ``pos`` (``avail`` of them) can still be a trigger record.

    Used only to break a tie where both the 6- and 16-byte readings pass the checksum (P16):
    a record has no source bits beyond the four documented and 0/1 link and charging bytes.
    """
    if avail > 7 and buf[pos + 7] & ~KNOWN_SOURCE_BITS & 0xFF:
        return False
    if avail > 11 and buf[pos + 11] > 1:
        return False
    if avail > 12 and buf[pos + 12] > 1:
        return False
    return True
