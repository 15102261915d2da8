"""The HTTP backend: /status.json, /events (SSE), /metrics (read back with prometheus-client's
own parser), read-only refusals, bounded event streams, shutdown, flags and config."""

from __future__ import annotations

import http.client
import json
import math
import socket
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from helpers import run_within, wait_for
from prometheus_client.parser import text_string_to_metric_families

from backends.http.backend import HttpBackend
from backends.http.options import HttpOptions
from gateway import config
from gateway.backend import Backend, BackendError, GatewayContext, Routes
from gateway.config import ConfigError
from gateway.dispatcher import Dispatcher
from gateway.model import LinkEvent, SmUpdate, Status
from gateway.vehicles import SERVICE as VEHICLES
from gateway.vehicles import SourceVehicle

SIMPLE = 0  # sm_type of the SIMPLE state machine
STATES = {"IDLE": 0, "ARMED": 1, "BOOST": 2}  # dialects/states.py: the SIMPLE enum


def sm(t_ms: int, altitude: float, state: int = 2, armed: bool = True,
       vehicle: str = "") -> SmUpdate:
    """An update from the source ``sim`` (without a vehicle: the gateway's one source's)."""
    return SmUpdate(timestamp_ms=t_ms, state=state, armed=armed, sm_type=SIMPLE,
                    altitude_m=altitude, acceleration_mps2=0.0, accel_vert_mps2=0.0,
                    velocity_mps=12.5, roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0,
                    origin="sim", vehicle=vehicle)


class Probe(Backend):
    """Another backend of the gateway, counting what it takes (its counters must show up)."""

    NAME = "probe"

    def __init__(self) -> None:
        super().__init__()
        self.sent = 0

    def routes(self) -> Routes:
        return Routes().on(SmUpdate, self.take)

    def take(self, msg: SmUpdate) -> None:
        self.sent += 1

    def stats(self) -> dict[str, Any]:
        return {"sent": self.sent, "dropped": 3, "errors": 1, "link": 1}


@pytest.fixture
def gw() -> Iterator[tuple[Dispatcher, HttpBackend, Probe]]:
    d = Dispatcher()
    b = HttpBackend(HttpOptions(port=0, event_interval_s=0.05, max_clients=2))
    probe = Probe()
    ctx = GatewayContext(emit=d.dispatch)
    ctx.services["gateway.stats"] = lambda: {"backends": d.stats(), "sources": {}}
    ctx.services[VEHICLES] = [SourceVehicle("sim", "sim")]  # one source, as `run --source sim`
    for x in (b, probe):
        x.attach(ctx)
        d.add(x)
    assert d.start() == []
    try:
        yield d, b, probe
    finally:
        d.close()


def request(b: HttpBackend, method: str, path: str) -> tuple[int, dict[str, str], bytes]:
    host, port = b.address()
    conn = http.client.HTTPConnection(host, port, timeout=5)
    try:
        conn.request(method, path)
        r = conn.getresponse()
        return r.status, dict(r.getheaders()), r.read()
    finally:
        conn.close()


def climb(d: Dispatcher, altitudes: list[float]) -> None:
    for i, alt in enumerate(altitudes):
        d.dispatch(sm(1000 + 100 * i, alt))


ALTITUDES = [10.0, 55.5, 120.25, 310.0, 298.5]  # up, then past apogee


def test_status_json_has_the_latest_values(gw: Any) -> None:
    d, b, _ = gw
    code, _, body = request(b, "GET", "/status.json")
    assert code == 200 and json.loads(body)["vehicle"]["altitude_m"] is None  # nothing heard
    d.dispatch(LinkEvent(source="sim", up=True))
    d.dispatch(Status(timestamp_ms=900, state=2, sm_type=SIMPLE,
                      flags=Status.make_flags(armed=True, imu_ok=True)))
    climb(d, ALTITUDES)
    code, headers, body = request(b, "GET", "/status.json")
    assert code == 200 and headers["Content-Type"] == "application/json"
    s = json.loads(body)
    v = s["vehicle"]
    assert v["altitude_m"] == ALTITUDES[-1]
    assert v["max_altitude_m"] == max(ALTITUDES)
    assert v["state"] == "BOOST" and v["state_id"] == STATES["BOOST"] and v["armed"] is True
    assert v["health"]["imu_ok"] is True and v["health"]["baro_ok"] is False
    assert s["link"] == {"up": True, "sources": {"sim": True}}
    assert s["messages_in"] == {"link": 1, "status": 1, "sm_update": len(ALTITUDES)}
    assert s["backends"]["probe"] == {"sent": len(ALTITUDES), "dropped": 3, "errors": 1,
                                      "link": 1}
    assert s["backends"]["http"]["link"] == 1
    d.dispatch(LinkEvent(source="sim", up=False, silence_s=3.0))
    assert json.loads(request(b, "GET", "/status.json")[2])["link"]["up"] is False


