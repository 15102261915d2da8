"""The router's compiled common case (``backends/mavlink/_route_speedups.c``) routes exactly as
the pure-Python path does: the same datagrams out of every link in the same order, the same
counters, tables and mailboxes — on batches hypothesis makes of good, corrupt, targeted,
signed, MAVLink 1, unknown and node-addressed frames from known and new sources."""

from __future__ import annotations

import sys
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mavlink_peer import upstream_dialect

import backends.mavlink.router as router_mod
from backends.mavlink.router import Link, Router
from gateway.io import mmsg

dev = upstream_dialect()
SPEEDUPS = router_mod._speedups


@pytest.mark.skipif(sys.platform != "linux" or sys.implementation.name != "cpython",
                    reason="the compiled paths are built for CPython on Linux")
def test_the_compiled_paths_are_built_and_used() -> None:
    # The project's install builds them (pyproject's ext-modules); optional only so that an
    # install without a C compiler still works.  Here, with one, their absence is a failure.
    hint = ("not built: the install needs a C compiler and Python's headers (the build "
            "skips optional extensions it cannot compile)")
    assert router_mod.COMPILED and SPEEDUPS is not None, f"_route_speedups {hint}"
    assert mmsg.COMPILED, f"_mmsg_speedups {hint}"


class SendLink(Link):
    """A datagram link written one datagram at a time (as a TCP or serial link is)."""

    datagram = True

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.sent: list[bytes] = []

    def send(self, data: bytes) -> bool:
        self.sent.append(data)
        return len(data) % 7 != 0  # some sends fail (a full queue): counted apart


