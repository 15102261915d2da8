#!/usr/bin/env python3
"""Two emulated XBee modules (802.15.4 / DigiMesh-like, API mode) joined by an emulated air.

Each module's UART is a TCP server on loopback: a gateway reaches it with the pyserial URL
``socket://127.0.0.1:PORT`` (:attr:`XBeePair.url_a` / :attr:`XBeePair.url_b`), as a real
module behind a serial-to-TCP bridge.  All frames go through :mod:`backends.xbee.frames`.

UART (per module)
    One TCP client at a time; a new one replaces (closes) the old.  Bytes the module has for
    its host while no client is attached are dropped (``dropped_no_client``), as on a UART
    with nothing connected.  A new client gets a fresh :class:`~frames.FrameDecoder`.  The
    module answers in its own API mode (1 or 2).  Frames with a bad checksum, length or
    escape and bytes outside frames are counted (:meth:`XBeeModule.uart_errors`, the
    decoder's counters) and skipped; they are *not* folded into ``ER``, which counts RF
    errors as on the real module.  Frames a host should not send (0x88, 0x90 …) and unknown
    types are counted in ``ignored_frames``.

AT commands (0x08 local; 0x17 remote, same table; frame id 0 = no response)
    ``PL`` power level 0..4 (query, set; another value → status 3 invalid parameter);
    ``DB`` RSSI of the last RF packet this module received, as the −dBm byte (status 1 ERROR
    before the first one); ``ER`` RF receive errors, ``GD`` good packets, ``TR`` transmit
    errors, ``EA`` MAC ACK failures: 16-bit saturating counters, 2 bytes, settable (write 0 to
    reset); ``NP`` largest payload (2 bytes, read only); ``SH``/``SL`` the address halves
    (4 bytes each); ``AP`` the API mode (1 byte; setting another mode → status 3); ``DC`` duty
    cycle (%, the module's airtime in the last second, 1 byte); ``RR``/``MT`` stored only (no
    retries are modelled: every transmission is one try); ``AC``/``WR`` accepted (no effect).
    Anything else → status 2 invalid command; a set of a read-only one → status 3.  A command
    that is not two printable ASCII characters gets no answer (``ignored_frames``).

Transmit (0x10)
    Destination the other module's 64-bit address (unicast) or ``000000000000FFFF``
    (broadcast).  Data over ``NP`` → 0x8B delivery 0x74, nothing sent.  Own address → 0x8B
    0x23 (self-addressed); any other address → 0x8B 0x24 (address not found), counted in TR,
    nothing sent (chosen over a silent loss: a wrong destination is a configuration error a
    test should see at once).  Otherwise the packet goes over the air at the sender's PL *at
    the time of the request*.  Unicast: 0x8B 0x00 if delivered, 0x01 (MAC ACK failure, counted
    in TR and EA) if not; with transmit option 0x01 (disable ACK) always 0x00.  Broadcast:
    0x8B 0x00 whether delivered or not.  The 0x8B comes when the packet reaches (or would have
    reached) the far side.  Delivered as 0x90 (src64 = the sender, src16 0xFFFE, options 0x01
    acked unicast, 0x00 unacked unicast, 0x02 broadcast); the receiver's ``GD`` counts it and
    its DB becomes ``rssi[pl]`` (+ Gaussian noise of ``rssi_noise_db``, rounded).

Remote AT (0x17 → 0x97)
    Two legs over the air: the request at the requester's PL, then (if it arrived and the
    frame id is not 0) the response at the responder's PL after the command was applied (a
    remote ``PL`` set answers at the new level).  The command takes effect on the far module
    when the request arrives, even if the response is lost.  A lost leg gives 0x97 status 4
    (TX failure) when it would have arrived (no 2 s timeout); a destination that is not the
    other module gives it at once, with ``src64`` = the requested address.  Both
    legs update the receiver's DB and GD, and appear in the event log, but not in the per-power
    data counters.

Air
    Each transmission is lost with probability ``loss[pl]`` (one draw of
    ``random.Random(seed)`` per transmission, always made), or when a blackout is on at the
    time it is sent or due; loss draws also count in the receiver's ``ER`` (heard, corrupted),
    blackout drops do not (nothing heard).  A module sends one transmission at a time, each
    taking the airtime of its data + 29 bytes of PHY/MAC overhead at ``bitrate`` (250 kbit/s),
    and arrives ``latency_s`` after its end: in order per direction, and a module's throughput
    is bounded as on a real radio.
    :meth:`XBeePair.blackout` (for some seconds) / :meth:`XBeePair.set_blackout` drop
    everything both ways; :meth:`XBeePair.set_loss` / :meth:`XBeePair.set_rssi` change the
    model at run time.  Per module (as sender): ``tx_sent`` / ``tx_delivered`` / ``tx_lost`` /
    ``tx_blackout`` lists indexed by PL, for 0x10 data packets.  :attr:`XBeePair.events` is
    the log of every transmission (:class:`AirEvent`, appended when it is resolved).

One background thread owns every socket (a selector, woken by a socketpair; timed
deliveries from a heap); nothing sleeps.  :meth:`XBeePair.wait` blocks on a condition
notified after every loop turn.

Run: ``python tests/xbee_pair.py --api-a 2 --api-b 2 --loss 0.6,0.3,0.05,0,0
--rssi=-95,-90,-84,-78,-72 [--port-a N --port-b N] [--seed N]`` prints both URLs, then the
counters every second, until Ctrl-C / SIGTERM.
"""

