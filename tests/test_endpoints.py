"""The one endpoint grammar (gateway/io/endpoints.py): every form it accepts, every mistake
with its exact text, arbitrary text never raising anything but EndpointError, the run flags
refusing a bad endpoint in one line with exit 2 before anything starts (the same words in a
configuration file and in check-config), IPv6 bound on [::1], and source URL prefixes taken
from the installed entry points."""

from __future__ import annotations

import contextlib
import importlib
import re
import socket
import subprocess
import sys
import textwrap
import uuid
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway import config, registry
from gateway.config import ConfigError
from gateway.io.endpoints import (
    KINDS,
    SERIAL,
    TCP,
    TCPIN,
    Endpoint,
    EndpointError,
    check_host,
    check_port,
    check_serial_port,
    list_validator,
    parse_address,
    parse_endpoint,
    usage,
)
from gateway.io.transport import open_tcp_listener, open_udp
from gateway.sources import parse_source_url

REPO = Path(__file__).resolve().parents[1]
STREAM = (TCPIN, TCP, SERIAL)

# -- what is accepted ------------------------------------------------------------------------------

ACCEPTED: list[tuple[str, dict[str, Any], Endpoint]] = [
    ("tcpin:0.0.0.0:5760", {}, Endpoint("tcpin", "0.0.0.0", 5760, text="tcpin:0.0.0.0:5760")),
    ("tcpin:5760", {}, Endpoint("tcpin", "0.0.0.0", 5760, text="tcpin:5760")),
    ("tcpin::5760", {}, Endpoint("tcpin", "0.0.0.0", 5760, text="tcpin::5760")),
    ("tcpin:[::1]:5760", {}, Endpoint("tcpin", "::1", 5760, text="tcpin:[::1]:5760")),
    ("tcpin:[fe80::1%eth0]:1", {}, Endpoint("tcpin", "fe80::1%eth0", 1,
                                              text="tcpin:[fe80::1%eth0]:1")),
    ("tcpin:localhost:0", {}, Endpoint("tcpin", "localhost", 0, text="tcpin:localhost:0")),
    ("TCPIN:gcs.local.:65535", {}, Endpoint("tcpin", "gcs.local.", 65535,
                                            text="TCPIN:gcs.local.:65535")),
    ("tcp:5760", {}, Endpoint("tcp", "127.0.0.1", 5760, text="tcp:5760")),
    ("tcp:my-gcs_2:5760", {}, Endpoint("tcp", "my-gcs_2", 5760, text="tcp:my-gcs_2:5760")),
    ("  udpin:14550 ", {}, Endpoint("udpin", "0.0.0.0", 14550, text="udpin:14550")),
    ("udp:[::]:14550", {}, Endpoint("udpin", "::", 14550, text="udp:[::]:14550")),
    ("udpout:10.0.0.255:14550", {}, Endpoint("udpout", "10.0.0.255", 14550,
                                             text="udpout:10.0.0.255:14550")),
    ("tcpin:9000", {"listen_host": "127.0.0.1"},
     Endpoint("tcpin", "127.0.0.1", 9000, text="tcpin:9000")),
    ("8080", {"bare": TCPIN, "listen_host": "127.0.0.1"},
     Endpoint("tcpin", "127.0.0.1", 8080, text="8080")),
    ("[::1]:8080", {"bare": TCPIN}, Endpoint("tcpin", "::1", 8080, text="[::1]:8080")),
    ("serial:/dev/ttyUSB0", {}, Endpoint("serial", device="/dev/ttyUSB0",
                                         text="serial:/dev/ttyUSB0")),
    ("serial:ttyS1,57600", {}, Endpoint("serial", device="ttyS1", baudrate=57600,
                                        text="serial:ttyS1,57600")),
    ("/dev/ttyACM0,115200", {}, Endpoint("serial", device="/dev/ttyACM0", baudrate=115200,
                                         text="/dev/ttyACM0,115200")),
    ("/dev/ttyACM0", {"default_baud": 57600}, Endpoint("serial", device="/dev/ttyACM0",
                                                       baudrate=57600, text="/dev/ttyACM0")),
    ("COM7", {}, Endpoint("serial", device="COM7", text="COM7")),
    ("com12,9600", {}, Endpoint("serial", device="com12", baudrate=9600, text="com12,9600")),
    ("loop://", {}, Endpoint("serial", device="loop://", text="loop://")),
    ("LOOP://", {}, Endpoint("serial", device="LOOP://", text="LOOP://")),
    ("socket://[::1]:7777", {}, Endpoint("serial", device="socket://[::1]:7777",
                                         text="socket://[::1]:7777")),
    ("rfc2217://host:2217?ign_set_control", {},
     Endpoint("serial", device="rfc2217://host:2217?ign_set_control",
              text="rfc2217://host:2217?ign_set_control")),
    ("serial:spy://loop://?file=/dev/null,9600", {},
     Endpoint("serial", device="spy://loop://?file=/dev/null", baudrate=9600,
              text="serial:spy://loop://?file=/dev/null,9600")),
    ("hwgrep://0403:6001", {}, Endpoint("serial", device="hwgrep://0403:6001",
                                        text="hwgrep://0403:6001")),
]


