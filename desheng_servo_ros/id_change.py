"""``~/set_id`` and ``~/factory_reset`` as procedures without I/O, run by the driver and the model.

Each procedure is a generator: it yields a step and is sent what came of it, so the same lines
decide the driver's answer (``ServoServices``, each step a blocking call on the bus) and the
model's (``bus_services``, each step a transaction of ``BusSchedule`` in virtual time, searched
by ``test_servo_model.py``). Steps:

- :class:`Ask`: send a request and wait for its reply; sent back a :class:`Heard`;
- :class:`Quiet`: wait this long off the bus (a second servo's reply ends meanwhile);
- :class:`Unsolicited`: sent back how many replies of that id and size no request took;
- :class:`Servos`: sent back the servo list as it is now;
- :class:`PortBack`: sent back whether the port is open (after a wait for it to come back);
- :class:`Rename`: the servo at `old` is at `new` now (the node renames its joint).

The rules: ``schedule.set_id_refusal`` (two joints never share an id), ``schedule.judge_probe``
(how many servos answer at an id), ``schedule.patient_wait`` (a PING whose silence becomes the
answer waits patiently), and "never report a success or a refusal not seen" (UNKNOWN when the
frame left and what it did was not seen).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Collection, Generator, Optional, Sequence, Tuple

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.registers import encode_value
from desheng_servo_ros.schedule import (judge_probe, PROBE_READS, probe_quiet_s,
                                        set_id_refusal)
from desheng_servo_ros.state import FACTORY_ID, ID, Outcome, POSITION, Result

# An id change whose frame left without an acknowledgement (lost, or the link dropped) is
# settled by asking the bus; a link that went down gets this long to come back for that.
SETTLE_WAIT_S = 2.0


@dataclass(frozen=True)
class Ask:
    """Send `frame` and wait for the reply of `servo_id` with `nparams` parameters.

    `retries`: attempts after the first (None: the bus's usual); `patient`: wait
    ``schedule.patient_wait``, not the usual margin; `flush`: discard stale input first.
    """

    frame: bytes
    servo_id: int
    nparams: int
    retries: Optional[int] = 0
    patient: bool = False
    flush: bool = True


@dataclass(frozen=True)
class Heard:
    """What came of an :class:`Ask`: its reply, or None and why (`why`).

    `garbled`: bytes came and no frame (S24); `lost`: the link went down; `left`: whether the
    frame left (False only when the port was not open: nothing was sent).
    """

    reply: Optional[proto.Reply]
    why: str = ''
    garbled: bool = False
    lost: bool = False
    left: bool = True


@dataclass(frozen=True)
class Quiet:
    """Wait `seconds` off the bus."""

    seconds: float


@dataclass(frozen=True)
class Unsolicited:
    """Ask how many replies of `servo_id` with `size` parameters no request took so far."""

    servo_id: int
    size: int


@dataclass(frozen=True)
class Servos:
    """Ask for the servo list as it is now."""


@dataclass(frozen=True)
class PortBack:
    """Ask whether the port is open, waiting up to `seconds` for it."""

    seconds: float


@dataclass(frozen=True)
class Rename:
    """The servo at `old` answers at `new` now."""

    old: int
    new: int


Steps = Generator[Any, Any, Any]


class LinkLost(Exception):
    """The link went down during a request of the procedure (`heard` says how)."""

    def __init__(self, heard: Heard) -> None:
        super().__init__(heard.why)
        self.heard = heard


def ask(step: Ask) -> Steps:
    """Yield `step`; return its :class:`Heard`, raising LinkLost when the link went down."""
    heard = yield step
    if heard.lost:
        raise LinkLost(heard)
    return heard


def answers(servo_id: int) -> Steps:
    """PING up to twice, patiently: 'yes', 'garbled' (something answers, not cleanly) or 'no'."""
    garbled = False
    for _ in range(2):
        heard = yield from ask(Ask(proto.encode_ping(servo_id), servo_id, 0, patient=True))
        if heard.reply is not None:
            return 'yes'
        garbled = garbled or heard.garbled
    return 'garbled' if garbled else 'no'


def how_many_answer(servo_id: int, baud: int, values_differ: bool = True) -> Steps:
    """Return ('none' | 'one' | 'unsure' | 'several', why): READs the position PROBE_READS times.

    The judgement is ``schedule.judge_probe``'s. Each READ waits patiently: a reply later than
    the read loop's margin (a host that stalled) is still its reply, and only a READ unanswered
    then makes the probe unsure. A second whole reply follows the first at once: each reply is
    followed by a quiet wait for it to end (it would collide with the next READ). Only the
    first READ discards stale input: a second reply later than that (the device or the reader
    fell behind) is then taken by the next READ or counted unsolicited, never thrown away
    (thrown away, beside a busy loop, it let set_id rename two servos at one id).
    """
    # Replies that no READ waited for, of the READs' size only: a late reply to an earlier
    # request (a PING of the scan when the device stalled) is one reply to one request.
    before = yield Unsolicited(servo_id, POSITION.size)
    frame = proto.encode_read(servo_id, POSITION.address, POSITION.size)
    values, garbled = [], 0
    for k in range(PROBE_READS):
        heard = yield from ask(Ask(frame, servo_id, POSITION.size, patient=True,
                                   flush=k == 0))
        if heard.reply is not None:
            values.append(int.from_bytes(heard.reply.params, 'big'))
            yield Quiet(probe_quiet_s(baud))
        elif heard.garbled:
            garbled += 1
    after = yield Unsolicited(servo_id, POSITION.size)
    return judge_probe(values, garbled, after - before, values_differ)


def unknown(what: str, why: str, then: str) -> Result:
    """Answer an outcome the bus did not tell: never a success or refusal not seen."""
    return Result.unknown(f'UNKNOWN whether {what}: its frame left, then {why}; {then}',
                          cause='no_reply')


def set_id(old: int, new: int, servos: Sequence[Any], baud: int) -> Steps:
    """Give the servo at `old` the id `new`, if exactly one servo answers at `old`; the Result.

    `servos`: the servo list (``ServoRecord``) when the call came.
    """
    refusal = set_id_refusal(servos, old, new)
    if refusal is not None:
        return Result.refused('bad_input', f'refused: {refusal}')
    try:
        taken = yield from answers(new)
        if taken != 'no':
            how = '' if taken == 'yes' else ' (with a garbled reply: more than one servo?)'
            return Result.refused('bad_input', f'refused: id {new} already answers on the '
                                               f'bus{how}; pick a free id (~/scan)')
        count, why = yield from how_many_answer(old, baud)
    except LinkLost as exc:
        # Nothing was written yet: the probe only read.
        if not exc.heard.left:
            return Result.refused('offline', f'port not open: {exc}; nothing sent')
        return Result.refused('offline', f'the probe was cut short ({exc}); nothing changed')
    if count == 'none':
        return Result.refused('no_servo', f'servo {old} does not answer; nothing changed')
    if count == 'several':
        return Result.refused('shared_id', (
            f'more than one servo answers at id {old} ({why}): a new id would go to all of '
            'them. Disconnect or power off all but one, then try again; nothing changed'))
    if count == 'unsure':
        return Result.refused('lossy_bus', (
            f'servo {old} answers, but {why}: whether it is alone at id {old} and id {new} is '
            'free cannot be told; nothing changed. Try again'))
    # Checked again where the list could have changed meanwhile (a scan, a rename).
    refusal = set_id_refusal((yield Servos()), old, new)
    if refusal is not None:
        return Result.refused('bad_input', f'refused: {refusal}')
    what = f'servo {old} now has id {new}'
    heard = yield Ask(proto.encode_write(old, ID.address, encode_value(ID, new)), old, 0,
                      retries=None)
    if heard.reply is None and not heard.left:
        return Result.refused('offline', f'port not open: {heard.why}; nothing sent')
    lost = None if heard.reply is not None else heard.why
    try:
        if lost is not None and not (yield PortBack(SETTLE_WAIT_S)):
            return unknown(what, lost, f'~/scan tells (id {new} answers if it did)')
        if (yield from answers(new)) != 'yes':
            if lost is None:
                return Result.failed(f'servo {old} acknowledged but does not answer at id '
                                     f'{new}; check with ~/scan')
            if (yield from answers(old)) == 'yes':
                return Result.failed(f'servo {old} did not take id {new} ({lost}): it still '
                                     f'answers at id {old}; nothing changed')
            return unknown(what, lost, f'neither id {old} nor {new} answers now; check with '
                                       '~/scan')
        if lost is not None and (yield from answers(old)) == 'yes':
            # Both answer: it did not move, and a servo the probe before did not hear (its PINGs
            # lost) is at the new id. Seen, so not unknown; nothing renamed.
            return Result.failed(f'servo {old} did not take id {new} ({lost}): it still answers '
                                 f'at id {old}, and id {new} answers too (a servo the probe '
                                 'before did not hear); check with ~/scan', 'shared_id')
        # Done only if it is alone there: a servo at the new id whose PING replies were lost
        # would now share it (the same probe as before the change).
        after, why = yield from how_many_answer(new, baud)
    except LinkLost as exc:
        return unknown(what, str(exc), f'~/scan tells (id {new} answers if it did)')
    yield Rename(old, new)
    if after == 'several':
        return Result.failed(
            f'servo {old} took id {new}, and more than one servo answers there now ({why}): id '
            f'{new} was taken by a servo the probe did not hear. Connect them one at a time and '
            'give each its own id', 'shared_id')
    if after != 'one':
        return Result.unknown(f'servo {old} answers at id {new}, but whether it is alone there '
                              f'was not seen ({why or "no reply"}); check with ~/scan',
                              'lossy_bus')
    return Result.done(f'servo {old} now answers at id {new}' + (
        '' if lost is None else f' (its acknowledgement was lost: {lost})'))


def factory_reset(servo_id: int, configured: Collection[int], baud: int) -> Steps:
    """RESET the servo at `servo_id` to its factory registers; the Result.

    `configured`: the ids the driver was told (``servo_ids``), for the advice on giving the id
    back. The id and the confirmation are checked before. A RESET moves the servo to the
    factory id (S23): where another servo answers there, the answer warns.
    """
    what = f'servo {servo_id} reset to factory settings'
    try:
        taken = servo_id != FACTORY_ID and (yield from answers(FACTORY_ID)) != 'no'
    except LinkLost as exc:
        if not exc.heard.left:
            return Result.refused('offline', f'port not open: {exc}; nothing sent')
        return Result.refused('offline', f'the probe of the factory id was cut short ({exc}); '
                                         'no RESET sent, nothing changed')
    heard = yield Ask(proto.encode_reset(servo_id), servo_id, 0, retries=None)
    if heard.reply is None and not heard.left:
        return Result.refused('offline', f'port not open: {heard.why}; nothing sent')
    lost = None if heard.reply is not None else heard.why
    try:
        if lost is not None and not (yield PortBack(SETTLE_WAIT_S)):
            return unknown(what, lost, f'~/scan tells (a reset servo answers at the factory id '
                                       f'{FACTORY_ID})')
        at_own = (yield from answers(servo_id)) == 'yes'
        if at_own:
            at_factory = 'no'
        elif servo_id == FACTORY_ID:
            at_factory = 'none'  # the id it would move to is its own, which did not answer
        else:
            at_factory = (yield from how_many_answer(FACTORY_ID, baud))[0]
    except LinkLost as exc:
        return unknown(what, str(exc), '~/scan tells')
    if lost is not None:
        if at_own:
            # A servo that keeps its id on RESET (S23) or one that never got it: the bus cannot
            # tell them apart.
            return unknown(what, lost, f'it still answers at id {servo_id}; read its registers '
                                       'with ~/read_register')
        if at_factory == 'none':
            where = f'id {servo_id} (the factory id) does not answer' \
                if servo_id == FACTORY_ID else \
                f'neither id {servo_id} nor the factory id {FACTORY_ID} answers'
            return unknown(what, lost, f'{where} now; check with ~/scan')
        if taken:
            # The servo at the factory id now may be the one that answered there before: a
            # servo that never heard the RESET (or an id no servo has) looks the same.
            return unknown(what, lost, f'id {servo_id} no longer answers, and the factory id '
                                       f'{FACTORY_ID} answers as it did before the RESET; '
                                       '~/scan and ~/read_register tell')
        # Most likely the reset servo; but the silence before the RESET is no proof: a wire that
        # lost those PINGs hid a servo that was there all along (the bench-size search).
        return unknown(what, lost, f'id {servo_id} no longer answers, and the factory id '
                                   f'{FACTORY_ID} answers now but did not answer before the '
                                   'RESET: most likely the reset servo; ~/scan and '
                                   '~/read_register tell')
    if at_own:
        return Result.done(f'servo {servo_id} reset to factory settings (torque off)')
    give_back = (f'give it its id back with ~/set_id {FACTORY_ID} -> {servo_id}'
                 + (f' (this driver refuses that while servo_ids lists {servo_id}: run it '
                    f'without {servo_id} for the change)' if servo_id in configured else ''))
    if taken:
        owner = next((s.name for s in (yield Servos()) if s.id == FACTORY_ID), 'another servo')
        return Result(Outcome.DONE, (
            f'servo {servo_id} reset to factory settings. WARNING: it now has the factory id '
            f'{FACTORY_ID}, which {owner} already had: '
            + ('more than one servo answers there' if at_factory == 'several' else
               'check with ~/scan')
            + f', and ~/set_id refuses an id more than one servo answers to. Disconnect {owner} '
            f'(or power it off), then {give_back}'), cause='shared_id')
    if at_factory != 'none':
        return Result.done(f'servo {servo_id} reset to factory settings and now answers at the '
                           f'factory id {FACTORY_ID}; {give_back}')
    return Result.done(f'servo {servo_id} acknowledged RESET but no longer answers')


def run_to_end(steps: Steps, carry_out: Any) -> Any:
    """Run `steps` to its end, each step carried out by ``carry_out(step)``; its return value."""
    answer: Any = None
    while True:
        try:
            step = steps.send(answer)
        except StopIteration as stop:
            return stop.value
        answer = carry_out(step)


__all__: Tuple[str, ...] = ('Ask', 'Heard', 'LinkLost', 'PortBack', 'Quiet', 'Rename',
                            'SETTLE_WAIT_S', 'Servos', 'Unsolicited', 'answers',
                            'factory_reset', 'how_many_answer', 'run_to_end', 'set_id',
                            'unknown')
