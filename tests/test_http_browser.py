"""The status page in a real browser: Debian's headless Chromium loads the page of an HTTP
backend fed two simulated climbs (vehicles alpha and beta), and the altitude each vehicle's
card shows changes (the EventSource updates the DOM).  Chromium is driven over its DevTools
protocol (the ``websockets`` client); skips, saying why, where no Chromium is installed
(``.ci/run`` installs it)."""

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


#: the two vehicles and the altitude each climbs from: far enough apart that alpha, climbing
#: 150 m/s, stays below beta's start for the feeder's whole life (500 m apart, a browser
#: slow to start on a loaded machine let alpha pass 500 m before the page was read)
START_M = {"alpha": 0.0, "beta": 100_000.0}


def climbing(d: Dispatcher, stop: threading.Event) -> None:
    """Two rockets climbing at 150 m/s, an update each every 50 ms, until ``stop``."""
    for name in START_M:
        d.dispatch(LinkEvent(source=f"{name}-src", up=True))
    for i in itertools.count():
        for name, start in START_M.items():
            d.dispatch(SmUpdate(timestamp_ms=50 * i, state=2, armed=True, sm_type=0,
                                altitude_m=start + 7.5 * i, acceleration_mps2=30.0,
                                accel_vert_mps2=30.0, velocity_mps=150.0, roll_rad=0.0,
                                pitch_rad=0.0, yaw_rad=0.0, origin=f"{name}-src",
                                vehicle=name))
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
        return self.selected(f"#{element_id}")

    def selected(self, selector: str) -> str:
        """The text of the first element ``selector`` selects ("None" when none does)."""
        r = self.call("Runtime.evaluate", returnByValue=True,
                      expression=f"document.querySelector({selector!r})?.textContent")
        return str(r["result"].get("value"))

    def field(self, vehicle: str, name: str) -> str:
        """A field of a vehicle's card."""
        return self.selected(f'[data-vehicle="{vehicle}"] [data-field="{name}"]')


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


def shown_altitude(tools: DevTools, vehicle: str) -> float | None:
    try:
        return float(tools.field(vehicle, "altitude"))
    except ValueError:  # "—" until the first event, "None" until the card exists
        return None


def test_each_vehicle_card_shows_its_altitude_changing_live(browser: DevTools) -> None:
    seen: dict[str, list[float]] = {name: [] for name in START_M}

    def new_values() -> bool:
        for name, values in seen.items():
            alt = shown_altitude(browser, name)
            if alt is not None and (not values or alt != values[-1]):
                values.append(alt)
        return all(len(values) >= 2 for values in seen.values())

    assert wait_for(new_values, timeout=20, poll_s=0.05), f"altitudes shown: {seen}"
    for name, values in seen.items():
        assert values[1] > values[0], f"{name}'s climb went down on the page"
    # each card its own rocket: beta climbs from 100 km, alpha from 0 (7.5 m per update)
    assert min(seen["beta"]) >= START_M["beta"] > max(seen["alpha"])
    assert browser.text("conn") == "live"
    for name in START_M:
        assert browser.field(name, "state") == "BOOST"
        assert browser.field(name, "armed") == "ARMED"
        assert browser.field(name, "link") == "up"
    cards = browser.call("Runtime.evaluate", returnByValue=True, expression=(
        "[...document.querySelectorAll('#vehicles .vehicle')].map(c => c.dataset.vehicle)"))
    assert cards["result"]["value"] == list(START_M)
    rows = browser.call("Runtime.evaluate", returnByValue=True, expression=(
        "[...document.querySelectorAll('#backends tr')].map(r => r.cells[0].textContent)"))
    assert rows["result"]["value"] == ["http"]
