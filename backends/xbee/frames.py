"""Sans-I/O XBee API frames (Digi API mode 1 and 2): typed records, an encoder and a
streaming decoder.  See ``shared/specs/xbee.md``.

A frame is ``7E | length (u16 BE) | frame data | checksum``: ``length`` counts the frame data
(type byte first), the checksum is ``0xFF − (sum of frame data & 0xFF)``, so a good frame's
data plus checksum sums to 0xFF.  API mode 2 (escaped) sends every byte after the leading
0x7E that is 0x7E, 0x7D, 0x11 or 0x13 as ``7D, byte ^ 0x20``; length and checksum are computed
on the unescaped bytes.  Multi-byte fields are big-endian.

Records (``NamedTuple``; addresses are ints, AT commands two-letter ``str``):

========  ==========================  ====================================================
type      record                      fields (wire order unless noted)
========  ==========================  ====================================================
0x08      :class:`AtCommand`          frame_id, command, parameter
0x10      :class:`TransmitRequest`    frame_id, dest64, data, dest16, radius, options
                                      (wire: id, dest64, dest16, radius, options, data)
0x17      :class:`RemoteAtCommand`    frame_id, dest64, command, parameter, dest16, options
                                      (wire: id, dest64, dest16, options, command, param)
0x88      :class:`AtResponse`         frame_id, command, status, value
0x8A      :class:`ModemStatus`        status (0 = hardware reset: re-apply PL after it)
0x8B      :class:`TransmitStatus`     frame_id, dest16, retries, delivery, discovery
0x90      :class:`ReceivePacket`      src64, src16, options, data
0x97      :class:`RemoteAtResponse`   frame_id, src64, src16, command, status, value
other     :class:`UnknownFrame`       frame_type, data (everything after the type byte)
========  ==========================  ====================================================

:func:`encode` turns any record into a frame; :class:`FrameDecoder` turns a byte stream into
records.  Frame id 0 asks the module for no response (no 0x8B / 0x88 / 0x97).

Decoder rules (the project's one resync rule): find 0x7E, read the length, check it is
1..``max_length``, wait for the whole frame, check the checksum; on any failure count it and
drop *one* byte, then rescan from the next 0x7E.  In API 2 a raw 0x7E can never be inside a
frame, so a frame cut short by a new 0x7E fails at once (counted as ``bad_length``), and a
0x7D followed by anything but an escaped 0x7E/0x7D/0x11/0x13, or a raw 0x11/0x13 inside a
frame, is a ``bad_escape``.  A checksum-valid frame of a type not listed above is returned as
an :class:`UnknownFrame` (and counted in ``unknown_type``); one of a listed type that is too
short for its fixed fields (or has the wrong size, for the fixed-size 0x8A/0x8B) is dropped
and counted in ``bad_length``.  The decoder never raises on any input, and the bytes it holds
back never exceed one maximal frame.

AT value helpers: :func:`pl_param`/:func:`decode_pl` (power level 0..4), :func:`decode_db`
(RSSI of the last received packet, returned in dBm, negative), :func:`decode_counter` and
:func:`counter_delta` (ER/GD/TR/EA: 16-bit counters that saturate at 0xFFFF and reset to 0),
:func:`decode_np` (largest RF payload in bytes), :func:`int_param`/:func:`at_int` (numeric AT
values, big-endian with leading zeros optional).  They raise :class:`AtValueError`.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

from gateway.counters import Counters
from gateway.resync import BAD, WAIT, ResyncDecoder

START = 0x7E
ESCAPE = 0x7D
XON = 0x11
XOFF = 0x13
ESCAPE_XOR = 0x20
#: Bytes API mode 2 escapes (everywhere after the start delimiter).
ESCAPED_BYTES = frozenset({START, ESCAPE, XON, XOFF})
API_MODES = (1, 2)

#: The decoder's default bound on a frame's length field (frame data bytes).  The largest
#: frame this link uses is a 0x10 with a full payload: 14 + NP (NP ≤ 256 on every XBee).
MAX_FRAME_DATA = 512
#: What the 16-bit length field can hold (the encoder's limit).
MAX_LENGTH_FIELD = 0xFFFF

TYPE_AT_COMMAND = 0x08
TYPE_TRANSMIT_REQUEST = 0x10
TYPE_REMOTE_AT_COMMAND = 0x17
TYPE_AT_RESPONSE = 0x88
TYPE_MODEM_STATUS = 0x8A
TYPE_TRANSMIT_STATUS = 0x8B
TYPE_RECEIVE_PACKET = 0x90
TYPE_REMOTE_AT_RESPONSE = 0x97

BROADCAST_64 = 0x000000000000FFFF
COORDINATOR_64 = 0x0000000000000000
UNKNOWN_16 = 0xFFFE
#: Frame id 0: the module sends no status/response frame for this request.
NO_RESPONSE = 0

# 0x10 transmit options (bit field; 0 = the module's TO default)
TX_DISABLE_ACK = 0x01
# 0x90 receive options (bit field)
RX_ACKED = 0x01
RX_BROADCAST = 0x02
# 0x17 remote AT options (bit field)
REMOTE_DISABLE_ACK = 0x01
REMOTE_APPLY_CHANGES = 0x02
REMOTE_EXTENDED_TIMEOUT = 0x40

# 0x8B delivery status (Digi; the common ones)
DELIVERY_SUCCESS = 0x00
DELIVERY_NAMES: dict[int, str] = {
    0x00: "success",
    0x01: "MAC ACK failure",
    0x02: "CCA failure",
    0x15: "invalid destination endpoint",
    0x21: "network ACK failure",
    0x22: "not joined to network",
    0x23: "self-addressed",
    0x24: "address not found",
    0x25: "route not found",
    0x74: "payload too large",
}

# 0x88 / 0x97 command status
AT_OK = 0
AT_ERROR = 1
AT_INVALID_COMMAND = 2
AT_INVALID_PARAMETER = 3
AT_TX_FAILURE = 4  # remote only: the request never reached the far module
AT_STATUS_NAMES: dict[int, str] = {
    0: "OK", 1: "ERROR", 2: "invalid command", 3: "invalid parameter", 4: "TX failure",
}

# 0x8A modem status (the ones a point-to-point link sees)
MODEM_HARDWARE_RESET = 0x00
MODEM_WATCHDOG_RESET = 0x01

# AT commands the link uses
AT_POWER_LEVEL = "PL"  # TX power level 0..4 (set and query)
AT_RSSI = "DB"  # RSSI of the last received packet, −dBm
AT_RX_ERRORS = "ER"  # receive errors (16-bit, saturating)
AT_GOOD_PACKETS = "GD"  # good received packets (16-bit, saturating)
AT_TX_ERRORS = "TR"  # transmission failures (16-bit, saturating)
AT_ACK_FAILURES = "EA"  # MAC ACK failures (16-bit, saturating)
AT_MAX_PAYLOAD = "NP"  # largest RF payload in bytes
AT_SERIAL_HIGH = "SH"  # upper 32 bits of the module's 64-bit address
AT_SERIAL_LOW = "SL"  # lower 32 bits
AT_API_MODE = "AP"  # 1 = API, 2 = API escaped
AT_APPLY_CHANGES = "AC"
AT_WRITE = "WR"  # save settings to non-volatile memory

POWER_LEVELS = range(5)  # PL 0 (lowest) .. 4 (highest)
COUNTER_MAX = 0xFFFF


class FrameError(ValueError):
    """A record that cannot be encoded, or frame data that does not decode."""


class AtValueError(ValueError):
    """An AT parameter or response value out of its range."""


# -- records ----------------------------------------------------------------------------------

class AtCommand(NamedTuple):
    """0x08 AT Command: query (empty ``parameter``) or set a local AT parameter."""

    frame_id: int
    command: str
    parameter: bytes = b""


class AtResponse(NamedTuple):
    """0x88 AT Command Response; ``status`` 0 = OK, ``value`` the queried value (big-endian)."""

    frame_id: int
    command: str
    status: int
    value: bytes = b""

    @property
    def ok(self) -> bool:
        return self.status == AT_OK


class TransmitRequest(NamedTuple):
    """0x10 Transmit Request: ``data`` (RF payload ≤ NP) to ``dest64`` (BROADCAST_64 for all)."""

    frame_id: int
    dest64: int
    data: bytes
    dest16: int = UNKNOWN_16
    radius: int = 0  # broadcast radius, 0 = maximum hops
    options: int = 0  # 0 = the module's TO setting


class TransmitStatus(NamedTuple):
    """0x8B Transmit Status of the 0x10 with the same ``frame_id``; ``delivery`` 0 = success."""

    frame_id: int
    dest16: int
    retries: int
    delivery: int
    discovery: int

    @property
    def ok(self) -> bool:
        return self.delivery == DELIVERY_SUCCESS


class ReceivePacket(NamedTuple):
    """0x90 Receive Packet: RF ``data`` from ``src64`` (the address to answer to)."""

    src64: int
    src16: int
    options: int
    data: bytes

    @property
    def acked(self) -> bool:
        return bool(self.options & RX_ACKED)

    @property
    def broadcast(self) -> bool:
        return bool(self.options & RX_BROADCAST)


class RemoteAtCommand(NamedTuple):
    """0x17 Remote AT Command: query or set the far module's parameter (e.g. its PL)."""

    frame_id: int
    dest64: int
    command: str
    parameter: bytes = b""
    dest16: int = UNKNOWN_16
    options: int = REMOTE_APPLY_CHANGES