from __future__ import annotations

import argparse
import contextlib
import heapq
import itertools
import math
import random
import selectors
import signal
import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from backends.xbee import frames as xf

ADDRESS_A = 0x0013A20041A0000A
ADDRESS_B = 0x0013A20041B0000B
DEFAULT_LOSS = (0.0, 0.0, 0.0, 0.0, 0.0)
DEFAULT_RSSI = (-90.0, -85.0, -80.0, -75.0, -70.0)
DEFAULT_NP = 100
DEFAULT_LATENCY_S = 0.002
BITRATE = 250_000
#: PHY (preamble, SFD, length) + MAC (frame control, sequence, PAN, two 64-bit addresses, FCS)
RF_OVERHEAD_BYTES = 29
UART_OUT_CAP = 1 << 20
EVENT_LOG_CAP = 200_000
DELIVERY_SELF_ADDRESSED = 0x23
DELIVERY_ADDRESS_NOT_FOUND = 0x24
DELIVERY_PAYLOAD_TOO_LARGE = 0x74
DELIVERY_MAC_ACK_FAILURE = 0x01
_COUNTERS = {"ER": "er", "GD": "gd", "TR": "tr", "EA": "ea"}


class AirEvent(NamedTuple):
    """One transmission over the emulated air, logged when resolved.

    ``kind``: ``"data"`` (0x10), ``"remote_at"`` (0x17 request leg) or ``"remote_at_response"``;
    ``reason``: ``"ok"``, ``"loss"`` or ``"blackout"``.
    """

    t_sent: float  # time.monotonic() at transmission
    t_done: float  # when it arrived (or would have)
    src: str  # "a" or "b"
    kind: str
    power: int
    broadcast: bool
    delivered: bool
    reason: str
    payload: bytes


def _check_levels(name: str, values: Sequence[float], lo: float, hi: float) -> tuple[float, ...]:
    vals = tuple(float(v) for v in values)
    if len(vals) != 5 or not all(lo <= v <= hi for v in vals):
        raise ValueError(f"{name} {values!r}: must be 5 values (PL 0..4) in {lo}..{hi}")
    return vals


