"""gateway.io.transport.resolve: an address literal skips the resolver (start-up time) and
gives what the resolver gives."""

from __future__ import annotations

import socket

import pytest

from gateway.io.transport import TransportError, resolve


@pytest.mark.parametrize("host", ["127.0.0.1", "0.0.0.0", "::1", "::"])
@pytest.mark.parametrize("kind", [socket.SOCK_DGRAM, socket.SOCK_STREAM])
def test_a_literal_resolves_as_getaddrinfo_does(host: str, kind: int) -> None:
    family, _, _, _, addr = socket.getaddrinfo(host, 14550, type=kind)[0]
    assert resolve(host, 14550, kind) == (family, addr)


def test_a_name_still_goes_to_the_resolver() -> None:
    family, addr = resolve("localhost", 14550, socket.SOCK_DGRAM)
    assert family in (socket.AF_INET, socket.AF_INET6)
    assert addr[1] == 14550
    with pytest.raises(TransportError, match="cannot resolve"):
        resolve("no-such-host.invalid", 1, socket.SOCK_DGRAM)
