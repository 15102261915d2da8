"""Many vehicles on Zenoh (issue 22): keys, liveliness and late joiners per vehicle, the Zenoh
source keeping remote vehicles apart, and ``listen --compact`` one line per vehicle — against
real Zenoh sessions on loopback and real TCP feeds of Aurora wire frames."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import logging
import re
import socket
import threading
from collections.abc import Iterator

import pytest
from helpers import post
from zenoh_peer import Recorder, free_endpoint, peer_config, serving, wait_for_gateway, wait_until

from backends.zenoh.options import ZenohOptions

zenoh = pytest.importorskip("zenoh")

from backends.zenoh import backend as backend_module  # noqa: E402
from backends.zenoh import cli as listen_cli  # noqa: E402
from backends.zenoh import source as source_module  # noqa: E402
from backends.zenoh.backend import ZenohBackend  # noqa: E402
from backends.zenoh.keys import make_attachment  # noqa: E402
from gateway import config, wire  # noqa: E402
from gateway.app import Gateway  # noqa: E402
from gateway.backend import Backend, Routes  # noqa: E402
from gateway.model import LinkStats, SmUpdate, Status  # noqa: E402

#: the two rockets: one hovering near 100 m, one near 500 m
ALTITUDES = {"alpha": 100.0, "beta": 500.0}
NEAR_M = 1.0


class FrameFeed:
    """A TCP server feeding Aurora wire frames (SM_UPDATE near ``altitude_m``, a STATUS every
    tenth frame) at ~50 Hz to whoever connects: what a ``socket://`` source reads."""

    def __init__(self, altitude_m: float) -> None:
        self.altitude_m = altitude_m
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def frame(self, i: int) -> bytes:
        if i % 10 == 9:
            return wire.encode(Status(i * 20, 3, 0, 0x03))
        alt = self.altitude_m + (i % 5) * 0.1
        return wire.encode(SmUpdate(i * 20, 3, True, 0, alt, 0.5, 0.1, 1.0, 0.0, 0.0, 0.0))

    def _serve(self) -> None:
        self.server.settimeout(0.2)
        while not self.stop.is_set():
            try:
                conn, _ = self.server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn:
                i = 0
                while not self.stop.is_set():
                    try:
                        conn.sendall(self.frame(i))
                    except OSError:
                        break
                    i += 1
                    self.stop.wait(0.02)  # the feed's pace, not a synchronisation

    def close(self) -> None:
        self.stop.set()
        self.server.close()
        self.thread.join(5)


@pytest.fixture
def feeds() -> Iterator[dict[str, FrameFeed]]:
    made = {name: FrameFeed(alt) for name, alt in ALTITUDES.items()}
    yield made
    for f in made.values():
        f.close()


def two_vehicle_gateway(feeds: dict[str, FrameFeed], endpoint: str, **zenoh_opts) -> Gateway:
    """``run --source alpha=socket://… --source beta=socket://… --zenoh-listen ENDPOINT``."""
    return Gateway(config.parse({
        "gateway": {"status_interval_s": 0.0},
        "sources": [{"type": "serial", "url": f.url, "vehicle": name}
                    for name, f in feeds.items()],
        "backends": {"zenoh": {"listen": [endpoint], "stats_interval_s": 0.2,
                               **zenoh_opts}}}))


def altitudes(samples, vehicle: str) -> list[float]:
    return [s.json()["altitude_m"] for s in samples if s.key == f"aurora/{vehicle}/sm_update"]


def near(values: list[float], target: float) -> bool:
    return bool(values) and all(abs(v - target) <= NEAR_M for v in values)


# -- the backend -------------------------------------------------------------------------------

