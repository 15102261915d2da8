#!/usr/bin/env python3
"""A fake HC-12 433 MHz radio module behind an RFC 2217 server.

Why RFC 2217: the gateway opens ``rfc2217://127.0.0.1:PORT`` with pyserial exactly as it opens
a USB adapter, and every baud-rate change and every RTS/DTR edge it makes reaches the
emulator as a real RFC 2217 command (pyserial's own ``serial.rfc2217.PortManager`` decodes
them), in stream order with the data bytes.  A pty pair could not carry the modem lines or
the baud rate; this way the backend's real code paths run unchanged.

The module, as modelled:

* **SET** is wired to the adapter's RTS (``--set-line dtr`` for DTR): an asserted line pulls
  SET low and the module enters AT-command mode; deasserted, it returns to transparent mode.
  A client that disconnects drops its lines (SET released), as a closed tty does.
* **AT mode** speaks 9600 baud 8N1 only.  Bytes sent at another rate are garbage to it (it
  ignores them); its replies reach a host at another rate as garbage.  A command ends with CR
  or LF or after 20 ms of silence, as on the module.  Commands: ``AT``, ``AT+Bnnnn``,
  ``AT+Cnnn``, ``AT+Pn``, ``AT+FUn`` (FU2 caps the UART rate at 4800, FU4 forces 1200),
  ``AT+RX``, ``AT+RB``/``RC``/``RF``/``RP``, ``AT+V``, ``AT+DEFAULT``, ``AT+SLEEP``; anything
  else starting with AT answers ``ERROR``.
* **Settings persist** in a JSON file (``--settings``) across "power cycles"
  (:meth:`Hc12Model.power_cycle`, or restarting the emulator).
* **Transparent mode** passes bytes to the air: they are timestamped as they arrive from the
  host (``rx_log``: the far side of the host's port), queued in a transmit buffer
  (``--tx-buffer`` bytes, overflow counted as ``air_dropped``) and leave at the air link's
  rate, ``min(UART rate, over-the-air rate of the mode) / 10`` bytes a second (960 B/s at
  the factory FU3/9600).  Bytes at a UART rate other than the module's are garbled.
  ``--air-port`` serves the air side over TCP: a client receives what the module transmits
  (e.g. ``aurora-gateway run --source socket://127.0.0.1:AIRPORT``) and what it sends is
  "heard over the air" and passed to the host.
* **Faults** (``--fault``, or :meth:`Hc12Model.set_fault`): ``silent`` (AT commands are
  ignored: no answer, no effect), ``garbage`` (the command takes effect, the answer is
  noise), ``slow`` (the answer comes ``--fault-delay`` seconds late).

Run: ``python tools/hc12_emulator.py [--port N] [--settings FILE]`` prints the URL to use
(``rfc2217://127.0.0.1:N``) and serves until Ctrl-C.  Tests import it and use
:class:`Hc12Emulator` in-process.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import signal
import socket
import threading
import time
from collections.abc import Callable, Container, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from serial.rfc2217 import PortManager

AT_BAUD = 9600
BAUD_RATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)
POWER_DBM = {1: -1, 2: 2, 3: 5, 4: 8, 5: 11, 6: 14, 7: 17, 8: 20}
FU3_AIR_BPS = {1200: 5000, 2400: 5000, 4800: 15000, 9600: 15000, 19200: 58000, 38400: 58000,
               57600: 236000, 115200: 236000}
COMMAND_GAP_S = 0.02
TICK_S = 0.005
VERSION = "HC-12_V2.4 (aurora-gateway emulator)"


@dataclass
class Settings:
    """What the module keeps in its flash."""

    mode: int = 3
    baud: int = 9600
    channel: int = 1
    power: int = 8

    @classmethod
    def load(cls, path: Path | None) -> Settings:
        if path is None or not path.exists():
            return cls()
        data = json.loads(path.read_text(encoding="utf-8"))
        return cls(**{k: int(v) for k, v in data.items() if k in cls.__dataclass_fields__})

    def save(self, path: Path | None) -> None:
        if path is None:
            return
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(asdict(self)), encoding="utf-8")
        os.replace(tmp, path)  # atomic: a "power cut" never leaves half a file

    @property
    def air_bytes_per_s(self) -> float:
        air = {1: 250000, 2: 250000, 4: 500}.get(self.mode, FU3_AIR_BPS.get(self.baud, 15000))
        return min(self.baud, air) / 10.0


def garble(data: bytes) -> bytes:
    """What bytes sent at the wrong baud rate look like on the other side: not ASCII."""
    return bytes(0x80 | ((b * 37 + 11) & 0x7F) for b in data)


#: The setting commands: AT+<letter><digits> → (the Settings field, its allowed values, the reply).
_SETTERS: tuple[tuple[re.Pattern[str], str, Container[int], str], ...] = (
    (re.compile(r"AT\+B(\d+)"), "baud", BAUD_RATES, "OK+B{}"),
    (re.compile(r"AT\+C(\d{1,3})"), "channel", range(1, 128), "OK+C{:03d}"),
    (re.compile(r"AT\+P(\d)"), "power", POWER_DBM.keys(), "OK+P{}"),
    (re.compile(r"AT\+FU(\d)"), "mode", range(1, 5), "OK+FU{}"),
)


def _baud_in_mode(mode: int, baud: int) -> int:
    """The UART rate after switching to FU``mode``: FU2 allows at most 4800, FU4 only 1200."""
    if mode == 2:
        return min(baud, 4800)
    return 1200 if mode == 4 else baud


def _power_reply(s: Settings) -> str:
    return f"OK+RP:{POWER_DBM[s.power]:+d}dBm"


#: The query commands and their replies.
_QUERIES: dict[str, Callable[[Settings], list[str]]] = {
    "AT+RX": lambda s: [f"OK+FU{s.mode}", f"OK+B{s.baud}", f"OK+C{s.channel:03d}",
                        _power_reply(s)],
    "AT+RB": lambda s: [f"OK+B{s.baud}"],
    "AT+RC": lambda s: [f"OK+C{s.channel:03d}"],
    "AT+RF": lambda s: [f"OK+FU{s.mode}"],
    "AT+RP": lambda s: [_power_reply(s)],
}

class Hc12Model:
    """The module: SET pin, host UART, AT parser, transmit buffer, air side.  Thread-safe; tests
    wait on :meth:`wait_for` (a condition variable), never on sleeps."""

    def __init__(self, settings_path: str | Path | None = None, set_line: str = "rts",
                 tx_buffer: int = 1024, clock: Callable[[], float] = time.monotonic) -> None:
        if set_line not in ("rts", "dtr"):
            raise ValueError("set_line must be rts or dtr")
        self.settings_path = Path(settings_path) if settings_path else None
        self.set_line = set_line
        self.tx_buffer = tx_buffer
        self._clock = clock
        self.cond = threading.Condition(threading.RLock())
        self.settings = Settings.load(self.settings_path)
        self.fault: str | None = None
        self.fault_delay_s = 2.0
        self.host_out: Callable[[bytes], None] | None = None
        self.air_listeners: list[Callable[[bytes], None]] = []
        self._reset_runtime()

    def _reset_runtime(self) -> None:
        self.host_baud = AT_BAUD
        self.rts = False
        self.dtr = False
        self.at_mode = False
        self.sleeping = False
        self.events: list[tuple[float, str, Any]] = []
        self.at_rx = bytearray()  # every byte received while SET was asserted
        self.at_commands: list[str] = []
        self.replies: list[bytes] = []
        self.rx_log: list[tuple[float, bytes]] = []  # transparent bytes as they arrived
        self.air_out = bytearray()
        self.air_log: list[tuple[float, int]] = []
        self.garbled_bytes = 0
        self.air_dropped = 0
        self.heard_dropped = 0
        self._at_buf = bytearray()
        self._at_last = 0.0
        self._due: list[tuple[float, bytes]] = []
        self._txq = bytearray()
        self._air_credit = 0.0
        self._air_stamp: float | None = None

    # -- inspection ------------------------------------------------------------------------------

    def _event(self, kind: str, value: Any) -> None:
        self.events.append((self._clock(), kind, value))
        self.cond.notify_all()

    def wait_for(self, predicate: Callable[[], bool], timeout: float) -> bool:
        """Wait until ``predicate()`` (evaluated under the model's lock) holds."""
        with self.cond:
            return self.cond.wait_for(predicate, timeout)

    def event_values(self, kind: str) -> list[Any]:
        with self.cond:
            return [v for _, k, v in self.events if k == kind]

    def set_fault(self, kind: str | None, delay_s: float = 2.0) -> None:
        if kind not in (None, "silent", "garbage", "slow"):
            raise ValueError(f"unknown fault {kind!r}")
        with self.cond:
            self.fault = kind
            self.fault_delay_s = delay_s

    def power_cycle(self) -> None:
        """Power off and on: settings reload from the file, everything else starts afresh."""
        with self.cond:
            self.settings = Settings.load(self.settings_path)
            self._reset_runtime()
            self._event("power_cycle", asdict(self.settings))

    # -- the host side (called by the RFC 2217 connection) -----------------------------------------

    @property
    def set_asserted(self) -> bool:
        return self.rts if self.set_line == "rts" else self.dtr

    def set_host_baud(self, baud: int) -> None:
        with self.cond:
            if baud != self.host_baud:
                self.host_baud = baud
            self._event("baud", baud)

    def set_modem(self, *, rts: bool | None = None, dtr: bool | None = None) -> None:
        with self.cond:
            before = self.set_asserted
            if rts is not None:
                self.rts = rts
            if dtr is not None:
                self.dtr = dtr
            after = self.set_asserted
            if after != before:
                self._set_changed(after)

    def _set_changed(self, asserted: bool) -> None:
        self._event("set", asserted)
        if asserted:
            self.at_mode = True
            self.sleeping = False
            self._at_buf.clear()
        else:
            if self._at_buf:
                self._run_command(bytes(self._at_buf))
                self._at_buf.clear()
            self.at_mode = False
            if self._pending_sleep():
                self.sleeping = True

    def _pending_sleep(self) -> bool:
        return bool(self.at_commands) and self.at_commands[-1].upper() == "AT+SLEEP"

    def host_disconnected(self) -> None:
        with self.cond:
            self.set_modem(rts=False, dtr=False)
            self._event("disconnect", None)

    def uart_rx(self, data: bytes) -> None:
        """Bytes from the host's TX line."""
        with self.cond:
            now = self._clock()
            if self.at_mode:
                self.at_rx += data
                if self.host_baud != AT_BAUD:
                    data = garble(data)
                    self.garbled_bytes += len(data)
                for b in data:
                    if b in (0x0D, 0x0A):
                        if self._at_buf:
                            self._run_command(bytes(self._at_buf))
                            self._at_buf.clear()
                    else:
                        self._at_buf.append(b)
                self._at_last = now
                self.cond.notify_all()
                return
            if self.sleeping:
                return
            self.rx_log.append((now, bytes(data)))
            if self.host_baud != self.settings.baud:
                data = garble(data)
                self.garbled_bytes += len(data)
            room = self.tx_buffer - len(self._txq)
            if len(data) > room:
                self.air_dropped += len(data) - max(room, 0)
                data = data[:max(room, 0)]
            self._txq += data
            self.cond.notify_all()

    def _to_host(self, data: bytes, rate: int) -> None:
        if self.host_baud != rate:
            data = garble(data)
        out = self.host_out
        if out is not None:
            out(data)

    # -- the air side ------------------------------------------------------------------------------

    def air_inject(self, data: bytes) -> None:
        """Bytes the module hears over the air: passed to the host in transparent mode."""
        with self.cond:
            if self.at_mode or self.sleeping:
                self.heard_dropped += len(data)
                return
            self._to_host(data, self.settings.baud)

    # -- AT commands -------------------------------------------------------------------------------

    def _run_command(self, raw: bytes) -> None:
        try:
            text = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            return  # noise (wrong baud rate): the module ignores it
        if not text.upper().startswith("AT"):
            return
        self.at_commands.append(text)
        self._event("at", text)
        if self.fault == "silent":
            return
        lines = self._execute(text.upper())
        reply = b"".join(line.encode() + b"\r\n" for line in lines)
        if self.fault == "garbage":
            reply = garble(reply) + b"\xfe\x00\xff"
        self.replies.append(reply)
        delay = self.fault_delay_s if self.fault == "slow" else 0.0
        self._due.append((self._clock() + delay, reply))
        self.cond.notify_all()

    def _execute(self, cmd: str) -> list[str]:
        s = self.settings
        for pattern, field, allowed, reply in _SETTERS:
            if m := pattern.fullmatch(cmd):
                value = int(m[1])
                if value not in allowed:
                    return ["ERROR"]
                setattr(s, field, value)
                if field == "mode":
                    s.baud = _baud_in_mode(value, s.baud)
                self._save()
                return [reply.format(value)]
        if query := _QUERIES.get(cmd):
            return query(s)
        if cmd == "AT":
            return ["OK"]
        if cmd == "AT+V":
            return [VERSION]
        if cmd == "AT+DEFAULT":
            self.settings = Settings()
            self._save()
            return ["OK+DEFAULT"]
        if cmd == "AT+SLEEP":
            return ["OK+SLEEP"]
        return ["ERROR"]

    def _save(self) -> None:
        self.settings.save(self.settings_path)
        self._event("settings", asdict(self.settings))

    # -- time passes -------------------------------------------------------------------------------

    def tick(self) -> None:
        """Housekeeping (every few ms): end commands on silence, send due replies, transmit."""
        with self.cond:
            now = self._clock()
            if self.at_mode and self._at_buf and now - self._at_last >= COMMAND_GAP_S:
                self._run_command(bytes(self._at_buf))
                self._at_buf.clear()
            if self._due:
                ready = [r for t, r in self._due if t <= now]
                self._due = [(t, r) for t, r in self._due if t > now]
                for reply in ready:
                    if self.at_mode:  # a reply after SET was released is never sent
                        self._to_host(reply, AT_BAUD)
                        self._event("reply", reply)
            stamp, self._air_stamp = self._air_stamp, now
            if not self._txq:
                self._air_credit = 0.0
                return
            if stamp is not None:
                self._air_credit += (now - stamp) * self.settings.air_bytes_per_s
            n = min(int(self._air_credit), len(self._txq))
            if n <= 0:
                return
            self._air_credit -= n
            out = bytes(self._txq[:n])
            del self._txq[:n]
            self.air_out += out
            self.air_log.append((now, n))
            listeners = list(self.air_listeners)
            self.cond.notify_all()
        for listener in listeners:
            listener(out)


class _UartLines:
    """The serial-port face PortManager drives: baud rate and modem lines go to the model."""

    bytesize = 8
    parity = "N"
    stopbits = 1
    xonxoff = False
    rtscts = False
    break_condition = False
    cts = True
    dsr = True
    ri = False
    cd = False

    def __init__(self, model: Hc12Model) -> None:
        self._model = model

    @property
    def baudrate(self) -> int:
        return self._model.host_baud

    @baudrate.setter
    def baudrate(self, value: int) -> None:
        self._model.set_host_baud(int(value))

    @property
    def rts(self) -> bool:
        return self._model.rts

    @rts.setter
    def rts(self, value: bool) -> None:
        self._model.set_modem(rts=bool(value))

    @property
    def dtr(self) -> bool:
        return self._model.dtr

    @dtr.setter
    def dtr(self, value: bool) -> None:
        self._model.set_modem(dtr=bool(value))

    def reset_input_buffer(self) -> None:
        pass

    def reset_output_buffer(self) -> None:
        pass


class _Connection:
    """A thread-safe writer PortManager can use."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.lock = threading.Lock()

    def write(self, data: bytes) -> None:
        with self.lock, contextlib.suppress(OSError):
            self.sock.sendall(data)


class Hc12Emulator:
    """The model behind an RFC 2217 server on ``host:port`` (0 = a free port), one client at a
    time like a real serial port, plus an optional TCP air side."""

    def __init__(self, settings_path: str | Path | None = None, *, host: str = "127.0.0.1",
                 port: int = 0, set_line: str = "rts", air_port: int | None = None,
                 tx_buffer: int = 1024) -> None:
        self.model = Hc12Model(settings_path, set_line, tx_buffer)
        self.host = host
        self._listener = socket.create_server((host, port))
        self.port = self._listener.getsockname()[1]
        self._air_listener = (socket.create_server((host, air_port))
                              if air_port is not None else None)
        self.air_port = self._air_listener.getsockname()[1] if self._air_listener else None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._client: socket.socket | None = None
        self.connections = 0

    @property
    def url(self) -> str:
        return f"rfc2217://{self.host}:{self.port}"

    def start(self) -> Hc12Emulator:
        for target, name in ((self._accept_loop, "accept"), (self._tick_loop, "tick")):
            t = threading.Thread(target=target, name=f"hc12-emu-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        if self._air_listener is not None:
            t = threading.Thread(target=self._air_loop, name="hc12-emu-air", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def stop(self) -> None:
        self._stop.set()
        for s in (self._listener, self._air_listener, self._client):
            if s is not None:
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
                with contextlib.suppress(OSError):
                    s.close()
        for t in self._threads:
            t.join(2.0)

    def unplug(self) -> None:
        """Pull the cable: drop the host's connection as a vanishing USB adapter would."""
        client = self._client
        if client is not None:
            with contextlib.suppress(OSError):
                client.shutdown(socket.SHUT_RDWR)

    def __enter__(self) -> Hc12Emulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _tick_loop(self) -> None:
        while not self._stop.wait(TICK_S):
            self.model.tick()

    def _accept_loop(self) -> None:
        for sock in self._accepted(self._listener):
            if self._client is not None:  # busy, like an open tty
                sock.close()
                continue
            self._client = sock
            t = threading.Thread(target=self._serve, args=(sock,), name="hc12-emu-client",
                                 daemon=True)
            t.start()

    def _accepted(self, listener: socket.socket) -> Iterator[socket.socket]:
        """The connections ``listener`` accepts until the emulator stops or it is closed."""
        listener.settimeout(0.2)
        while not self._stop.is_set():
            try:
                sock, _ = listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            yield sock

    def _received(self, sock: socket.socket) -> Iterator[bytes]:
        """What ``sock`` receives until the peer closes, the socket fails or the emulator stops."""
        while not self._stop.is_set():
            try:
                data = sock.recv(4096)
            except OSError:
                return
            if not data:
                return
            yield data

    def _serve(self, sock: socket.socket) -> None:
        model = self.model
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn = _Connection(sock)
        with model.cond:
            self.connections += 1
            model._event("connect", self.connections)
        manager = PortManager(_UartLines(model), conn)
        model.host_out = lambda data: conn.write(b"".join(manager.escape(data)))
        try:
            for data in self._received(sock):
                # Byte by byte, so a baud or SET change between data bytes applies exactly there.
                for byte in manager.filter(data):
                    model.uart_rx(byte)
        finally:
            model.host_out = None
            model.host_disconnected()
            self._client = None
            with contextlib.suppress(OSError):
                sock.close()

    def _air_loop(self) -> None:
        assert self._air_listener is not None
        for sock in self._accepted(self._air_listener):
            threading.Thread(target=self._serve_air, args=(sock,), daemon=True).start()

    def _serve_air(self, sock: socket.socket) -> None:
        conn = _Connection(sock)
        self.model.air_listeners.append(conn.write)
        try:
            for data in self._received(sock):
                self.model.air_inject(data)
        finally:
            with contextlib.suppress(ValueError):
                self.model.air_listeners.remove(conn.write)
            sock.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="A fake HC-12 radio module behind an RFC 2217 "
                                "server (see the module docstring).")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=0, help="RFC 2217 port (0 = any free port)")
    p.add_argument("--settings", metavar="FILE",
                   help="where the module keeps its settings across restarts")
    p.add_argument("--set-line", choices=("rts", "dtr"), default="rts")
    p.add_argument("--air-port", type=int, metavar="N",
                   help="serve the air side on this TCP port (0 = any free port)")
    p.add_argument("--tx-buffer", type=int, default=1024, metavar="BYTES")
    p.add_argument("--fault", choices=("silent", "garbage", "slow"))
    p.add_argument("--fault-delay", type=float, default=2.0, metavar="S")
    args = p.parse_args(argv)
    emu = Hc12Emulator(args.settings, host=args.host, port=args.port, set_line=args.set_line,
                       air_port=args.air_port, tx_buffer=args.tx_buffer)
    if args.fault:
        emu.model.set_fault(args.fault, args.fault_delay)
    stopped: list[int] = []  # a handler takes no lock: it may interrupt the one it needs
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: stopped.append(signum))
    emu.start()
    print(emu.url, flush=True)
    if emu.air_port is not None:
        print(f"air: socket://{args.host}:{emu.air_port}", flush=True)
    s = emu.model.settings
    print(f"HC-12 emulator: FU{s.mode} {s.baud} baud channel {s.channel} power {s.power}; "
          f"SET on {args.set_line}", flush=True)
    while not stopped:
        time.sleep(0.1)
    emu.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
