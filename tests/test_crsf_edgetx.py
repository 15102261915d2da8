"""What an EdgeTX radio shows for what the CRSF backend sends.

:class:`EdgeTxRadio` is written here, independently of ``backends.crsf``, from the EdgeTX
semantics in ``shared/specs/crsf.md`` (and EdgeTX's ``crossfire.cpp``): its own bitwise CRC,
big-endian fields, a field whose bytes are all 0xFF ignored, attitude shown as value / 10
(truncated: milliradians), the packed barometric altitude, GPS altitude − 1000, the
flight-mode text cut at ``min(16, len)`` (13 characters; without a NUL the last one is lost).
Sensors keep EdgeTX's integer value and precision.  The end-to-end tests reuse it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from backends.crsf.backend import CrsfBackend
from backends.crsf.frames import (
    FRAME_ATTITUDE,
    FRAME_BARO_ALTITUDE,
    FRAME_BATTERY,
    FRAME_FLIGHT_MODE,
    FRAME_GPS,
    FRAME_VARIO,
    FRAME_VOLTAGES,
    Attitude,
    BaroAltitude,
    Battery,
    FlightMode,
    Gps,
    Temperatures,
    Vario,
    Voltages,
    encode,
)
from backends.crsf.options import CrsfOptions
from gateway.model import Battery as ModelBattery
from gateway.model import Position, SmUpdate, Status, VehicleState

# -- the radio ---------------------------------------------------------------------------------

SYNCS = (0xC8, 0xEA, 0xEC)


def crc8_dvb_s2(data: bytes) -> int:
    """Bitwise CRC-8, polynomial 0xD5, init 0, MSB first."""
    c = 0
    for b in data:
        c ^= b
        for _ in range(8):
            c = ((c << 1) ^ 0xD5) & 0xFF if c & 0x80 else (c << 1) & 0xFF
    return c


def field_value(buf: bytes, index: int, size: int, signed: bool) -> int | None:
    """EdgeTX's getCrossfireTelemetryValue: None when every byte is 0xFF."""
    raw = buf[index:index + size]
    if all(b == 0xFF for b in raw):
        return None
    v = -1 if signed and raw[0] & 0x80 else 0
    for b in raw:
        v = (v << 8) | b
    return v


def c_div(a: int, b: int) -> int:
    """C integer division, truncating toward zero."""
    q = abs(a) // abs(b)
    return q if (a < 0) == (b < 0) else -q