@pytest.mark.parametrize(("text", "options", "expected"), ACCEPTED, ids=[a[0] for a in ACCEPTED])
def test_every_form_is_accepted(text: str, options: dict[str, Any], expected: Endpoint) -> None:
    assert parse_endpoint(text, KINDS, **options) == expected


# -- every mistake, its exact words ----------------------------------------------------------------

MISTAKES: list[tuple[str, dict[str, Any], str]] = [
    ("", {}, "empty endpoint"),
    ("   ", {}, "empty endpoint"),
    ("tcpin:[::1", {}, "'tcpin:[::1': unclosed '['"),
    ("[::1", {"bare": TCPIN}, "'[::1': unclosed '['"),
    ("[::1", {}, "'[::1': unclosed '['"),
    ("tcpin:[::1]5760", {}, "'tcpin:[::1]5760': expected :PORT after ']'"),
    ("tcpin:[1.2.3.4]:5760", {}, "'tcpin:[1.2.3.4]:5760': invalid IPv6 address '1.2.3.4'"),
    ("tcpin:::1:5760", {}, "'tcpin:::1:5760': an IPv6 address needs brackets: [::1]:PORT"),
    ("tcp:fe80::1", {}, "'tcp:fe80::1': an IPv6 address needs brackets: [::1]:PORT"),
    ("tcpin:[::1]:x", {}, "'tcpin:[::1]:x': port 'x' is not a number"),
    ("host:abc", {"bare": TCPIN}, "'host:abc': port 'abc' is not a number"),
    ("tcp:host", {}, "'tcp:host': port 'host' is not a number"),
    ("tcp:host:-1", {}, "'tcp:host:-1': port '-1' is not a number"),
    ("tcp:host:", {}, "'tcp:host:': no port"),
    ("tcpin:host:99999", {}, "'tcpin:host:99999': port 99999 is out of range (0 to 65535)"),
    ("udpin:[::1]:65536", {}, "'udpin:[::1]:65536': port 65536 is out of range (0 to 65535)"),
    ("tcp:host:0", {}, "'tcp:host:0': port 0 is out of range (1 to 65535)"),
    ("udpout:h:123456789012", {}, "'udpout:h:123456789012': port 123456789012 is out of range "
                                  "(1 to 65535)"),
    ("tcpin:300.1.1.1:5760", {}, "'tcpin:300.1.1.1:5760': invalid IP address '300.1.1.1'"),
    ("tcp:1.2.3:5760", {}, "'tcp:1.2.3:5760': invalid IP address '1.2.3'"),
    ("tcp:bad host:5760", {}, "'tcp:bad host:5760': invalid host name 'bad host'"),
    ("tcp:-x:5760", {}, "'tcp:-x:5760': invalid host name '-x'"),
    ("udpot:127.0.0.1:14550", {}, "'udpot:127.0.0.1:14550': unknown kind 'udpot'"),
    ("udpot:127.0.0.1:14550", {"bare": TCPIN}, "'udpot:127.0.0.1:14550': unknown kind 'udpot'"),
    ("localhost:5760", {}, "'localhost:5760': no kind given"),
    ("nonsense", {}, "'nonsense': not an endpoint"),
    ("serial:,9600", {}, "'serial:,9600': no serial device"),
    ("/dev/ttyUSB0,fast", {}, "'/dev/ttyUSB0,fast': baud rate 'fast' is not a whole number "
                              "≥ 50"),
    ("COM3,10", {}, "'COM3,10': baud rate '10' is not a whole number ≥ 50"),
    ("nosuch://x", {}, "'nosuch://x': unknown URL scheme 'nosuch' (pyserial knows "),
    ("socket://host", {}, "'socket://host': no port"),
    ("socket://:7777", {}, "'socket://:7777': no host"),
    ("rfc2217://", {}, "'rfc2217://': rfc2217:// needs HOST:PORT"),
    ("socket://h:70000", {}, "'socket://h:70000': port 70000 is out of range (1 to 65535)"),
]


