"""Channels (seed 003): mailbox overwrite and version polling, ring depth 32 dropping the newest,
FIFO drains, producers that never block and lose nothing uncounted."""

from __future__ import annotations

import threading

import pytest
from helpers import run_within

from gateway.channels import RING_DEPTH, Mailbox, Ring
from gateway.model import SmUpdate

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


def test_a_lazy_value_is_made_only_when_read_from_the_latest_argument() -> None:
    made: list[int] = []

    def make(arg: int) -> str:
        made.append(arg)
        return f"v{arg}"

    mb: Mailbox[str] = Mailbox()
    for k in range(1000):
        mb.put_lazy(make, k)
    assert made == [] and mb.version == 1000
    assert mb.poll(0) == (1000, "v999") and made == [999]
    assert mb.poll(1000) == (1000, None) and made == [999]  # nothing new: nothing made
    mb.put("plain")
    assert mb.peek() == "plain" and mb.version == 1001


def test_a_reader_never_sees_a_version_with_another_publish_s_value() -> None:
    """One producer, one reader on another thread: every (version, value) read belongs to
    one publish (the value is its version)."""
    mb: Mailbox[int] = Mailbox()
    stop = threading.Event()
    bad: list[tuple[int, int | None]] = []

    def produce() -> None:
        for k in range(1, 200_001):
            if k % 2:
                mb.put(k)
            else:
                mb.put_lazy(int, k)
        stop.set()

    def read() -> None:
        seen = 0
        while not stop.is_set():
            version, value = mb.poll(seen)
            if version != seen:
                if value != version:
                    bad.append((version, value))
                seen = version

    threads = [threading.Thread(target=produce), threading.Thread(target=read)]
    def both() -> None:
        for t in threads:
            t.start()
        for t in threads:
            t.join()

    run_within(both, DEADLINE_S * 6)
    assert bad == [] and mb.version == 200_000


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
