"""The Zenoh backend and source against real Zenoh sessions on loopback."""

from __future__ import annotations

import json
import threading

import pytest
from helpers import post
from zenoh_peer import (
    Recorder,
    RouterProcess,
    free_endpoint,
    peer_config,
    serving,
    wait_for_gateway,
    wait_until,
)

from backends.zenoh.options import ZenohOptions, ZenohSourceOptions

zenoh = pytest.importorskip("zenoh")

from backends.zenoh import encoding as enc  # noqa: E402
from backends.zenoh.backend import ZenohBackend  # noqa: E402
from backends.zenoh.keys import make_attachment  # noqa: E402
from backends.zenoh.session import SessionOptions  # noqa: E402
from backends.zenoh.source import ZenohSource  # noqa: E402
from gateway import config, wire  # noqa: E402
from gateway.app import Gateway  # noqa: E402
from gateway.backend import Backend, Outcome, Routes  # noqa: E402
from gateway.flight import FlightModel  # noqa: E402
from gateway.model import LinkEvent, LinkStats, RawFrame, SmUpdate, Status, kind  # noqa: E402
from gateway.sources.sim import flight_messages  # noqa: E402

VEHICLE = "r1"


def zenoh_backend(**options) -> ZenohBackend:
    """A Zenoh backend in a gateway whose one source, ``serial``, is vehicle ``r1``."""
    return serving(ZenohBackend(ZenohOptions(**options)), VEHICLE)


def flight(n: int, rate_hz: float = 10.0, vehicle: str = VEHICLE) -> list[SmUpdate | Status]:
    """The first ``n`` messages of the simulated flight, as decoded from their frames."""
    out = []
    for _, m in flight_messages(FlightModel(), rate_hz, 1.0, 1):
        out.append(wire.decode_all(wire.encode(m), origin="serial", vehicle=vehicle)[0])
        if len(out) == n:
            break
    return out


def first_sm_update() -> SmUpdate:
    return next(m for m in flight(3) if isinstance(m, SmUpdate))


def send(backend: ZenohBackend, msg) -> Outcome:
    return post(backend, msg)


@pytest.fixture
def endpoint():
    return free_endpoint()


@pytest.fixture
def backend(endpoint):
    b = zenoh_backend(listen=[endpoint], gateway_id="gw-test")
    b.init()
    assert b.wait_ready(20), "the session did not open"
    yield b
    b.close()


@pytest.fixture
def subscriber(endpoint):
    s = zenoh.open(peer_config(connect=[endpoint]))
    yield s
    s.close()


def test_publishes_json_and_raw_frames_with_attachment(backend, subscriber):
    rec = Recorder()
    subscriber.declare_subscriber("aurora/**", rec)
    wait_for_gateway(subscriber, "aurora", VEHICLE)
    msgs = flight(12)
    assert all(send(backend, m) == Outcome.ACCEPTED for m in msgs)
    unknown = RawFrame(0xAB, b"\x01\x02\x03", wire.frame(0xAB, b"\x01\x02\x03"), "serial")
    assert send(backend, unknown) == Outcome.ACCEPTED
    n_sm = sum(isinstance(m, SmUpdate) for m in msgs)
    n_st = len(msgs) - n_sm
    assert rec.wait_for(lambda s: len(s) >= 2 * len(msgs) + 1), rec.snapshot()

    sm = rec.matching(f"aurora/{VEHICLE}/sm_update")
    assert len(sm) == n_sm
    assert [s.seq for s in sm] == list(range(n_sm))
    assert {s.gateway for s in rec.snapshot()} == {"gw-test"}
    assert all(s.encoding == "application/json" for s in sm)
    first = next(m for m in msgs if isinstance(m, SmUpdate))
    assert sm[0].json() == json.loads(enc.to_json(first))
    assert len(rec.matching(f"aurora/{VEHICLE}/status")) == n_st
    raw1 = rec.matching(f"aurora/{VEHICLE}/raw/1")
    assert [s.payload for s in raw1] == [m.raw for m in msgs if isinstance(m, SmUpdate)]
    assert raw1[0].encoding == enc.WIRE
    assert [s.payload for s in rec.matching(f"aurora/{VEHICLE}/raw/171")] == [unknown.raw]
    assert backend.stats()["sent"] == len(msgs) + 1


