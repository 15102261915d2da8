"""Fleets: a router, gateways as separate processes (the real CLI), subscribers; a router
restart; access control; the ``listen`` tool.  Every process is started on free loopback
ports by the test and stopped in ``finally``."""

from __future__ import annotations

import itertools
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import ROOT as REPO
from helpers import post
from zenoh_peer import (
    Recorder,
    RouterProcess,
    free_endpoint,
    free_port,
    peer_config,
    serving,
    stop_process,
    wait_for_gateway,
)

from backends.zenoh.options import ZenohOptions

zenoh = pytest.importorskip("zenoh")

from backends.zenoh.backend import ZenohBackend  # noqa: E402
from backends.zenoh.session import SessionOptions  # noqa: E402
from gateway import registry  # noqa: E402
from gateway.flight import FlightModel  # noqa: E402
from gateway.model import SmUpdate  # noqa: E402
from gateway.sources.sim import flight_messages  # noqa: E402

ENV = {**os.environ, "PYTHONPATH": str(REPO)}
RATE_HZ = 50
START_S = 90.0  # cold start of two Python gateways on a loaded 2-core machine
RESUME_BOUND_S = 20.0


def gateway_process(tmp_path: Path, vehicle: str, *flags: str) -> subprocess.Popen:
    """``aurora-gateway run`` with the simulated flight and only the Zenoh backend."""
    cfg = tmp_path / f"{vehicle}.toml"
    cfg.write_text(f'[gateway]\nstatus_interval_s = 0\n\n[[sources]]\ntype = "sim"\n'
                   f'vehicle = "{vehicle}"\nrate_hz = {RATE_HZ}.0\nstatus_hz = 2.0\n\n'
                   f'[backends.zenoh]\ngateway_id = "gw-{vehicle}"\n')
    log = (tmp_path / f"{vehicle}.log").open("w")
    cmd = [sys.executable, "-m", "gateway", "run", "-c", str(cfg), *flags]
    return subprocess.Popen(cmd, cwd=REPO, env=ENV, stdout=subprocess.DEVNULL, stderr=log)


def logs(tmp_path: Path) -> str:
    return "\n".join(f"--- {p.name}\n{p.read_text()}" for p in sorted(tmp_path.glob("*.log")))


def sm_updates(rec: Recorder, vehicle: str):
    return rec.matching(f"aurora/{vehicle}/sm_update")


def test_fleet_survives_a_router_restart(tmp_path, capsys):
    """Two gateways (clients) and a subscriber meet at a router; the router is killed and
    started again: both gateways resume on their own, and only the outage is lost."""
    vehicles = ("rocket1", "rocket2")
    router = RouterProcess()
    gateways: list[subprocess.Popen] = []
    sub = None
    try:
        router.start()
        ep = router.endpoint
        gateways = [gateway_process(tmp_path, v, "--zenoh-mode", "client", "--zenoh-connect",
                                    ep) for v in vehicles]
        sub = zenoh.open(peer_config(connect=[ep], mode="client"))
        rec = Recorder()
        sub.declare_subscriber("aurora/**", rec)  # one subscription sees the whole fleet

        def each_has(n: int, after: float = 0.0):
            return lambda _: all(sum(s.rx > after for s in sm_updates(rec, v)) >= n
                                 for v in vehicles)

        assert rec.wait_for(each_has(25), START_S), logs(tmp_path)
        assert {s.key.split("/")[1] for s in rec.snapshot()} == set(vehicles)

        router.kill()  # a crash: SIGKILL
        t_kill = time.monotonic()
        router.start()
        t_back = router.started_at
        assert rec.wait_for(each_has(25, after=t_back), RESUME_BOUND_S + 30), logs(tmp_path)
    finally:
        for p in gateways:
            stop_process(p)
        if sub is not None:
            sub.close()
        router.stop()
    assert all(p.returncode == 0 for p in gateways), logs(tmp_path)

    report = [f"router restart: outage {t_back - t_kill:.2f} s (kill → listening again)"]
    for v in vehicles:
        got = sm_updates(rec, v)
        assert {s.gateway for s in got} == {f"gw-{v}"}
        seqs = [s.seq for s in got]
        steps = [b - a for a, b in itertools.pairwise(seqs)]
        assert all(d >= 1 for d in steps), "duplicated or reordered updates"
        gaps = [i for i, d in enumerate(steps) if d > 1]
        assert len(gaps) <= 1, f"{v}: updates lost outside the outage: {gaps}"
        first_after = next(s for s in got if s.rx > t_back)
        resume = first_after.rx - t_back
        assert resume < RESUME_BOUND_S
        lost = 0
        if gaps:
            before, after = got[gaps[0]], got[gaps[0] + 1]
            assert before.rx <= t_back < after.rx, "the gap is not the outage"
            lost = after.seq - before.seq - 1
            flight_s = (after.json()["timestamp_ms"] - before.json()["timestamp_ms"]) / 1000
            report.append(f"{v}: resumed {resume:.2f} s after the router was back; lost "
                          f"{lost} updates (seq {before.seq + 1}..{after.seq - 1}, "
                          f"{flight_s:.2f} s of flight at {RATE_HZ} Hz); "
                          f"{len(got)} received, none lost before or after")
        else:
            report.append(f"{v}: resumed {resume:.2f} s after the router was back; nothing "
                          f"lost; {len(got)} received")
    with capsys.disabled():
        print("\n" + "\n".join(report))