class RemoteAtResponse(NamedTuple):
    """0x97 Remote AT Command Response from ``src64``; ``status`` 4 = request not delivered."""

    frame_id: int
    src64: int
    src16: int
    command: str
    status: int
    value: bytes = b""

    @property
    def ok(self) -> bool:
        return self.status == AT_OK


class ModemStatus(NamedTuple):
    """0x8A Modem Status (0 = hardware reset, 1 = watchdog reset …)."""

    status: int


class UnknownFrame(NamedTuple):
    """A checksum-valid frame of a type this module does not decode, kept whole."""

    frame_type: int
    data: bytes


Frame = (AtCommand | AtResponse | TransmitRequest | TransmitStatus | ReceivePacket
         | RemoteAtCommand | RemoteAtResponse | ModemStatus | UnknownFrame)


# -- building blocks --------------------------------------------------------------------------

def checksum(frame_data: bytes) -> int:
    """The checksum of ``frame_data`` (type byte onwards): 0xFF − (sum & 0xFF)."""
    return 0xFF - (sum(frame_data) & 0xFF)


_ESCAPE_RE = re.compile(b"[\x7e\x7d\x11\x13]")


def _escape_one(m: re.Match[bytes]) -> bytes:
    return bytes((ESCAPE, m[0][0] ^ ESCAPE_XOR))


