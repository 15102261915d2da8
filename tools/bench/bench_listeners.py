"""Benchmark: the gateway's listeners under hostile and heavy clients, from the outside.

Starts a real gateway (``python -m gateway run --source sim …``, of this tree or of
``--tree DIR``: the same command in another checkout, e.g. the code before a change) and
drives it over loopback only, bounded in count and time.  Scenarios (``--scenario``, default
all):

``slowloris``
    ``--slow`` (1000) connections to ``--http``, each sending one byte of a request head per
    second.  Every 0.5 s: the gateway's threads (``/proc/PID/task``) and RSS; every 0.2 s a
    normal client fetches ``/`` (latency, failures).  Reports how many slow connections were
    answered 503 at once, how many were cut and how long after they connected (they stall
    from the first byte: the head never completes in time), how many are still open at the
    end.
``sse``
    16 ``/events`` viewers read their first event, then stop reading (default socket buffers).
    Reports when each is cut (its TCP state leaves ESTABLISHED: a reset or a FIN), then
    whether a new viewer gets the stream, and how fast.
``connects``
    500 connects to ``--http`` at once, each sending ``GET /status.json``.  Reports how many
    got 200, 503, nothing (reset, timeout), and the longest wait for the first byte.
``idle``
    The gateway under ``RLIMIT_NOFILE`` 256 with ``--uavtalk tcpin:``, ``--fprime tcpin:``,
    ``--http`` and ``--record-dir``; 300 idle connections to the UAVTalk port.  Reports how
    many were refused (closed at once) and whether the status page answers, the recording
    grows and an F´ client gets telemetry, before and after.

Prints figures; asserts nothing.  The bench raises its own descriptor limit (soft up to
hard) for its 1000 sockets.

Run: ``.venv/bin/python tools/bench/bench_listeners.py [--tree /work/wt-before]
[--scenario slowloris|sse|connects|idle] [--slow N] [--seconds S]``
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import http.client
import multiprocessing
import os
import resource
import selectors
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
TCP_ESTABLISHED = 1


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def gateway(tree: Path, args: list[str], nofile: int | None = None) -> Iterator[
        subprocess.Popen[bytes]]:
    """A gateway of ``tree`` running ``args`` (stderr to a temporary file), stopped after."""
    bindir = tree / ".venv" / "bin"
    # python -m gateway where the tree has it; the console command (the same code) before
    command = ([str(bindir / "python"), "-m", "gateway"]
               if (tree / "gateway" / "__main__.py").exists() else [str(bindir / "aurora-gateway")])

    def limit() -> None:
        if nofile is not None:
            resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, nofile))

    log = tempfile.NamedTemporaryFile(prefix="bench-gw-", suffix=".log",  # noqa: SIM115
                                      delete=False)  # (read back after the run)
    proc = subprocess.Popen([*command, "run", "--source", "sim", *args],
                            cwd=tree, stdout=subprocess.DEVNULL, stderr=log,
                            preexec_fn=limit)
    try:
        yield proc
    finally:
        proc.send_signal(2)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()
        tail = Path(log.name).read_text(errors="replace").splitlines()
        for line in tail:
            if line.startswith(("stopped after", "dropped:", "clients:")):
                print(f"    gateway: {line}")
        os.unlink(log.name)


def wait_http(port: int, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError, http.client.HTTPException):
            if get(port, "/status.json")[0] == 200:
                return
        time.sleep(0.1)
    raise SystemExit(f"the gateway's page on port {port} never answered")


def get(port: int, path: str, timeout: float = 5.0) -> tuple[int, float]:
    """(status, seconds) of one GET on a fresh connection."""
    t0 = time.monotonic()
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        conn.request("GET", path)
        r = conn.getresponse()
        r.read()
        return r.status, time.monotonic() - t0
    finally:
        conn.close()


def threads(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/task"))


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def tcp_state(sock: socket.socket) -> int:
    try:
        return sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 8)[0]
    except OSError:
        return 0


def raise_nofile() -> int:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < hard:
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


def pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    values = sorted(values)
    return values[min(len(values) - 1, int(q * len(values)))]


def normal_client(port: int, stop: Any, ready: Any, out: Any) -> None:
    """GET / every 0.2 s until ``stop``; (latencies, failures, slow ones) to ``out``."""
    latency: list[float] = []
    failures: list[str] = []
    slow: list[str] = []
    t0 = time.monotonic()
    ready.set()
    while not stop.wait(0.2):
        start = time.monotonic() - t0
        try:
            code, took = get(port, "/", timeout=5)
        except (OSError, http.client.HTTPException) as exc:
            failures.append(type(exc).__name__)
            continue
        if code != 200:
            failures.append(str(code))
        else:
            latency.append(took)
            if took > 0.1:
                slow.append(f"{took * 1000:.0f} ms at {start:.1f} s")
    out.put((latency, failures, slow))


class Sampler:
    """Threads and RSS of ``pid`` every 0.5 s; a normal client's GET / every 0.2 s (in a
    process of its own: the bench's sockets do not slow it down)."""

    def __init__(self, pid: int, port: int) -> None:
        self.pid, self.port = pid, port
        self.threads: list[int] = []
        self.rss: list[int] = []
        self.latency: list[float] = []
        self.failures: list[str] = []
        self.slow: list[str] = []
        self.stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        ctx = multiprocessing.get_context("spawn")
        self._client_stop = ctx.Event()
        self._ready = ctx.Event()
        self._out = ctx.Queue()
        self._client = ctx.Process(target=normal_client,
                                   args=(port, self._client_stop, self._ready, self._out),
                                   daemon=True)

    def __enter__(self) -> Sampler:
        self._client.start()
        self._ready.wait(20)  # the client runs before the load starts
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self._client_stop.set()
        self.latency, self.failures, self.slow = self._out.get(timeout=20)
        self._client.join(10)
        self._thread.join(10)

    def _sample(self) -> None:
        while not self.stop.wait(0.5):
            with contextlib.suppress(OSError):
                self.threads.append(threads(self.pid))
                self.rss.append(rss_kib(self.pid))


