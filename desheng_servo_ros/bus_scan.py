"""The PING sweep of ``ServoBusLink.scan``: who answers on the bus, cleanly, late or garbled.

A sweep PINGs each id once with the normal margin (an absent id costs a few ms). What comes back
is judged per PING window, and the windows can be wrong about whose bytes they hold: a servo
answers in the order it was asked, but when the device (or a loaded host between it and the
driver) falls behind, a reply lands one or more windows after its PING's. A clean late reply
names its id; bytes that make no frame (two servos at one id, S24) do not. So garbage in a
window makes that id and the one before it suspects, and if neither turns out to answer
garbled, every id that was silent since the last reply before that window is asked again:
the device answers in order, so the garbage came from one of them (docs/protocols.md, "Scan").
"""

from __future__ import annotations

from dataclasses import dataclass
import time
from typing import Any, Dict, Iterable, List, Optional, Set

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.schedule import LATE_REPLY_WINDOW_S, patient_wait
from uav_serial_common.serial_link import LinkTimeout
# At most this many such windows after the last PING while replies keep coming.
LISTEN_ROUNDS = 10


@dataclass
class _Window:
    """A stretch of the sweep in which bytes were thrown away (garbage): whose it may be."""

    index: int    # the PING whose window it was (the last one: after the sweep)
    anchor: int   # index of the last id whose reply had come before it (-1: none)
    began: float  # when it began (monotonic): the garbage came after


def sweep(link: Any, ids: Iterable[int]) -> List[int]:
    """PING each id of `ids` on `link` (a ServoBusLink); return those that answered, in order.

    Clean, late or garbled answers all count (see the module's docstring); late and suspect ids
    are confirmed one at a time with a long wait.
    """
    ids = list(ids)
    wanted = set(ids)
    answered: Set[int] = set()
    suspects: Set[int] = set()
    late: Dict[int, float] = {}
    sent: List[float] = []
    garbage: List[_Window] = []
    replied_at = -1  # index of the last id whose reply has come (in time or late)
    position = {servo_id: k for k, servo_id in enumerate(ids)}
    stats, decoder = link.link.stats, link.decoder
    link._late_sink = late
    try:
        for index, servo_id in enumerate(ids):
            replied_at = max([replied_at] + [position.get(i, -1) for i in late])
            anchor = replied_at
            mark = (stats.bytes_in, stats.frames_in, decoder.bytes_discarded)
            sent.append(time.monotonic())
            try:
                link.transact(proto.encode_ping(servo_id), servo_id, 0, retries=0, flush=False)
                answered.add(servo_id)
                replied_at = index
            except LinkTimeout:
                pass
            # Bytes thrown away, or bytes and no frame at all: someone answered garbled, in
            # this window or late from an earlier one (the frame in it may be another's).
            if decoder.bytes_discarded > mark[2]:
                garbage.append(_Window(index, anchor, sent[index]))
            if decoder.bytes_discarded > mark[2] or (stats.bytes_in > mark[0]
                                                     and stats.frames_in == mark[1]):
                suspects.add(servo_id)
                if index:
                    suspects.add(ids[index - 1])
        if ids:
            _listen(link, garbage, len(ids) - 1,
                    max([replied_at] + [position.get(i, -1) for i in late]))
    finally:
        link._late_sink = None
    garbled: Set[int] = set()
    for servo_id in sorted((set(late) | suspects) & wanted - answered):
        outcome = confirm(link, servo_id)
        if outcome:
            answered.add(servo_id)
        if outcome == 'garbled':
            garbled.add(servo_id)
    asked = (set(late) | suspects) & wanted
    # How late a reply came in this sweep: garbage is looked for no further back than that.
    lateness = max([0.0] + [at - sent[position[i]] for i, at in late.items() if i in position])
    for window in garbage:
        if set(ids[max(0, window.index - 1):window.index + 1]) & garbled:
            continue
        # Nobody near that window answers garbled: the bytes were late from further back.
        reach = LATE_REPLY_WINDOW_S + lateness + link.margin_s
        for k in range(window.anchor + 1, window.index + 1):
            servo_id = ids[k]
            if servo_id in answered or servo_id in asked or window.began - sent[k] > reach:
                continue
            asked.add(servo_id)
            if confirm(link, servo_id):
                answered.add(servo_id)
    return [i for i in ids if i in answered]


def _listen(link: Any, garbage: List[_Window], last: int, anchor: int) -> None:
    """After the last PING: listen until the line has been quiet for LATE_REPLY_WINDOW_S.

    A device that fell behind is still answering: its late replies come now (collected by id),
    and garbage among them counts against the ids after `anchor`.
    """
    stats, decoder = link.link.stats, link.decoder
    for _ in range(LISTEN_ROUNDS):
        mark = (stats.bytes_in, decoder.bytes_discarded)
        began = time.monotonic()
        time.sleep(LATE_REPLY_WINDOW_S)
        if decoder.bytes_discarded > mark[1]:
            garbage.append(_Window(last, anchor, began))
        if stats.bytes_in == mark[0] and not link.link.unread_input():
            return


def confirm(link: Any, servo_id: int) -> Optional[str]:
    """PING up to twice with a long wait: 'clean', 'garbled' or None (learns a late margin).

    The wait is at least the id's own reply timeout: a scan must not be quicker to call an id
    silent than the read loop is.
    """
    frame = proto.encode_ping(servo_id)
    wait = patient_wait(len(frame), 0, link.baud, link.timeout_for(len(frame), 0, servo_id))
    for _ in range(2):
        before = link.garbled_by_id[servo_id]
        try:
            reply = link.transact(frame, servo_id, 0, retries=0, timeout=wait)
        except LinkTimeout:
            if link.garbled_by_id[servo_id] != before:
                return 'garbled'
            continue
        link.learn_from(servo_id, reply)
        return 'clean'
    return None