@pytest.mark.parametrize(("text", "options", "problem"), MISTAKES,
                         ids=[f"{m[0]!r}" for m in MISTAKES])
def test_every_mistake_has_its_one_text(text: str, options: dict[str, Any], problem: str) -> None:
    with pytest.raises(EndpointError) as info:
        parse_endpoint(text, KINDS, **options)
    message = str(info.value)
    assert "\n" not in message
    forms = f"; expected {usage(KINDS, options.get('bare'))}"
    if problem.endswith("knows "):  # the schemes are pyserial's: the start is ours
        assert message.startswith(problem) and message.endswith(forms), message
    else:
        assert message == problem + forms


def test_a_kind_the_caller_does_not_take_is_named() -> None:
    stream = "; expected " + usage(STREAM)
    for text, kind in (("udpin:1.2.3.4:5", "udpin"), ("udp:5", "udpin"),
                       ("udpout:h:1", "udpout")):
        with pytest.raises(EndpointError) as info:
            parse_endpoint(text, STREAM)
        assert str(info.value) == f"{text!r}: {kind} is not allowed here{stream}"
    net = "; expected " + usage((TCPIN,), TCPIN)
    for text in ("/dev/ttyUSB0", "loop://", "serial:x"):
        with pytest.raises(EndpointError) as info:
            parse_endpoint(text, (TCPIN,), bare=TCPIN)
        assert str(info.value) == f"{text!r}: serial is not allowed here{net}"


def test_the_accepted_forms_are_named() -> None:
    assert usage((TCPIN,), TCPIN) == "[HOST:]PORT or tcpin:[HOST:]PORT; IPv6 as [::1]:PORT"
    assert usage(STREAM) == (
        "tcpin:[HOST:]PORT, tcp:[HOST:]PORT or [serial:]DEVICE[,BAUD] (/dev/…, COMn or a "
        "pyserial URL: loop://, socket://HOST:PORT …); IPv6 as [::1]:PORT")
    assert usage((SERIAL,), serial_baud=False) == (
        "[serial:]DEVICE (/dev/…, COMn or a pyserial URL: loop://, socket://HOST:PORT …)")