# -- access control ----------------------------------------------------------------------------

ACL_CONFIG = REPO / "examples" / "zenoh-router-acl.json5"
CREDENTIALS = dict(line.split(":", 1) for line in
                   (REPO / "examples" / "zenoh-credentials.txt").read_text().split())


def credentials(user: str) -> dict[str, str]:
    return {"user": user, "password": CREDENTIALS[user]}


def test_acl_dashboards_may_subscribe_but_not_publish():
    router = RouterProcess(config=ACL_CONFIG)
    gw = None
    sessions = []
    try:
        router.start()
        ep = router.endpoint
        with pytest.raises(zenoh.ZError):  # no valid credentials, no session
            SessionOptions(mode="client", connect=[ep], user="dashboard",
                           password="wrong").open()
        gw = serving(ZenohBackend(ZenohOptions(mode="client", connect=[ep], gateway_id="gw",
                                               **credentials("gateway"))), "rocket1")
        gw.init()
        assert gw.wait_ready(20)
        dash_opts = SessionOptions(mode="client", connect=[ep], **credentials("dashboard"))
        dashboard, observer = dash_opts.open(), dash_opts.open()
        sessions += [dashboard, observer]
        seen = Recorder()
        observer.declare_subscriber("aurora/**", seen)
        wait_for_gateway(observer, "aurora", "rocket1")

        # A dashboard forges an update.  When its query (sent after the put, on the same
        # link) has been answered, the router has dealt with the put.
        dashboard.put("aurora/rocket1/sm_update", b'{"forged": true}')
        wait_for_gateway(dashboard, "aurora", "rocket1")
        # The gateway publishes afterwards; had the router forwarded the forgery, the
        # observer would have received it first.
        m = next(m for _, m in flight_messages(FlightModel(), 10, 0, 1)
                 if isinstance(m, SmUpdate))._replace(vehicle="rocket1")
        post(gw, m)
        assert seen.wait_for(lambda s: any(x.gateway == "gw" for x in s), 20)
        assert [x.payload for x in seen.snapshot() if b"forged" in x.payload] == []
        assert all(x.gateway == "gw" for x in seen.snapshot())
    finally:
        for s in sessions:
            s.close()
        if gw is not None:
            gw.close()
        router.stop()


# -- the listen tool ---------------------------------------------------------------------------

def listen(ep: str, *args: str, timeout: float = 60.0) -> tuple[list[dict], str]:
    cmd = [sys.executable, "-m", "backends.zenoh.cli", "listen", "--connect", ep, *args]
    done = subprocess.run(cmd, cwd=REPO, env=ENV, capture_output=True, text=True,
                          timeout=timeout, check=False)
    assert done.returncode == 0, done.stderr
    return [json.loads(line) for line in done.stdout.splitlines()], done.stderr


