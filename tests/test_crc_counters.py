"""Every link with a checksum counts its failures where the stop report's "crc errors" finds
them: each source's and backend's ``stats()`` holds them under a key containing ``crc``, once
(a nested per-client table must not count them a second time).  One corrupt frame goes to each
over a real connection; ``crc_errors`` (the stop report's sum) must say exactly 1."""

from __future__ import annotations

import contextlib
import socket
import struct
import zlib
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from helpers import wait_for

from backends.crsf.backend import CrsfBackend
from backends.crsf.frames import LinkStatistics, encode
from backends.crsf.options import CrsfOptions
from backends.fprime.backend import FprimeBackend
from backends.fprime.options import FprimeOptions
from backends.uavtalk import codec as uavtalk
from backends.uavtalk.backend import UavtalkBackend
from backends.uavtalk.objects import ObjectSet
from backends.uavtalk.options import UavtalkOptions, UavtalkSourceOptions
from backends.uavtalk.source import UavtalkSource
from backends.xbee import frames as xf
from backends.xbee.backend import XbeeBackend
from backends.xbee.options import XbeeOptions, XbeeSourceOptions
from backends.xbee.source import XbeeSource
from gateway.backend import GatewayContext
from gateway.flight_summary import crc_errors
from gateway.outcome import Outcome

DEADLINE_S = 10.0


def corrupt(frame: bytes) -> bytes:
    """``frame`` with its last byte (its checksum's) changed."""
    return frame[:-1] + bytes(((frame[-1] + 1) & 0xFF,))


def uavtalk_packet() -> bytes:
    gcs_stats = ObjectSet.load().by_name("GCSTelemetryStats")
    return uavtalk.encode(uavtalk.Packet(uavtalk.PacketType.OBJ, gcs_stats.id, 0,
                                         bytes(gcs_stats.size)))


def fprime_frame() -> bytes:
    packet = struct.pack(">HI", 0, 0x1234)
    head = b"\xde\xad\xbe\xef" + struct.pack(">I", len(packet))
    return head + packet + struct.pack(">I", zlib.crc32(packet, zlib.crc32(head)))


def one_crc_error(stats: Callable[[], dict[str, Any]]) -> None:
    assert wait_for(lambda: crc_errors({"link": stats()})["link"] >= 1, DEADLINE_S)
    assert crc_errors({"link": stats()}) == {"link": 1}  # counted once, nested tables too


# -- listeners the gateway accepts on (tcpin) ---------------------------------------------------

@pytest.mark.parametrize("case", ["fprime", "uavtalk"])
def test_a_backend_serving_tcp_clients_counts_a_bad_checksum_once(case: str) -> None:
    b: Any
    if case == "fprime":
        b = FprimeBackend(FprimeOptions(endpoints=["tcpin:127.0.0.1:0"], framing="fprime"))
        bad = corrupt(fprime_frame())
    else:
        b = UavtalkBackend(UavtalkOptions(endpoints=["tcpin:127.0.0.1:0"]))
        bad = corrupt(uavtalk_packet())
    b.attach(GatewayContext())
    b.init()
    try:
        with socket.create_connection(b.address(), timeout=DEADLINE_S) as peer:
            assert wait_for(lambda: b.stats()["clients"] == 1, DEADLINE_S)
            peer.sendall(bad)
            one_crc_error(b.stats)
        assert wait_for(lambda: b.stats()["clients"] == 0, DEADLINE_S)
        assert crc_errors({"link": b.stats()}) == {"link": 1}  # the client gone: still 1
    finally:
        b.close()


# -- links the gateway opens (a TCP device or a socket:// URL) ---------------------------------

@contextlib.contextmanager
def device() -> Iterator[tuple[str, Callable[[], socket.socket]]]:
    """A TCP listener standing in for a device: its port, and a function that accepts."""
    with socket.create_server(("127.0.0.1", 0)) as listener:
        listener.settimeout(DEADLINE_S)

        def accept() -> socket.socket:
            return listener.accept()[0]

        yield str(listener.getsockname()[1]), accept


def _open(case: str, port: str) -> tuple[Any, bytes, Callable[[], None]]:
    """The link of ``case`` on the device at ``port``, started; the corrupt frame to send it;
    how to stop it."""
    url = f"socket://127.0.0.1:{port}"
    if case in ("uavtalk source", "xbee source"):
        src: Any
        if case == "uavtalk source":
            src = UavtalkSource(UavtalkSourceOptions(url=f"tcp:127.0.0.1:{port}"))
            bad = corrupt(uavtalk_packet())
        else:
            src = XbeeSource(XbeeSourceOptions(url=url))
            bad = corrupt(xf.encode(xf.AtCommand(9, "NP"), 1))
        src.start(lambda _msg: Outcome.ACCEPTED)
        return src, bad, src.stop
    b: Any
    if case == "xbee backend":
        b = XbeeBackend(XbeeOptions(url=url))
        bad = corrupt(xf.encode(xf.AtCommand(9, "NP"), 1))
    else:
        b = CrsfBackend(CrsfOptions(url=url))
        bad = corrupt(encode(LinkStatistics(-60, -61, 100, 5, 0, 4, 2, -70, 90, 8)))
    b.attach(GatewayContext())
    b.init()
    return b, bad, b.close


@pytest.mark.parametrize("case", ["uavtalk source", "xbee source", "xbee backend",
                                  "crsf backend"])
def test_a_link_to_a_device_counts_a_bad_checksum_once(case: str) -> None:
    with device() as (port, accept):
        link, bad, stop = _open(case, port)
        try:
            with accept() as conn:
                # up first: pyserial's socket:// drops what arrived before its open() ended
                assert wait_for(lambda: link.stats()["link"] == 1, DEADLINE_S)
                conn.sendall(bad)
                one_crc_error(link.stats)
        finally:
            stop()