@dataclass
class EdgeTxRadio:
    """Sensor name → (integer value, precision) as EdgeTX stores it; ``FM`` → text."""

    sensors: dict[str, Any] = field(default_factory=dict)
    history: list[tuple[str, Any]] = field(default_factory=list)
    buf: bytearray = field(default_factory=bytearray)
    crc_errors: int = 0
    #: the attitude frames' raw fields (100 µrad) before EdgeTX divides them by 10
    raw_attitude: list[tuple[int | None, ...]] = field(default_factory=list)

    def feed(self, data: bytes) -> None:
        self.buf += data
        while True:
            while self.buf and self.buf[0] not in SYNCS:
                del self.buf[0]
            if len(self.buf) < 2:
                return
            n = self.buf[1]
            if not 2 <= n <= 62:
                del self.buf[0]
                continue
            if len(self.buf) < n + 2:
                return
            frame = bytes(self.buf[:n + 2])
            if crc8_dvb_s2(frame[2:-1]) != frame[-1]:
                self.crc_errors += 1
                del self.buf[0]
                continue
            del self.buf[:n + 2]
            self.process(frame)

    def _set(self, name: str, value: Any) -> None:
        self.sensors[name] = value
        self.history.append((name, value))

    def process(self, rx: bytes) -> None:
        length, ftype = rx[1], rx[2]
        if ftype == 0x07:
            v = field_value(rx, 3, 2, True)
            if v is not None:
                self._set("VSpd", v)  # cm/s, precision 2
        elif ftype == 0x09:
            v = field_value(rx, 3, 2, False)
            if v is not None:
                self._set("Alt", (v & 0x7FFF) * 100 if v & 0x8000 else (v - 10000) * 10)
            if length > 5:
                v = field_value(rx, 5, 2, True)
                if v is not None:
                    self._set("VSpd", v)
        elif ftype == 0x02:
            for name, idx, size, signed, conv in (
                    ("Lat", 3, 4, True, lambda v: c_div(v, 10)),  # 1e-6 degrees
                    ("Lon", 7, 4, True, lambda v: c_div(v, 10)),
                    ("GSpd", 11, 2, False, lambda v: v),  # 0.1 km/h
                    ("Hdg", 13, 2, False, lambda v: v),  # 0.01 degrees
                    ("GAlt", 15, 2, False, lambda v: v - 1000),  # metres
                    ("Sats", 17, 1, False, lambda v: v)):
                v = field_value(rx, idx, size, signed)
                if v is not None:
                    self._set(name, conv(v))
        elif ftype == 0x08:
            for name, idx, size in (("RxBt", 3, 2), ("Curr", 5, 2), ("Capa", 7, 3),
                                    ("Bat%", 10, 1)):
                v = field_value(rx, idx, size, False)
                if v is not None:
                    self._set(name, v)
        elif ftype == 0x1E:
            self.raw_attitude.append(tuple(field_value(rx, i, 2, True) for i in (3, 5, 7)))
            for name, idx in (("Ptch", 3), ("Roll", 5), ("Yaw", 7)):
                v = field_value(rx, idx, 2, True)
                if v is not None:
                    self._set(name, c_div(v, 10))  # milliradians, precision 3
        elif ftype == 0x21:
            text_end = min(16, length)
            text = bytes(rx[3:text_end]).split(b"\0", 1)[0]
            self._set("FM", text.decode("ascii"))
        elif ftype == 0x0A:
            v = field_value(rx, 3, 2, False)
            if v is not None:
                self._set("ASpd", v)
        elif ftype == 0x0D:
            for i in range((length - 3) // 2):  # EdgeTX: while i * 2 < len - 4
                v = field_value(rx, 4 + 2 * i, 2, True)
                if v is not None:
                    self._set(f"Tmp{rx[3]}.{i}", v)  # 0.1 °C
        elif ftype == 0x0E and rx[3] >= 128:
            for i in range((length - 3) // 2):
                v = field_value(rx, 4 + 2 * i, 2, False)
                if v is not None:
                    self._set(f"Volt{i}", c_div(v, 10))  # 0.01 V

    def texts(self) -> list[str]:
        """Flight-mode texts in order, repeats collapsed."""
        out: list[str] = []
        for name, v in self.history:
            if name == "FM" and (not out or out[-1] != v):
                out.append(v)
        return out


def show(frame: bytes) -> dict[str, Any]:
    radio = EdgeTxRadio()
    radio.feed(frame)
    assert radio.crc_errors == 0
    return radio.sensors


# -- the spec's vectors as the radio shows them ------------------------------------------------

SPEC_SHOWN = [
    ("C8 0A 08 00 21 01 28 00 04 D2 43 B2", {"RxBt": 33, "Curr": 296, "Capa": 1234, "Bat%": 67}),
    ("C8 08 1E 2E 39 65 EC 85 5A 05", {"Ptch": 1183, "Roll": 2609, "Yaw": -3139}),
    ("C8 11 02 21 60 EC 00 61 27 D3 80 02 4B 39 C6 0D 11 09 6B",
     {"Lat": 56_000_000, "Lon": 163_000_000, "GSpd": 587, "Hdg": 14790, "GAlt": 2345,
      "Sats": 9}),
    ("C8 08 21 41 43 52 4F 2A 00 14", {"FM": "ACRO*"}),
    ("C8 04 07 00 FA F1", {"VSpd": 250}),
    ("C8 06 09 2B E2 FF 6A 66", {"Alt": 12340, "VSpd": -150}),
    ("C8 04 0A 03 84 39", {"ASpd": 900}),
    ("C8 07 0D 01 00 FA FF CE 1F", {"Tmp1.0": 250, "Tmp1.1": -50}),
    ("EC 0A 08 00 00 00 00 00 00 00 00 6D", {"RxBt": 0, "Curr": 0, "Capa": 0, "Bat%": 0}),
    ("EC 08 1E 00 00 00 00 00 00 30", {"Ptch": 0, "Roll": 0, "Yaw": 0}),
]


@pytest.mark.parametrize(("hexbytes", "expected"), SPEC_SHOWN, ids=[h[:8] for h, _ in SPEC_SHOWN])
def test_radio_reads_the_spec_vectors(hexbytes: str, expected: dict[str, Any]) -> None:
    assert show(bytes.fromhex(hexbytes)) == expected


def test_radio_crc_check_value() -> None:
    assert crc8_dvb_s2(b"123456789") == 0xBC


# -- what the encoder sends shows the right values -----------------------------------------

def wrapped(a: float) -> float:
    return math.remainder(a, 2 * math.pi)


@given(st.floats(-50, 50), st.floats(-50, 50), st.floats(-50, 50))
def test_attitude_shows_milliradians_wrapped(p: float, r: float, y: float) -> None:
    s = show(encode(Attitude(p, r, y)))
    for name, v in (("Ptch", p), ("Roll", r), ("Yaw", y)):
        # 100 µrad on the wire (±1 step if nudged), then truncated to mrad by the radio
        assert abs(s[name] / 1000 - wrapped(v)) <= 0.001 + 0.0002, name
        assert -3142 <= s[name] <= 3142


@given(st.floats(-1000, 2276.7), st.floats(-327, 327))
def test_baro_altitude_shows_decimetres_below_2276_m(alt: float, vs: float) -> None:
    s = show(encode(BaroAltitude(alt, vs)))
    assert abs(s["Alt"] / 100 - alt) <= 0.05 + 1e-9
    assert abs(s["VSpd"] / 100 - vs) <= 0.01 + 1e-9  # ±1 step only when nudged off 0xFFFF


@given(st.floats(2277, 32766))
def test_baro_altitude_shows_metres_above(alt: float) -> None:
    s = show(encode(BaroAltitude(alt, 0.0)))
    assert abs(s["Alt"] / 100 - alt) <= 0.5 + 1e-9


@pytest.mark.parametrize("cms", [-1, -2, -256, -257, 0, 1, -32768])
def test_negative_vertical_speeds_are_not_swallowed(cms: int) -> None:
    """−1 cm/s would be 0xFFFF, which EdgeTX ignores: it is nudged and still shows."""
    for rec in (Vario(cms / 100), BaroAltitude(10.0, cms / 100)):
        s = show(encode(rec))
        assert "VSpd" in s
        assert abs(s["VSpd"] - cms) <= 1
        assert (s["VSpd"] < 0) == (cms < 0)


@given(st.floats(-1000, 31000))
def test_gps_altitude_offset_and_not_clamped_at_5_km(alt: float) -> None:
    s = show(encode(Gps(47.0, 8.0, 10.0, 90.0, alt, 12)))
    assert abs(s["GAlt"] - alt) <= 0.5
    assert s["Lat"] == 47_000_000 and s["Lon"] == 8_000_000 and s["Sats"] == 12


def test_unknown_fields_are_not_shown() -> None:
    s = show(encode(Gps(47.5, -122.25)))
    assert s == {"Lat": 47_500_000, "Lon": -122_250_000}
    assert show(encode(Battery(12.6))) == {"RxBt": 126}


# -- the backend's mapping, message → mailbox → frame → radio -----------------------------------

def latest_frame(backend: CrsfBackend, ftype: int) -> bytes:
    rec = backend.scheduler.mailbox(ftype).peek()
    assert rec is not None, f"nothing published for 0x{ftype:02X}"
    return encode(rec)


def sm_update(state: int = 2, armed: bool = True, alt: float = 123.45, vel: float = -3.21,
              roll: float = 0.5, pitch: float = 1.2, yaw: float = -2.0) -> SmUpdate:
    return SmUpdate(timestamp_ms=1000, state=state, armed=armed, sm_type=0, altitude_m=alt,
                    acceleration_mps2=9.8, accel_vert_mps2=9.8, velocity_mps=vel,
                    roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw)


def test_sm_update_maps_to_attitude_altitude_vario_and_flight_mode() -> None:
    b = CrsfBackend()
    b.send_sm_update(sm_update())
    assert show(latest_frame(b, FRAME_ATTITUDE)) == {"Ptch": 1200, "Roll": 500, "Yaw": -2000}
    assert show(latest_frame(b, FRAME_BARO_ALTITUDE)) == {"Alt": 12350, "VSpd": -321}
    assert show(latest_frame(b, FRAME_VARIO)) == {"VSpd": -321}
    assert show(latest_frame(b, FRAME_FLIGHT_MODE)) == {"FM": "BOOST"}


def test_pitch_sign_is_configurable() -> None:
    b = CrsfBackend(CrsfOptions(pitch="nose-down"))
    b.send_sm_update(sm_update(pitch=0.25))
    assert show(latest_frame(b, FRAME_ATTITUDE))["Ptch"] == -250


def test_flight_mode_star_when_disarmed_and_configurable_suffix() -> None:
    b = CrsfBackend()
    b.send_sm_update(sm_update(state=0, armed=False))
    assert show(latest_frame(b, FRAME_FLIGHT_MODE)) == {"FM": "IDLE*"}
    b2 = CrsfBackend(CrsfOptions(disarmed_suffix=""))
    b2.send_sm_update(sm_update(state=0, armed=False))
    assert show(latest_frame(b2, FRAME_FLIGHT_MODE)) == {"FM": "IDLE"}


def test_status_health_marker_and_13_character_limit() -> None:
    b = CrsfBackend()
    flags = Status.make_flags(armed=False, imu_ok=True, baro_ok=False, calibrated=True,
                              log_ready=True)
    b.send_status(Status(timestamp_ms=5, state=6, sm_type=0, flags=flags))  # REDUNDANT
    fm = show(latest_frame(b, FRAME_FLIGHT_MODE))["FM"]
    assert fm == "REDUNDA!BARO*" and len(fm) == 13
    # healthy again: the marker goes, and an SmUpdate keeps the latest health
    ok = Status.make_flags(armed=True, imu_ok=True, baro_ok=True, calibrated=True,
                           log_ready=True)
    b.send_status(Status(timestamp_ms=6, state=6, sm_type=0, flags=ok))
    b.send_sm_update(sm_update(state=6, armed=True))
    assert show(latest_frame(b, FRAME_FLIGHT_MODE)) == {"FM": "REDUNDANT"}


@given(st.text(alphabet=st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=40),
       st.booleans())
def test_any_mode_text_shows_whole_within_13_characters(mode: str, armed: bool) -> None:
    b = CrsfBackend()
    b.send_vehicle_state(VehicleState(armed=armed, mode=mode or "X"))
    fm = show(latest_frame(b, FRAME_FLIGHT_MODE))["FM"]
    assert len(fm) <= 13
    assert fm.endswith("" if armed else "*")
    assert (mode or "X").startswith(fm.removesuffix("" if armed else "*"))


def test_position_battery_and_voltages() -> None:
    b = CrsfBackend()
    b.send_position(Position(lat_deg=46.5, lon_deg=6.6, alt_amsl_m=8421.0,
                             ground_speed_mps=10.0, course_deg=270.0, satellites=14))
    assert show(latest_frame(b, FRAME_GPS)) == {"Lat": 46_500_000, "Lon": 6_600_000,
                                                "GSpd": 360, "Hdg": 27000, "GAlt": 8421,
                                                "Sats": 14}
    b.send_battery(ModelBattery(voltage_v=7.4, current_a=1.5, consumed_mah=120,
                                remaining_pct=80))
    assert show(latest_frame(b, FRAME_BATTERY)) == {"RxBt": 74, "Curr": 15, "Capa": 120,
                                                    "Bat%": 80}
    assert b.scheduler.mailbox(FRAME_VOLTAGES).peek() is None  # one battery: 0x08 says it all
    b.send_battery(ModelBattery(voltage_v=9.05, battery_id=2))
    assert show(latest_frame(b, FRAME_VOLTAGES)) == {"Volt0": 740, "Volt2": 905}


def test_vehicle_state_maps_what_it_reports() -> None:
    b = CrsfBackend()
    b.send_vehicle_state(VehicleState(armed=True, mode="AUTO", roll_rad=0.1, pitch_rad=None,
                                      yaw_rad=3.0, altitude_m=50.0, climb_mps=1.25))
    assert show(latest_frame(b, FRAME_ATTITUDE)) == {"Roll": 100, "Yaw": 3000}
    assert show(latest_frame(b, FRAME_BARO_ALTITUDE)) == {"Alt": 5000, "VSpd": 125}
    assert show(latest_frame(b, FRAME_FLIGHT_MODE)) == {"FM": "AUTO"}


@settings(max_examples=60)
@given(st.floats(-2 * math.pi, 2 * math.pi), st.floats(-500, 2000), st.floats(-300, 300))
def test_any_sm_update_shows_within_resolution(angle: float, alt: float, vel: float) -> None:
    b = CrsfBackend()
    b.send_sm_update(sm_update(alt=alt, vel=vel, roll=angle, pitch=-angle, yaw=angle / 2))
    att = show(latest_frame(b, FRAME_ATTITUDE))
    assert abs(att["Roll"] / 1000 - wrapped(angle)) <= 0.0012
    assert abs(att["Ptch"] / 1000 - wrapped(-angle)) <= 0.0012
    baro = show(latest_frame(b, FRAME_BARO_ALTITUDE))
    assert abs(baro["Alt"] / 100 - alt) <= 0.05 + 1e-9
    assert abs(baro["VSpd"] / 100 - vel) <= 0.01 + 1e-9


def test_temperatures_and_voltages_frames() -> None:
    # −0.1 °C would be 0xFFFF (ignored): nudged to −0.2 °C; an unknown one is not shown
    assert show(encode(Temperatures(3, (21.5, -0.1, None)))) == {"Tmp3.0": 215, "Tmp3.1": -2}
    assert show(encode(Voltages(128, (3.7, 12.34)))) == {"Volt0": 370, "Volt1": 1234}
    assert show(encode(FlightMode("LANDED"))) == {"FM": "LANDED"}
