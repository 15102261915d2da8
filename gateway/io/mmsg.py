"""Many datagrams per system call: Linux's ``recvmmsg``/``sendmmsg`` through ctypes.

A router's cost per datagram is mostly the system calls and the Python steps around them;
reading every datagram waiting on a socket with one ``recvmmsg`` and writing a batch to one
destination with one ``sendmmsg`` takes one call (and one release of the GIL) per batch
instead of per datagram.

:data:`AVAILABLE` says whether this platform has them (64-bit Linux, CPython, a libc that
exports both); :class:`MmsgSocket` is only made where it is true, and every caller keeps a
plain ``recvfrom_into``/``send`` path for the rest (:class:`gateway.io.transport.UdpPort`).
``AURORA_NO_MMSG=1`` in the environment turns the fast path off (to compare, and to test the
fallback on Linux).

The per-datagram work around the two calls — the list of bytes made from what ``recvmmsg``
wrote, the iovecs pointed at what ``sendmmsg`` writes — is done by the compiled
``_mmsg_speedups`` where the install built it (:data:`COMPILED`), on the same headers, else in
Python here; ``AURORA_NO_SPEEDUPS=1`` turns it off.
"""

from __future__ import annotations

import ctypes
import errno
import mmap
import os
import select
import socket
import sys
from typing import Any

MSG_DONTWAIT = 0x40
MSG_TRUNC = 0x20
#: Datagrams read per ``recvmmsg`` at most (and written per ``sendmmsg``).
BATCH = 64
#: The room for one received datagram: the largest UDP payload.  The buffers are anonymous
#: memory mapped lazily: only the pages datagrams were written to are resident.
SLOT = 65536


class _IoVec(ctypes.Structure):
    _fields_ = [("base", ctypes.c_void_p), ("len", ctypes.c_size_t)]


class _MsgHdr(ctypes.Structure):
    _fields_ = [("name", ctypes.c_void_p), ("namelen", ctypes.c_uint32),
                ("iov", ctypes.c_void_p), ("iovlen", ctypes.c_size_t),
                ("control", ctypes.c_void_p), ("controllen", ctypes.c_size_t),
                ("flags", ctypes.c_int)]


class _MMsgHdr(ctypes.Structure):
    _fields_ = [("hdr", _MsgHdr), ("len", ctypes.c_uint)]


_SOCKADDR = 28  # sockaddr_in6, the larger of the two families
#: Where a ``bytes`` object's data starts, from its address (CPython's layout).
_BYTES_DATA = bytes.__basicsize__ - 1


def _load() -> tuple[Any, Any] | None:
    if (sys.platform != "linux" or ctypes.sizeof(ctypes.c_void_p) != 8
            or sys.implementation.name != "cpython" or os.environ.get("AURORA_NO_MMSG")):
        return None
    try:  # the process's own symbols (libc's among them): no find_library (a subprocess)
        libc = ctypes.CDLL(None, use_errno=True)
        recv, send = libc.recvmmsg, libc.sendmmsg
    except (OSError, AttributeError):
        return None
    recv.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_uint, ctypes.c_int,
                     ctypes.c_void_p]
    send.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_uint, ctypes.c_int]
    recv.restype = send.restype = ctypes.c_int
    probe = b"layout probe"  # the data pointer of a bytes object, as sendmmsg is given it
    if ctypes.string_at(id(probe) + _BYTES_DATA, len(probe)) != probe:
        return None
    return recv, send


_FUNCS = _load()
AVAILABLE = _FUNCS is not None

try:  # the per-datagram work compiled (optional: the wheel may be built without it)
    from gateway.io import _mmsg_speedups as _speedups
except ImportError:
    _speedups = None  # type: ignore[assignment]
if _speedups is not None and (not hasattr(_speedups, "recv")
                              or os.environ.get("AURORA_NO_SPEEDUPS")):
    _speedups = None  # type: ignore[assignment]
#: Whether the compiled helpers do the per-datagram work (else the ctypes path below).
COMPILED = _speedups is not None