def test_two_vehicles_each_under_their_own_keys_with_their_own_presence(feeds):
    endpoint = free_endpoint()
    gw = two_vehicle_gateway(feeds, endpoint, gateway_id="gw-two")
    events: list[tuple[str, bool]] = []
    cond = threading.Condition()

    def on_token(sample) -> None:
        with cond:
            events.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))
            cond.notify_all()

    with zenoh.open(peer_config(connect=[endpoint])) as sub:
        sub.liveliness().declare_subscriber("aurora/*/gateway/*", on_token, history=True)
        rec = Recorder()
        sub.declare_subscriber("aurora/**", rec)
        gw.start()
        try:
            tokens = {f"aurora/{v}/gateway/gw-two" for v in ALTITUDES}
            with cond:  # one token per configured vehicle, as the session opens
                assert cond.wait_for(lambda: tokens <= {k for k, up in events if up}, 20)
            assert rec.wait_for(lambda s: all(len(altitudes(s, v)) >= 20 for v in ALTITUDES))
            samples = rec.snapshot()
            for vehicle, alt in ALTITUDES.items():
                assert near(altitudes(samples, vehicle), alt), (vehicle, altitudes(samples,
                                                                                   vehicle))
                # the raw frames under each vehicle decode to its own rocket's altitudes
                raw = [wire.decode_all(s.payload)[0].altitude_m for s in samples
                       if s.key == f"aurora/{vehicle}/raw/1"]
                assert near(raw, alt)
                assert any(s.key == f"aurora/{vehicle}/status" for s in samples)
            # a source's link event (it has no vehicle) goes under the source's vehicle (it
            # came with the first frame, perhaps before this subscription: asked for)
            links = {str(r.ok.key_expr): json.loads(r.ok.payload.to_bytes())
                     for r in sub.get("aurora/*/link", timeout=10) if r.ok is not None}
            assert links == {f"aurora/{v}/link": {"source": f.url, "up": True,
                                                  "silence_s": 0.0}
                             for v, f in feeds.items()}
            # every key is a vehicle's: nothing else under aurora/*/…
            assert {s.key.split("/")[1] for s in samples} == set(ALTITUDES)
            zb = gw.dispatcher.backends()[0]
            assert zb.stats()["vehicles"] == 2
        finally:
            gw.stop()
        with cond:  # both tokens gone with the gateway
            assert cond.wait_for(lambda: all((t, False) in events for t in tokens), 20)


def test_a_late_joiner_gets_each_vehicles_latest_state_at_once(feeds):
    endpoint = free_endpoint()
    gw = two_vehicle_gateway(feeds, endpoint)
    gw.start()
    try:
        zb = gw.dispatcher.backends()[0]
        assert wait_until(lambda: all(f"aurora/{v}/sm_update" in zb.latest() for v in ALTITUDES))
        with zenoh.open(peer_config(connect=[endpoint])) as late:
            for vehicle, alt in ALTITUDES.items():
                got = {str(s.key_expr): s for s in wait_for_gateway(late, "aurora", vehicle)}
                # one vehicle's query: that vehicle's keys only, with its own values
                assert {k.split("/")[1] for k in got} == {vehicle}
                assert {f"aurora/{vehicle}/{k}" for k in ("sm_update", "raw/1")} <= set(got)
                doc = json.loads(got[f"aurora/{vehicle}/sm_update"].payload.to_bytes())
                assert abs(doc["altitude_m"] - alt) <= NEAR_M
            # every vehicle's at once, each key answered once (by its vehicle's queryable
            # alone: no consolidation hides duplicates here)
            everything = [str(r.ok.key_expr) for r in late.get(
                "aurora/**", timeout=10, consolidation=zenoh.ConsolidationMode.NONE)
                if r.ok is not None]
            assert len(everything) == len(set(everything))
            assert {k for k in everything if k.endswith("/sm_update")} == {
                "aurora/alpha/sm_update", "aurora/beta/sm_update"}
    finally:
        gw.stop()


def test_the_gateways_counters_are_its_own_not_a_vehicles(feeds):
    """``stats_interval_s``: on ``aurora/@gateways/<id>/stats``, which ``aurora/**`` never
    matches; a subscriber naming it gets them."""
    endpoint = free_endpoint()
    gw = two_vehicle_gateway(feeds, endpoint, gateway_id="gw-stats")
    with zenoh.open(peer_config(connect=[endpoint])) as sub:
        everything, stats = Recorder(), Recorder()
        sub.declare_subscriber("aurora/**", everything)
        sub.declare_subscriber("aurora/@gateways/*/stats", stats)
        gw.start()
        try:
            assert stats.wait_for(lambda s: len(s) >= 2)
            doc = stats.snapshot()[-1].json()
            assert set(doc) == {"backends", "sources"} and "zenoh" in doc["backends"]
            assert {s.key for s in stats.snapshot()} == {"aurora/@gateways/gw-stats/stats"}
            assert everything.wait_for(lambda s: len(s) >= 10)
            assert not any("stats" in s.key for s in everything.snapshot())
        finally:
            gw.stop()