def test_a_serial_key_with_its_own_baud_rate_refuses_one_in_the_url() -> None:
    check_serial_port("/dev/ttyUSB0")
    check_serial_port("socket://127.0.0.1:7777")
    with pytest.raises(EndpointError, match=r"^'localhost:5760': not an endpoint; expected "
                                            r"\[serial:\]DEVICE .*socket://HOST:PORT"):
        check_serial_port("localhost:5760")
    with pytest.raises(EndpointError, match=r"^'/dev/ttyUSB0,9600': no ,BAUD here: the baud "
                                            r"rate has its own key; expected \[serial:\]DEVICE "):
        check_serial_port("/dev/ttyUSB0,9600")


def test_a_list_needs_at_least_one_and_every_item_is_checked() -> None:
    check = list_validator(STREAM)
    check(["tcpin:0", "loop://"])
    with pytest.raises(EndpointError, match=r"^at least one endpoint is needed; expected tcpin:"):
        check([])
    with pytest.raises(EndpointError, match=r"^5 is not a string; expected tcpin:"):
        check(["tcpin:0", 5])
    with pytest.raises(EndpointError, match=r"^'tcp:h:x': port 'x' is not a number"):
        check(["tcp:h:x"])


def test_a_host_key_and_a_bare_address() -> None:
    for good in ("127.0.0.1", "::1", "fe80::1%eth0", "localhost", "0.0.0.0"):
        check_host(good)
    for bad, problem in (("", "empty host"), ("[::1]", "'[::1]': an IPv6 address goes without "
                                                        "brackets in a host key"),
                         ("300.1.1.1", "'300.1.1.1': invalid IP address '300.1.1.1'"),
                         ("a b", "'a b': invalid host name 'a b'")):
        with pytest.raises(EndpointError) as info:
            check_host(bad)
        assert str(info.value) == f"{problem}; expected a host name or an IP address"
    check_port(0)
    check_port(65535)
    for bad, problem in ((70000, "port 70000 is out of range (0 to 65535)"),
                         (-1, "port '-1' is not a number"), ("80", "port '80' is not a number")):
        with pytest.raises(EndpointError) as info:
            check_port(bad)
        assert str(info.value) == problem
    assert parse_address("[::1]:7447", default_host=None) == ("::1", 7447)
    with pytest.raises(EndpointError, match=r"^':7447': no host; expected HOST:PORT "):
        parse_address(":7447", default_host=None)


@settings(max_examples=400, deadline=None)
@given(st.text(max_size=40) | st.from_regex(
    r"(tcpin|tcp|udpin|udpout|udp|serial|socket|loop|x)?:?(//)?\[?[0-9a-f:.%]{0,12}\]?:?"
    r"[0-9a-z]{0,7}(,[0-9a-z]{0,4})?", fullmatch=True))
def test_arbitrary_text_parses_or_raises_the_one_error(text: str) -> None:
    for kinds, bare in ((KINDS, None), ((TCPIN,), TCPIN), ((SERIAL,), None)):
        try:
            ep = parse_endpoint(text, kinds, bare=bare)
        except EndpointError as exc:
            assert "\n" not in str(exc)
        else:
            assert ep.kind in kinds
            assert 0 <= ep.port <= 65535
            assert ep.text == text.strip()
    for check in (check_host, lambda t: parse_address(t, default_host=None)):
        with contextlib.suppress(EndpointError):  # and nothing else
            check(text)


# -- the command line, a file and check-config: one line, exit 2 -----------------------------------

DONE_WHEN = [
    (["--http", ""], "argument --http: empty endpoint; expected [HOST:]PORT"),
    (["--http", "[::1"], "argument --http: '[::1': unclosed '['; expected [HOST:]PORT"),
    (["--uavtalk", "tcpin:[::1]:x"],
     "argument --uavtalk: 'tcpin:[::1]:x': port 'x' is not a number; expected tcpin:"),
    (["--fprime", "tcpin:host:99999"],
     "argument --fprime: 'tcpin:host:99999': port 99999 is out of range (0 to 65535); "
     "expected tcpin:"),
    (["--foxglove", "host:abc"],
     "argument --foxglove: 'host:abc': port 'abc' is not a number; expected [HOST:]PORT"),
    (["--mavlink", "tcpin:300.1.1.1:5760"],
     "argument --mavlink: 'tcpin:300.1.1.1:5760': invalid IP address '300.1.1.1'; "
     "expected tcpin:"),
]


