"""The MAVLink backend's and source's options, declared once (see :mod:`gateway.options`):
their schemas, their ``run`` flags (``--mavlink``, ``--mavlink-sysid``,
``--mavlink-signing-key``) and their documentation come from here.  A light module (the
``aurora_gateway.backend_options`` / ``source_options`` entry points): it imports neither
pymavlink nor the dialect, only the endpoint grammar (:mod:`gateway.io.endpoints`, standard
library), which checks every endpoint key and the ``--mavlink`` flag."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from gateway.io.endpoints import KINDS, list_validator, text_of, validator
from gateway.options import ConfigError, Flag, ListenerOptions, Options, lazy, option

#: The default endpoint: QGroundControl on this machine.
QGC_UDP = "udpout:127.0.0.1:14550"
#: MAV_COMP_ID_ONBOARD_COMPUTER: the source's component id towards the vehicle
MAV_COMP_ID_ONBOARD_COMPUTER = 191

#: Default stream rates (Hz).  Event-driven streams send at most this often (never faster than
#: the rocket's updates); 0 turns a stream off.  The ``*_hz`` options below.
DEFAULT_RATES: dict[str, float] = {
    "heartbeat_hz": 1.0,
    "sys_status_hz": 1.0,
    "extended_sys_state_hz": 1.0,
    "attitude_hz": 25.0,
    "altitude_hz": 10.0,
    "vfr_hud_hz": 10.0,
    "named_value_hz": 5.0,
    "position_hz": 5.0,
    "battery_hz": 2.0,
    "aurora_sm_update_hz": 50.0,
    "aurora_status_hz": 10.0,
    "radio_status_hz": 2.0,
    "rc_channels_hz": 10.0,
}


def _rate(key: str, help_text: str) -> float:
    rate: float = option(DEFAULT_RATES[key], help_text + " (Hz, 0 = off)", minimum=0,
                         maximum=1000)
    return rate


def _one_signing(options: MavlinkOptions | MavlinkSourceOptions) -> None:
    if options.signing_key_file and options.signing_passphrase:
        raise ConfigError("signing_key_file and signing_passphrase: give one, not both")


@dataclass(frozen=True, kw_only=True)
class MavlinkOptions(ListenerOptions):
    """``[backends.mavlink]``: the rocket to ground stations, and the router between them."""

    TITLE: ClassVar[str] = "MAVLink backend"
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = {"endpoints": [QGC_UDP]}
    endpoints: list[str] = option(
        [QGC_UDP], "endpoints: udpout:/udpin:/tcpin:/tcp:HOST:PORT, serial:DEVICE[,BAUD]",
        validator=list_validator(KINDS),
        flag=Flag("--mavlink", "MAVLink endpoint (repeatable; replaces the configured ones): "
                  "udpout:HOST:PORT, udpin:HOST:PORT, tcpin:HOST:PORT, tcp:HOST:PORT (IPv6 as "
                  f"[::1]:PORT), serial:DEVICE[,BAUD] (default {QGC_UDP}, QGroundControl on this "
                  "machine); with --source mavlink:ENDPOINT, the vehicle is routed to and "
                  "from them, as by mavlink-router", metavar="ENDPOINT",
                  convert=text_of(KINDS)))
    sysid: int = option(1, "MAVLink system id of the first vehicle (the first source's); the "
                        "next vehicles take the next ids (a source's mavlink_sysid fixes its "
                        "own); an id another system on the links uses is skipped (logged)",
                        minimum=1, maximum=254, flag=Flag("--mavlink-sysid", metavar="N"))
    compid: int = option(1, "component id (1 = autopilot: what QGroundControl needs)",
                         minimum=1, maximum=255)
    route: bool = option(True, "forward traffic between endpoints (mavlink-router style)")
    system_timeout_s: float = option(30.0, "a system silent this long is forgotten: its id "
                                     "counts as free again", minimum=1.0, maximum=3600.0)
    stale_after_s: float = option(3.0, "no update for this long: system status 'uninit'",
                                  minimum=0.1)
    pad_altitude_amsl_m: float = option(0.0, "pad altitude above mean sea level, added to "
                                        "the rocket's altitude above the pad for AMSL fields")
    signing_key_file: str = option(
        "", "MAVLink 2 signing key: 32 raw bytes or 64 hex digits",
        flag=Flag("--mavlink-signing-key", "sign MAVLink 2 traffic with this key file and "
                  "require signed commands", metavar="FILE"))
    signing_passphrase: str = option("", "MAVLink 2 signing passphrase (key = SHA-256 of it, "
                                     "as MAVProxy and QGroundControl derive it)", secret=True)
    serial_queue_depth: int = option(256, "frames queued per link (every endpoint kind)",
                                     minimum=1)
    tlog: str = option(
        "", "directory for MAVLink telemetry logs (.tlog): every frame the gateway routes or "
        "sends, both directions, once; one file per run and a new one when a vehicle starts "
        "a new flight (\"\" = none)",
        flag=Flag("--tlog", "write every MAVLink frame the gateway routes or sends, both "
                  "directions, as telemetry logs (.tlog, for QGroundControl, MAVExplorer, "
                  "mavlogdump.py) into DIR: one per run, a new one per flight",
                  metavar="DIR"))
    heartbeat_hz: float = _rate("heartbeat_hz", "HEARTBEAT")
    sys_status_hz: float = _rate("sys_status_hz", "SYS_STATUS")
    extended_sys_state_hz: float = _rate("extended_sys_state_hz", "EXTENDED_SYS_STATE")
    attitude_hz: float = _rate("attitude_hz", "ATTITUDE, at most")
    altitude_hz: float = _rate("altitude_hz", "ALTITUDE, at most")
    vfr_hud_hz: float = _rate("vfr_hud_hz", "VFR_HUD, at most")
    named_value_hz: float = _rate("named_value_hz", "NAMED_VALUE_FLOAT accel/accel_vert, at most")
    position_hz: float = _rate("position_hz", "GLOBAL_POSITION_INT/GPS_RAW_INT, at most")
    battery_hz: float = _rate("battery_hz", "BATTERY_STATUS, at most")
    aurora_sm_update_hz: float = _rate("aurora_sm_update_hz", "AURORA_SM_UPDATE, at most")
    aurora_status_hz: float = _rate("aurora_status_hz", "AURORA_STATUS, at most")
    radio_status_hz: float = _rate("radio_status_hz",
                                   "RADIO_STATUS from a radio's link statistics, at most")
    rc_channels_hz: float = _rate("rc_channels_hz", "RC_CHANNELS from the commands the rocket's "
                                  "link received, at most")

    def check(self) -> None:
        _one_signing(self)

    def rates(self) -> dict[str, float]:
        """The stream rates (the ``*_hz`` options), by option name."""
        return {key: getattr(self, key) for key in DEFAULT_RATES}


@dataclass(frozen=True, kw_only=True)
class MavlinkSourceOptions(Options):
    """``[[sources]] type = "mavlink"``: a MAVLink vehicle, the gateway as its companion."""

    url: str = option(help="the vehicle's endpoint: udpin:0.0.0.0:14551, "
                      "serial:/dev/ttyACM0,115200, tcp:HOST:5760 …", validator=validator(KINDS))
    endpoints: list[str] = option([], "more endpoints routed to and from the vehicle (a ground "
                                  "station sharing the link)",
                                  validator=list_validator(KINDS, minimum=0))
    sysid: int = option(0, "our system id towards the vehicle; 0 = automatic: 250, or the "
                        "next lower one nobody on the links uses", minimum=0, maximum=254)
    compid: int = option(MAV_COMP_ID_ONBOARD_COMPUTER, "our component id", minimum=1,
                         maximum=255)
    target_system: int = option(0, "the vehicle's system id; 0 = every autopilot heard, each "
                                "its own vehicle '<vehicle>-<system id>'", minimum=0,
                                maximum=255)
    rate_hz: float = option(10.0, "most vehicle-state and position messages per second",
                            minimum=0.1, maximum=1000)
    heartbeat_hz: float = option(1.0, "our heartbeat (ground stations are recognised by it); "
                                 "0 = none", minimum=0, maximum=10)
    request_streams: bool = option(True, "ask the vehicle for its telemetry and mode names")
    signing_key_file: str = option("", "MAVLink 2 signing key file")
    signing_passphrase: str = option("", "MAVLink 2 signing passphrase", secret=True)
    queue_depth: int = option(256, "frames queued per link", minimum=1)

    def check(self) -> None:
        _one_signing(self)


@dataclass(frozen=True, kw_only=True)
class TlogSourceOptions(Options):
    """``[[sources]] type = "tlog"``: a MAVLink telemetry log (``.tlog``) replayed as the
    vehicles it recorded."""

    TITLE: ClassVar[str] = "telemetry log source"
    path: str = option(help="telemetry log: each MAVLink frame after its 8-byte big-endian "
                       "UNIX time in microseconds (MAVProxy, QGroundControl, mavlink-router, "
                       "run --tlog, export --format tlog)",
                       validator=lazy("backends.mavlink.tlog_source:check_file"))
    speed: float = option(1.0, "1 = the recorded speed, N = N times faster, 0 = as fast as "
                          "possible", minimum=0,
                          flag=Flag("--tlog-speed", "replay --source tlog:FILE N times faster "
                                    "(0 = as fast as possible)", metavar="N"))
    loop: bool = option(False, "start again at the end")
    rate_hz: float = option(10.0, "most vehicle-state and position messages per second of "
                            "flight time", minimum=0.1, maximum=1000)
