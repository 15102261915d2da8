"""The status page in a real browser: Debian's headless Chromium loads the page of an HTTP
backend fed a simulated climb, and the altitude it shows changes (the EventSource updates
the DOM).  Chromium is driven over its DevTools protocol (the ``websockets`` client); skips,
saying why, where no Chromium is installed (``.ci/run`` installs it)."""

from __future__ import annotations

import itertools
import json
import shutil
import subprocess
import threading
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import wait_for

from backends.http.backend import HttpBackend
from backends.http.options import HttpOptions
from gateway.backend import GatewayContext
from gateway.dispatcher import Dispatcher
from gateway.model import LinkEvent, SmUpdate

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="no Chromium: install Debian's chromium "
    "(apt-get install -y chromium chromium-driver; .ci/run does it as root)")

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run",
         "--window-size=1000,700", "--remote-debugging-port=0"]


def climbing(d: Dispatcher, stop: threading.Event) -> None:
    """A rocket climbing at 150 m/s, an update every 50 ms, until ``stop``."""
    d.dispatch(LinkEvent(source="sim", up=True))
    for i in itertools.count():
        d.dispatch(SmUpdate(timestamp_ms=50 * i, state=2, armed=True, sm_type=0,
                            altitude_m=7.5 * i, acceleration_mps2=30.0, accel_vert_mps2=30.0,
                            velocity_mps=150.0, roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0))
        if stop.wait(0.05):  # pacing the simulated flight, not synchronising the test
            return


@pytest.fixture
def page_url() -> Iterator[str]:
    d = Dispatcher()
    b = HttpBackend(HttpOptions(port=0))
    ctx = GatewayContext(emit=d.dispatch)
    ctx.services["gateway.stats"] = lambda: {"backends": d.stats(), "sources": {}}
    b.attach(ctx)
    d.add(b)
    assert d.start() == []
    stop = threading.Event()
    feeder = threading.Thread(target=climbing, args=(d, stop), daemon=True)
    feeder.start()
    host, port = b.address()
    try:
        yield f"http://{host}:{port}/"
    finally:
        stop.set()
        feeder.join(2)
        d.close()


class DevTools:
    """A minimal DevTools protocol client for one page target."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.ids = itertools.count(1)

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        n = next(self.ids)
        self.ws.send(json.dumps({"id": n, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv(timeout=10))
            if reply.get("id") == n:
                assert "error" not in reply, reply
                return dict(reply["result"])

    def text(self, element_id: str) -> str:
        r = self.call("Runtime.evaluate", returnByValue=True,
                      expression=f"document.getElementById({element_id!r}).textContent")
        return str(r["result"].get("value"))


@pytest.fixture
def browser(page_url: str, tmp_path: Path) -> Iterator[DevTools]:
    pytest.importorskip("websockets", reason="the DevTools client needs websockets")
    from websockets.sync.client import connect

    assert CHROMIUM is not None
    profile = tmp_path / "profile"
    proc = subprocess.Popen([CHROMIUM, *FLAGS, f"--user-data-dir={profile}", page_url],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    port_file = profile / "DevToolsActivePort"
    try:
        assert wait_for(lambda: port_file.exists() and port_file.read_text().count("\n") >= 1,
                        timeout=20), "Chromium did not open its DevTools port"
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
            targets = json.load(r)
        page = next(t for t in targets if t.get("type") == "page")
        with connect(page["webSocketDebuggerUrl"], max_size=None, open_timeout=10) as ws:
            yield DevTools(ws)
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def shown_altitude(tools: DevTools) -> float | None:
    try:
        return float(tools.text("altitude"))
    except ValueError:  # "—" until the first event
        return None


def test_the_page_shows_the_altitude_changing_live(browser: DevTools) -> None:
    seen: list[float] = []

    def new_value() -> bool:
        alt = shown_altitude(browser)
        if alt is not None and (not seen or alt != seen[-1]):
            seen.append(alt)
        return len(seen) >= 2

    assert wait_for(new_value, timeout=20, poll_s=0.05), f"altitude shown: {seen}"
    assert seen[1] > seen[0], "the climb's altitude went down on the page"
    assert browser.text("conn") == "live"
    assert browser.text("state") == "BOOST" and browser.text("armed") == "ARMED"
    assert browser.text("link") == "up"
    rows = browser.call("Runtime.evaluate", returnByValue=True, expression=(
        "[...document.querySelectorAll('#backends tr')].map(r => r.cells[0].textContent)"))
    assert rows["result"]["value"] == ["http"]