def _gateway(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "gateway", *argv], capture_output=True,
                          text=True, timeout=60, cwd=REPO)


@pytest.mark.parametrize(("flags", "expected"), DONE_WHEN, ids=[f[0][0] for f in DONE_WHEN])
def test_a_bad_endpoint_flag_is_one_line_and_exit_2(flags: list[str], expected: str) -> None:
    r = _gateway("run", "--duration", "30", *flags)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith(f"aurora-gateway run: {expected}"), lines[0]


BAD_FILES = [
    ('[backends.uavtalk]\nendpoints = ["tcpin:[::1]:x"]\n', "backends.uavtalk.endpoints",
     "'tcpin:[::1]:x': port 'x' is not a number; expected tcpin:"),
    ('[backends.fprime]\nendpoints = ["tcpin:host:99999"]\n', "backends.fprime.endpoints",
     "'tcpin:host:99999': port 99999 is out of range (0 to 65535); expected tcpin:"),
    ('[backends.mavlink]\nendpoints = ["tcpin:300.1.1.1:5760"]\n', "backends.mavlink.endpoints",
     "'tcpin:300.1.1.1:5760': invalid IP address '300.1.1.1'; expected tcpin:"),
    ('[backends.http]\nhost = "[::1"\n', "backends.http.host",
     "'[::1': an IPv6 address goes without brackets in a host key"),
    ('[[sources]]\ntype = "mavlink"\nurl = "udpin:[::1]:x"\n', "sources[0].url",
     "'udpin:[::1]:x': port 'x' is not a number; expected tcpin:"),
    ('[[sources]]\ntype = "serial"\nurl = "socket://h:x"\n', "sources[0].url",
     "'socket://h:x': port 'x' is not a number; expected [serial:]DEVICE"),
    ('[backends.zenoh]\nconnect = ["tcp/[::1:7447"]\n', "backends.zenoh.connect",
     "'tcp/[::1:7447': '[::1:7447': unclosed '['; expected HOST:PORT"),
]


@pytest.mark.parametrize(("toml", "key", "expected"), BAD_FILES, ids=[b[1] for b in BAD_FILES])
def test_the_same_mistake_in_a_file_names_the_key(tmp_path: Path, toml: str, key: str,
                                                  expected: str) -> None:
    path = tmp_path / "gw.toml"
    path.write_text(toml)
    for command in (["run", "--config", str(path), "--duration", "30"],
                    ["check-config", str(path)]):
        r = _gateway(*command)
        assert r.returncode == 2, r.stderr
        lines = r.stderr.splitlines()
        assert len(lines) == 1, r.stderr
        assert re.match(rf"aurora-gateway(: | check-config: \S+: ){re.escape(key)}: ",
                        lines[0]), lines[0]
        assert expected in lines[0], lines[0]


def test_every_endpoint_flag_uses_the_grammar(capsys: pytest.CaptureFixture[str]) -> None:
    """The same mistake gives the same words through every flag that takes an address."""
    from gateway.commands.cli import build_parser

    parser = build_parser()
    cases = [(flag, "tcpin:h:x", "'tcpin:h:x': port 'x' is not a number; expected ")
             for flag in ("--http", "--foxglove", "--mavlink", "--uavtalk", "--fprime")]
    cases += [(flag, "nosuch://x", "'nosuch://x': unknown URL scheme 'nosuch' (pyserial knows ")
              for flag in ("--hc12", "--xbee", "--crsf")]
    cases += [(flag, "tcp/h:x", "'tcp/h:x': 'h:x': port 'x' is not a number; expected ")
              for flag in ("--zenoh-connect", "--zenoh-listen")]
    for flag, value, words in cases:
        with pytest.raises(SystemExit) as info:
            parser.parse_args(["run", flag, value])
        assert info.value.code == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"argument {flag}: {words}" in err, err
    args = parser.parse_args(["run", "--crsf", "pty", "--hc12", "loop://", "--http", "[::1]:0",
                              "--mavlink", "udp:[::1]:0", "--zenoh-listen", "tcp/[::1]:0"])
    # a flag holds what its key will (the options declarations): the text the grammar
    # accepted, or the host and port keys --http sets
    assert (args.crsf, args.hc12, args.http["host"], parse_endpoint(args.mavlink[0]).kind) == (
        "pty", "loop://", "::1", "udpin")
    assert (args.http["port"], args.mavlink, args.zenoh_listen) == (
        0, ["udp:[::1]:0"], ["tcp/[::1]:0"])