@dataclass(eq=False)
class XBeeModule:
    """One emulated module: settings, counters and its UART (owned by the pair's thread)."""

    name: str
    address64: int
    api_mode: int = 1
    np: int = DEFAULT_NP
    pl: int = 4
    last_rssi_dbm: int | None = None
    er: int = 0
    gd: int = 0
    tr: int = 0
    ea: int = 0
    rr: int = 0
    mt: int = 0
    loss: tuple[float, ...] = DEFAULT_LOSS
    port: int = 0
    tx_sent: list[int] = field(default_factory=lambda: [0] * 5)
    tx_delivered: list[int] = field(default_factory=lambda: [0] * 5)
    tx_lost: list[int] = field(default_factory=lambda: [0] * 5)
    tx_blackout: list[int] = field(default_factory=lambda: [0] * 5)
    frames_in: int = 0
    frames_out: int = 0
    ignored_frames: int = 0
    dropped_no_client: int = 0
    dropped_uart_full: int = 0
    clients: int = 0
    _sock: socket.socket | None = field(default=None, repr=False)
    _client: socket.socket | None = field(default=None, repr=False)
    _out: bytearray = field(default_factory=bytearray, repr=False)
    _decoder: xf.FrameDecoder | None = field(default=None, repr=False)
    _decoder_totals: dict[str, int] = field(default_factory=dict, repr=False)
    _airtime: deque[tuple[float, float]] = field(default_factory=deque, repr=False)

    @property
    def url(self) -> str:
        """The pyserial URL of this module's UART."""
        return f"socket://127.0.0.1:{self.port}"

    @property
    def connected(self) -> bool:
        """Whether a host is attached to the UART now."""
        return self._client is not None

    def decoder_stats(self) -> dict[str, int]:
        """The UART frame decoder's counters, summed over every client so far."""
        out = dict(self._decoder_totals)
        if self._decoder is not None:
            for k, v in self._decoder.stats.as_dict().items():
                out[k] = out.get(k, 0) + v
        return out

    def uart_errors(self) -> int:
        """Bad frames seen on the UART (checksum, length, escape): counted and skipped."""
        st = self.decoder_stats()
        return st.get("crc_failures", 0) + st.get("bad_length", 0) + st.get("bad_escape", 0)

    def counters(self) -> dict[str, Any]:
        """A snapshot of the module's state and counters (for printing or asserting)."""
        return {
            "address64": f"{self.address64:016X}", "api_mode": self.api_mode, "pl": self.pl,
            "np": self.np, "db": self.last_rssi_dbm, "ER": self.er, "GD": self.gd,
            "TR": self.tr, "EA": self.ea, "tx_sent": list(self.tx_sent),
            "tx_delivered": list(self.tx_delivered), "tx_lost": list(self.tx_lost),
            "tx_blackout": list(self.tx_blackout), "frames_in": self.frames_in,
            "frames_out": self.frames_out, "ignored_frames": self.ignored_frames,
            "uart_errors": self.uart_errors(), "dropped_no_client": self.dropped_no_client,
            "dropped_uart_full": self.dropped_uart_full, "clients": self.clients,
            "connected": self.connected,
        }

    def bump(self, counter: str) -> None:
        """Add one to ER/GD/TR/EA (``"er"`` …), saturating at 0xFFFF."""
        setattr(self, counter, min(getattr(self, counter) + 1, xf.COUNTER_MAX))

    def duty_cycle(self, now: float) -> int:
        """Percent of the last second this module spent transmitting."""
        while self._airtime and self._airtime[0][0] < now - 1.0:
            self._airtime.popleft()
        return min(100, round(100 * sum(a for _, a in self._airtime)))

    def at(self, command: str, parameter: bytes, now: float) -> tuple[int, bytes]:
        """Apply one AT command: (status, value)."""
        setting = bool(parameter)
        if command == "PL":
            if not setting:
                return xf.AT_OK, bytes((self.pl,))
            level = int.from_bytes(parameter, "big")
            if level not in xf.POWER_LEVELS:
                return xf.AT_INVALID_PARAMETER, b""
            self.pl = level
            return xf.AT_OK, b""
        if command in _COUNTERS:
            attr = _COUNTERS[command]
            if not setting:
                return xf.AT_OK, getattr(self, attr).to_bytes(2, "big")
            value = int.from_bytes(parameter, "big")
            if value > xf.COUNTER_MAX:
                return xf.AT_INVALID_PARAMETER, b""
            setattr(self, attr, value)
            return xf.AT_OK, b""
        if command in ("RR", "MT"):
            attr = command.lower()
            if not setting:
                return xf.AT_OK, bytes((getattr(self, attr),))
            value = int.from_bytes(parameter, "big")
            if value > 0xFF:
                return xf.AT_INVALID_PARAMETER, b""
            setattr(self, attr, value)
            return xf.AT_OK, b""
        if command in ("AC", "WR"):
            return xf.AT_OK, b""
        if command == "AP":
            if setting and int.from_bytes(parameter, "big") != self.api_mode:
                return xf.AT_INVALID_PARAMETER, b""
            return xf.AT_OK, (b"" if setting else bytes((self.api_mode,)))
        read_only: dict[str, Callable[[], bytes]] = {
            "NP": lambda: self.np.to_bytes(2, "big"),
            "SH": lambda: (self.address64 >> 32).to_bytes(4, "big"),
            "SL": lambda: (self.address64 & 0xFFFFFFFF).to_bytes(4, "big"),
            "DC": lambda: bytes((self.duty_cycle(now),)),
        }
        if command == "DB":
            if setting:
                return xf.AT_INVALID_PARAMETER, b""
            if self.last_rssi_dbm is None:
                return xf.AT_ERROR, b""
            return xf.AT_OK, bytes((min(0xFF, max(0, -self.last_rssi_dbm)),))
        if command in read_only:
            if setting:
                return xf.AT_INVALID_PARAMETER, b""
            return xf.AT_OK, read_only[command]()
        return xf.AT_INVALID_COMMAND, b""