def slowloris(tree: Path, n: int, seconds: float) -> None:
    port = free_port()
    with gateway(tree, ["--only", "http", "--http", f"127.0.0.1:{port}"]) as proc:
        wait_http(port)
        time.sleep(1.0)
        base_threads, base_rss = threads(proc.pid), rss_kib(proc.pid)
        head = b"GET / HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"a" * 200
        sel = selectors.DefaultSelector()
        conns: dict[socket.socket, dict[str, Any]] = {}
        with Sampler(proc.pid, port) as sampler:
            for _ in range(n):
                s = socket.socket()
                s.setblocking(False)
                err = s.connect_ex(("127.0.0.1", port))
                if err not in (0, errno.EINPROGRESS):
                    s.close()
                    continue
                conns[s] = {"t0": time.monotonic(), "sent": 0, "end": None, "got": b""}
                sel.register(s, selectors.EVENT_READ)
            opened = time.monotonic()
            next_byte = opened
            while time.monotonic() - opened < seconds:
                now = time.monotonic()
                if now >= next_byte:  # one header byte per second on every open one
                    next_byte += 1.0
                    for s, c in conns.items():
                        if c["end"] is None and c["sent"] < len(head):
                            with contextlib.suppress(OSError):
                                s.send(head[c["sent"]:c["sent"] + 1])
                                c["sent"] += 1
                for key, _ in sel.select(max(0.0, min(0.1, next_byte - now))):
                    s = key.fileobj  # type: ignore[assignment]
                    c = conns[s]
                    try:
                        data = s.recv(4096)
                    except BlockingIOError:
                        continue
                    except OSError:
                        data = b""
                    c["got"] += data
                    if not data:
                        c["end"] = time.monotonic()
                        sel.unregister(s)
            still = sum(1 for c in conns.values() if c["end"] is None)
        for s in conns:
            s.close()
        refused = [c for c in conns.values() if c["got"].startswith(b"HTTP/1.1 503")]
        cut = [c["end"] - c["t0"] for c in conns.values()
               if c["end"] is not None and not c["got"]]
        print(f"  slowloris x{len(conns)} for {seconds:.0f} s "
              f"({'the code in ' + str(tree)}):")
        print(f"    threads: before {base_threads}, max {max(sampler.threads, default=0)}")
        print(f"    RSS: before {base_rss / 1024:.1f} MiB, max growth "
              f"{(max(sampler.rss, default=base_rss) - base_rss) / 1024:.1f} MiB")
        print(f"    answered 503 at once: {len(refused)}; cut (no answer): {len(cut)}, "
              f"after connecting: median {pct(cut, 0.5):.1f} s, max "
              f"{max(cut, default=float('nan')):.1f} s; still open at the end: {still}")
        lat = sampler.latency
        print(f"    normal client GET /: {len(lat)} ok, {len(sampler.failures)} failed "
              f"({', '.join(sorted(set(sampler.failures))) or '-'}); latency median "
              f"{pct(lat, 0.5) * 1000:.1f} ms, p99 {pct(lat, 0.99) * 1000:.1f} ms, max "
              f"{max(lat, default=float('nan')) * 1000:.1f} ms"
              + (f"; over 100 ms: {', '.join(sampler.slow)}" if sampler.slow else ""))