def test_default_run_publishes_and_listen_shows_the_flight(tmp_path):
    """The embedded default run (its Zenoh port moved to a free one) and ``listen``."""
    ep = free_endpoint()
    others = [f"--disable={n}" for n in registry.backend_names() if n != "zenoh"]
    log = (tmp_path / "gateway.log").open("w")
    gw = subprocess.Popen([sys.executable, "-m", "gateway", "run", "--zenoh-listen", ep,
                           "--sim-speed", "5", "--status-interval", "0", *others],
                          cwd=REPO, env=ENV, stdout=subprocess.DEVNULL, stderr=log)
    try:
        lines, err = listen(ep, "--count", "40")
        assert len(lines) == 40
        # the embedded default's source, sim, is vehicle "sim": aurora/sim/…
        assert all(x["vehicle"] == "sim" and x["key"].startswith("aurora/sim/")
                   for x in lines)
        sm = [x for x in lines if x["kind"] == "sm_update"]
        assert sm and all(x["value"]["state_name"] in ("IDLE", "ARMED", "BOOST") for x in sm)
        live = [x["seq"] for x in sm if not x.get("latest")]
        assert live == sorted(live) and len(set(live)) == len(live)
        assert "0 lost" in err
        raw, _ = listen(ep, "aurora/**", "--no-query", "--count", "30")
        frames = [x for x in raw if x["kind"] == "raw"]
        assert frames and all(x["value"]["type"] in (1, 2) and x["hex"].startswith("a55a")
                              for x in frames)
        seen, _ = listen(ep, "--gateways", "--no-query", "--count", "1")
        tokens = [x for x in seen if "gateway_token" in x]
        assert tokens and tokens[0]["alive"] is True
        assert tokens[0]["gateway_token"].startswith("aurora/sim/gateway/")
    finally:
        stop_process(gw)
    assert gw.returncode == 0, (tmp_path / "gateway.log").read_text()


# -- TLS ---------------------------------------------------------------------------------------

def make_certificates(d: Path) -> None:
    """A throw-away CA and two certificates it signs (router, gateway), for localhost."""
    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True)

    run("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
        "-keyout", "ca.key", "-out", "ca.pem", "-days", "2", "-subj", "/CN=Aurora test CA")
    for name in ("router", "gateway"):
        run("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
            "-keyout", f"{name}.key", "-out", f"{name}.csr", "-subj", f"/CN={name}")
        (d / f"{name}.ext").write_text(
            "subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
            "keyUsage=digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\n")
        run("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
            "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile", f"{name}.ext")


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")
def test_mutual_tls_between_gateway_and_router(tmp_path):
    make_certificates(tmp_path)

    def tls(name: str) -> dict[str, object]:
        return {"tls_root_ca": str(tmp_path / "ca.pem"),
                "tls_certificate": str(tmp_path / f"{name}.pem"),
                "tls_private_key": str(tmp_path / f"{name}.key"), "tls_mtls": True}

    ep = f"tls/localhost:{free_port()}"
    router = SessionOptions(mode="router", listen=[ep], **tls("router")).open()
    gw = sub = None
    try:
        with pytest.raises(zenoh.ZError):  # no client certificate: refused
            SessionOptions(mode="client", connect=[ep],
                           tls_root_ca=str(tmp_path / "ca.pem")).open()
        gw = serving(ZenohBackend(ZenohOptions(mode="client", connect=[ep], **tls("gateway"))),
                     "rocket1")
        gw.init()
        assert gw.wait_ready(20)
        sub = SessionOptions(mode="client", connect=[ep], **tls("gateway")).open()
        rec = Recorder()
        sub.declare_subscriber("aurora/**", rec)
        wait_for_gateway(sub, "aurora", "rocket1")
        m = next(m for _, m in flight_messages(FlightModel(), 10, 0, 1)
                 if isinstance(m, SmUpdate))._replace(vehicle="rocket1")
        post(gw, m)
        assert rec.wait_for(lambda s: any(x.key == "aurora/rocket1/sm_update" for x in s))
    finally:
        if sub is not None:
            sub.close()
        if gw is not None:
            gw.close()
        router.close()