def test_vehicles_are_bounded_and_a_message_without_one_needs_a_source(monkeypatch):
    monkeypatch.setattr(backend_module, "MAX_VEHICLES", 2)
    endpoint = free_endpoint()
    b = ZenohBackend(ZenohOptions(listen=[endpoint], raw=False))  # no source configured
    b.init()
    try:
        assert b.wait_ready(20)
        m = SmUpdate(1, 3, True, 0, 10.0, 0, 0, 0, 0, 0, 0)
        with zenoh.open(peer_config(connect=[endpoint])) as sub:
            rec = Recorder()
            sub.declare_subscriber("aurora/**", rec)
            post(b, m._replace(vehicle="v1"))
            wait_for_gateway(sub, "aurora", "v1")  # its presence came with its first message
            for v in ("v1", "v2", "v3", "v4", "v3", ""):
                post(b, m._replace(vehicle=v))
            assert b.wait_idle(20)
            st = b.stats()
            assert st["vehicles"] == 2 and st["dropped_vehicle_limit"] == 3
            assert st["skipped_no_vehicle"] == 1
            # (the first message may have gone before this subscription reached the gateway;
            # wait_for_gateway made sure the others reach it)
            assert rec.wait_for(lambda s: {x.key for x in s} == {"aurora/v1/sm_update",
                                                                 "aurora/v2/sm_update"})
            tokens = [str(r.ok.key_expr) for r in sub.liveliness().get("aurora/*/gateway/*",
                                                                        timeout=10)
                      if r.ok is not None]
            assert sorted(t.split("/")[1] for t in tokens) == ["v1", "v2"]
    finally:
        b.close()


def test_a_message_without_a_vehicle_goes_under_its_sources_or_the_first_sources():
    endpoint = free_endpoint()
    b = ZenohBackend(ZenohOptions(listen=[endpoint], raw=False))
    serving(b, "alpha", "beta", source="radio")  # sources radio (alpha) and radio-2 (beta)
    b.init()
    try:
        assert b.wait_ready(20)
        with zenoh.open(peer_config(connect=[endpoint])) as sub:
            rec = Recorder()
            sub.declare_subscriber("aurora/**", rec)
            wait_for_gateway(sub, "aurora", "alpha")
            wait_for_gateway(sub, "aurora", "beta")
            post(b, LinkStats(rssi_dbm=-70.0, origin="radio-2"))  # beta's source
            post(b, LinkStats(rssi_dbm=-80.0, origin="crsf"))  # a backend's own: the first
            assert rec.wait_for(lambda s: len(s) >= 2)
            got = {s.key: s.json()["rssi_dbm"] for s in rec.snapshot()}
            assert got == {"aurora/beta/link_stats": -70.0, "aurora/alpha/link_stats": -80.0}
    finally:
        b.close()


# -- the source --------------------------------------------------------------------------------

class Capture(Backend):
    """A backend that keeps the SM updates the dispatcher hands it."""

    def __init__(self) -> None:
        super().__init__("capture")
        self.seen: list[SmUpdate] = []
        self.cond = threading.Condition()

    def routes(self) -> Routes:
        return Routes().on(SmUpdate, self.keep)

    def keep(self, msg: SmUpdate) -> None:
        with self.cond:
            self.seen.append(msg)
            self.cond.notify_all()

    def by_vehicle(self) -> dict[str, list[SmUpdate]]:
        with self.cond:
            out: dict[str, list[SmUpdate]] = {}
            for m in self.seen:
                out.setdefault(m.vehicle, []).append(m)
            return out


@pytest.mark.parametrize("keys,follow", [("raw", "*"), ("json", "*"), ("raw", "beta")])
def test_a_chained_gateway_keeps_the_vehicles_names(feeds, keys, follow):
    """Gateway A hears alpha and beta; gateway B follows A over Zenoh: B's messages carry
    A's vehicle names, each with its own rocket's values (``follow`` picks which)."""
    endpoint, b_endpoint = free_endpoint(), free_endpoint()
    a = two_vehicle_gateway(feeds, endpoint)
    b = Gateway(config.parse({
        "gateway": {"status_interval_s": 0.0},
        "sources": [{"type": "zenoh", "connect": [endpoint], "keys": keys, "follow": follow,
                     "name": "from-a"}],
        "backends": {"zenoh": {"listen": [b_endpoint], "stats_interval_s": 0.2,
                               "gateway_id": "gw-b"}}}))
    capture = Capture()
    b.dispatcher.add(capture)
    a.start()
    b.start()
    wanted = set(ALTITUDES) if follow == "*" else {follow}
    try:
        with capture.cond:
            assert capture.cond.wait_for(
                lambda: {v for v in wanted
                         if sum(m.vehicle == v for m in capture.seen) >= 10} == wanted, 30)
        got = capture.by_vehicle()
        assert set(got) == wanted
        a_id = a.dispatcher.backends()[0].gateway_id
        for vehicle, msgs in got.items():
            assert near([m.altitude_m for m in msgs], ALTITUDES[vehicle]), vehicle
            assert {m.origin for m in msgs} == {"from-a"}
            assert {m.via for m in msgs} == {f"zenoh:{a_id}"}
        src = b.sources[0].stats()
        assert src["vehicles"] == len(wanted)
        # B publishes none of it again, and announces no vehicle of its own: neither A's
        # (they came over Zenoh) nor its Zenoh source's name
        zb = b.dispatcher.backends()[0]
        assert zb.wait_idle(20)
        st = zb.stats()
        assert st["vehicles"] == 0 and st["skipped_from_zenoh"] > 0 and st["sent"] == 0
        with zenoh.open(peer_config(connect=[b_endpoint])) as observer:
            stats = Recorder()
            observer.declare_subscriber("aurora/@gateways/gw-b/stats", stats)
            assert stats.wait_for(lambda s: len(s) >= 1)  # B's session reaches us
            tokens = [r.ok for r in observer.liveliness().get("aurora/*/gateway/gw-b",
                                                              timeout=10) if r.ok is not None]
            assert tokens == []
    finally:
        b.stop()
        a.stop()