def _decode_addr(raw: bytes) -> Any:
    """A ``sockaddr`` as Python's socket module gives it: (host, port) or, for IPv6,
    (host, port, flowinfo, scope_id)."""
    family = int.from_bytes(raw[0:2], sys.byteorder)
    port = int.from_bytes(raw[2:4], "big")
    if family == socket.AF_INET:
        return socket.inet_ntop(socket.AF_INET, raw[4:8]), port
    return (socket.inet_ntop(socket.AF_INET6, raw[8:24]), port,
            int.from_bytes(raw[4:8], "big"), int.from_bytes(raw[24:28], sys.byteorder))


def encode_addr(family: int, addr: Any) -> bytes:
    """The ``sockaddr`` bytes of a Python address of ``family`` (the inverse of decoding)."""
    fam = family.to_bytes(2, sys.byteorder)
    port = int(addr[1]).to_bytes(2, "big")
    if family == socket.AF_INET:
        return fam + port + socket.inet_pton(socket.AF_INET, addr[0]) + bytes(8)
    flow = int(addr[2]) if len(addr) > 2 else 0
    scope = int(addr[3]) if len(addr) > 3 else 0
    return (fam + port + flow.to_bytes(4, "big") + socket.inet_pton(socket.AF_INET6, addr[0])
            + scope.to_bytes(4, sys.byteorder))


_UNNAMED = (0, 0)  # send headers with no destination (a connected socket)
_ALL_SENT = (0, 0, 0)