def test_nan_altitude_is_null_and_never_the_maximum(gw: Any) -> None:
    d, b, _ = gw
    climb(d, [5.0, math.nan])
    v = json.loads(request(b, "GET", "/status.json")[2])["vehicle"]
    assert v["altitude_m"] is None and v["max_altitude_m"] == 5.0


def metrics(b: HttpBackend) -> dict[str, dict[tuple[tuple[str, str], ...], float]]:
    code, headers, body = request(b, "GET", "/metrics")
    assert code == 200 and headers["Content-Type"].startswith("text/plain")
    out: dict[str, dict[tuple[tuple[str, str], ...], float]] = {}
    for family in text_string_to_metric_families(body.decode()):
        for s in family.samples:
            out.setdefault(s.name, {})[tuple(sorted(s.labels.items()))] = s.value
    return out


def test_metrics_parse_with_prometheus_client_and_hold_the_values(gw: Any) -> None:
    d, b, _ = gw
    d.dispatch(LinkEvent(source="sim", up=True))
    climb(d, ALTITUDES)
    m = metrics(b)
    sim = (("vehicle", "sim"),)  # the per-vehicle series: labelled with the vehicle
    assert m["aurora_altitude_meters"] == {sim: ALTITUDES[-1]}
    assert m["aurora_max_altitude_meters"] == {sim: max(ALTITUDES)}
    assert m["aurora_armed"] == {sim: 1.0}
    assert m["aurora_link_up"] == {sim: 1.0}
    assert m["aurora_state"] == {(("state", "BOOST"), *sim): float(STATES["BOOST"])}
    assert m["aurora_backend_sent_total"][(("backend", "probe"),)] == len(ALTITUDES)
    assert m["aurora_backend_dropped_total"][(("backend", "probe"),)] == 3
    assert m["aurora_backend_errors_total"][(("backend", "probe"),)] == 1
    assert m["aurora_backend_link"][(("backend", "http"),)] == 1
    assert m["aurora_messages_in_total"] == {(("kind", "sm_update"), *sim): len(ALTITUDES)}
    assert m["aurora_link_events_total"] == {(): 1.0}
    assert m["aurora_vehicles"] == {(): 1.0} and m["aurora_vehicles_refused_total"] == {(): 0}
    # the first scrape was a response the http backend sent (counted once written): the
    # next scrape shows it
    assert wait_for(lambda: b.stats()["sent"] >= 1)
    assert metrics(b)["aurora_backend_sent_total"][(("backend", "http"),)] >= 1


def read_event(r: http.client.HTTPResponse) -> dict[str, Any]:
    """The next ``data:`` event of a stream (fields per the SSE format, blank line ends it)."""
    data: list[str] = []
    while True:
        line = r.readline()
        assert line, "the stream ended"
        text = line.decode().rstrip("\r\n")
        if not text:
            if data:
                return dict(json.loads("\n".join(data)))
            continue
        field, _, value = text.partition(":")
        if field == "data":
            data.append(value[1:] if value.startswith(" ") else value)


def test_events_deliver_the_latest_values_live(gw: Any) -> None:
    d, b, _ = gw
    climb(d, [42.0])
    host, port = b.address()
    conn = http.client.HTTPConnection(host, port, timeout=5)
    try:
        conn.request("GET", "/events")
        r = conn.getresponse()
        assert r.status == 200 and r.getheader("Content-Type") == "text/event-stream"
        assert read_event(r)["vehicle"]["altitude_m"] == 42.0
        assert b.stats()["clients"] == 1
        d.dispatch(sm(5000, 777.0))
        for _ in range(100):  # one event per 0.05 s: the new value within a few
            if read_event(r)["vehicle"]["altitude_m"] == 777.0:
                break
        else:
            pytest.fail("the stream never showed the new altitude")
    finally:
        r.close()
        conn.close()
    assert wait_for(lambda: b.stats()["clients"] == 0), "the stream's slot was not freed"
    assert b.stats()["sent"] >= 2


