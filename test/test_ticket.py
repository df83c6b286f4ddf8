"""The shared ticket: a frame's fate, settled once by one thread and waited for by another."""

import gc
import threading
import weakref

from uav_serial_common.ticket import Ticket


def test_a_ticket_settled_before_the_wait_is_answered_at_once():
    ticket = Ticket()
    assert not ticket.settled and ticket.outcome is None
    assert ticket.settle('sent')
    assert ticket.settled and ticket.wait(0.0)
    assert (ticket.outcome, ticket.detail) == ('sent', None)


def test_a_ticket_settled_during_the_wait_wakes_the_waiter():
    ticket = Ticket()
    started = threading.Event()

    def carrier():
        started.wait(10)
        ticket.settle('failed', 'the port closed')
    thread = threading.Thread(target=carrier, daemon=True)
    thread.start()
    started.set()
    assert ticket.wait(30)
    assert (ticket.outcome, ticket.detail) == ('failed', 'the port closed')
    thread.join(10)


def test_a_wait_that_times_out_says_so_and_a_late_settle_is_still_recorded():
    ticket = Ticket()
    assert not ticket.wait(0.01) and not ticket.settled
    assert not ticket.wait(-1.0)  # a deadline already past: no wait, no error
    assert ticket.settle('sent')  # after the caller gave up: harmless
    assert ticket.settled and ticket.wait(0.0)


def test_the_first_settle_wins():
    ticket = Ticket()
    assert ticket.settle('dropped', 'a stop after it')
    assert not ticket.settle('sent')
    assert (ticket.outcome, ticket.detail) == ('dropped', 'a stop after it')


def test_concurrent_settles_leave_exactly_one_winner_seen_by_every_waiter():
    for _ in range(50):
        ticket = Ticket()
        gate = threading.Barrier(8)
        won, seen = [], []

        def settle(n):
            gate.wait(10)
            if ticket.settle('sent', n):
                won.append(n)

        def wait():
            gate.wait(10)
            if ticket.wait(30):
                seen.append((ticket.outcome, ticket.detail))
        threads = [threading.Thread(target=settle, args=(n,), daemon=True) for n in range(4)]
        threads += [threading.Thread(target=wait, daemon=True) for _ in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(30)
        assert len(won) == 1
        assert seen == [('sent', won[0])] * 4


def test_a_ticket_nobody_waits_for_is_not_kept():
    ticket = Ticket()
    ticket.wait(0.0)
    ticket.settle('sent')
    ref = weakref.ref(ticket)
    del ticket
    gc.collect()
    assert ref() is None


def test_a_subclass_adds_its_own_fields():
    class Posted(Ticket):
        __slots__ = ('frames',)

        def __init__(self, frames):
            super().__init__()
            self.frames = frames
    posted = Posted([b'\x01'])
    assert posted.settle('written') and posted.frames == [b'\x01'] and posted.settled
    assert 'written' in repr(posted)