def test_packed_encoding(endpoint, subscriber):
    b = zenoh_backend(listen=[endpoint], encoding="packed", raw=False)
    b.init()
    try:
        assert b.wait_ready(20)
        rec = Recorder()
        subscriber.declare_subscriber(f"aurora/{VEHICLE}/*", rec)
        wait_for_gateway(subscriber, "aurora", VEHICLE)
        msgs = flight(3)
        for m in msgs:
            send(b, m)
        assert rec.wait_for(lambda s: len(s) >= 3)
        for m, s in zip(msgs, rec.snapshot(), strict=True):
            assert s.payload == m.raw[4:-2]
            assert enc.decode(kind(m), s.payload, s.encoding) == m._replace(origin="", vehicle="")
        assert rec.matching(f"aurora/{VEHICLE}/raw/1") == []
    finally:
        b.close()


def test_late_joiner_gets_the_latest_value_of_each_key(backend, endpoint):
    msgs = flight(25)
    for m in msgs:
        send(backend, m)
    # a message without a vehicle whose origin is the source: under the source's vehicle
    send(backend, LinkStats(rssi_dbm=-60.0, link_quality_pct=100, origin="serial"))
    assert wait_until(lambda: backend.processed == backend.accepted)
    with zenoh.open(peer_config(connect=[endpoint])) as late:
        latest = {str(s.key_expr): s for s in wait_for_gateway(late, "aurora", VEHICLE)}
    last_sm = [m for m in msgs if isinstance(m, SmUpdate)][-1]
    last_st = [m for m in msgs if isinstance(m, Status)][-1]
    assert set(latest) == {f"aurora/{VEHICLE}/{k}" for k in
                           ("sm_update", "status", "raw/1", "raw/2", "link_stats")}
    assert json.loads(latest[f"aurora/{VEHICLE}/sm_update"].payload.to_bytes()) == json.loads(
        enc.to_json(last_sm))
    assert latest[f"aurora/{VEHICLE}/raw/2"].payload.to_bytes() == last_st.raw
    assert latest[f"aurora/{VEHICLE}/sm_update"].attachment.to_bytes() == make_attachment(
        "gw-test", sum(isinstance(m, SmUpdate) for m in msgs) - 1)


def test_liveliness_token_appears_and_vanishes(endpoint, subscriber):
    events: list[tuple[str, bool]] = []
    cond = threading.Condition()

    def on_token(sample) -> None:
        with cond:
            events.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))
            cond.notify_all()

    subscriber.liveliness().declare_subscriber("aurora/*/gateway/*", on_token, history=True)
    b = zenoh_backend(listen=[endpoint], gateway_id="gw-live")
    b.init()
    token = f"aurora/{VEHICLE}/gateway/gw-live"
    try:
        with cond:
            assert cond.wait_for(lambda: (token, True) in events, 20)
    finally:
        b.close()
    with cond:
        assert cond.wait_for(lambda: (token, False) in events, 20)


def test_block_mode_counts_every_loss_in_its_queue(endpoint, subscriber):
    """With congestion control BLOCK nothing is lost inside Zenoh: whatever the hand-off
    queue refused is counted, and everything it accepted arrives, in order."""
    b = zenoh_backend(listen=[endpoint], raw=False, queue_depth=4, queue_s=0,
                      congestion_control="block")
    b.init()
    try:
        assert b.wait_ready(20)
        rec = Recorder()
        subscriber.declare_subscriber(f"aurora/{VEHICLE}/sm_update", rec)
        wait_for_gateway(subscriber, "aurora", VEHICLE)
        m = first_sm_update()
        outcomes = []
        for _ in range(20):  # bursts of back-to-back hooks outrun a worker with a queue of 4
            outcomes += [send(b, m) for _ in range(200)]
            assert wait_until(lambda: b.processed == b.accepted)
        accepted = outcomes.count(Outcome.ACCEPTED)
        full = outcomes.count(Outcome.QUEUE_FULL)
        assert accepted + full == len(outcomes)
        assert accepted >= 20 * 4 and full > 0
        assert b.stats()["dropped_queue_full"] == full
        assert rec.wait_for(lambda s: len(s) >= accepted)
        assert [s.seq for s in rec.snapshot()] == list(range(accepted))
    finally:
        b.close()


def test_not_ready_until_the_router_comes_then_publishes():
    ep = free_endpoint()
    b = zenoh_backend(mode="client", connect=[ep], reconnect_max_s=0.5)
    b.init()  # the router is not there: init does not fail, the worker keeps trying
    router = RouterProcess(ep)
    try:
        assert not b.ready
        m = first_sm_update()
        assert send(b, m) == Outcome.NOT_READY
        assert b.stats()["dropped_not_ready"] == 1
        router.start()
        assert b.wait_ready(20), b.stats()
        assert b.stats()["open_failures"] >= 1
        with zenoh.open(peer_config(connect=[ep], mode="client")) as sub:
            rec = Recorder()
            sub.declare_subscriber("aurora/**", rec)
            wait_for_gateway(sub, "aurora", VEHICLE)
            assert send(b, m) == Outcome.ACCEPTED
            assert rec.wait_for(lambda s: any(x.key.endswith("/sm_update") for x in s))
    finally:
        b.close()
        router.stop()