class XBeePair:
    """Modules A and B joined by an emulated air; see the module docstring.

    ``loss``/``rssi``: per power level 0..4, the probability a transmission is lost and the
    RSSI (dBm) it arrives with.  ``seed`` seeds the loss RNG (and, derived, the RSSI noise).
    Sockets are bound at construction (:attr:`url_a`, :attr:`url_b`); :meth:`start` (or
    ``with``) runs the thread; :meth:`close` is safe twice.
    """

    def __init__(self, api_a: int = 1, api_b: int = 1, *,
                 loss: Sequence[float] = DEFAULT_LOSS, rssi: Sequence[float] = DEFAULT_RSSI,
                 seed: int | None = None, np: int = DEFAULT_NP,
                 latency_s: float = DEFAULT_LATENCY_S, bitrate: int = BITRATE,
                 rssi_noise_db: float = 0.0, address_a: int = ADDRESS_A,
                 address_b: int = ADDRESS_B, port_a: int = 0, port_b: int = 0,
                 host: str = "127.0.0.1", log_events: bool = True) -> None:
        for mode in (api_a, api_b):
            if mode not in xf.API_MODES:
                raise ValueError(f"api mode {mode!r}: must be 1 or 2")
        if address_a == address_b:
            raise ValueError("the two modules need distinct addresses")
        if not 1 <= np <= 0xFFFF:
            raise ValueError(f"np {np}: must be 1..65535")
        if latency_s < 0 or bitrate <= 0 or rssi_noise_db < 0:
            raise ValueError("latency_s and rssi_noise_db must be >= 0, bitrate > 0")
        loss_t = _check_levels("loss", loss, 0.0, 1.0)
        self._rssi = _check_levels("rssi", rssi, -255.0, 0.0)
        self.latency_s = latency_s
        self.bitrate = bitrate
        self.rssi_noise_db = rssi_noise_db
        self._rng = random.Random(seed)
        self._noise_rng = random.Random(None if seed is None else f"rssi-noise-{seed}")
        self.module_a = XBeeModule("a", address_a, api_a, np=np, loss=loss_t)
        self.module_b = XBeeModule("b", address_b, api_b, np=np, loss=loss_t)
        self.events: deque[AirEvent] = deque(maxlen=EVENT_LOG_CAP if log_events else 0)
        self._blackout_until = 0.0  # monotonic; math.inf while set_blackout(True)
        self._cond = threading.Condition()
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._tie = itertools.count()
        self._busy_until: dict[str, float] = {"a": 0.0, "b": 0.0}
        self._stop = False
        #: exceptions the loop caught (a bug in the emulator; tests should see 0)
        self.internal_errors = 0
        self.last_internal_error = ""
        self._thread: threading.Thread | None = None
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, ("wake", None))
        for mod, port in ((self.module_a, port_a), (self.module_b, port_b)):
            srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            srv.bind((host, port))
            srv.listen(4)
            srv.setblocking(False)
            mod._sock = srv
            mod.port = srv.getsockname()[1]
            self._sel.register(srv, selectors.EVENT_READ, ("listen", mod))

    # -- public API ---------------------------------------------------------------------------

    @property
    def url_a(self) -> str:
        """pyserial URL of module A's UART."""
        return self.module_a.url

    @property
    def url_b(self) -> str:
        """pyserial URL of module B's UART."""
        return self.module_b.url

    @property
    def modules(self) -> tuple[XBeeModule, XBeeModule]:
        return self.module_a, self.module_b

    def start(self) -> XBeePair:
        """Start the background thread (once)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="xbee-pair", daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop the thread and close every socket; safe twice."""
        self._stop = True
        self._wake()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5)
        for mod in self.modules:
            for s in (mod._client, mod._sock):
                if s is not None:
                    s.close()
            mod._client = mod._sock = None
        for s in (self._wake_r, self._wake_w):
            s.close()
        self._sel.close()

    def __enter__(self) -> XBeePair:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def set_loss(self, loss: Sequence[float], sender: str | None = None) -> None:
        """New loss probabilities per PL, for both directions or only from ``sender``."""
        loss_t = _check_levels("loss", loss, 0.0, 1.0)
        for mod in self.modules:
            if sender is None or mod.name == sender:
                mod.loss = loss_t

    def set_rssi(self, rssi: Sequence[float]) -> None:
        """New arrival RSSI (dBm) per PL."""
        self._rssi = _check_levels("rssi", rssi, -255.0, 0.0)

    @property
    def loss(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(loss from A, loss from B) per PL."""
        return self.module_a.loss, self.module_b.loss

    @property
    def rssi(self) -> tuple[float, ...]:
        return self._rssi

    def blackout(self, seconds: float) -> None:
        """Drop everything both ways from now for ``seconds``."""
        self._blackout_until = time.monotonic() + seconds
        self._wake()

    def set_blackout(self, on: bool) -> None:
        """Start (until turned off) or end a blackout."""
        self._blackout_until = math.inf if on else 0.0
        self._wake()

    @property
    def in_blackout(self) -> bool:
        return time.monotonic() < self._blackout_until

    def wait(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Block until ``predicate()`` holds (checked after every emulator loop turn) or
        ``timeout`` passes; returns its last value."""
        with self._cond:
            return self._cond.wait_for(predicate, timeout)

    def event_list(self) -> list[AirEvent]:
        """A copy of the event log."""
        with self._cond:
            return list(self.events)

    def counters(self) -> dict[str, Any]:
        """Both modules' counters plus the air's state."""
        return {"a": self.module_a.counters(), "b": self.module_b.counters(),
                "blackout": self.in_blackout, "internal_errors": self.internal_errors}

    def summary(self) -> str:
        """One line of the main counters (what ``__main__`` prints every second)."""
        parts = []
        for m in self.modules:
            parts.append(f"{m.name.upper()} pl={m.pl} db={m.last_rssi_dbm} "
                         f"sent={m.tx_sent} delivered={m.tx_delivered} ER={m.er} GD={m.gd} "
                         f"TR={m.tr} EA={m.ea} uart_err={m.uart_errors()} "
                         f"{'connected' if m.connected else 'no client'}")
        return " | ".join(parts) + (" | BLACKOUT" if self.in_blackout else "")

    # -- the loop -----------------------------------------------------------------------------

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # closed, or full: the loop wakes anyway
            self._wake_w.send(b"\0")

    def _run(self) -> None:
        while not self._stop:
            now = time.monotonic()
            wakeups = [self._heap[0][0]] if self._heap else []
            if now < self._blackout_until != math.inf:
                wakeups.append(self._blackout_until)  # so waiters see the blackout end
            timeout = max(0.0, min(wakeups) - now) if wakeups else None
            for key, mask in self._sel.select(timeout):
                what, mod = key.data
                if what == "wake":
                    try:
                        while self._wake_r.recv(4096):
                            pass
                    except BlockingIOError:
                        pass
                elif what == "listen":
                    self._accept(mod)
                else:
                    if mask & selectors.EVENT_READ:
                        self._read(mod)
                    if mask & selectors.EVENT_WRITE and mod._client is key.fileobj:
                        self._flush(mod)
            now = time.monotonic()
            while self._heap and self._heap[0][0] <= now:
                _, _, fn = heapq.heappop(self._heap)
                try:
                    fn()
                except Exception as exc:
                    self._internal_error(None, exc)
            with self._cond:
                self._cond.notify_all()

    def _internal_error(self, mod: XBeeModule | None, exc: Exception) -> None:
        self.internal_errors += 1
        self.last_internal_error = f"{mod.name if mod else 'air'}: {exc!r}"

    def _accept(self, mod: XBeeModule) -> None:
        assert mod._sock is not None
        try:
            conn, _ = mod._sock.accept()
        except (BlockingIOError, InterruptedError):
            return
        self._drop_client(mod)
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        mod._client = conn
        mod._decoder = xf.FrameDecoder(mod.api_mode)
        mod.clients += 1
        self._sel.register(conn, selectors.EVENT_READ, ("client", mod))

    def _drop_client(self, mod: XBeeModule) -> None:
        if mod._client is not None:
            self._sel.unregister(mod._client)
            mod._client.close()
            mod._client = None
        if mod._decoder is not None:
            for k, v in mod._decoder.stats.as_dict().items():
                mod._decoder_totals[k] = mod._decoder_totals.get(k, 0) + v
            mod._decoder = None
        mod._out.clear()

    def _read(self, mod: XBeeModule) -> None:
        client = mod._client
        if client is None:
            return
        try:
            data = client.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._drop_client(mod)
            return
        assert mod._decoder is not None
        now = time.monotonic()
        for frame in mod._decoder.feed(data):
            mod.frames_in += 1
            try:
                self._handle(mod, frame, now)
            except Exception as exc:  # a bug here must not stop the emulator: count it
                self._internal_error(mod, exc)

    def _flush(self, mod: XBeeModule) -> None:
        client = mod._client
        if client is None:
            return
        try:
            n = client.send(mod._out) if mod._out else 0
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError:
            self._drop_client(mod)
            return
        del mod._out[:n]
        self._sel.modify(client, selectors.EVENT_READ | (selectors.EVENT_WRITE if mod._out else 0),
                         ("client", mod))

    def _to_host(self, mod: XBeeModule, frame: xf.Frame) -> None:
        """Send a frame to the module's host (dropped when none is attached)."""
        if mod._client is None:
            mod.dropped_no_client += 1
            return
        data = xf.encode(frame, mod.api_mode)
        if len(mod._out) + len(data) > UART_OUT_CAP:
            mod.dropped_uart_full += 1
            return
        mod.frames_out += 1
        mod._out += data
        self._flush(mod)

    def _other(self, mod: XBeeModule) -> XBeeModule:
        return self.module_b if mod is self.module_a else self.module_a

    # -- frames from a host -------------------------------------------------------------------

    def _handle(self, mod: XBeeModule, frame: xf.Frame, now: float) -> None:
        if isinstance(frame, xf.AtCommand | xf.RemoteAtCommand) and not (
                frame.command.isascii() and frame.command.isprintable()):
            mod.ignored_frames += 1  # not an AT command a module could even echo back
        elif isinstance(frame, xf.AtCommand):
            status, value = mod.at(frame.command, frame.parameter, now)
            if frame.frame_id != xf.NO_RESPONSE:
                self._to_host(mod, xf.AtResponse(frame.frame_id, frame.command, status, value))
        elif isinstance(frame, xf.TransmitRequest):
            self._transmit_request(mod, frame, now)
        elif isinstance(frame, xf.RemoteAtCommand):
            self._remote_at(mod, frame, now)
        else:
            mod.ignored_frames += 1

    def _tx_status(self, mod: XBeeModule, frame_id: int, delivery: int) -> None:
        if frame_id != xf.NO_RESPONSE:
            self._to_host(mod, xf.TransmitStatus(frame_id, xf.UNKNOWN_16, 0, delivery, 0))

    def _transmit_request(self, src: XBeeModule, req: xf.TransmitRequest, now: float) -> None:
        dst = self._other(src)
        if len(req.data) > src.np:
            self._tx_status(src, req.frame_id, DELIVERY_PAYLOAD_TOO_LARGE)
            return
        broadcast = req.dest64 == xf.BROADCAST_64
        if not broadcast and req.dest64 != dst.address64:
            src.bump("tr")
            bad = (DELIVERY_SELF_ADDRESSED if req.dest64 == src.address64
                   else DELIVERY_ADDRESS_NOT_FOUND)
            self._tx_status(src, req.frame_id, bad)
            return
        acked = not broadcast and not req.options & xf.TX_DISABLE_ACK
        pl = src.pl
        src.tx_sent[pl] += 1

        def done(delivered: bool, reason: str) -> None:
            if delivered:
                src.tx_delivered[pl] += 1
                opts = xf.RX_BROADCAST if broadcast else (xf.RX_ACKED if acked else 0)
                self._to_host(dst, xf.ReceivePacket(src.address64, xf.UNKNOWN_16, opts,
                                                    req.data))
            elif reason == "blackout":
                src.tx_blackout[pl] += 1
            else:
                src.tx_lost[pl] += 1
            if acked and not delivered:
                src.bump("tr")
                src.bump("ea")
                self._tx_status(src, req.frame_id, DELIVERY_MAC_ACK_FAILURE)
            else:
                self._tx_status(src, req.frame_id, xf.DELIVERY_SUCCESS)

        self._air(src, dst, "data", pl, broadcast, req.data, now, done)

    def _remote_at(self, src: XBeeModule, req: xf.RemoteAtCommand, now: float) -> None:
        dst = self._other(src)

        def fail() -> None:
            if req.frame_id != xf.NO_RESPONSE:
                self._to_host(src, xf.RemoteAtResponse(req.frame_id, req.dest64, xf.UNKNOWN_16,
                                                       req.command, xf.AT_TX_FAILURE))

        if req.dest64 != dst.address64:
            fail()
            return
        payload = req.command.encode("latin-1") + req.parameter

        def arrived(delivered: bool, reason: str) -> None:
            if not delivered:
                fail()
                return
            t = time.monotonic()
            status, value = dst.at(req.command, req.parameter, t)
            if req.frame_id == xf.NO_RESPONSE:
                return

            def answered(ok: bool, why: str) -> None:
                if ok:
                    self._to_host(src, xf.RemoteAtResponse(req.frame_id, dst.address64,
                                                           xf.UNKNOWN_16, req.command, status,
                                                           value))
                else:
                    fail()

            self._air(dst, src, "remote_at_response", dst.pl, False,
                      payload[:2] + bytes((status,)) + value, t, answered)

        self._air(src, dst, "remote_at", src.pl, False, payload, now, arrived)

    # -- the air ------------------------------------------------------------------------------

    def _air(self, src: XBeeModule, dst: XBeeModule, kind: str, pl: int, broadcast: bool,
             payload: bytes, now: float, done: Callable[[bool, str], None]) -> None:
        """One transmission from ``src`` at ``pl``; ``done(delivered, reason)`` when due."""
        lost = self._rng.random() < src.loss[pl]
        blackout_at_send = now < self._blackout_until
        airtime = (len(payload) + RF_OVERHEAD_BYTES) * 8 / self.bitrate
        start = max(now, self._busy_until[src.name])  # one transmission at a time
        self._busy_until[src.name] = start + airtime
        src._airtime.append((start, airtime))
        due = start + airtime + self.latency_s

        def resolve() -> None:
            t = time.monotonic()
            if blackout_at_send or t < self._blackout_until:
                delivered, reason = False, "blackout"
            elif lost:
                delivered, reason = False, "loss"
                dst.bump("er")
            else:
                delivered, reason = True, "ok"
                dst.bump("gd")
                rssi = self._rssi[pl]
                if self.rssi_noise_db:
                    rssi += self._noise_rng.gauss(0.0, self.rssi_noise_db)
                dst.last_rssi_dbm = round(rssi)
            with self._cond:
                self.events.append(AirEvent(now, t, src.name, kind, pl, broadcast, delivered,
                                            reason, bytes(payload)))
            done(delivered, reason)

        heapq.heappush(self._heap, (due, next(self._tie), resolve))


# -- manual use -------------------------------------------------------------------------------

def _floats(text: str) -> list[float]:
    return [float(v) for v in text.split(",")]


def main(argv: Sequence[str] | None = None) -> int:
    """Run a pair until Ctrl-C / SIGTERM, printing the URLs and then counters every second."""
    p = argparse.ArgumentParser(description="Two emulated XBee modules behind TCP ports.")
    p.add_argument("--api-a", type=int, choices=(1, 2), default=1)
    p.add_argument("--api-b", type=int, choices=(1, 2), default=1)
    p.add_argument("--loss", type=_floats, default=list(DEFAULT_LOSS),
                   help="5 loss probabilities, PL 0..4, comma-separated")
    p.add_argument("--rssi", type=_floats, default=list(DEFAULT_RSSI),
                   help="5 RSSI values in dBm, PL 0..4 (write --rssi=-95,…)")
    p.add_argument("--rssi-noise", type=float, default=0.0, help="σ of RSSI noise, dB")
    p.add_argument("--latency", type=float, default=DEFAULT_LATENCY_S, help="seconds")
    p.add_argument("--np", type=int, default=DEFAULT_NP)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--port-a", type=int, default=0)
    p.add_argument("--port-b", type=int, default=0)
    args = p.parse_args(argv)
    try:
        pair = XBeePair(args.api_a, args.api_b, loss=args.loss, rssi=args.rssi, seed=args.seed,
                        np=args.np, latency_s=args.latency, rssi_noise_db=args.rssi_noise,
                        port_a=args.port_a, port_b=args.port_b, log_events=False)
    except (ValueError, OSError) as exc:
        print(f"xbee_pair: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with pair:
        print(f"A {pair.url_a} {pair.module_a.address64:016X} api {args.api_a}", flush=True)
        print(f"B {pair.url_b} {pair.module_b.address64:016X} api {args.api_b}", flush=True)
        try:
            while not stop.wait(1.0):
                print(pair.summary(), flush=True)
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