def sse(tree: Path, viewers: int, seconds: float) -> None:
    port = free_port()
    with gateway(tree, ["--only", "http", "--http", f"127.0.0.1:{port}"]):
        wait_http(port)
        socks = []
        for _ in range(viewers):
            s = socket.create_connection(("127.0.0.1", port), timeout=5)
            s.sendall(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
            first = s.recv(65536)
            if not first.startswith(b"HTTP/1.1 200") and not first.startswith(b"HTTP/1.0 200"):
                print(f"    viewer refused: {first[:40]!r}")
            socks.append(s)
        stopped = time.monotonic()  # they read no more from here
        cut_at: dict[int, float] = {}
        while time.monotonic() - stopped < seconds and len(cut_at) < len(socks):
            for i, s in enumerate(socks):
                if i not in cut_at and tcp_state(s) != TCP_ESTABLISHED:
                    cut_at[i] = time.monotonic() - stopped
            time.sleep(0.1)
        t0 = time.monotonic()
        verdict = "no answer"
        try:
            s = socket.create_connection(("127.0.0.1", port), timeout=5)
            s.sendall(b"GET /events HTTP/1.1\r\nHost: x\r\n\r\n")
            got = b""
            while b"data:" not in got and time.monotonic() - t0 < 5:
                chunk = s.recv(65536)
                if not chunk:
                    break
                got += chunk
            verdict = (f"gets the stream in {(time.monotonic() - t0) * 1000:.0f} ms"
                       if b"data:" in got else f"refused: {got[:30]!r}")
            s.close()
        except OSError as exc:
            verdict = f"failed: {exc}"
        for s in socks:
            s.close()
        times = sorted(cut_at.values())
        print(f"  {viewers} event-stream viewers that stop reading ({tree}):")
        print(f"    cut within {seconds:.0f} s: {len(times)}; after they stopped: "
              f"min {min(times, default=float('nan')):.1f} s, max "
              f"{max(times, default=float('nan')):.1f} s")
        print(f"    then a new viewer {verdict}")


def connects(tree: Path, n: int) -> None:
    port = free_port()
    with gateway(tree, ["--only", "http", "--http", f"127.0.0.1:{port}"]):
        wait_http(port)
        sel = selectors.DefaultSelector()
        conns: dict[socket.socket, dict[str, Any]] = {}
        t0 = time.monotonic()
        for _ in range(n):
            s = socket.socket()
            s.setblocking(False)
            s.connect_ex(("127.0.0.1", port))
            conns[s] = {"t0": time.monotonic(), "first": None, "got": b"", "sent": False,
                        "done": False}
            sel.register(s, selectors.EVENT_WRITE)
        request = b"GET /status.json HTTP/1.1\r\nHost: x\r\n\r\n"
        while time.monotonic() - t0 < 10 and not all(c["done"] for c in conns.values()):
            for key, mask in sel.select(0.1):
                s = key.fileobj  # type: ignore[assignment]
                c = conns[s]
                if mask & selectors.EVENT_WRITE and not c["sent"]:
                    with contextlib.suppress(OSError):
                        s.send(request)
                    c["sent"] = True
                    sel.modify(s, selectors.EVENT_READ)
                    continue
                try:
                    data = s.recv(65536)
                except BlockingIOError:
                    continue
                except OSError:
                    data = b""
                if data and c["first"] is None:
                    c["first"] = time.monotonic() - c["t0"]
                c["got"] += data
                if not data:
                    c["done"] = True
                    sel.unregister(s)
        for s in conns:
            s.close()
        codes: dict[str, int] = {}
        for c in conns.values():
            head = c["got"][:12]
            k = head[9:12].decode() if head.startswith(b"HTTP/1.") else (
                "reset/closed" if c["done"] else "waiting")
            codes[k] = codes.get(k, 0) + 1
        waits = [c["first"] for c in conns.values() if c["first"] is not None]
        print(f"  {n} simultaneous connects ({tree}): "
              + ", ".join(f"{k}: {v}" for k, v in sorted(codes.items())))
        print(f"    first byte: median {pct(waits, 0.5) * 1000:.0f} ms, max "
              f"{max(waits, default=float('nan')) * 1000:.0f} ms; "
              f"waited > 1 s: {sum(1 for w in waits if w > 1) + codes.get('waiting', 0)}")


def idle(tree: Path, n: int) -> None:
    hport, uport, fport = free_port(), free_port(), free_port()
    with tempfile.TemporaryDirectory() as rec_dir, gateway(tree, [
            "--only", "http", "--only", "uavtalk", "--only", "fprime",
            "--http", f"127.0.0.1:{hport}", "--uavtalk", f"tcpin:127.0.0.1:{uport}",
            "--fprime", f"tcpin:127.0.0.1:{fport}", "--record-dir", rec_dir,
            "--sim-speed", "10"], nofile=256):
        wait_http(hport)

        def health(label: str) -> None:
            try:
                code, took = get(hport, "/status.json")
                page = f"{code} in {took * 1000:.0f} ms"
            except (OSError, http.client.HTTPException) as exc:
                page = f"failed ({type(exc).__name__})"
            size0 = sum(p.stat().st_size for p in Path(rec_dir).iterdir())
            fprime = "no"
            try:
                with socket.create_connection(("127.0.0.1", fport), timeout=3) as f:
                    f.settimeout(3)
                    fprime = f"{len(f.recv(65536))} bytes" if f.recv(1) else "closed"
            except OSError as exc:
                fprime = f"failed ({type(exc).__name__})"
            time.sleep(2)
            size1 = sum(p.stat().st_size for p in Path(rec_dir).iterdir())
            files = len(list(Path(rec_dir).iterdir()))
            print(f"    {label}: status page {page}; recording +{size1 - size0} bytes in 2 s "
                  f"({files} files); F´ client gets telemetry: {fprime}")

        print(f"  {n} idle UAVTalk clients, gateway under RLIMIT_NOFILE 256 ({tree}):")
        health("before")
        socks: list[socket.socket] = []
        failed = 0
        for _ in range(n):
            try:
                s = socket.create_connection(("127.0.0.1", uport), timeout=3)
            except OSError:
                failed += 1
                continue
            socks.append(s)
        time.sleep(1.0)
        closed = 0
        for s in socks:
            s.setblocking(False)
            try:
                closed += s.recv(1) == b""
            except BlockingIOError:
                pass
            except OSError:
                closed += 1
        print(f"    connected {len(socks)} (connect failed {failed}); closed by the gateway "
              f"(refused) {closed}; still open {len(socks) - closed}")
        health("with them")
        for s in socks:
            s.close()


SCENARIOS: dict[str, Callable[[argparse.Namespace], None]] = {
    "slowloris": lambda a: slowloris(a.tree, a.slow, a.seconds),
    "sse": lambda a: sse(a.tree, 16, a.seconds),
    "connects": lambda a: connects(a.tree, 500),
    "idle": lambda a: idle(a.tree, 300),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tree", type=Path, default=ROOT,
                    help="the checkout whose gateway runs (its .venv)")
    ap.add_argument("--scenario", action="append", choices=sorted(SCENARIOS))
    ap.add_argument("--slow", type=int, default=1000, help="slowloris connections")
    ap.add_argument("--seconds", type=float, default=15.0,
                    help="how long the slowloris and event-stream scenarios watch")
    a = ap.parse_args()
    limit = raise_nofile()
    print(f"bench_listeners: {a.tree} (descriptors here: {limit}; Python "
          f"{sys.version.split()[0]})")
    for name in a.scenario or list(SCENARIOS):
        SCENARIOS[name](a)


if __name__ == "__main__":
    main()