def escape(data: bytes) -> bytes:
    """API mode 2 escaping of ``data`` (everything after the start delimiter)."""
    return _ESCAPE_RE.sub(_escape_one, data)


def wrap(frame_data: bytes, api_mode: int = 1) -> bytes:
    """A whole frame around ``frame_data``: start, length, data, checksum, escaped in API 2."""
    _check_mode(api_mode)
    if not 1 <= len(frame_data) <= MAX_LENGTH_FIELD:
        raise FrameError(f"frame data of {len(frame_data)} bytes: must be 1..{MAX_LENGTH_FIELD}")
    body = len(frame_data).to_bytes(2, "big") + frame_data + bytes((checksum(frame_data),))
    return bytes((START,)) + (escape(body) if api_mode == 2 else body)


def _check_mode(api_mode: int) -> None:
    if api_mode not in API_MODES:
        raise ValueError(f"api_mode {api_mode!r}: must be 1 (API) or 2 (API escaped)")


def _uint(name: str, value: int, nbytes: int) -> bytes:
    if not isinstance(value, int) or not 0 <= value < 1 << (8 * nbytes):
        raise FrameError(f"{name} {value!r}: must be an integer 0..{(1 << (8 * nbytes)) - 1}")
    return value.to_bytes(nbytes, "big")


def _command(command: str) -> bytes:
    if not isinstance(command, str) or len(command) != 2 or not command.isascii():
        raise FrameError(f"AT command {command!r}: must be two ASCII characters")
    return command.encode("ascii")


def _bytes(name: str, value: bytes) -> bytes:
    if not isinstance(value, bytes | bytearray | memoryview):
        raise FrameError(f"{name} must be bytes, not {type(value).__name__}")
    return bytes(value)


def _data_at_command(f: AtCommand) -> bytes:
    return (bytes((TYPE_AT_COMMAND,)) + _uint("frame_id", f.frame_id, 1) + _command(f.command)
            + _bytes("parameter", f.parameter))


def _data_at_response(f: AtResponse) -> bytes:
    return (bytes((TYPE_AT_RESPONSE,)) + _uint("frame_id", f.frame_id, 1) + _command(f.command)
            + _uint("status", f.status, 1) + _bytes("value", f.value))


def _data_transmit_request(f: TransmitRequest) -> bytes:
    return (bytes((TYPE_TRANSMIT_REQUEST,)) + _uint("frame_id", f.frame_id, 1)
            + _uint("dest64", f.dest64, 8) + _uint("dest16", f.dest16, 2)
            + _uint("radius", f.radius, 1) + _uint("options", f.options, 1)
            + _bytes("data", f.data))