def test_event_streams_are_capped_and_refusals_counted(gw: Any) -> None:
    _, b, _ = gw
    host, port = b.address()
    conns = [http.client.HTTPConnection(host, port, timeout=5) for _ in range(2)]
    responses: list[http.client.HTTPResponse] = []
    try:
        for c in conns:
            c.request("GET", "/events")
            r = c.getresponse()
            responses.append(r)
            assert r.status == 200
            read_event(r)
        assert b.stats()["clients"] == 2
        code, headers, _ = request(b, "GET", "/events")
        assert code == 503 and "Retry-After" in headers
        st = b.stats()
        assert st["dropped"] == 1 and st["clients_refused"] == 1
        responses.pop().close()
        conns[-1].close()
        assert wait_for(lambda: b.stats()["clients"] == 1), "a closed stream kept its slot"
    finally:
        for r in responses:
            r.close()
        for c in conns:
            c.close()


def test_page_is_served_and_wires_the_event_stream(gw: Any) -> None:
    _, b, _ = gw
    code, headers, body = request(b, "GET", "/")
    assert code == 200 and headers["Content-Type"].startswith("text/html")
    page = body.decode()
    assert 'new EventSource("events")' in page
    for element in ("vehicles", "backends"):  # the vehicles' cards are made by the script
        assert f'id="{element}"' in page
    code, _, body = request(b, "HEAD", "/")
    assert code == 200 and body == b""


@pytest.mark.parametrize("path", ["/nope", "/status", "/metrics/x", "/../etc/passwd"])
def test_other_paths_are_404(gw: Any, path: str) -> None:
    _, b, _ = gw
    assert request(b, "GET", path)[0] == 404


@pytest.mark.parametrize("method", ["POST", "PUT", "DELETE", "PATCH"])
def test_nothing_changes_state(gw: Any, method: str) -> None:
    d, b, _ = gw
    climb(d, [100.0])
    def vehicle() -> dict[str, Any]:
        v = dict(json.loads(request(b, "GET", "/status.json")[2])["vehicle"])
        del v["age_s"]  # time passes
        return v

    before = vehicle()
    for path in ("/", "/status.json", "/metrics", "/events"):
        code, headers, _ = request(b, method, path)
        assert code == 405 and headers["Allow"] == "GET, HEAD"
    assert vehicle() == before


def test_close_ends_open_streams_within_a_second_and_is_safe_twice() -> None:
    b = HttpBackend(HttpOptions(port=0, event_interval_s=0.05))
    b.init()
    host, port = b.address()
    conn = http.client.HTTPConnection(host, port, timeout=5)
    conn.request("GET", "/events")
    r = conn.getresponse()
    read_event(r)
    start = time.monotonic()
    run_within(b.close, timeout=1.0)
    assert time.monotonic() - start < 1.0
    b.close()
    assert b.stats()["link"] == 0
    ended = threading.Event()

    def drain() -> None:
        while r.readline():
            pass
        ended.set()

    threading.Thread(target=drain, daemon=True).start()
    assert ended.wait(2.0), "the stream was left open after close()"
    conn.close()
    with pytest.raises(OSError), socket.create_connection((host, port), timeout=1):
        pass


def test_a_busy_port_refuses_the_start() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        b = HttpBackend(HttpOptions(port=port))
        with pytest.raises(BackendError, match=str(port)):
            b.init()
        b.close()


def test_run_flags_loopback_by_default_and_off_by_default() -> None:
    from gateway.commands.cli import build_parser, config_from_args

    assert HttpBackend.EMBEDDED_DEFAULT is None
    assert "http" not in {p.name for p in config.embedded_default().backends}
    args = build_parser().parse_args(["run"])
    assert "http" not in {p.name for p in config_from_args(args).backends}
    for flag, host, port in (("8080", "127.0.0.1", 8080),
                             ("0.0.0.0:9000", "0.0.0.0", 9000),
                             ("[::1]:9001", "::1", 9001)):
        args = build_parser().parse_args(["run", "--http", flag])
        opts = {p.name: p for p in config_from_args(args).backends}["http"].options
        assert (opts["host"], opts["port"]) == (host, port)
    for bad in ("127.0.0.1:web", "", "[::1"):  # refused as the flag is read (exit 2)
        with pytest.raises(SystemExit):
            build_parser().parse_args(["run", "--http", bad])


