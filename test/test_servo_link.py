"""ServoBusLink against the simulated bus on a pty: matching, timeouts, retries, bus timing."""

import threading
import time

from desheng_servo_ros import protocol as proto
from desheng_servo_ros.link import (_PriorityLock, DERIVED_MARGIN_S, LinkTimeout,
                                    PRIORITY_LOOP, PRIORITY_SERVICE, PRIORITY_URGENT,
                                    ServoBusLink)
from desheng_servo_ros.virtual_node import VirtualServoBus
import pytest
from uav_serial_common.process import wait_for
from servo_rig import Wire
from uav_serial_common.pty_port import wire_time


RIG_MARGIN_MS = 500.0
"""The rig's reply margin: a pty's derived 2 ms is shorter than a loaded host's stalls, which
would count as lost replies in tests about faults and order; the derived one is tested apart.
The virtual bus runs in this process, where a loaded host holds its thread (it answers when it
gets the GIL back): 20 ms lost a reply in about one make test of eight beside a busy loop (a
retry too many), and 9 % of replies took longer than 20 ms, 1 % longer than 60 ms and 0.1 %
longer than 150 ms (at most 0.49 s) with three such processes beside a busy loop, and 200 ms
still lost one in ten runs at a load of 10. A lost reply costs the tests here this margin each,
a few times."""


@pytest.fixture(scope='module')
def bus(tmp_path_factory):
    dev = VirtualServoBus(str(tmp_path_factory.mktemp('servo_link') / 'bus'), [1, 2, 3],
                          seed=1).start()
    wire = Wire(dev.runner)
    link = ServoBusLink(dev.path, 115200, max_retries=1, response_timeout_ms=RIG_MARGIN_MS)
    link.start()
    assert link.wait_port_open(5)
    yield dev, wire, link
    link.stop()
    dev.stop()


def test_read_returns_the_addressed_servos_reply(bus):
    dev, wire, link = bus
    with dev.runner.locked():
        dev.sim.move_by_hand(2, 1000)
    reply = link.read(2, 0x38, 2)
    assert reply.servo_id == 2 and int.from_bytes(reply.params, 'big') == 1000
    assert link.ping(3).servo_id == 3


def test_timeout_is_the_wire_time_plus_the_margin_the_port_allows(bus):
    _, _, link = bus
    # Before the port was looked at: two periods of an FTDI adapter's default timer + 2 ms.
    unopened = ServoBusLink('/nonexistent/servobus', 115200)
    assert unopened.latency is None
    assert unopened.timeout_for(8, 4) == pytest.approx(wire_time(18, 115200) + DERIVED_MARGIN_S)
    # A pty has no latency timer: the margin is the host's few ms.
    assert link.latency.kind == 'pty' and 'pseudo-terminal' in link.latency.summary()
    try:
        link.response_timeout_ms = 0.0
        assert link.margin_s == pytest.approx(link.latency.reply_margin_s())
        assert link.margin_s < 0.005
        assert link.timeout_for(8, 4) == pytest.approx(wire_time(18, 115200) + link.margin_s)
        link.response_timeout_ms = 3.0
        assert link.timeout_for(8, 4) == pytest.approx(wire_time(18, 115200) + 0.003)
    finally:
        link.response_timeout_ms = RIG_MARGIN_MS


def test_a_lost_or_corrupted_reply_is_retried(bus):
    dev, wire, link = bus
    retries = link.link.stats.retries
    errors = link.checksum_errors
    dev.runner.faults.drop_next = 1
    assert link.read(1, 0x03, 2).params == bytes((1, 28))
    dev.runner.faults.corrupt_next = 1
    assert link.read(1, 0x03, 2).params == bytes((1, 28))
    assert link.link.stats.retries == retries + 2
    assert link.checksum_errors == errors + 1


def test_a_silent_servo_times_out_after_every_retry(bus):
    dev, wire, link = bus
    mark = wire.mark()
    with pytest.raises(LinkTimeout):
        link.ping(77)
    # Logged when the bus has read them: the second a moment after the driver gave up.
    wait_for(lambda: len(wire.requests(mark)) >= 2, 2, what='both PINGs on the bus')
    assert [r.raw for r in wire.requests(mark)] == [proto.encode_ping(77)] * 2
    with pytest.raises(LinkTimeout):
        link.ping(77, retries=0)


