"""Channels (seed 003): mailbox overwrite and version polling, ring depth 32 dropping the newest,
FIFO drains, producers that never block and lose nothing uncounted, and ChannelBackend behind a
real dispatcher."""

from __future__ import annotations

import threading

import pytest
from helpers import run_within

from gateway.backend import Outcome
from gateway.channels import RING_DEPTH, ChannelBackend, Channels, Mailbox, Ring
from gateway.dispatcher import Dispatcher
from gateway.model import LinkEvent, RawFrame, SmUpdate, Status

DEADLINE_S = 5.0


def sm(t: int) -> SmUpdate:
    return SmUpdate(t, 1, False, 0, float(t), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def test_mailbox_is_empty_until_the_first_put() -> None:
    mb: Mailbox[int] = Mailbox()
    assert mb.peek() is None
    assert mb.version == 0
    assert mb.poll(0) == (0, None)


def test_mailbox_keeps_only_the_latest_value() -> None:
    mb: Mailbox[str] = Mailbox()
    for v in ("a", "b", "c"):
        mb.put(v)
    assert mb.peek() == "c"
    assert mb.peek() == "c"  # peeking does not consume
    assert mb.version == 3


def test_mailbox_poll_reports_only_what_is_newer_than_seen() -> None:
    mb: Mailbox[str] = Mailbox()
    mb.put("first")
    seen, value = mb.poll(0)
    assert (seen, value) == (1, "first")
    assert mb.poll(seen) == (seen, None)  # nothing new
    mb.put("second")
    mb.put("third")  # two publishes between polls: the consumer sees only the latest
    seen, value = mb.poll(seen)
    assert (seen, value) == (3, "third")
    assert mb.poll(seen) == (3, None)


# -- ring -----------------------------------------------------------------------------------


def test_ring_default_depth_is_32_and_a_full_ring_drops_the_newest() -> None:
    ring: Ring[int] = Ring()
    assert ring.depth == RING_DEPTH == 32
    accepted = [ring.put(i) for i in range(40)]
    assert accepted == [True] * 32 + [False] * 8
    assert ring.dropped == 8
    assert len(ring) == 32
    assert ring.drain() == list(range(32))  # the first 32 kept, the newest 8 dropped


def test_ring_drains_fifo_in_batches_of_max_items() -> None:
    ring: Ring[int] = Ring(depth=10)
    for i in range(10):
        ring.put(i)
    assert ring.drain(max_items=4) == [0, 1, 2, 3]
    assert ring.drain(max_items=4) == [4, 5, 6, 7]
    ring.put(10)
    assert ring.drain(max_items=4) == [8, 9, 10]
    assert ring.drain(max_items=4) == []
    assert ring.drain() == []
    assert ring.dropped == 0


def test_ring_accepts_again_after_a_drain() -> None:
    ring: Ring[int] = Ring(depth=2)
    assert [ring.put(i) for i in range(3)] == [True, True, False]
    assert ring.drain(1) == [0]
    assert ring.put(3) is True
    assert ring.drain() == [1, 3]
    assert ring.dropped == 1


def test_ring_refuses_a_depth_below_one() -> None:
    with pytest.raises(ValueError):
        Ring(0)


def test_put_into_a_full_ring_returns_immediately() -> None:
    ring: Ring[int] = Ring(depth=4)
    for i in range(4):
        ring.put(i)
    results = run_within(lambda: [ring.put(i) for i in range(10_000)])
    assert not any(results)
    assert ring.dropped == 10_000


def test_concurrent_producers_lose_nothing_but_the_counted_drops() -> None:
    ring: Ring[tuple[int, int]] = Ring(depth=32)
    mailbox: Mailbox[tuple[int, int]] = Mailbox()
    producers, per_producer = 8, 2_000
    go = threading.Barrier(producers + 1)
    done = threading.Event()
    accepted = [0] * producers

    def produce(p: int) -> None:
        go.wait(DEADLINE_S)
        for k in range(per_producer):
            mailbox.put((p, k))
            if ring.put((p, k)):
                accepted[p] += 1

    drained: list[tuple[int, int]] = []

    def consume() -> None:
        go.wait(DEADLINE_S)
        while not done.is_set():
            drained.extend(ring.drain(8))
        drained.extend(ring.drain())

    threads = [threading.Thread(target=produce, args=(p,)) for p in range(producers)]
    consumer = threading.Thread(target=consume)
    for t in threads:
        t.start()
    consumer.start()
    for t in threads:
        t.join(DEADLINE_S)
        assert not t.is_alive()
    done.set()
    consumer.join(DEADLINE_S)
    assert not consumer.is_alive()

    total = producers * per_producer
    assert len(drained) + ring.dropped == total
    assert len(drained) == sum(accepted)
    assert len(set(drained)) == len(drained)  # nothing duplicated
    for p in range(producers):  # each producer's values stay in order (FIFO)
        mine = [k for q, k in drained if q == p]
        assert mine == sorted(mine)
    assert mailbox.version == total


# -- channels and the backend ---------------------------------------------------------------


def test_channels_are_created_per_kind_on_first_use() -> None:
    ch = Channels(ring_depth=4)
    assert ch.kinds() == []
    assert ch.latest("sm_update") is None
    assert ch["sm_update"] is ch["sm_update"]
    assert ch["sm_update"].ring.depth == 4
    assert ch.publish(sm(1)) is True
    assert ch.latest("sm_update") == sm(1)
    assert ch.kinds() == ["sm_update"]


def test_channel_backend_fills_a_mailbox_and_ring_per_kind_through_the_dispatcher() -> None:
    backend = ChannelBackend()
    d = Dispatcher([backend])
    assert d.start() == []
    st = Status(5, 1, 0, 0x0F)
    raw = RawFrame(0x42, b"\x01\x02")
    up = LinkEvent("sim", True)
    for msg in (sm(1), st, sm(2), raw, up, sm(3)):
        assert d.dispatch(msg) is Outcome.ACCEPTED
    ch = backend.channels
    assert sorted(ch.kinds()) == ["link", "raw", "sm_update", "status"]
    assert ch.latest("sm_update") == sm(3)
    assert ch.latest("status") == st
    assert ch.latest("raw") == raw
    assert ch.latest("link") == up
    assert ch["sm_update"].mailbox.version == 3
    assert ch["sm_update"].ring.drain() == [sm(1), sm(2), sm(3)]
    assert ch["status"].ring.drain() == [st]


def test_channel_backend_accepts_with_a_full_ring_and_still_updates_the_mailbox() -> None:
    """A full ring (nobody drains it) must not make every dispatch look failed: the latest
    value still reaches pollers, and the ring counts its own drops."""
    backend = ChannelBackend(Channels(ring_depth=RING_DEPTH))
    d = Dispatcher([backend])
    d.start()
    results = [d.dispatch(sm(i)) for i in range(RING_DEPTH + 3)]
    assert results == [Outcome.ACCEPTED] * (RING_DEPTH + 3)
    ch = backend.channels["sm_update"]
    assert ch.mailbox.peek() == sm(RING_DEPTH + 2)  # the latest still reaches pollers
    assert ch.ring.dropped == 3
    assert d.stats()["channels"] == {"accepted": RING_DEPTH + 3, "ring_dropped_sm_update": 3}
    st = Status(1, 0, 0, 0)
    assert d.dispatch(st) is Outcome.ACCEPTED
    assert backend.channels.latest("status") == st