@pytest.mark.parametrize(("key", "value"), [("port", 70000), ("port", "80"),
                                            ("max_clients", 0), ("event_interval_s", 0),
                                            ("client_timeout_s", -1), ("colour", "red")])
def test_bad_config_names_the_key(key: str, value: Any) -> None:
    with pytest.raises(ConfigError, match=rf"backends\.http\.{key}"):
        config.parse({"backends": {"http": {key: value}}})


def test_status_json_and_metrics_keep_each_vehicle_apart(gw: Any) -> None:
    """Two rockets through one gateway: alpha near 100 m, beta near 500 m; every entry and
    every series holds its own rocket's values only."""
    d, b, _ = gw
    d.dispatch(LinkEvent(source="a-src", up=True))
    d.dispatch(LinkEvent(source="b-src", up=False, silence_s=3.0))
    for i in range(20):
        d.dispatch(sm(1000 + 10 * i, 100.0 + i % 3, vehicle="alpha")._replace(origin="a-src"))
        d.dispatch(sm(1000 + 10 * i, 500.0 + i % 5, state=1, armed=False,
                      vehicle="beta")._replace(origin="b-src"))
    s = json.loads(request(b, "GET", "/status.json")[2])
    assert list(s["vehicles"]) == ["alpha", "beta"]
    alpha, beta = s["vehicles"]["alpha"], s["vehicles"]["beta"]
    assert alpha["name"] == "alpha" and alpha["source"] == "a-src"
    assert alpha["altitude_m"] == 100.0 + 19 % 3 and alpha["max_altitude_m"] == 102.0
    assert beta["altitude_m"] == 500.0 + 19 % 5 and beta["max_altitude_m"] == 504.0
    assert (alpha["state"], alpha["armed"], beta["state"], beta["armed"]) == (
        "BOOST", True, "ARMED", False)
    assert alpha["link"] is True and beta["link"] is False
    assert alpha["messages_in"] == beta["messages_in"] == {"sm_update": 20}
    assert 0 <= alpha["age_s"] < 60 and alpha["position"] is None
    # the single-vehicle view is the first vehicle heard (no message of "sim" yet)
    assert s["vehicle"] == alpha
    assert s["messages_in"] == {"link": 2, "sm_update": 40}
    m = metrics(b)
    assert m["aurora_altitude_meters"] == {(("vehicle", "alpha"),): 101.0,
                                           (("vehicle", "beta"),): 504.0}
    assert m["aurora_max_altitude_meters"] == {(("vehicle", "alpha"),): 102.0,
                                               (("vehicle", "beta"),): 504.0}
    assert m["aurora_link_up"] == {(("vehicle", "alpha"),): 1.0, (("vehicle", "beta"),): 0.0}
    assert m["aurora_state"] == {(("state", "BOOST"), ("vehicle", "alpha")): 2.0,
                                 (("state", "ARMED"), ("vehicle", "beta")): 1.0}
    # the configured source's vehicle, once heard, is the single-vehicle view
    d.dispatch(sm(5000, 42.0))
    s = json.loads(request(b, "GET", "/status.json")[2])
    assert list(s["vehicles"]) == ["sim", "alpha", "beta"]  # the configured one first
    assert s["vehicle"]["name"] == "sim" and s["vehicle"]["altitude_m"] == 42.0


def test_vehicles_past_the_cap_are_counted_not_kept(gw: Any) -> None:
    """A peer inventing vehicle names cannot grow the table: past MAX_VEHICLES their
    messages are counted (vehicles_refused), the vehicles kept still update."""
    from backends.http.backend import MAX_VEHICLES

    d, b, _ = gw
    for i in range(MAX_VEHICLES + 40):
        d.dispatch(sm(1000, float(i), vehicle=f"v{i}"))
    d.dispatch(sm(2000, 999.0, vehicle="v0"))
    s = json.loads(request(b, "GET", "/status.json")[2])
    assert len(s["vehicles"]) == MAX_VEHICLES and "v255" in s["vehicles"]
    assert f"v{MAX_VEHICLES}" not in s["vehicles"]
    assert s["vehicles_refused"] == 40 and b.stats()["vehicles_refused"] == 40
    assert s["vehicles"]["v0"]["altitude_m"] == 999.0
    m = metrics(b)
    assert len(m["aurora_altitude_meters"]) == MAX_VEHICLES
    assert m["aurora_vehicles_refused_total"] == {(): 40.0}
