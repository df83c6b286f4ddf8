"""``~/set_id``'s procedure (``id_change``) stepped without I/O: each outcome it can answer.

The driver (``ServoServices.set_id``) and the bus model (``bus_services``) run this same
generator; here a scripted bus answers its steps, in no time.
"""

from desheng_servo_ros import id_change as idc
from desheng_servo_ros import protocol as proto
from desheng_servo_ros.schedule import PROBE_READS
from desheng_servo_ros.state import ID, Outcome, POSITION, ServoRecord
from desheng_servo_ros.units import Joint

BAUD = 115200


class ScriptedBus:
    """Servos by id (a count each) that answer at once; faults by the request's frame."""

    def __init__(self, at_ids, lose_write_ack=False, cut=None, moves_on_write=True,
                 apart=False, after_write=None):
        self.at = dict(at_ids)
        self.after_write = after_write  # called with `at` once the WRITE is carried out
        self.apart = apart        # two servos at one id: replies apart (else they collide)
        self.unsolicited = 0
        self.lose_write_ack = lose_write_ack
        self.cut = cut            # the first request of this instruction: the link goes down
        self.moves_on_write = moves_on_write
        self.steps = []
        self.renamed = []
        self.servos = (ServoRecord(Joint(1, 'servo_1'), 0), ServoRecord(Joint(3, 'servo_3'), 1))

    def carry(self, step):
        self.steps.append(step)
        if isinstance(step, idc.Ask):
            return self._answer(step)
        if isinstance(step, idc.Unsolicited):
            return self.unsolicited
        if isinstance(step, idc.Servos):
            return self.servos
        if isinstance(step, idc.PortBack):
            return True
        if isinstance(step, idc.Rename):
            self.renamed.append((step.old, step.new))
        return None

    def _answer(self, step):
        instruction = step.frame[4]
        if self.cut == instruction:
            self.cut = None
            return idc.Heard(None, 'the link went down during the request', lost=True)
        servo_id = step.servo_id
        if instruction == proto.Instruction.WRITE:
            new = step.frame[6]
            if self.moves_on_write and self.at.get(servo_id):
                self.at[new] = self.at.get(new, 0) + self.at.pop(servo_id)
            if self.after_write is not None:
                self.after_write(self.at)
            if self.lose_write_ack:
                return idc.Heard(None, f'no reply from servo {servo_id}')
            return idc.Heard(proto.Reply(servo_id, 0, b'', b''))
        count = self.at.get(servo_id, 0)
        if count == 0:
            return idc.Heard(None, f'no reply from servo {servo_id}')
        if count > 1 and not self.apart:
            return idc.Heard(None, f'no reply from servo {servo_id}', garbled=True)
        self.unsolicited += count - 1  # the other servos' replies, after the one taken
        params = b'\x08\x00' if step.nparams == POSITION.size else b''
        return idc.Heard(proto.Reply(servo_id, 0, params, b''))


def set_id(bus, old=3, new=9):
    return idc.run_to_end(idc.set_id(old, new, bus.servos, BAUD), bus.carry)


def test_one_servo_is_renamed_and_the_probe_ran_before_and_after():
    bus = ScriptedBus({1: 1, 3: 1})
    result = set_id(bus)
    assert (result.outcome, result.message) == (Outcome.DONE, 'servo 3 now answers at id 9')
    assert bus.renamed == [(3, 9)]
    reads = [s.servo_id for s in bus.steps
             if isinstance(s, idc.Ask) and s.frame[4] == proto.Instruction.READ]
    assert reads == [3] * PROBE_READS + [9] * PROBE_READS
    # Every PING and READ of the probe waits patiently; only the first READ of each flushes.
    probes = [s for s in bus.steps
              if isinstance(s, idc.Ask) and s.frame[4] != proto.Instruction.WRITE]
    assert all(s.patient for s in probes)
    assert [s.flush for s in probes if s.frame[4] == proto.Instruction.READ] == \
        ([True] + [False] * (PROBE_READS - 1)) * 2