class BatchLink(SendLink):
    """A link that takes a batch (as a UDP endpoint does): the router appends to its list."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self._batch: list[bytes] | None = None

    def start_batch(self) -> None:
        self._batch = []

    def batch_sink(self) -> list[bytes] | None:
        return self._batch

    def flush_batch(self) -> None:
        batch, self._batch = self._batch, None
        self.sent.extend(batch or ())

    def send(self, data: bytes) -> bool:
        if self._batch is not None:  # as a UDP endpoint: kept for the batch's one write
            self._batch.append(data)
            return True
        return super().send(data)


class Node:
    sysid, compid = 200, 191
    consumed = frozenset({0, 76})  # HEARTBEAT, COMMAND_LONG: decoded at once
    latest = frozenset({30, 33})  # ATTITUDE, GLOBAL_POSITION_INT: the mailbox

    def __init__(self) -> None:
        self.handled: list[tuple[str, int, int]] = []

    def handle(self, msg: Any, src_sysid: int, src_compid: int) -> list[Any]:
        self.handled.append((msg.get_type(), src_sysid, src_compid))
        return []


def pack(mav: Any, msg: Any, signed: bool = False) -> bytes:
    buf = bytes(msg.pack(mav))
    mav.seq = (mav.seq + 1) & 0xFF
    if signed:  # the incompat flag and 13 signature bytes (not verified: no key here)
        b = bytearray(buf)
        b[2] |= 0x01
        crc_extra = dev.mavlink_map[msg.id].crc_extra
        from gateway.crc import mcrf4xx
        crc = mcrf4xx(bytes(b[1:-2]) + bytes((crc_extra,)))
        b[-2:] = crc.to_bytes(2, "little")
        buf = bytes(b) + bytes(range(13))
    return buf


KINDS = ("attitude", "position", "heartbeat", "command_to_node", "command_to_1",
         "command_to_unknown", "param", "corrupt", "v1", "signed", "unknown_id", "truncated",
         "bytearray", "gap", "node_id", "short")
frame = st.tuples(st.sampled_from((1, 2, 3, 200)), st.sampled_from((1, 2)),
                  st.sampled_from(KINDS))
batches = st.lists(st.lists(frame, min_size=1, max_size=25), min_size=1, max_size=6)


def make(spec: tuple[int, int, str], mavs: dict[tuple[int, int], Any], t: int) -> Any:
    sysid, compid, kind = spec
    mav = mavs.setdefault((sysid, compid), dev.MAVLink(None, sysid, compid))
    if kind == "gap":
        mav.seq = (mav.seq + 5) & 0xFF
        kind = "attitude"
    if kind == "position":
        return pack(mav, dev.MAVLink_global_position_int_message(t, 1, 2, 3, 4, 5, 6, 7, 8))
    if kind == "heartbeat":
        return pack(mav, dev.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3))
    if kind.startswith("command_to_"):
        target = {"node": 200, "1": 1, "unknown": 77}[kind.removeprefix("command_to_")]
        return pack(mav, dev.MAVLink_command_long_message(target, 1, 400, 0, 1, 0, 0, 0, 0, 0,
                                                          0))
    if kind == "param":
        return pack(mav, dev.MAVLink_param_value_message(b"X", 1.0, 9, 1, 0))
    if kind == "v1":
        v1 = dev.MAVLink(None, sysid, compid)
        v1.WIRE_PROTOCOL_VERSION = "1.0"
        return bytes(dev.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(v1))
    good = pack(mav, dev.MAVLink_attitude_message(t, 0.1, 0.2, 0.3, 0, 0, 0),
                signed=kind == "signed")
    if kind == "corrupt":
        return good[:-1] + bytes((good[-1] ^ 0xFF,))
    if kind == "unknown_id":
        b = bytearray(good)
        b[7:10] = (0x7F, 0x7F, 0x01)
        return bytes(b)
    if kind == "truncated":
        return good[:-3]
    if kind == "short":
        return good[:12]
    if kind == "bytearray":
        return bytearray(good)
    return good


def run(batches_: list[list[tuple[int, int, str]]], speedups: Any,
        monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    monkeypatch.setattr(router_mod, "_speedups", speedups)
    router = Router()
    links: list[SendLink] = [BatchLink("in"), BatchLink("gcs"), SendLink("serial"),
                             BatchLink("other")]
    for lk in links:
        router.add_link(lk)
    node = Node()
    router.add_node(node)
    router.claim(node)
    gcs_mav = dev.MAVLink(None, 255, 190)
    router.receive(links[1], pack(gcs_mav, dev.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3)))
    router.receive(links[3], pack(dev.MAVLink(None, 3, 1),  # system 3 is also seen there
                                  dev.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3)))
    mavs: dict[tuple[int, int], Any] = {}
    collected = []
    t = 0
    for specs in batches_:
        data = []
        for spec in specs:
            data.append(make(spec, mavs, t))
            t += 1
        router.receive_many(links[0], data)
        collected.append(router.collect(node))
    return {
        "sent": {lk.name: lk.sent for lk in links},
        "link_stats": {lk.name: lk.stats() for lk in links},
        "last_seq": {lk.name: lk.last_seq for lk in links},
        "router": router.stats.as_dict(),
        "seen_at": sorted(router.seen_at),
        "seen_systems": router.seen_systems,
        "collected": collected,
        "handled": node.handled,
        "sysid": node.sysid,
    }


@pytest.mark.skipif(SPEEDUPS is None, reason="the compiled router was not built")
@settings(max_examples=150, deadline=None)
@given(batches)
def test_the_compiled_loop_routes_as_the_python_one(
        batches_: list[list[tuple[int, int, str]]]) -> None:
    with pytest.MonkeyPatch.context() as mp:
        python = run(batches_, None, mp)
    with pytest.MonkeyPatch.context() as mp:
        compiled = run(batches_, SPEEDUPS, mp)
    assert compiled == python


@pytest.mark.skipif(SPEEDUPS is None, reason="the compiled router was not built")
def test_a_plain_telemetry_stream_takes_the_compiled_loop(monkeypatch: pytest.MonkeyPatch
                                                           ) -> None:
    # Proof that the loop is not skipped: every datagram of a plain stream is routed by it
    # (the general path is never called), and the mailbox keeps the last of each.
    calls = []
    real = SPEEDUPS.route

    def counting(*args: Any) -> Any:
        out = real(*args)
        calls.append((args[1], out[0]))
        return out

    counted = type(sys)("counted")
    counted.route = counting  # type: ignore[attr-defined]
    specs = [[(1, 1, "attitude")] * 20, [(1, 1, "attitude"), (1, 1, "position")] * 10]
    result = run(specs, counted, monkeypatch)
    # the first batch's first datagram introduces system 1 (the general path); then none
    assert calls[0] == (0, 0) and calls[1] == (1, 20) and calls[2] == (0, 20)
    assert result["router"]["mailboxed"] == 40 and result["collected"] == [1, 2]
    read = [m for m, sysid, _ in result["handled"] if sysid == 1]  # (not the setup's beats)
    assert read == ["ATTITUDE", "ATTITUDE", "GLOBAL_POSITION_INT"]
    assert len(result["sent"]["gcs"]) == 1 + 40  # system 3's heartbeat, then all of them


def run_raw(batches_: list[list[bytes]], speedups: Any,
            monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """:func:`run` of datagrams given as bytes (after the vehicle is seen on the link)."""
    monkeypatch.setattr(router_mod, "_speedups", speedups)
    router = Router()
    links: list[SendLink] = [BatchLink("in"), BatchLink("gcs"), SendLink("serial")]
    for lk in links:
        router.add_link(lk)
    node = Node()
    router.add_node(node)
    router.claim(node)
    router.receive(links[0], pack(dev.MAVLink(None, 1, 1),
                                  dev.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3)))
    collected = []
    for data in batches_:
        router.receive_many(links[0], list(data))
        collected.append(router.collect(node))
    return {"sent": {lk.name: lk.sent for lk in links},
            "link_stats": {lk.name: lk.stats() for lk in links},
            "last_seq": links[0].last_seq, "router": router.stats.as_dict(),
            "collected": collected, "handled": node.handled}


_GOOD = pack(dev.MAVLink(None, 1, 1), dev.MAVLink_attitude_message(7, 0.1, 0.2, 0.3, 0, 0, 0))
mutated = st.builds(lambda i, x, cut: (_GOOD[:i] + bytes((_GOOD[i] ^ x,)) + _GOOD[i + 1:])[:cut],
                    st.integers(0, len(_GOOD) - 1), st.integers(1, 255),
                    st.integers(0, len(_GOOD) + 1))
datagram = st.one_of(st.just(_GOOD), mutated, st.binary(max_size=300),
                     st.binary(max_size=40).map(lambda b: b"\xfd" + b))


@pytest.mark.skipif(SPEEDUPS is None, reason="the compiled router was not built")
@settings(max_examples=300, deadline=None)
@given(st.lists(st.lists(datagram, min_size=1, max_size=20), min_size=1, max_size=4))
def test_damaged_and_random_datagrams_are_routed_as_the_python_loop_does(
        batches_: list[list[bytes]]) -> None:
    # Every byte of a good frame flipped, the frame cut anywhere, and random bytes (with and
    # without the MAVLink 2 start byte): the compiled loop reads no byte past a datagram and
    # takes the general path exactly where the Python loop does.
    with pytest.MonkeyPatch.context() as mp:
        python = run_raw(batches_, None, mp)
    with pytest.MonkeyPatch.context() as mp:
        compiled = run_raw(batches_, SPEEDUPS, mp)
    assert compiled == python


class FailingLink(SendLink):
    """A link whose third send raises (a bug in a link): the error must come out of
    ``receive_many`` as it does from the Python loop, and the router go on routing."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.calls = 0

    def send(self, data: bytes) -> bool:
        self.calls += 1
        if self.calls == 3:
            raise RuntimeError("link bug")
        self.sent.append(data)
        return True


