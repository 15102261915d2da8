"""The two names of the Foxglove WebSocket protocol, and the handshake rewrite between them.

foxglove-sdk's server (0.30) accepts only the subprotocol ``foxglove.sdk.v1``; clients of the
older generation (Lichtblick up to 1.21, the open-source Foxglove Studio, the
``@foxglove/ws-protocol`` npm client) offer only ``foxglove.websocket.v1``.  The messages
are the same (the SDK's protocol module cites the ws-protocol spec for each: ``serverInfo``,
``advertise``, ``subscribe``, binary ``messageData`` = 0x01, u32 subscription id, u64 log
time, payload, little-endian), so :class:`~backends.foxglove.relay.ProtocolRelay` renames the
protocol in the opening handshake only — the request's ``Sec-WebSocket-Protocol`` on the way
in, the answer's on the way out — and copies every byte after it unchanged.
``Sec-WebSocket-Accept`` is derived from the key alone, so the rewrite keeps it valid.
"""

from __future__ import annotations

SDK = "foxglove.sdk.v1"
LEGACY = "foxglove.websocket.v1"
#: The names a client may offer and be served under (the SDK's first).
ACCEPTED = (SDK, LEGACY)
HEADER = b"sec-websocket-protocol"
END = b"\r\n\r\n"
#: The longest request (or answer) head read before it is refused: a browser's request with
#: its cookies is a few KiB.
MAX_HEAD = 32 * 1024


def offered(head: bytes) -> list[str]:
    """The subprotocols a request head offers (every ``Sec-WebSocket-Protocol`` line, in
    order; names are case-sensitive, as the SDK compares them)."""
    names: list[str] = []
    for line in head.split(b"\r\n")[1:]:
        key, sep, value = line.partition(b":")
        if sep and key.strip().lower() == HEADER:
            names.extend(n.strip() for n in value.decode("latin-1").split(",") if n.strip())
    return names


def served_as(names: list[str]) -> str | None:
    """The name a client offering ``names`` is answered under (None: neither)."""
    if SDK in names:
        return SDK
    if LEGACY in names:
        return LEGACY
    return None


def _replace_header(head: bytes, value: bytes) -> bytes:
    """``head`` with its ``Sec-WebSocket-Protocol`` lines replaced by one carrying ``value``
    (in place of the first of them)."""
    lines = head.split(b"\r\n")
    out = lines[:1]
    done = False
    for line in lines[1:]:
        key, sep, _ = line.partition(b":")
        if sep and key.strip().lower() == HEADER:
            if not done:
                out.append(b"Sec-WebSocket-Protocol: " + value)
                done = True
            continue
        out.append(line)
    return b"\r\n".join(out)


def to_sdk(request_head: bytes) -> bytes:
    """A legacy client's request head as the SDK's server accepts it."""
    return _replace_header(request_head, SDK.encode())


def to_legacy(answer_head: bytes) -> bytes:
    """The SDK's answer head as a legacy client expects it (its protocol is the one the
    client offered; a client must fail a connection that names another)."""
    if not offered(answer_head):
        return answer_head  # an answer without the header (a refusal): nothing to rename
    return _replace_header(answer_head, LEGACY.encode())


def status(answer_head: bytes) -> int:
    """The status code of an HTTP answer head (0 when it is not one)."""
    parts = answer_head.split(b"\r\n", 1)[0].split(b" ", 2)
    try:
        return int(parts[1]) if len(parts) >= 2 and parts[0].startswith(b"HTTP/") else 0
    except ValueError:
        return 0