def test_the_source_bounds_remote_vehicles_and_refuses_bad_names(monkeypatch, caplog):
    monkeypatch.setattr(source_module, "MAX_VEHICLES", 2)
    monkeypatch.setattr(source_module, "LOGGED_VEHICLES", 1)
    caplog.set_level(logging.INFO, logger="backends.zenoh.source")
    endpoint = free_endpoint()
    frame = wire.encode(SmUpdate(1, 3, True, 0, 42.0, 0, 0, 0, 0, 0, 0))
    with zenoh.open(peer_config(listen=[endpoint])) as remote:
        b = Gateway(config.parse({
            "gateway": {"status_interval_s": 0.0},
            "sources": [{"type": "zenoh", "connect": [endpoint], "name": "in"}]}))
        capture = Capture()
        b.dispatcher.add(capture)
        b.start()
        try:
            src = b.sources[0]
            assert src.ready.wait(20)
            names = ["v1", "v2", "v3", "9lives", "a.b"]
            pubs = [remote.declare_publisher(f"aurora/{v}/raw/1") for v in names]
            assert wait_until(lambda: all(p.matching_status.matching for p in pubs))
            for i, p in enumerate(pubs):
                p.put(frame, attachment=make_attachment("remote", i))
            assert wait_until(lambda: src.received == len(names))
            assert wait_until(lambda: src.stats()["emitted"] == 2)
            st = src.stats()
            assert st["vehicles"] == 2 and st["dropped_vehicle_limit"] == 1
            assert st["bad_vehicle_names"] == 2
            assert set(capture.by_vehicle()) == {"v1", "v2"}
            lines = [r.getMessage() for r in caplog.records]
            assert len([ln for ln in lines if "following" in ln]) == 2, lines
            assert len([ln for ln in lines if "ignoring vehicle" in ln]) == 2, lines
        finally:
            b.stop()


# -- listen --compact --------------------------------------------------------------------------

def final_block(text: str) -> list[str]:
    """The lines ``--compact`` drew last (the block is redrawn in place)."""
    last = re.split(r"\x1b\[\d+F|\r", text)[-1]
    return [ln for ln in last.replace("\x1b[K", "").splitlines() if ln]


def test_listen_compact_shows_one_line_per_vehicle(feeds):
    endpoint = free_endpoint()
    gw = two_vehicle_gateway(feeds, endpoint)
    gw.start()
    try:
        parser = argparse.ArgumentParser()
        listen_cli.add_command(parser.add_subparsers())
        args = parser.parse_args(["listen", "--connect", endpoint, "--compact",
                                  "--count", "60"])
        out = io.StringIO()
        with contextlib.redirect_stderr(io.StringIO()):
            assert listen_cli.run_listen(args, out=out) == 0
    finally:
        gw.stop()
    lines = final_block(out.getvalue())
    assert len(lines) == 3, lines
    alpha, beta, totals = lines
    assert alpha.startswith("alpha ") and beta.startswith("beta  ")
    for line, alt in ((alpha, 100.0), (beta, 500.0)):
        shown = float(re.search(r"alt +(-?[\d.]+) m", line).group(1))
        assert abs(shown - alt) <= NEAR_M, line
    assert totals.startswith("2 vehicle(s), 60 rx")


def test_compact_view_lines_are_bounded(monkeypatch):
    monkeypatch.setattr(listen_cli, "MAX_VEHICLES", 2)
    view = listen_cli.CompactView(io.StringIO())
    for v in ("c", "a", "b"):
        view.update({"vehicle": v, "kind": "sm_update",
                     "value": {"state_name": "IDLE", "altitude_m": 1.0}}, "s")
    lines = view.lines("s")
    assert [ln.split()[0] for ln in lines[:-1]] == ["a", "c"]
    assert lines[-1] == "2 vehicle(s), s, 1 updates of further vehicles"