def _data_transmit_status(f: TransmitStatus) -> bytes:
    return (bytes((TYPE_TRANSMIT_STATUS,)) + _uint("frame_id", f.frame_id, 1)
            + _uint("dest16", f.dest16, 2) + _uint("retries", f.retries, 1)
            + _uint("delivery", f.delivery, 1) + _uint("discovery", f.discovery, 1))


def _data_receive_packet(f: ReceivePacket) -> bytes:
    return (bytes((TYPE_RECEIVE_PACKET,)) + _uint("src64", f.src64, 8)
            + _uint("src16", f.src16, 2) + _uint("options", f.options, 1)
            + _bytes("data", f.data))


def _data_remote_at_command(f: RemoteAtCommand) -> bytes:
    return (bytes((TYPE_REMOTE_AT_COMMAND,)) + _uint("frame_id", f.frame_id, 1)
            + _uint("dest64", f.dest64, 8) + _uint("dest16", f.dest16, 2)
            + _uint("options", f.options, 1) + _command(f.command)
            + _bytes("parameter", f.parameter))


def _data_remote_at_response(f: RemoteAtResponse) -> bytes:
    return (bytes((TYPE_REMOTE_AT_RESPONSE,)) + _uint("frame_id", f.frame_id, 1)
            + _uint("src64", f.src64, 8) + _uint("src16", f.src16, 2) + _command(f.command)
            + _uint("status", f.status, 1) + _bytes("value", f.value))


def _data_modem_status(f: ModemStatus) -> bytes:
    return bytes((TYPE_MODEM_STATUS,)) + _uint("status", f.status, 1)


def _data_unknown(f: UnknownFrame) -> bytes:
    return _uint("frame_type", f.frame_type, 1) + _bytes("data", f.data)


_ENCODERS: dict[type, Callable[..., bytes]] = {
    AtCommand: _data_at_command,
    AtResponse: _data_at_response,
    TransmitRequest: _data_transmit_request,
    TransmitStatus: _data_transmit_status,
    ReceivePacket: _data_receive_packet,
    RemoteAtCommand: _data_remote_at_command,
    RemoteAtResponse: _data_remote_at_response,
    ModemStatus: _data_modem_status,
    UnknownFrame: _data_unknown,
}


def frame_data(frame: Frame) -> bytes:
    """The unescaped frame data of ``frame`` (type byte onwards, no length or checksum)."""
    enc = _ENCODERS.get(type(frame))
    if enc is None:
        raise FrameError(f"not an XBee frame record: {type(frame).__name__}")
    return enc(frame)


def encode(frame: Frame, api_mode: int = 1) -> bytes:
    """``frame`` as the bytes to write to a module in ``api_mode`` (1 or 2).

    Raises :class:`FrameError` (a ValueError) for a field out of range, an AT command that is
    not two ASCII letters, or frame data over 65535 bytes; ValueError for another api_mode.
    """
    return wrap(frame_data(frame), api_mode)


# -- decoding frame data ----------------------------------------------------------------------

def _cmd(b: bytes) -> str:
    return b.decode("latin-1")  # any two bytes decode; real commands are ASCII


def _dec_at_command(d: bytes) -> Frame:
    return AtCommand(d[1], _cmd(d[2:4]), d[4:])


def _dec_at_response(d: bytes) -> Frame:
    return AtResponse(d[1], _cmd(d[2:4]), d[4], d[5:])


def _dec_transmit_request(d: bytes) -> Frame:
    return TransmitRequest(d[1], int.from_bytes(d[2:10], "big"), d[14:],
                           int.from_bytes(d[10:12], "big"), d[12], d[13])


def _dec_transmit_status(d: bytes) -> Frame:
    return TransmitStatus(d[1], int.from_bytes(d[2:4], "big"), d[4], d[5], d[6])


def _dec_receive_packet(d: bytes) -> Frame:
    return ReceivePacket(int.from_bytes(d[1:9], "big"), int.from_bytes(d[9:11], "big"),
                         d[11], d[12:])


def _dec_remote_at_command(d: bytes) -> Frame:
    return RemoteAtCommand(d[1], int.from_bytes(d[2:10], "big"), _cmd(d[13:15]), d[15:],
                           int.from_bytes(d[10:12], "big"), d[12])


def _dec_remote_at_response(d: bytes) -> Frame:
    return RemoteAtResponse(d[1], int.from_bytes(d[2:10], "big"),
                            int.from_bytes(d[10:12], "big"), _cmd(d[12:14]), d[14], d[15:])


