"""A UDP route's wake-ups without the interpreter: the compiled lane.

Between bursts of a stream, the router's cost is the interpreter's per wake-up, not the
system calls (tools/bench/README.md: a C loop making the gateway's calls costs what
mavlink-router does; a four-call Python loop 1.2–1.4× that).  So while a ``udpin``/``udpout``
endpoint's datagrams take the router's common path to connected ``udpout`` links, the loop
thread stays in one compiled call (``_route_speedups.lane``).  It waits on the port and on the
loop's own epoll descriptor until the loop's next timer, reads with ``recvmmsg``, routes with
the compiled loop under the router's lock, writes each link's batch with one ``sendmmsg``
and adds every counter the Python path adds — and comes back here for anything else:

* the loop has work (an event, a call from another thread, a timer due): the lane ends,
  and the port engine starts it again once that work is done (the port unwatched meanwhile;
  each call reads a ready port at least once, so the loop's work cannot starve it);
* a datagram from a sender other than the latest peer, or a failed read: the port's path;
* a datagram the compiled loop stops at (a new source, a targeted message …): the general
  path for the rest, as :meth:`Router._route_datagrams_compiled` does;
* another thread set the router up otherwise (a tap, a signing key, another link): the
  port's path, and the lane ends;
* a link that cannot be written now: ``flush_batch``; a short ``sendmmsg``: the port's
  ``write_many`` goes on from it (``MmsgSocket.send``'s ``first``).

Each of those keeps the order of the datagrams and the counts the Python path makes, and
the lane goes on after it.  A paced stream (reads of fewer than ``BURST_MIN`` datagrams) is
held as the port engine holds it (``COALESCE_S``); bursts are read whole as they come: in
compiled code a wake-up costs less than holding one (the rule: ``hold_rule`` in the C file).
Where the lane does not apply (no compiler, not Linux, signing,
a tap, another kind of link) the Python path runs as before.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable
from typing import Any

from gateway.io import port as port_mod

__all__ = ["lane_runner"]

try:
    from backends.mavlink._route_speedups import lane as _lane
except (ImportError, AttributeError):  # not built, or not Linux: the Python path
    _lane = None  # type: ignore[assignment]

#: AURORA_NO_LANE=1 turns the lane off (the Python path only: an A/B, or a doubt).
ENABLED = _lane is not None and not os.environ.get("AURORA_NO_LANE")


def lane_runner(endpoint: Any, engine: Any, port: Any,
                feed: Callable[[list[bytes], list[Any]], None]
                ) -> Callable[[Callable[[], None]], bool] | None:
    """A callable ``run(begin)`` that runs ``endpoint``'s lane until the loop has work (True:
    it ran; ``begin()`` is called first, once), or returns False when the lane does not apply
    now; None when it never can for this port.  ``feed(datagrams, senders)``: the port's own
    path for what the lane hands back."""
    if not ENABLED:
        return None
    mm = getattr(port, "mmsg", None)
    if mm is None or getattr(mm, "_fast_recv", None) is None or not port.datagram:
        return None
    from backends.mavlink import router as router_mod

    if router_mod._speedups is None:  # (AURORA_NO_SPEEDUPS: the Python path throughout)
        return None

    def run(begin: Callable[[], None]) -> bool:
        router = endpoint.router
        loop = engine.loop
        if (router is None or router.verifier is not None or router.tap is not None
                or not router.forward or mm.refused):
            return False
        if port.dest is None:  # udpin: only the latest peer's datagrams take the lane
            last = mm._last_sender
            if not last[0] or last[1][0] != port.last_peer:
                return False
            expect: bytes | None = last[0]
        else:
            expect = None
        outs: list[tuple[Any, ...]] = []
        batching = router._batching
        for lk in batching:
            if lk is endpoint:
                continue
            p = getattr(lk, "port", None)
            e = getattr(lk, "engine", None)
            om = getattr(p, "mmsg", None)
            if (p is None or e is None or om is None or not p.connected
                    or om._fast_send is None or om._hdr_name != (0, 0)
                    or lk._batch is not None):
                return False
            outs.append((om._fd, om._shdrs_addr, [], lk, e, e.stats, lk.counters))
        if not outs or loop.lane_wait() is None:
            return False
        begin()
        lock = router.lock
        rargs: tuple[Any, ...] = (
            router_mod.INFO, endpoint.seen, router.seen_at, router._own, endpoint.last_seq,
            router._boxes, router._mailboxes_of, {}, router._dests_for(endpoint), endpoint)
        out_t = tuple(outs)
        while True:
            wait = loop.lane_wait()  # (again each time: what was handed back may add work)
            if wait is None:
                return True
            loop_fd, due = wait
            try:
                got = _lane(mm._fd, mm._rhdrs_addr, mm.batch, loop_fd, due, expect, rargs,
                            out_t, engine.stats, endpoint.framer_stats, endpoint.counters,
                            router, lock, batching, float(engine.coalesce_s),
                            port_mod.COALESCE_GAP_S, port_mod.BURST_MIN)
            except BaseException:
                _settle(out_t, lock)
                raise
            reason = got[0]
            if reason == 0:
                return True
            if reason == 1:  # the port's path: another sender, or a failed read
                datagrams, raws, err = got[1], got[2], got[3]
                if err:
                    if err == errno.ECONNREFUSED:  # as recv_senders counts it
                        port.send_refused += 1
                        continue
                    raise OSError(err, os.strerror(err))
                feed(datagrams, mm.senders_of(raws))
                return True  # (a new peer: the lane starts again from the engine)
            if reason == 5:  # the router was set up otherwise meanwhile: the port's path
                feed(got[1], [port.last_peer] if expect is not None else [])
                return True
            if reason == 4:  # a short sendmmsg: MmsgSocket.send goes on (counted already)
                with lock:
                    _write_rest(out_t, got[1], got[2])
                continue
            try:
                if reason == 2:  # the general path from datagram `stop` on
                    router._route_datagrams_compiled(endpoint, got[1][got[2]:])
                else:  # link `k` could not take its batch in one call
                    out_t[got[1]][3].flush_batch(got[2])
            finally:
                _settle(out_t, lock)
            if engine.port is not port:
                return True

    return run


def _write_rest(outs: tuple[Any, ...], k: int, first: int | None) -> None:
    """Links ``k`` on still hold their batch: the rest of link ``k``'s after its first
    call's ``first`` (written, or -errno), then the others', as their ports write them."""
    for j in range(k, len(outs)):
        batch, link, engine = outs[j][2], outs[j][3], outs[j][4]
        if batch:
            try:
                link.port.write_many(batch, first if j == k else None)
            except Exception as exc:  # as PortEngine.send_datagrams takes a failed write
                engine.stats.write_errors += 1
                engine._fail(exc, "write failed")
            del batch[:]


def _settle(outs: tuple[Any, ...], lock: Any) -> None:
    """After a hand-back or a failure: what each link still holds is written — a batch
    being routed by its ``flush_batch``, one already counted by its port — the lane's lists
    emptied, and the router's lock released if it is held."""
    owned = lock._is_owned()
    try:
        with lock:
            for j, out in enumerate(outs):
                if out[3]._batch is not None:
                    out[3].flush_batch()
                elif out[2]:
                    _write_rest(outs[j:j + 1], 0, None)
                del out[2][:]
    finally:
        if owned:
            lock.release()
