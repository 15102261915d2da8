"""The router's batch path (``receive_many``, the common case inlined) routes exactly as one
datagram at a time does: same frames out, same counters, same mailboxes."""

from __future__ import annotations

from typing import Any

from mavlink_peer import upstream_dialect

from backends.mavlink.router import Link, Router

dev = upstream_dialect()


class RecordingLink(Link):
    """A datagram link that keeps what the router sends it."""

    datagram = True

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.sent: list[bytes] = []

    def send(self, data: bytes) -> bool:
        self.sent.append(data)
        return True


class MailboxNode:
    sysid, compid = 200, 191
    consumed = frozenset({0})  # HEARTBEAT: decoded at once (the general path)
    latest = frozenset({30})  # ATTITUDE: kept in the mailbox

    def __init__(self) -> None:
        self.handled: list[str] = []

    def handle(self, msg: Any, src_sysid: int, src_compid: int) -> list[Any]:
        self.handled.append(msg.get_type())
        return []


def datagrams() -> list[bytes]:
    """Telemetry of two systems, a heartbeat, a targeted command, a corrupt frame, a MAVLink 1
    frame, a sequence gap and a source seen for the first time mid-batch."""
    a, b = dev.MAVLink(None, 1, 1), dev.MAVLink(None, 2, 1)
    out = []

    def pack(mav: Any, msg: Any) -> bytes:
        buf: bytes = msg.pack(mav)
        mav.seq = (mav.seq + 1) & 0xFF
        return buf

    for i in range(30):
        out.append(pack(a, dev.MAVLink_attitude_message(i, 0.1, 0.2, 0.3, 0, 0, 0)))
        if i == 5:
            out.append(pack(b, dev.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3)))
        if i == 8:
            bad = bytearray(out[-1])
            bad[-1] ^= 0xFF
            out.append(bytes(bad))
        if i == 12:
            out.append(pack(a, dev.MAVLink_command_long_message(2, 1, 400, 0, 1, 0, 0, 0, 0,
                                                                 0, 0)))
        if i == 15:
            a.seq = (a.seq + 3) & 0xFF
        if i == 20:
            out.append(pack(b, dev.MAVLink_attitude_message(i, 0, 0, 0, 0, 0, 0)))
            v1 = dev.MAVLink(None, 3, 1)
            v1.WIRE_PROTOCOL_VERSION = "1.0"
            out.append(bytes(dev.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(v1)))
    return out


def routed(one_at_a_time: bool) -> tuple[Router, list[RecordingLink], MailboxNode]:
    router = Router()
    links = [RecordingLink(n) for n in ("in", "out1", "out2")]
    for lk in links:
        router.add_link(lk)
    node = MailboxNode()
    router.add_node(node)
    router.claim(node)
    src, gcs = links[0], links[1]
    gcs_mav = dev.MAVLink(None, 255, 190)  # a ground station seen on out1
    router.receive(gcs, dev.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(gcs_mav))
    data = datagrams()
    for lk in links:
        lk.sent.clear()
    if one_at_a_time:
        for d in data:
            router.receive(src, d)
    else:
        router.receive_many(src, data[:3])  # the first sighting of system 1 in the batch
        router.receive_many(src, data[3:])
    return router, links, node


def test_receive_many_routes_as_receive_does() -> None:
    one, one_links, one_node = routed(True)
    many, many_links, many_node = routed(False)
    for a, b in zip(one_links, many_links, strict=True):
        assert a.sent == b.sent
        assert a.stats() == b.stats()
        assert a.last_seq == b.last_seq
    assert one.stats.as_dict() == many.stats.as_dict()
    assert one.stats.forwarded > 30 and one.stats.mailboxed > 25
    assert one_links[0].framer_stats.crc_errors == 1
    assert one_links[0].counters.seq_lost == 3
    assert one.seen_systems == many.seen_systems
    assert set(one.seen_at) == set(many.seen_at) == {1, 2, 3, 255}
    assert one.collect(one_node) == many.collect(many_node) == 2  # ATTITUDE of 1 and of 2
    assert one_node.handled == many_node.handled
    assert "HEARTBEAT" in one_node.handled