def _dec_modem_status(d: bytes) -> Frame:
    return ModemStatus(d[1])


# frame type → (minimum frame data length, exact?, decoder)
_DECODERS: dict[int, tuple[int, bool, Callable[[bytes], Frame]]] = {
    TYPE_AT_COMMAND: (4, False, _dec_at_command),
    TYPE_AT_RESPONSE: (5, False, _dec_at_response),
    TYPE_TRANSMIT_REQUEST: (14, False, _dec_transmit_request),
    TYPE_TRANSMIT_STATUS: (7, True, _dec_transmit_status),
    TYPE_RECEIVE_PACKET: (12, False, _dec_receive_packet),
    TYPE_REMOTE_AT_COMMAND: (15, False, _dec_remote_at_command),
    TYPE_REMOTE_AT_RESPONSE: (15, False, _dec_remote_at_response),
    TYPE_MODEM_STATUS: (2, True, _dec_modem_status),
}


def decode_frame_data(data: bytes) -> Frame:
    """The record for unescaped ``data`` (type byte onwards, checksum already checked).

    An unlisted type gives an :class:`UnknownFrame`; a listed type with a length its fixed
    fields do not allow raises :class:`FrameError`.
    """
    if not data:
        raise FrameError("empty frame data")
    data = bytes(data)
    spec = _DECODERS.get(data[0])
    if spec is None:
        return UnknownFrame(data[0], data[1:])
    size, exact, dec = spec
    if len(data) < size or (exact and len(data) != size):
        want = f"{size}" if exact else f"at least {size}"
        raise FrameError(f"frame type 0x{data[0]:02X} with {len(data)} bytes of frame data "
                         f"(needs {want})")
    return dec(data)


# -- the stream decoder -----------------------------------------------------------------------

@dataclass
class FrameDecoderStats(Counters):
    """What a :class:`FrameDecoder` has seen.

    ``frames`` counts every checksum-valid frame returned (``unknown_type`` of them as
    :class:`UnknownFrame`); ``bad_length`` counts length fields out of bounds, API 2 frames cut
    short by a new 0x7E, and checksum-valid frames too short for their type (dropped);
    ``garbage_bytes`` counts every byte outside a checksum-valid frame.  ``crc_failures``
    counts frames whose checksum (0xFF minus the byte sum) fails: not a CRC, but named like
    every other decoder's check failures, so the stop report's "crc errors" count them.
    """

    bytes_in: int = 0
    frames: int = 0
    crc_failures: int = 0
    bad_length: int = 0
    bad_escape: int = 0
    garbage_bytes: int = 0
    unknown_type: int = 0


_WAIT, _OK, _BAD_LENGTH, _BAD_ESCAPE, _BAD_CHECKSUM = range(5)
_ESCAPED_VALUES = frozenset(b ^ ESCAPE_XOR for b in ESCAPED_BYTES)