# -- IPv6 bound where it says ----------------------------------------------------------------------

def _has_v6_loopback() -> bool:
    if not socket.has_ipv6:
        return False
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_STREAM) as s:
            s.bind(("::1", 0))
    except OSError:
        return False
    return True


needs_v6 = pytest.mark.skipif(not _has_v6_loopback(), reason="no IPv6 loopback on this machine")


@needs_v6
def test_tcpin_on_v6_loopback_binds_there() -> None:
    ep = parse_endpoint("tcpin:[::1]:0", STREAM)
    server = open_tcp_listener(ep.host, ep.port)
    try:
        host, port = server.getsockname()[:2]
        assert (server.family, host) == (socket.AF_INET6, "::1")
        with socket.create_connection(("::1", port), timeout=5) as client:
            server.setblocking(True)
            server.settimeout(5)
            conn, peer = server.accept()
            client.sendall(b"ping")
            assert conn.recv(4) == b"ping" and peer[0] == "::1"
            conn.close()
    finally:
        server.close()


@needs_v6
def test_udpin_on_v6_loopback_binds_there() -> None:
    ep = parse_endpoint("udpin:[::1]:0")
    port = open_udp(ep.host, ep.port, listen=True)
    try:
        host, bound = port.address()[:2]
        assert (port.sock.family, host) == (socket.AF_INET6, "::1")
        with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as peer:
            peer.sendto(b"ping", ("::1", bound))
            port.sock.settimeout(5)
            assert port.sock.recvfrom(16)[0] == b"ping"
    finally:
        port.close()


@needs_v6
def test_a_backend_given_a_v6_tcpin_endpoint_serves_on_it() -> None:
    """--uavtalk tcpin:[::1]:0 end to end: the backend's listener is on ::1 and takes a GCS."""
    from backends.uavtalk.backend import UavtalkBackend
    from backends.uavtalk.options import UavtalkOptions
    from gateway.backend import GatewayContext
    from gateway.dispatcher import Dispatcher

    d = Dispatcher()
    b = UavtalkBackend(UavtalkOptions(endpoints=["tcpin:[::1]:0"]))
    b.attach(GatewayContext(emit=d.dispatch))
    d.add(b)
    d.start()
    try:
        host, port = b.address()[:2]
        assert host == "::1"
        with socket.create_connection(("::1", port), timeout=5) as gcs:
            assert gcs.family == socket.AF_INET6
    finally:
        d.close()


# -- source URLs: the prefixes are the installed entry points --------------------------------------