def test_updates_published_while_the_router_is_gone_are_counted_as_unrouted():
    router = RouterProcess().start()
    b = zenoh_backend(mode="client", connect=[router.endpoint], raw=False)
    try:
        b.init()
        assert b.wait_ready(20)
        assert wait_until(lambda: b.stats()["connected"] == 1)
        m = first_sm_update()
        send(b, m)
        assert wait_until(lambda: b.processed == b.accepted)
        assert b.stats()["unrouted"] == 0
        router.kill()
        assert wait_until(lambda: b.stats()["connected"] == 0)
        for _ in range(5):
            assert send(b, m) == Outcome.ACCEPTED  # the session is still open
        assert wait_until(lambda: b.processed == b.accepted)
        assert b.stats()["unrouted"] == 5
        router.start()  # and it comes back on its own
        assert wait_until(lambda: b.stats()["connected"] == 1)
    finally:
        b.close()
        router.stop()


def test_second_session_on_a_taken_default_port_joins_the_first():
    ep = free_endpoint()
    with zenoh.open(peer_config(listen=[ep])) as first:
        rec = Recorder()
        first.declare_subscriber("aurora/**", rec)
        opts = SessionOptions(default_listen=[ep])
        assert opts.uses_default_listen
        second = opts.open()  # the port is taken: listen elsewhere, connect to it
        try:
            assert wait_until(lambda: len(second.info.peers_zid()) >= 1)
            pub = second.declare_publisher("aurora/x/probe")
            assert wait_until(lambda: pub.matching_status.matching)
            pub.put(b"hello")
            assert rec.wait_for(lambda s: len(s) == 1)
        finally:
            second.close()


# -- gateway to gateway ------------------------------------------------------------------------

def test_own_publications_never_come_back_through_a_source(endpoint, backend):
    src = ZenohSource(ZenohSourceOptions(connect=[endpoint], follow=VEHICLE))
    src.attach(backend.context)  # one gateway: the backend's id is in the shared context
    got: list = []
    src.start(got.append)
    try:
        assert src.ready.wait(20)
        m = first_sm_update()

        def published_and_came_back() -> bool:
            send(backend, m)
            return src.ignored_own >= 1

        # Publish until the source's subscription has reached the backend …
        assert wait_until(published_and_came_back, interval=0.05), src.stats()
        # … then everything the backend publishes is recognised as its own.
        before = src.ignored_own
        for m in flight(5):
            send(backend, m)
        assert wait_until(lambda: src.ignored_own >= before + 5), src.stats()
        assert got == [] and src.emitted == 0 and src.received == 0
    finally:
        src.stop()


class Capture(Backend):
    """A backend that keeps what the dispatcher hands it."""

    def __init__(self) -> None:
        super().__init__("capture")
        self.seen: list = []
        self.cond = threading.Condition()

    def routes(self) -> Routes:
        keep = self.keep
        return (Routes().on(SmUpdate, keep).on(Status, keep).on(RawFrame, keep)
                .on(LinkEvent, keep))

    def keep(self, msg) -> None:
        with self.cond:
            self.seen.append(msg)
            self.cond.notify_all()