def test_frames_without_reply_hold_the_bus_for_their_wire_time(bus):
    _, _, link = bus
    writes = []
    write = link.link.write

    def timed_write(data):
        writes.append((time.monotonic(), bytes(data)))
        write(data)
    link.link.write = timed_write
    try:
        targets = [(i, 2048, 0) for i in range(1, 40)]
        link.sync_write_positions(targets)
        link.ping(1)
    finally:
        del link.link.write
    (t_sync, sync), (t_ping, ping) = writes
    assert sync == proto.encode_sync_write_positions(targets) and ping == proto.encode_ping(1)
    # The PING is written only once the SYNC WRITE has left the wire (a lower bound only).
    assert t_ping - t_sync >= wire_time(len(sync), 115200)


def test_the_bus_lock_serves_higher_priorities_first():
    lock = _PriorityLock()
    assert lock.acquire(PRIORITY_LOOP, 1.0)
    order = []
    threads = [threading.Thread(target=lambda p=p: (lock.acquire(p, 5.0), order.append(p),
                                                    lock.release()))
               for p in (PRIORITY_LOOP, PRIORITY_SERVICE, PRIORITY_URGENT)]
    for t in threads:
        t.start()
        # Queue them in this order, lowest priority first.
        wait_for(lambda t=t: sum(lock._waiting) == threads.index(t) + 1, 5,
                 what='the waiter queued')
    assert lock.waiting_above(PRIORITY_LOOP)
    lock.release()
    for t in threads:
        t.join(5)
    assert order == [PRIORITY_URGENT, PRIORITY_SERVICE, PRIORITY_LOOP]
    assert lock.acquire(PRIORITY_LOOP, 0.1)
    assert not lock.acquire(PRIORITY_URGENT, 0.05)


class Plan:
    """A read plan over a list of servo ids (position READs), recording what it is told."""

    def __init__(self, ids, retries=1, on_reply=None):
        self.todo = list(ids)
        self.retries = retries
        self.on_reply = on_reply
        self.results = []

    def next_read(self):
        if not self.todo:
            return None
        servo_id = self.todo.pop(0)
        return proto.encode_read(servo_id, 0x38, 4), servo_id, 4, self.retries, servo_id

    def on_read(self, tag, reply):
        self.results.append((tag, None if reply is None else reply.servo_id))
        if self.on_reply is not None:
            self.on_reply(self)


def test_a_read_chain_retries_a_lost_reply_at_once_and_reports_a_missing_servo(bus):
    dev, wire, link = bus
    mark = wire.mark()
    retries = link.link.stats.retries
    transactions, failed = link.transactions, link.failed_transactions
    dev.runner.faults.drop_next = 1
    plan = Plan([1, 2, 77, 3])
    assert link.read_chain(plan) == 6
    assert plan.results == [(1, 1), (2, 2), (77, None), (3, 3)]
    assert [r.servo_id for r in wire.requests(mark)] == [1, 1, 2, 77, 77, 3]
    assert link.link.stats.retries == retries + 2
    assert (link.transactions, link.failed_transactions) == (transactions + 4, failed + 1)
    # A READ planned without retries is given up after its first silence.
    plan = Plan([77, 1], retries=0)
    assert link.read_chain(plan) == 2 and plan.results == [(77, None), (1, 1)]


def test_a_read_chain_yields_the_bus_between_two_reads_to_a_waiting_service(bus):
    _, wire, link = bus
    pings = []

    def ask_once(plan):
        if len(plan.results) == 3:
            threading.Thread(target=lambda: pings.append(link.ping(2).servo_id)).start()
    mark = wire.mark()
    retries = link.link.stats.retries
    plan = Plan([1] * 10000, on_reply=ask_once)
    sent = link.read_chain(plan)
    # The chain gave up the bus soon after the service queued, not after 10000 READs (a READ
    # retried after a host stall is one more frame sent).
    assert 3 <= len(plan.results) == sent - (link.link.stats.retries - retries) < 10000
    wait_for(lambda: pings == [2], 5, what='the PING of the waiting service')
    requests = [r for r in wire.requests(mark)]
    assert requests[sent].instruction == proto.Instruction.PING