def test_an_id_of_a_joint_is_refused_before_anything_is_sent():
    bus = ScriptedBus({1: 1, 3: 1})
    result = set_id(bus, 3, 1)
    assert (result.outcome, result.cause) == (Outcome.REFUSED, 'bad_input')
    assert bus.steps == []


def test_a_new_id_that_answers_is_refused():
    bus = ScriptedBus({1: 1, 3: 1, 9: 1})
    result = set_id(bus)
    assert (result.outcome, result.cause) == (Outcome.REFUSED, 'bad_input')
    assert 'already answers' in result.message and bus.renamed == []


def test_two_servos_at_the_old_id_are_refused():
    bus = ScriptedBus({1: 1, 3: 2})
    result = set_id(bus)
    assert (result.outcome, result.cause) == (Outcome.REFUSED, 'shared_id')
    assert not any(isinstance(s, idc.Ask) and s.frame[4] == proto.Instruction.WRITE
                   for s in bus.steps)


def test_a_link_cut_during_the_probe_changes_nothing_and_says_so():
    bus = ScriptedBus({1: 1, 3: 1}, cut=proto.Instruction.READ)
    result = set_id(bus)
    assert (result.outcome, result.cause) == (Outcome.REFUSED, 'offline')
    assert 'cut short' in result.message and bus.renamed == []


def test_a_lost_acknowledgement_is_settled_by_asking_the_bus():
    bus = ScriptedBus({1: 1, 3: 1}, lose_write_ack=True)
    result = set_id(bus)
    assert result.outcome == Outcome.DONE and 'acknowledgement was lost' in result.message
    assert any(isinstance(s, idc.PortBack) for s in bus.steps)


def test_a_lost_acknowledgement_of_a_servo_still_at_its_id_is_a_failure():
    bus = ScriptedBus({1: 1, 3: 1}, lose_write_ack=True, moves_on_write=False)
    result = set_id(bus)
    assert result.outcome == Outcome.FAILED and 'still answers at id 3' in result.message
    assert bus.renamed == []


def test_a_lost_acknowledgement_and_a_silent_bus_is_unknown():
    # The servo goes silent (unplugged) after its WRITE.
    bus = ScriptedBus({1: 1, 3: 1}, lose_write_ack=True, after_write=lambda at: at.pop(9, None))
    result = set_id(bus)
    assert result.outcome == Outcome.UNKNOWN and 'neither id 3 nor 9 answers' in result.message


def test_a_second_servo_found_at_the_new_id_after_the_change_is_a_failure():
    # A servo at 9 whose PINGs were lost before the change answers there after it.
    bus = ScriptedBus({1: 1, 3: 1}, apart=True,
                      after_write=lambda at: at.update({9: at[9] + 1}))
    result = set_id(bus)
    assert (result.outcome, result.cause) == (Outcome.FAILED, 'shared_id')
    assert bus.renamed == [(3, 9)]  # the joint's servo is at 9 now


def test_the_write_carries_the_new_id():
    bus = ScriptedBus({1: 1, 3: 1})
    set_id(bus)
    write = next(s for s in bus.steps
                 if isinstance(s, idc.Ask) and s.frame[4] == proto.Instruction.WRITE)
    assert write.frame == proto.encode_write(3, ID.address, bytes([9]))
    assert write.retries is None  # the bus's usual retries


def test_a_lost_acknowledgement_with_both_ids_answering_is_a_failure_not_a_rename():
    # The WRITE never reached servo 3, and a servo at 9 whose PINGs were lost before the change
    # answers there: the old id still answering tells that nothing moved (it used to be DONE,
    # "servo 3 now answers at id 9", as soon as 9 answered alone).
    bus = ScriptedBus({1: 1, 3: 1}, lose_write_ack=True, moves_on_write=False,
                      after_write=lambda at: at.update({9: 1}))
    result = set_id(bus)
    assert (result.outcome, result.cause) == (Outcome.FAILED, 'shared_id'), result.message
    assert 'still answers at id 3, and id 9 answers too' in result.message
    assert bus.renamed == []