class MmsgSocket:
    """``recvmmsg``/``sendmmsg`` on one non-blocking UDP socket (only where
    :data:`AVAILABLE`).  Errors are returned as counts, never raised, except a read error
    that is not "nothing waiting" or "port unreachable" (raised as OSError)."""

    def __init__(self, sock: socket.socket, batch: int = BATCH) -> None:
        if _FUNCS is None:
            raise OSError("recvmmsg/sendmmsg are not available here")
        self._recv, self._send = _FUNCS
        self.sock = sock
        self.family = sock.family
        self.batch = batch
        self._fd = sock.fileno()
        self._rbuf = mmap.mmap(-1, batch * SLOT)
        rbase = ctypes.addressof(ctypes.c_char.from_buffer(self._rbuf))
        self._names = ctypes.create_string_buffer(batch * _SOCKADDR)
        nbase = ctypes.addressof(self._names)
        self._riov = (_IoVec * batch)()
        self._rhdrs = (_MMsgHdr * batch)()
        for i in range(batch):
            self._riov[i].base = rbase + i * SLOT
            self._riov[i].len = SLOT
            h = self._rhdrs[i].hdr
            h.name = nbase + i * _SOCKADDR
            h.namelen = _SOCKADDR
            h.iov = ctypes.addressof(self._riov[i])
            h.iovlen = 1
        self._rhdrs_addr = ctypes.addressof(self._rhdrs)
        size = ctypes.sizeof(_MMsgHdr)
        # the received lengths, namelens and flags as one strided view each (no ctypes
        # attribute access per datagram)
        u32 = memoryview(self._rhdrs).cast("B").cast("I")
        self._lens = u32[_MMsgHdr.len.offset // 4::size // 4]
        self._namelens = u32[_MsgHdr.namelen.offset // 4::size // 4]
        self._addr_cache: dict[bytes, Any] = {}
        #: recv_senders: the sender of the last call's one run, and what it returned for it
        self._last_sender: tuple[bytes, list[Any]] = (b"", [])
        # sending: one iovec per datagram, pointed at the bytes objects themselves
        self._siov = (_IoVec * batch)()
        self._shdrs = (_MMsgHdr * batch)()
        for i in range(batch):
            self._shdrs[i].hdr.iov = ctypes.addressof(self._siov[i])
            self._shdrs[i].hdr.iovlen = 1
        self._shdrs_addr = ctypes.addressof(self._shdrs)
        self._siov_q = memoryview(self._siov).cast("B").cast("Q")
        self._shdr_q = memoryview(self._shdrs).cast("B").cast("Q")
        self._hdr_words = size // 8
        self._dest_name: bytes | None = None
        self._hdr_name = _UNNAMED  # the destination every send header holds (none: connected)
        self._dest_buf = ctypes.create_string_buffer(_SOCKADDR)
        self._fast_recv = _speedups.recv if _speedups is not None else None
        self._fast_send = _speedups.send if _speedups is not None else None
        self.refused = 0  # ICMP "port unreachable" reported by a call (for an earlier send)
        self.truncated = 0

    def recv(self, with_addresses: bool) -> tuple[list[bytes], list[Any] | None]:
        """Every datagram waiting (up to :attr:`batch`), and their senders when asked."""
        fast = self._fast_recv
        while True:
            if fast is not None:
                got = fast(self._fd, self._rhdrs_addr, self.batch)
                if isinstance(got, list):
                    data: list[bytes] = got
                    n = len(data)
                    break
                err = -got
            else:
                n = self._recv(self._fd, self._rhdrs_addr, self.batch, MSG_DONTWAIT, None)
                if n >= 0:
                    buf = self._rbuf  # an mmap slice is a bytes object: one copy, no view
                    data = [buf[o:o + ln] for o, ln in zip(range(0, n * SLOT, SLOT),
                                                            self._lens[:n].tolist(),
                                                            strict=True)]
                    break
                err = ctypes.get_errno()
            if not self._retry(err):
                return [], None
        if n == 0:
            return [], None
        if not with_addresses:
            return data, None
        names = self._names.raw[:n * _SOCKADDR]
        addrs = []
        prev_raw, prev = b"", None
        for o, ln in zip(range(0, n * _SOCKADDR, _SOCKADDR), self._namelens[:n].tolist(),
                         strict=True):
            raw = names[o:o + ln]
            if raw != prev_raw:  # mostly a run from one sender: one lookup for the run
                prev_raw, prev = raw, self._address(raw)
            addrs.append(prev)
        return data, addrs

    def recv_senders(self) -> tuple[list[bytes], list[Any]]:
        """Every datagram waiting, as :meth:`recv`, and the sender of each run of consecutive
        datagrams from one sender, in order (what a table of peers needs; not to be changed:
        a list may be returned again)."""
        fast = self._fast_recv
        if fast is None:
            data, addrs = self.recv(True)
            senders: list[Any] = []
            prev = None
            for addr in addrs or ():
                if addr is not prev:  # (one object per run: see recv)
                    senders.append(addr)
                    prev = addr
            return data, senders
        while True:
            got = fast(self._fd, self._rhdrs_addr, self.batch, True)
            if isinstance(got, tuple):
                data, raws = got  # (a raw address per run of one sender's datagrams)
                return data, self.senders_of(raws)
            if not self._retry(-got):
                return [], []

    def senders_of(self, raws: list[bytes]) -> list[Any]:
        """The sender of each run of consecutive datagrams from one sender, as
        :meth:`recv_senders` gives them, from each datagram's raw address; mostly one
        sender, the one of the last call (then the same list again)."""
        runs = raws
        if len(raws) > 1:
            runs = []
            for raw in raws:
                if not runs or runs[-1] != raw:
                    runs.append(raw)
        if len(runs) == 1:
            last = self._last_sender
            if runs[0] != last[0]:
                last = self._last_sender = (runs[0], [self._address(runs[0])])
            return last[1]
        return [self._address(raw) for raw in runs]

    def _retry(self, err: int) -> bool:
        """After a failed ``recvmmsg``: whether to call again ("port unreachable" reported
        for an earlier send: counted), or that nothing is waiting (False); raises the rest."""
        if err in (errno.EAGAIN, errno.EINTR):
            return False
        if err == errno.ECONNREFUSED:
            self.refused += 1
            return True
        raise OSError(err, os.strerror(err))

    def _address(self, raw: bytes) -> Any:
        cache = self._addr_cache
        addr = cache.get(raw)
        if addr is None:
            if len(cache) >= 256:
                cache.clear()
            addr = cache[raw] = _decode_addr(raw)
        return addr

    def send(self, datagrams: list[bytes], dest: Any = None,
             first: int | None = None) -> tuple[int, int, int]:
        """Write ``datagrams`` in order (to ``dest``, or on the connected socket); returns
        (refused, dropped, failed): "port unreachable" reported (that datagram is lost),
        the rest of a batch the socket had no room for (EAGAIN), refused by another error.

        A connected socket whose peer is not listening gets "port unreachable" back for
        each datagram, and the kernel's ``sendmmsg`` then stops after one datagram per call
        without saying why: a batch would cost a call per datagram (twice mavlink-router's
        CPU while a ground station is down).  After two such calls in a row, with room to
        write, the rest of the batch is counted as refused and not sent — it would have
        been refused too.

        ``first``: the result of a ``sendmmsg`` of the whole batch on the connected socket
        that the caller already made (written, or -errno: a compiled lane's); the rest goes on
        from there."""
        fast = self._fast_send
        if first is not None and (dest is not None or fast is None or type(datagrams) is not list
                                  or self._hdr_name != _UNNAMED):
            raise ValueError("first: only after a connected batch's compiled call")
        if first is None and dest is None and fast is not None and type(datagrams) is list and \
                self._hdr_name == _UNNAMED:
            total = len(datagrams)  # a connected socket's batch (the router's hot path)
            if 0 < total <= self.batch:
                first = fast(self._fd, self._shdrs_addr, total, datagrams, 0)
                if first == total:
                    return _ALL_SENT
        name_addr, name_len = 0, 0
        if dest is not None:
            name = encode_addr(self.family, dest)
            if name != self._dest_name:
                ctypes.memmove(self._dest_buf, name, len(name))
                self._dest_name = name
            name_addr, name_len = ctypes.addressof(self._dest_buf), len(name)
        refused = failed = 0
        total = len(datagrams)
        start = 0
        iov, hdr, words = self._siov_q, self._shdr_q, self._hdr_words
        if (name_addr, name_len) != self._hdr_name:  # the headers' destination, when it changes
            for i in range(self.batch):
                hdr[i * words] = name_addr
                hdr[i * words + 1] = name_len
            self._hdr_name = (name_addr, name_len)
        short = 0  # calls in a row that stopped after one datagram of several
        if fast is not None and type(datagrams) is not list:
            datagrams = list(datagrams)
        while start < total:
            if first is not None:  # made above, for the whole batch
                size, n, first = total, first, None
                err = -n
            elif fast is not None:  # (it copies what is not bytes, and keeps each alive)
                size = min(self.batch, total - start)
                n = fast(self._fd, self._shdrs_addr, size, datagrams, start)
                err = -n
            else:
                # (the list holds every datagram alive while the kernel reads it)
                chunk = [d if type(d) is bytes else bytes(d)
                         for d in datagrams[start:start + self.batch]]
                size = len(chunk)
                i = 0
                for d in chunk:
                    iov[i] = id(d) + _BYTES_DATA
                    iov[i + 1] = len(d)
                    i += 2
                n = self._send(self._fd, self._shdrs_addr, size, MSG_DONTWAIT)
                err = ctypes.get_errno() if n < 0 else 0
            if n >= 0:
                start += n
                if n == 1 < size and not name_addr:
                    short += 1
                    if short >= 2 and start < total:
                        if select.select((), (self._fd,), (), 0)[1]:
                            return refused + total - start, 0, failed  # a refusing peer
                        return refused, total - start, failed  # no room: as EAGAIN
                else:
                    short = 0
                continue
            if err == errno.EINTR:
                continue
            if err in (errno.EAGAIN, errno.ENOBUFS):
                return refused, total - start, failed
            if err == errno.ECONNREFUSED:
                refused += 1
            else:
                failed += 1
                short = 0  # (another error: the short calls were not a refusing peer's)
            start += 1  # that one is lost; the rest goes on
        return refused, 0, failed