class FrameDecoder(ResyncDecoder[Frame]):
    """Turns a byte stream from a module in ``api_mode`` (1 or 2) into frame records.

    :meth:`feed` keeps a partial frame for the next call; corruption is counted in
    :attr:`stats`, never raised (see the module docstring for the rules).
    """

    __slots__ = ("api_mode", "max_length", "stats")

    def __init__(self, api_mode: int = 1, max_length: int = MAX_FRAME_DATA) -> None:
        _check_mode(api_mode)
        if not 1 <= max_length <= MAX_LENGTH_FIELD:
            raise ValueError(f"max_length {max_length}: must be 1..{MAX_LENGTH_FIELD}")
        super().__init__()
        self.api_mode = api_mode
        self.max_length = max_length
        self.stats = FrameDecoderStats()

    def _find_start(self, buf: bytes, pos: int) -> int:
        return buf.find(START, pos)

    def _frame_at(self, buf: bytes, i: int, out: list[Frame]) -> int:
        st = self.stats
        read = self._read_escaped if self.api_mode == 2 else self._read_plain
        verdict, data, end = read(buf, i)
        if verdict == _WAIT:
            return WAIT
        if verdict != _OK:
            if verdict == _BAD_LENGTH:
                st.bad_length += 1
            elif verdict == _BAD_ESCAPE:
                st.bad_escape += 1
            elif verdict == _BAD_CHECKSUM:
                st.crc_failures += 1
            return BAD
        try:
            frame = decode_frame_data(data)
        except FrameError:
            st.bad_length += 1
            return end  # a whole frame whose data does not decode: consumed, counted
        st.frames += 1
        if type(frame) is UnknownFrame:
            st.unknown_type += 1
        out.append(frame)
        return end

    def _count(self, bytes_in: int, skipped: int) -> None:
        self.stats.bytes_in += bytes_in
        self.stats.garbage_bytes += skipped

    def _read_plain(self, buf: bytes, i: int) -> tuple[int, bytes, int]:
        n = len(buf)
        if i + 3 > n:
            return _WAIT, b"", 0
        length = (buf[i + 1] << 8) | buf[i + 2]
        if not 1 <= length <= self.max_length:
            return _BAD_LENGTH, b"", 0
        end = i + 4 + length
        if end > n:
            return _WAIT, b"", 0
        body = buf[i + 3:end]
        if sum(body) & 0xFF != 0xFF:
            return _BAD_CHECKSUM, b"", 0
        return _OK, body[:-1], end

    def _read_escaped(self, buf: bytes, i: int) -> tuple[int, bytes, int]:
        n = len(buf)
        got = bytearray()
        need = 2  # the length field first, then length + checksum
        j = i + 1
        while len(got) < need:
            if j >= n:
                return _WAIT, b"", 0
            b = buf[j]
            if b == START:  # a new frame began: this one was cut short
                return _BAD_LENGTH, b"", 0
            if b == ESCAPE:
                if j + 1 >= n:
                    return _WAIT, b"", 0
                b = buf[j + 1]
                if b not in _ESCAPED_VALUES:
                    return _BAD_ESCAPE, b"", 0
                got.append(b ^ ESCAPE_XOR)
                j += 2
            elif b in (XON, XOFF):
                return _BAD_ESCAPE, b"", 0
            else:
                got.append(b)
                j += 1
            if need == 2 and len(got) == 2:
                length = (got[0] << 8) | got[1]
                if not 1 <= length <= self.max_length:
                    return _BAD_LENGTH, b"", 0
                need = 3 + length
        if sum(got[2:]) & 0xFF != 0xFF:
            return _BAD_CHECKSUM, b"", 0
        return _OK, bytes(got[2:-1]), j


def decode_all(data: bytes, api_mode: int = 1) -> list[Frame]:
    """Decode a complete byte string (feed, then flush); convenience for files and tests."""
    dec = FrameDecoder(api_mode)
    return dec.feed(data) + dec.flush()


# -- AT values --------------------------------------------------------------------------------

def int_param(value: int) -> bytes:
    """A numeric AT parameter: big-endian, no leading zero bytes (0 → ``00``)."""
    if not isinstance(value, int) or value < 0:
        raise AtValueError(f"AT parameter {value!r}: must be a non-negative integer")
    return value.to_bytes(max(1, (value.bit_length() + 7) // 8), "big")


def at_int(value: bytes, bits: int = 32) -> int:
    """A numeric AT value (big-endian, leading zeros optional) that must fit ``bits``."""
    if not value:
        raise AtValueError("empty AT value")
    v = int.from_bytes(value, "big")
    if v >> bits:
        raise AtValueError(f"AT value 0x{v:X} does not fit {bits} bits")
    return v


def pl_param(level: int) -> bytes:
    """The PL parameter for power ``level`` 0..4."""
    if level not in POWER_LEVELS:
        raise AtValueError(f"power level {level!r}: must be 0..4")
    return bytes((level,))


def decode_pl(value: bytes) -> int:
    """The power level 0..4 of a PL response."""
    level = at_int(value, 8)
    if level not in POWER_LEVELS:
        raise AtValueError(f"PL value {level}: must be 0..4")
    return level


def decode_db(value: bytes) -> int:
    """The RSSI in dBm (negative) of a DB response, which carries it as −dBm."""
    return -at_int(value, 8)


def decode_counter(value: bytes) -> int:
    """An ER/GD/TR/EA counter (0..0xFFFF; it stops at 0xFFFF until reset to 0)."""
    return at_int(value, 16)


def counter_delta(before: int, after: int) -> int:
    """Events counted between two readings of a saturating counter.

    A reading lower than the one before means the counter was reset (module restart or a
    write of 0), so ``after`` events happened since; a saturated counter gives 0.
    """
    return after - before if after >= before else after


def decode_np(value: bytes) -> int:
    """The largest RF payload in bytes of an NP response (at least 1)."""
    np_ = at_int(value, 16)
    if np_ < 1:
        raise AtValueError("NP value 0: a module always carries at least one byte")
    return np_