def link_error_case(speedups: Any, monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    monkeypatch.setattr(router_mod, "_speedups", speedups)
    router = Router()
    src, bad, good = BatchLink("in"), FailingLink("bad"), BatchLink("good")
    for lk in (src, bad, good):
        router.add_link(lk)
    mav = dev.MAVLink(None, 1, 1)
    router.receive(src, pack(mav, dev.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3)))
    frames = [pack(mav, dev.MAVLink_attitude_message(i, 0, 0, 0, 0, 0, 0)) for i in range(6)]
    with pytest.raises(RuntimeError, match="link bug"):
        router.receive_many(src, frames)
    assert len(bad.sent) == 2 and good.sent[-2:] == frames[:2]  # up to the failing send
    more = [pack(mav, dev.MAVLink_attitude_message(i, 0, 0, 0, 0, 0, 0)) for i in range(4)]
    router.receive_many(src, more)
    assert bad.sent[-4:] == more and good.sent[-4:] == more
    return {"sent": (bad.sent, good.sent), "stats": [lk.stats() for lk in (src, bad, good)],
            "router": router.stats.as_dict(), "last_seq": src.last_seq}


@pytest.mark.skipif(SPEEDUPS is None, reason="the compiled router was not built")
def test_an_error_in_a_link_comes_out_and_routing_goes_on() -> None:
    with pytest.MonkeyPatch.context() as mp:
        python = link_error_case(None, mp)
    with pytest.MonkeyPatch.context() as mp:
        compiled = link_error_case(SPEEDUPS, mp)
    assert compiled == python