@pytest.mark.parametrize("keys", ["raw", "json"])
def test_relay_feeds_the_dispatcher_and_never_republishes(keys, tmp_path):
    """A ground gateway follows a rocket-side publisher (another gateway's output: frames
    on raw/<type> and documents, attachment naming that gateway): the local dispatcher gets
    the messages, the local Zenoh backend publishes none of them again."""
    rocket_ep, ground_ep = free_endpoint(), free_endpoint()
    msgs = flight(20)
    with zenoh.open(peer_config(listen=[rocket_ep])) as rocket:
        cfg = config.parse({
            "sources": [{"type": "zenoh", "url": f"zenoh:{VEHICLE}@{rocket_ep}", "keys": keys,
                         "name": "from-rocket"}],
            "backends": {"zenoh": {"listen": [ground_ep], "gateway_id": "ground"}},
        })
        gw = Gateway(cfg)
        capture = Capture()
        gw.dispatcher.add(capture)
        seen, cond = capture.seen, capture.cond
        gw.start()
        try:
            src = gw.sources[0]
            assert src.ready.wait(20)
            pubs = {}
            for key in ("sm_update", "status", "raw/1", "raw/2"):
                pubs[key] = rocket.declare_publisher(f"aurora/{VEHICLE}/{key}")
            assert wait_until(lambda: all(p.matching_status.matching for k, p in pubs.items()
                                          if k.startswith("raw/") == (keys == "raw")))
            seqs: dict[str, int] = {}
            for i, m in enumerate(msgs):
                key = f"raw/{m.raw[2]}" if keys == "raw" else kind(m)
                seq = seqs[key] = seqs.get(key, -1) + (2 if i == 10 else 1)  # one gap
                att = make_attachment("rocket", seq)
                if keys == "raw":
                    pubs[key].put(m.raw, attachment=att)
                else:
                    pubs[key].put(enc.to_json(m), encoding=enc.JSON, attachment=att)
            with cond:
                assert cond.wait_for(
                    lambda: sum(not isinstance(x, LinkEvent) for x in seen) >= len(msgs), 20)
                relayed = [x for x in seen if not isinstance(x, LinkEvent)]
                links = [x for x in seen if isinstance(x, LinkEvent)]
            assert [x.fields() for x in relayed] == [m.fields() for m in msgs]
            assert {x.origin for x in relayed} == {"from-rocket"}
            assert {x.via for x in relayed} == {"zenoh:rocket"}  # where it came from
            if keys == "raw":
                assert [x.raw for x in relayed] == [m.raw for m in msgs]  # untouched frames
            assert links and links[0].source == "from-rocket" and links[0].up
            assert src.stats()["lost"] == 1  # the publisher's seq skipped one
            zb = gw.dispatcher.backends()[0]
            assert zb.wait_idle(20)  # its loop has handled what was handed over
            st = zb.stats()
            assert st["skipped_from_zenoh"] >= len(msgs) + 1  # and the link event
            # nothing relayed: its only puts are the gateway's own counters (gateway_stats)
            assert st["sent"] == 0 and st["puts"] == st["stats_published"]
        finally:
            gw.stop()


def test_two_gateways_in_one_process_share_no_loop_prevention_state() -> None:
    """Gateway A publishes; gateway B, in the same process, subscribes: B hears A (A is not
    B), while A's own source would ignore A's publications — nothing process-wide decides."""
    ep = free_endpoint()
    a = Gateway(config.parse({
        "sources": [{"type": "zenoh", "url": f"zenoh:{VEHICLE}@{ep}", "name": "a-in"}],
        "backends": {"zenoh": {"listen": [ep]}}}))
    b = Gateway(config.parse({
        "sources": [{"type": "zenoh", "url": f"zenoh:{VEHICLE}@{ep}", "name": "b-in"}],
        "backends": {}}))
    assert a.context.gateway_id != b.context.gateway_id
    got_b = Capture()
    b.dispatcher.add(got_b)
    got_a = Capture()
    a.dispatcher.add(got_a)
    a.start()
    b.start()
    try:
        zb = a.dispatcher.backends()[0]
        assert zb.wait_ready(20) and a.sources[0].ready.wait(20) and b.sources[0].ready.wait(20)
        m = first_sm_update()

        def b_heard_a() -> bool:
            send(zb, m)
            with got_b.cond:
                return any(isinstance(x, SmUpdate) for x in got_b.seen)

        assert wait_until(b_heard_a, interval=0.05), b.sources[0].stats()
        with got_b.cond:
            heard = [x for x in got_b.seen if isinstance(x, SmUpdate)]
        assert heard[0].via == f"zenoh:{a.context.gateway_id}"

        def a_ignored_its_own() -> bool:  # (B hearing a sample says nothing of when A's
            send(zb, m)                   # source gets it, or whether its subscription had
            return bool(a.sources[0].stats()["ignored_own"] >= 1)  # reached A's publisher)

        assert wait_until(a_ignored_its_own, interval=0.05), a.sources[0].stats()
        assert a.sources[0].stats()["emitted"] == 0
        assert not any(isinstance(x, SmUpdate) for x in got_a.seen)
    finally:
        b.stop()
        a.stop()


def test_a_router_coming_and_going_in_a_loop_costs_a_line_per_burst(backend, endpoint,
                                                                     caplog) -> None:
    import logging

    caplog.set_level(logging.INFO, logger="backends.zenoh.backend")
    n = 6
    for _ in range(n):  # a remote that says it is a router connects and leaves
        with zenoh.open(peer_config(connect=[endpoint], mode="router")):
            assert wait_until(lambda: backend.transports >= 1, 10)
        assert wait_until(lambda: backend.transports == 0, 10)

    def lines(text: str) -> int:
        return sum(text in r.getMessage() for r in caplog.records)

    assert wait_until(lambda: lines("lost a router") == 1, 5)
    assert lines("connected to a router") == 1  # the others are counted, one line per 10 s
    assert backend._transport_logs["router up"].events == n