def test_source_urls_built_in() -> None:
    assert parse_source_url("sim") == ("sim", {})
    assert parse_source_url("replay:f.aur") == ("replay", {"path": "f.aur"})
    assert parse_source_url("mavlink:udpin:0.0.0.0:14551") == (
        "mavlink", {"url": "udpin:0.0.0.0:14551"})
    assert parse_source_url("zenoh:rocket1@tcp/h:1") == ("zenoh", {"url": "zenoh:rocket1@tcp/h:1"})
    assert parse_source_url("serial:/dev/ttyUSB0") == ("serial", {"url": "/dev/ttyUSB0"})
    assert parse_source_url("/dev/ttyUSB0") == ("serial", {"url": "/dev/ttyUSB0"})
    assert parse_source_url("loop://") == ("serial", {"url": "loop://"})
    assert parse_source_url("COM3") == ("serial", {"url": "COM3"})
    with pytest.raises(ValueError, match=r"^no source 'warp'; expected NAME\[:…\] "
                                         r"for a source \(mavlink, replay, serial, sim"):
        parse_source_url("warp:9")
    with pytest.raises(ValueError, match=r"^empty source URL"):
        parse_source_url("")
    with pytest.raises(ValueError, match="sim takes nothing"):
        parse_source_url("sim:x")


def test_a_plugin_source_is_a_url_prefix(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    tag = uuid.uuid4().hex[:8]
    name = f"radar{tag}"
    (tmp_path / f"{name}_mod.py").write_text(textwrap.dedent("""
        from gateway.config import Key, Schema
        from gateway.sources import Source
        class RadarSource(Source):
            CONFIG = Schema(url=Key(str, "", "where"))
            def __init__(self, name=None, url=""):
                super().__init__(name)
                self.url = url
    """))
    dist = tmp_path / f"aurora_radar_{tag}-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: aurora-radar-{tag}\n"
                                   "Version: 1.0\n")
    (dist / "entry_points.txt").write_text(
        f"[aurora_gateway.sources]\n{name} = {name}_mod:RadarSource\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    registry._installed.cache_clear()
    try:
        assert parse_source_url(f"{name}:dish-2") == (name, {"url": "dish-2"})
        part = config.make_source(name, {"url": "dish-2"}, None, "--source[0]")
        assert part.cls.__name__ == "RadarSource"
    finally:
        registry._installed.cache_clear()
        sys.modules.pop(f"{name}_mod", None)


def test_entry_points_are_read_once(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[int] = []
    real = registry._read_entry_points

    def counting() -> Any:
        calls.append(1)
        return real()

    monkeypatch.setattr(registry, "_read_entry_points", counting)
    registry._installed.cache_clear()
    try:
        for _ in range(3):
            registry.source_names()
            registry.backend_names()
            registry.names(registry.COMMAND_GROUP)
        assert calls == [1]  # one scan of the installed distributions for every group
    finally:
        registry._installed.cache_clear()


def test_entry_points_are_those_importlib_metadata_finds() -> None:
    """The registry's own scan (no importlib.metadata import at start-up) finds what the
    standard library finds, in every group of every distribution installed here."""
    from importlib.metadata import entry_points

    found = registry._read_entry_points()
    assert found is not None
    groups = set(found) | {registry.BACKEND_GROUP, registry.SOURCE_GROUP,
                           registry.COMMAND_GROUP, registry.BACKEND_OPTIONS_GROUP,
                           registry.SOURCE_OPTIONS_GROUP}
    for group in groups:
        expected = sorted((ep.name, ep.value) for ep in entry_points(group=group))
        assert sorted(found.get(group, ())) == expected, group
    assert registry.names(registry.BACKEND_GROUP)["mavlink"]  # the project's own, installed


def test_where_the_scan_cannot_read_a_path_the_standard_library_reads_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    scanned = registry._installed()
    monkeypatch.setattr(registry, "_read_entry_points", lambda: None)  # as for a zip on the path
    registry._installed.cache_clear()
    try:
        assert registry._installed() == scanned
    finally:
        registry._installed.cache_clear()


def test_a_config_error_is_a_value_error() -> None:
    """EndpointError is a ValueError: Key validators turn it into a ConfigError naming the key."""
    with pytest.raises(ConfigError, match=r"^backends\.uavtalk\.endpoints: 'x': not an endpoint"):
        config.parse({"backends": {"uavtalk": {"endpoints": ["x"]}}})
