"""Benchmark: the gateway as a MAVLink router, side by side with mavlink-router (and MAVProxy).

Harness (the same for every router under test; the router is its own process)::

    sender process ──UDP──► router  (in 127.0.0.1:A) ──► (out 127.0.0.1:B) ──UDP──► this process
    (paced, one frame                                                             (receiver,
     per datagram)                                                                 kernel time)

Routers: ``aurora-gateway`` = ``aurora-gateway run --source mavlink:udpin:127.0.0.1:A --mavlink
udpout:127.0.0.1:B`` router-only (``--only mavlink`` where the flag exists, else ``--disable``
of every other backend) with ``--status-interval 0``; with ``--ours-form config`` a temporary
TOML instead: one ``[[sources]] type = "mavlink"`` with ``url = "udpin:…:A"`` and ``endpoints
= ["udpout:…:B"]`` and no backend at all (the config file's routing, which needs neither
the rocket's own node nor ``--mavlink``).  ``mavlink-router`` = ``mavlink-routerd -t 0 -c
<a conf of only TcpServerPort = 0> -e 127.0.0.1:B 127.0.0.1:A`` when ``mavlink-routerd`` is on
PATH or given with ``--mavlink-routerd``.  ``mavproxy`` = ``mavproxy.py --master=udpin:…
--out=udpout:… --daemon --non-interactive --default-modules=output --no-state --nowait
--streamrate=-1`` when ``mavproxy.py`` is next to the bench's Python, on PATH or given with
``--mavproxy``.  A router that is missing is skipped with a one-line note.

Traffic: an ArduPilot-like vehicle, system 1 component 1, MAVLink 2 frames packed once by
pymavlink's upstream ``ardupilotmega`` dialect (not the project's), per 60-frame cycle (what an
ArduCopter streams at roughly its SRx default rates, scaled up):

    ATTITUDE 20, GLOBAL_POSITION_INT 8, VFR_HUD 8, SYS_STATUS 4, GPS_RAW_INT 4, ALTITUDE 4,
    BATTERY_STATUS 2, HEARTBEAT 1   (51 of 60 = 17 of 20: what a ground-station translator reads)
    RAW_IMU 2, SCALED_PRESSURE 1, SERVO_OUTPUT_RAW 1, RC_CHANNELS 1, AHRS 1, MEMINFO 1,
    EKF_STATUS_REPORT 1, VIBRATION 1   (9 of 60: routed, decoded by nobody)

Each type's frames are spread evenly over the cycle (phases from ``--seed``); 40.5 bytes per
frame on average.  Every frame carries a unique 32-bit counter (from 0x10000000 up, never
reused in a run) in a field that varies in real traffic anyway (``time_boot_ms``, the low half
of ``time_usec``, ``energy_consumed``, ``freemem32``, SYS_STATUS ``errors_count1/2``, a float
of AHRS / EKF / VFR_HUD ``airspeed`` whose bits then read as a tiny positive number); the
sequence number is the counter's low byte and the CRC is recomputed with fastcrc's ``mcrf4xx``
and the message's ``crc_extra``.  HEARTBEAT keeps its payload (its ``custom_mode`` is the
vehicle's mode) and is told apart by sequence number.  A frame counts as received when system,
component, message id, counter and sequence all match; anything else at B is "foreign" (the
gateway's own node) or "stale" (an earlier phase).  Frames are built before a phase starts.

Per router and repetition: two starts (each spawned while the sender already sends 1 frame/ms:
the time from spawn to the first frame out; the second is "warm": for the Python routers the
bytecode cache written by the first, since routers run without ``PYTHONDONTWRITEBYTECODE``),
1 s warm-up at 2k msg/s, then a steady ``--steady-rate`` (10k msg/s) phase of
``--long-phase-s`` (5 s): CPU (the router's utime+stime from ``/proc`` over the phase and its
drain, per 100k frames sent), latency (sender's clock just before ``send`` → the receiving
socket's kernel timestamp, ``SO_TIMESTAMPNS``: the receiver's own scheduling is not counted)
and VmRSS / VmHWM after it.  Then the stepped rates (``--rates``) in ``--phase-s`` (3 s)
phases, from the steady rate upwards until the first phase that loses a frame (downwards
instead when that one already loses; lossless = every frame out within a 2 s drain after the
phase, which ends early after 0.2 s with nothing new); then the same in ``--long-phase-s``
phases starting two steps below the 3 s result; then one 3 s phase at twice the router's own
3 s rate (capped at the harness's limit): its loss.  Every wait has a deadline; a router that exits
is reported, not waited for.

Figures: medians of ``--repeat`` repetitions; ratios aurora-gateway / peer are taken inside
each repetition (the two ran back to back) and their median printed, beside the issue's goals.
Prints figures and asserts nothing: it is not a test.

Harness validity: first the harness runs alone (sender straight into the receiver) over the
same rates; a phase where the sender fell more than 5 % of the phase behind its schedule or
the receiving socket dropped anything (``/proc/net/udp``) is "harness-limited", and any router
result at or above the harness's own lossless limit is printed as "≥".  On the shared 2-core
development VM (2026-11-24, CPython 3.11.7, AMD EPYC) the harness alone was lossless and on
schedule up to 100k msg/s (the default top step; 120k fell behind), kernel-timestamped
latency p50 2–3 µs, p99 4–24 µs at 10k; at 100k msg/s the sender takes ~0.55 core and the
receiver ~0.35.  With a router busy on one of the two cores, figures above
~60k msg/s bound the machine as much as the router.
"""

from __future__ import annotations

import argparse
import bisect
import contextlib
import math
import multiprocessing as mp
import os
import platform
import random
import select
import shutil
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from array import array
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

BUILD_HELP = """\
mavlink-router (the peer) is not in any package index this bench uses; build it from its
repository with meson, submodule included.  tools/bench/build_mavlink_router.sh does all of
it outside the repository and prints the binary's path:

  --mavlink-routerd "$(tools/bench/build_mavlink_router.sh)"   # ~/.cache/aurora-bench/…

or by hand:

  git clone --recurse-submodules https://github.com/mavlink-router/mavlink-router
  cd mavlink-router            # (or: git submodule update --init for modules/mavlink_c_library_v2)
  python3 -m venv ~/meson-venv && ~/meson-venv/bin/pip install meson  # and ninja-build (apt)
  PATH=~/meson-venv/bin:$PATH meson setup build .
  #   (add -Dsystemdsystemunitdir=/tmp/unused where systemd's pkg-config file is missing)
  ninja -C build               # the project's default buildtype, debugoptimized
  # then put build/src/mavlink-routerd on PATH, or pass --mavlink-routerd build/src/mavlink-routerd

MAVProxy: pip install MAVProxy (a separate venv is fine), then --mavproxy <venv>/bin/mavproxy.py.
"""

SYSID, COMPID = 1, 1
COUNTER_BASE = 0x1000_0000
SENTINEL = 0x1A2B3C4D
HB_MSGID = 0
TICKS = os.sysconf("SC_CLK_TCK")
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux; not exported by Python
CMSG_LEN = socket.CMSG_SPACE(16)
QUIET_S = 0.2  # a phase's drain ends after this long with no new frame …
DRAIN_S = 2.0  # … or this long after the sender's last frame
LATE_FRACTION = 0.05  # sender this far behind its schedule: the phase is harness-limited

# (message, frames per 60-frame cycle, counter field(s)); values are set in _templates().
MIX: list[tuple[str, int]] = [
    ("ATTITUDE", 20), ("GLOBAL_POSITION_INT", 8), ("VFR_HUD", 8), ("SYS_STATUS", 4),
    ("GPS_RAW_INT", 4), ("ALTITUDE", 4), ("BATTERY_STATUS", 2), ("HEARTBEAT", 1),
    ("RAW_IMU", 2), ("SCALED_PRESSURE", 1), ("SERVO_OUTPUT_RAW", 1), ("RC_CHANNELS", 1),
    ("AHRS", 1), ("MEMINFO", 1), ("EKF_STATUS_REPORT", 1), ("VIBRATION", 1),
]
TRANSLATED = {"ATTITUDE", "GLOBAL_POSITION_INT", "VFR_HUD", "SYS_STATUS", "GPS_RAW_INT",
              "HEARTBEAT", "ALTITUDE", "BATTERY_STATUS"}


# -- traffic ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Traffic:
    """The frame templates and the cycle order, built once in the main process."""

    frames: list[bytes]  # per template: a packed frame
    offsets: list[int]  # per template: counter offset in the payload, -1 = HEARTBEAT
    extras: list[int]  # per template: crc_extra
    order: list[int]  # cycle position → template index
    msgids: list[int]  # cycle position → message id
    hb_payload: bytes
    hb_positions: list[int]  # cycle positions of HEARTBEAT

    def mean_len(self) -> float:
        return statistics.fmean(len(self.frames[t]) for t in self.order)


def _float_bits(v: int) -> float:
    return float(struct.unpack("<f", struct.pack("<I", v))[0])


def _templates(seed: int) -> Traffic:
    from pymavlink.dialects.v20 import ardupilotmega as apm

    rng = random.Random(seed)
    m = apm.MAVLink(None, SYSID, COMPID)
    s_lo, s_hi = SENTINEL & 0xFFFF, SENTINEL >> 16
    u64 = (7 << 32) | SENTINEL
    sf = _float_bits(SENTINEL)

    def r(a: float, b: float) -> float:
        return rng.uniform(a, b)

    msgs: dict[str, Any] = {
        "ATTITUDE": m.attitude_encode(
            time_boot_ms=SENTINEL, roll=r(-.3, .3), pitch=r(-.3, .3), yaw=r(-3, 3),
            rollspeed=r(-1, 1), pitchspeed=r(-1, 1), yawspeed=r(-1, 1)),
        "GLOBAL_POSITION_INT": m.global_position_int_encode(
            time_boot_ms=SENTINEL, lat=473977418, lon=85455939, alt=512340, relative_alt=24120,
            vx=153, vy=-87, vz=-31, hdg=27412),
        "VFR_HUD": m.vfr_hud_encode(airspeed=sf, groundspeed=r(1, 15), heading=274,
                                    throttle=47, alt=r(480, 520), climb=r(-2, 2)),
        "SYS_STATUS": m.sys_status_encode(
            onboard_control_sensors_present=0x3F20FC2F, onboard_control_sensors_enabled=0x3F20FC2F,
            onboard_control_sensors_health=0x3F20FC2F, load=312, voltage_battery=15873,
            current_battery=1420, battery_remaining=86, drop_rate_comm=0, errors_comm=0,
            errors_count1=s_lo, errors_count2=s_hi, errors_count3=0, errors_count4=0),
        "GPS_RAW_INT": m.gps_raw_int_encode(
            time_usec=u64, fix_type=3, lat=473977418, lon=85455939, alt=512120, eph=87, epv=121,
            vel=1534, cog=27412, satellites_visible=14, alt_ellipsoid=512600, h_acc=1200,
            v_acc=900, vel_acc=800, hdg_acc=2000, yaw=3),
        "ALTITUDE": m.altitude_encode(
            time_usec=u64, altitude_monotonic=r(480, 520), altitude_amsl=r(480, 520),
            altitude_local=r(10, 30), altitude_relative=r(10, 30), altitude_terrain=r(10, 30),
            bottom_clearance=r(10, 30)),
        "BATTERY_STATUS": m.battery_status_encode(
            id=0, battery_function=1, type=3, temperature=3500,
            voltages=[4012, 4011, 4013, 4010] + [65535] * 6, current_battery=1420,
            current_consumed=1210, energy_consumed=SENTINEL, battery_remaining=86,
            time_remaining=0, charge_state=1, voltages_ext=[0, 0, 0, 0], mode=0,
            fault_bitmask=0),
        "HEARTBEAT": m.heartbeat_encode(type=2, autopilot=3, base_mode=217, custom_mode=5,
                                        system_status=4, mavlink_version=3),
        "RAW_IMU": m.raw_imu_encode(
            time_usec=u64, xacc=12, yacc=-31, zacc=-1002, xgyro=3, ygyro=-2, zgyro=1, xmag=220,
            ymag=-45, zmag=390, id=0, temperature=3512),
        "SCALED_PRESSURE": m.scaled_pressure_encode(
            time_boot_ms=SENTINEL, press_abs=955.2, press_diff=0.01, temperature=3120,
            temperature_press_diff=3050),
        "SERVO_OUTPUT_RAW": m.servo_output_raw_encode(
            SENTINEL, 0, 1510, 1490, 1505, 1495, 1100, 1100, 1100, 1100),
        "RC_CHANNELS": m.rc_channels_encode(
            SENTINEL, 16, *[1500, 1500, 1100, 1500, 1800, 1000] + [1500] * 12, 212),
        "AHRS": m.ahrs_encode(
            omegaIx=r(-.01, .01), omegaIy=r(-.01, .01), omegaIz=r(-.01, .01), accel_weight=0.0,
            renorm_val=0.0, error_rp=sf, error_yaw=r(0, 1)),
        "MEMINFO": m.meminfo_encode(brkval=0, freemem=65535, freemem32=SENTINEL),
        "EKF_STATUS_REPORT": m.ekf_status_report_encode(
            flags=0x3A7, velocity_variance=sf, pos_horiz_variance=r(0, .2),
            pos_vert_variance=r(0, .2), compass_variance=r(0, .2),
            terrain_alt_variance=r(0, .2), airspeed_variance=r(0, .2)),
        "VIBRATION": m.vibration_encode(
            time_usec=u64, vibration_x=r(1, 20), vibration_y=r(1, 20), vibration_z=r(1, 20),
            clipping_0=0, clipping_1=0, clipping_2=3),
    }
    sentinel = struct.pack("<I", SENTINEL)
    frames: list[bytes] = []
    offsets: list[int] = []
    extras: list[int] = []
    index: dict[str, int] = {}
    for name, _count in MIX:
        msg = msgs[name]
        frame = msg.pack(m)
        payload = frame[10:10 + frame[1]]
        if name == "HEARTBEAT":
            off = -1
        else:
            off = payload.find(sentinel)
            if off < 0 or payload.find(sentinel, off + 1) >= 0:
                raise RuntimeError(f"{name}: counter field not found once in the payload")
        index[name] = len(frames)
        frames.append(frame)
        offsets.append(off)
        extras.append(msg.crc_extra)
    cycle = sum(c for _, c in MIX)
    slots: list[tuple[float, int]] = []
    for name, count in MIX:  # each type evenly spread, with a seeded phase
        phase = rng.random()
        slots += [((k + phase) / count, index[name]) for k in range(count)]
    order = [t for _, t in sorted(slots)]
    assert len(order) == cycle
    msgids = [frames[t][7] | frames[t][8] << 8 | frames[t][9] << 16 for t in order]
    hb = frames[index["HEARTBEAT"]]
    return Traffic(frames, offsets, extras, order, msgids, hb[10:10 + hb[1]],
                   [i for i, t in enumerate(order) if offsets[t] < 0])


def build_frames(tr: Traffic, start: int, n: int) -> list[bytes]:
    """Frames for counters ``start … start+n-1``: counter, sequence and CRC patched."""
    from fastcrc.crc16 import mcrf4xx

    pack_into = struct.pack_into
    frames, offsets, extras, order = tr.frames, tr.offsets, tr.extras, tr.order
    cycle = len(order)
    out = []
    for c in range(start, start + n):
        t = order[c % cycle]
        b = bytearray(frames[t])
        b[4] = c & 0xFF
        off = offsets[t]
        if off >= 0:
            pack_into("<I", b, 10 + off, c)
        end = len(b) - 2
        b[end] = extras[t]
        crc = mcrf4xx(bytes(b[1:end + 1]))
        b[end] = crc & 0xFF
        b[end + 1] = crc >> 8
        out.append(bytes(b))
    return out


# -- the sender (its own process) ------------------------------------------------------------

def sender_main(conn: Connection, tr: Traffic) -> None:
    """Serve commands: build, send (paced, reply with the send times), stream (until stop)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    frames: list[bytes] = []
    while True:
        try:
            cmd, *args = conn.recv()
        except EOFError:
            return
        if cmd == "quit":
            return
        if cmd == "build":
            t0 = time.perf_counter()
            frames = build_frames(tr, *args)
            conn.send(("built", time.perf_counter() - t0))
        elif cmd == "send":
            rate, port = args
            conn.send(("sent", *_paced(sock, frames, rate, port, None)))
        elif cmd == "stream":
            rate, port = args
            conn.send(("streaming",))
            conn.send(("streamed", *_paced(sock, frames, rate, port, conn)))


def _paced(sock: socket.socket, frames: Sequence[bytes], rate: float, port: int,
           stop: Connection | None) -> tuple[bytes, float, int, float]:
    """Send ``frames`` at ``rate`` (bursts of what is due, sleeping between); with ``stop``,
    until a message arrives there.  Returns the send times (``time.time()`` just before each
    send, packed doubles), the worst lateness against the schedule, send errors, CPU s."""
    dest = ("127.0.0.1", port)
    n = len(frames)
    times = array("d", bytes(8 * n))
    sendto, now_f, sleep = sock.sendto, time.time, time.sleep
    period = 1.0 / rate
    errors = 0
    late = 0.0
    cpu0 = time.process_time()
    t0 = now_f() + 0.002
    i = 0
    while i < n:
        now = now_f()
        due = min(n, int((now - t0) * rate) + 1)
        if due <= i:
            if stop is not None and stop.poll():
                break
            sleep(max(0.0, t0 + i * period - now))
            continue
        late = max(late, now - (t0 + i * period))
        while i < due:
            times[i] = now_f()
            try:
                sendto(frames[i], dest)
            except OSError:
                errors += 1
            i += 1
    if stop is not None and stop.poll(30.0):  # ran out of frames: the stop still comes
        stop.recv()
    return bytes(times[:i]), late, errors, time.process_time() - cpu0


# -- receiving --------------------------------------------------------------------------------

class Phase:
    """Frames of counters ``lo … lo+n-1`` seen at the receiver, with their kernel times."""

    def __init__(self, tr: Traffic, lo: int, n: int, track: bool = True) -> None:
        self.tr, self.lo, self.n, self.track = tr, lo, n, track
        self.cycle = len(tr.order)
        self.got = bytearray(n if track else 0)
        self.recv = array("d", bytes(8 * n)) if track else array("d")
        self.count = self.dup = self.foreign = self.stale = 0
        self.first_ts = math.inf
        self.last_new = 0.0  # monotonic time of the last frame of ours (new or stale)
        self.last_c = lo
        self.offsets = {tr.msgids[p]: tr.offsets[t] for p, t in enumerate(tr.order)}
        self._hb: dict[int, list[int]] = {}
        if track:
            for pos in tr.hb_positions:
                c = lo + (pos - lo) % self.cycle
                while c < lo + n:
                    self._hb.setdefault(c & 0xFF, []).append(c)
                    c += self.cycle
            for v in self._hb.values():
                v.sort()

    def feed(self, data: bytes, ts: float) -> None:
        size = len(data)
        if size >= 12 and data[0] == 0xFD and 12 + data[1] + (13 if data[2] & 1 else 0) == size:
            self._frame(data, 0, ts)
            return
        pos = 0  # more than one frame in a datagram (or not MAVLink 2)
        while pos + 12 <= size:
            if data[pos] != 0xFD:
                pos += 1
                continue
            end = pos + 12 + data[pos + 1] + (13 if data[pos + 2] & 1 else 0)
            if end > size:
                break
            self._frame(data, pos, ts)
            pos = end

    def _frame(self, data: bytes, pos: int, ts: float) -> None:
        if data[pos + 5] != SYSID or data[pos + 6] != COMPID:
            self.foreign += 1
            return
        msgid = data[pos + 7] | data[pos + 8] << 8 | data[pos + 9] << 16
        off = self.offsets.get(msgid)
        plen = data[pos + 1]
        seq = data[pos + 4]
        if off is None:
            self.foreign += 1
            return
        if off < 0:
            if data[pos + 10:pos + 10 + plen] != self.tr.hb_payload:
                self.foreign += 1
                return
            if not self.track:
                self.last_new = time.monotonic()
                return
            cands = self._hb.get(seq)
            if not cands:
                self.stale += 1
                return
            k = bisect.bisect_left(cands, self.last_c)
            c = min(cands[max(0, k - 1):k + 1], key=lambda x: abs(x - self.last_c))
        else:
            raw = data[pos + 10 + off:pos + 14 + off]
            c = int.from_bytes(raw.ljust(4, b"\0"), "little")
        if c & 0xFF != seq or self.tr.msgids[c % self.cycle] != msgid or c < COUNTER_BASE:
            self.foreign += 1
            return
        self.last_new = time.monotonic()
        i = c - self.lo
        if not self.track or not 0 <= i < self.n:
            self.stale += 1
            return
        if off >= 0:
            self.last_c = c
        if self.got[i]:
            self.dup += 1
            return
        self.got[i] = 1
        self.recv[i] = ts
        self.count += 1
        if ts < self.first_ts:
            self.first_ts = ts


def _udp_drops(port: int) -> int | None:
    """The kernel's drop counter of the UDP socket bound to 127.0.0.1:``port``."""
    want = f"0100007F:{port:04X}"
    try:
        with open("/proc/net/udp") as f:
            for line in f.readlines()[1:]:
                cols = line.split()
                if cols[1] == want:
                    return int(cols[-1])
    except OSError:
        return None
    return None


def _cpu_s(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rpartition(")")[2].split()
    except OSError:
        return math.nan
    return (int(fields[11]) + int(fields[12])) / TICKS


def _mem_mb(pid: int) -> tuple[float, float]:
    rss = hwm = math.nan
    with contextlib.suppress(OSError), open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                rss = int(line.split()[1]) / 1024
            elif line.startswith("VmHWM:"):
                hwm = int(line.split()[1]) / 1024
    return rss, hwm


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# -- routers ----------------------------------------------------------------------------------

@dataclass
class Router:
    name: str
    argv: Callable[[int, int, str], list[str]]  # (port in, port out, tmpdir) → command
    env: dict[str, str] | None = None


def _cacheable_env() -> dict[str, str]:
    """This environment without PYTHONDONTWRITEBYTECODE: a Python router's first start
    writes the bytecode cache its second ("warm") start reads."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def _gateway_router(exe: str, form: str) -> Router:
    help_text = subprocess.run([exe, "run", "--help"], capture_output=True, text=True,
                               timeout=60).stdout

    def argv(a: int, b: int, tmp: str) -> list[str]:
        if form == "config":
            path = Path(tmp) / "gateway.toml"
            path.write_text(
                "[gateway]\nstatus_interval_s = 0\n\n"
                f'[[sources]]\ntype = "mavlink"\nurl = "udpin:127.0.0.1:{a}"\n'
                f'endpoints = ["udpout:127.0.0.1:{b}"]\n')
            return [exe, "run", "-c", str(path), "--status-interval", "0"]
        cmd = [exe, "run", "--source", f"mavlink:udpin:127.0.0.1:{a}",
               "--mavlink", f"udpout:127.0.0.1:{b}", "--status-interval", "0"]
        if "--only" in help_text:
            return [*cmd, "--only", "mavlink"]
        for other in ("console", "crsf", "zenoh", "hc12"):
            cmd += ["--disable", other]
        return cmd

    return Router("aurora-gateway", argv, _cacheable_env())


def _mavlink_router(exe: str) -> Router:
    def argv(a: int, b: int, tmp: str) -> list[str]:
        conf = Path(tmp) / "main.conf"  # not /etc/mavlink-router/main.conf (an empty file
        conf.write_text("[General]\nTcpServerPort = 0\n")  # is refused)
        return [exe, "-t", "0", "-c", str(conf), "-e", f"127.0.0.1:{b}", f"127.0.0.1:{a}"]

    return Router("mavlink-router", argv)


def _mavproxy(exe: str) -> Router:
    def argv(a: int, b: int, tmp: str) -> list[str]:
        return [exe, f"--master=udpin:127.0.0.1:{a}", f"--out=udpout:127.0.0.1:{b}",
                "--daemon", "--non-interactive", "--default-modules=output", "--no-state",
                "--nowait", "--streamrate=-1"]

    return Router("mavproxy", argv, _cacheable_env())


# -- the harness ------------------------------------------------------------------------------

@dataclass
class PhaseResult:
    rate: float
    sent: int
    received: int
    lost: int
    lat_ms: list[float]
    cpu_s: float
    harness_limited: bool
    rx_drops: int
    router_drops: int | None
    dup: int
    foreign: int
    sender_cpu_s: float
    receiver_cpu_s: float

    @property
    def lossless(self) -> bool:
        return self.lost == 0 and self.sent > 0

    @property
    def loss_pct(self) -> float:
        return 100.0 * self.lost / max(self.sent, 1)


@dataclass
class RunResult:
    """One router, one repetition."""

    start_first_s: float | None = None
    start_warm_s: float | None = None
    steady: PhaseResult | None = None
    rss_mb: float = math.nan
    hwm_mb: float = math.nan
    max3: float | None = None  # highest lossless rate, 3 s phases (0: none)
    max3_ceiling: bool = False  # … lossless at the top step or the harness's limit
    max5: float | None = None
    max5_ceiling: bool = False
    loss2x: float | None = None
    rate2x: float | None = None
    notes: list[str] = field(default_factory=list)


class Harness:
    def __init__(self, tr: Traffic, args: argparse.Namespace) -> None:
        self.tr, self.args = tr, args
        self.rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 << 20)
        self.rx.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.rx.bind(("127.0.0.1", 0))
        self.rx.setblocking(False)
        self.port_out = int(self.rx.getsockname()[1])
        self.rcvbuf = self.rx.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        ctx = mp.get_context("fork")
        self.conn, child = ctx.Pipe()
        self.sender = ctx.Process(target=sender_main, args=(child, tr), daemon=True)
        self.sender.start()
        child.close()
        self.counter = COUNTER_BASE
        self.harness_limit: float | None = None  # highest rate the harness alone handled
        self.harness_note = "Harness alone: not measured (--no-harness-check)"

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.conn.send(("quit",))
        self.sender.join(5)
        if self.sender.is_alive():
            self.sender.kill()
        self.rx.close()

    def _reply(self, timeout: float) -> tuple[Any, ...]:
        if not self.conn.poll(timeout):
            raise RuntimeError("the sender process did not answer in time")
        return tuple(self.conn.recv())

    def _build(self, n: int) -> int:
        lo = self.counter
        self.counter += n
        self.conn.send(("build", lo, n))
        self._reply(120.0)
        return lo

    def _drain(self, ph: Phase) -> None:
        recvmsg, unpack, feed = self.rx.recvmsg, struct.unpack, ph.feed
        while True:
            try:
                data, anc, _flags, _addr = recvmsg(4096, CMSG_LEN)
            except BlockingIOError:
                return
            if anc:
                sec, ns = unpack("qq", anc[0][2][:16])
                feed(data, sec + ns * 1e-9)
            else:
                feed(data, time.time())

    def settle(self, max_s: float = 5.0) -> None:
        """Discard what is still arriving from earlier phases (until QUIET_S without any)."""
        ph = Phase(self.tr, COUNTER_BASE, 0, track=False)
        ph.last_new = start = time.monotonic()
        while True:
            now = time.monotonic()
            if now - ph.last_new > QUIET_S or now - start > max_s:
                return
            select.select([self.rx], [], [], 0.05)
            self._drain(ph)

    def phase(self, rate: float, duration: float, port: int, pid: int | None,
              alive: Callable[[], bool] = lambda: True) -> PhaseResult:
        n = max(1, round(rate * duration))
        lo = self._build(n)
        self.settle()
        ph = Phase(self.tr, lo, n)
        rx_drops0 = _udp_drops(self.port_out) or 0
        r_drops0 = _udp_drops(port) if pid is not None else None
        cpu0 = _cpu_s(pid) if pid is not None else math.nan
        own0 = time.process_time()
        self.conn.send(("send", rate, port))
        reply: tuple[Any, ...] | None = None
        deadline = time.monotonic() + duration * 3 + 30
        done_at = math.inf
        waitables: list[Any] = [self.rx, self.conn]
        while True:
            select.select(waitables, [], [], 0.05)
            self._drain(ph)
            now = time.monotonic()
            if reply is None and self.conn.poll():
                reply = self._reply(0)
                done_at = now
                ph.last_new = max(ph.last_new, now)
            if reply is not None and (ph.count >= n or now - ph.last_new > QUIET_S
                                      or now - done_at > DRAIN_S):
                break
            if now > deadline:
                break
        if reply is None:
            reply = self._reply(duration * 3 + 30)
        cpu1 = _cpu_s(pid) if pid is not None else math.nan
        r_drops1 = _udp_drops(port) if pid is not None else None
        rx_drops = (_udp_drops(self.port_out) or 0) - rx_drops0
        _tag, times_b, late, _errors, sender_cpu = reply
        sent_t = array("d")
        sent_t.frombytes(times_b)
        lat = [1e3 * (ph.recv[i] - sent_t[i]) for i in range(len(sent_t)) if ph.got[i]]
        limited = late > LATE_FRACTION * duration or rx_drops > 0
        return PhaseResult(rate, len(sent_t), ph.count, len(sent_t) - ph.count, lat,
                           cpu1 - cpu0, limited, rx_drops,
                           None if r_drops0 is None or r_drops1 is None
                           else r_drops1 - r_drops0, ph.dup, ph.foreign, sender_cpu,
                           time.process_time() - own0)

    def start(self, router: Router, port: int, tmp: str, log: Path
              ) -> tuple[subprocess.Popen[bytes], float | None]:
        """Spawn ``router`` while the sender streams 1 frame/ms into ``port``; the time from
        spawn to the first frame out (None: none within ``--start-timeout``)."""
        timeout = self.args.start_timeout
        n = int(1000 * (timeout + 5))
        lo = self._build(n)
        self.settle()
        ph = Phase(self.tr, lo, n)
        self.conn.send(("stream", 1000.0, port))
        self._reply(30.0)  # streaming
        with open(log, "ab") as out:
            t_spawn = time.time()
            proc = subprocess.Popen(router.argv(port, self.port_out, tmp), stdin=subprocess.DEVNULL,
                                    stdout=out, stderr=subprocess.STDOUT, env=router.env,
                                    cwd=tmp, start_new_session=True)
        deadline = time.monotonic() + timeout
        while ph.count == 0 and time.monotonic() < deadline and proc.poll() is None:
            select.select([self.rx], [], [], 0.02)
            self._drain(ph)
        self.conn.send(("stop",))
        self._reply(30.0)
        return proc, (ph.first_ts - t_spawn if ph.count else None)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def _log_tail(log: Path) -> str:
    try:
        lines = log.read_text(errors="replace").strip().splitlines()
    except OSError:
        return ""
    return " | ".join(lines[-3:])[-300:]


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _describe(p: PhaseResult) -> str:
    lat = sorted(p.lat_ms)
    q = (f"p50 {_pct(lat, 50):.2f} ms p99 {_pct(lat, 99):.2f} ms" if lat else "no latency")
    extra = []
    if p.router_drops:
        extra.append(f"router socket dropped {p.router_drops}")
    if p.harness_limited:
        extra.append("HARNESS-LIMITED")
    if p.dup:
        extra.append(f"{p.dup} duplicates")
    return (f"{p.rate:>7.0f} msg/s: lost {p.lost}/{p.sent} ({p.loss_pct:.2f} %), {q}"
            + (f", {', '.join(extra)}" if extra else ""))


def _pct(sorted_vals: Sequence[float], q: float) -> float:
    if not sorted_vals:
        return math.nan
    k = min(len(sorted_vals) - 1, max(0, math.ceil(q / 100 * len(sorted_vals)) - 1))
    return sorted_vals[k]


def _series(h: Harness, rates: list[float], duration: float, port: int, pid: int | None,
            alive: Callable[[], bool], label: str, start_at: int = 0
            ) -> tuple[float, bool]:
    """Highest lossless rate going up from ``rates[start_at]`` (down first if that one already
    loses); (0, False) when none; ceiling True when the top step or the harness's limit was
    reached without loss."""
    best, i, went_down = 0.0, start_at, False
    while 0 <= i < len(rates):
        if not alive():
            break
        p = h.phase(rates[i], duration, port, pid, alive)
        _progress(f"    {label} {duration:g} s {_describe(p)}")
        if p.harness_limited:
            return (best, True) if best else (0.0, False)
        if p.lossless:
            best = rates[i]
            if went_down:
                return best, False
            if h.harness_limit is not None and rates[i] >= h.harness_limit:
                return best, True
            i += 1
        else:
            if best or i == 0:
                return best, False
            went_down = True
            i -= 1
    return best, best > 0 and best == rates[-1]


def measure_router(h: Harness, router: Router, rates: list[float], label: str) -> RunResult:
    a = h.args
    res = RunResult()
    with tempfile.TemporaryDirectory(prefix="bench-router-") as tmp:
        log = Path(tmp) / "router.log"
        proc, res.start_first_s = h.start(router, _free_udp_port(), tmp, log)
        _progress(f"  {label}: first start → first frame out: {_fmt_s(res.start_first_s)}")
        if proc.poll() is not None:
            res.notes.append(f"first start exited with {proc.returncode}: {_log_tail(log)}")
        _stop(proc)
        port = _free_udp_port()
        proc, res.start_warm_s = h.start(router, port, tmp, log)
        _progress(f"  {label}: second start → first frame out: {_fmt_s(res.start_warm_s)}")
        pid = proc.pid

        def alive() -> bool:
            return proc.poll() is None

        try:
            if not alive():
                res.notes.append(f"exited with {proc.returncode}: {_log_tail(log)}")
                return res
            if res.start_warm_s is None:
                res.notes.append(f"forwarded nothing within {a.start_timeout:g} s of start")
            h.phase(2000, 1.0, port, pid, alive)  # warm-up, not counted
            res.steady = h.phase(a.steady_rate, a.long_phase_s, port, pid, alive)
            _progress(f"    {label} steady {a.long_phase_s:g} s {_describe(res.steady)}, "
                      f"CPU {res.steady.cpu_s:.2f} s")
            res.rss_mb, res.hwm_mb = _mem_mb(pid)
            first = max([i for i, r in enumerate(rates) if r <= a.steady_rate] or [0])
            res.max3, res.max3_ceiling = _series(h, rates, a.phase_s, port, pid, alive, label,
                                                 start_at=first)
            if not a.quick:
                top = rates.index(res.max3) if res.max3 in rates else 0
                res.max5, res.max5_ceiling = _series(h, rates, a.long_phase_s, port, pid, alive,
                                                     label, start_at=max(0, top - 2))
            if res.max3:
                rate2 = 2 * res.max3
                if h.harness_limit is not None and rate2 > h.harness_limit:
                    rate2 = h.harness_limit
                    res.notes.append(f"2× capped at the harness's limit {rate2:.0f} msg/s")
                if alive():
                    p = h.phase(rate2, a.phase_s, port, pid, alive)
                    _progress(f"    {label} 2× {a.phase_s:g} s {_describe(p)}")
                    res.loss2x, res.rate2x = p.loss_pct, rate2
            if not alive():
                res.notes.append(f"exited with {proc.returncode} during the run: "
                                 f"{_log_tail(log)}")
        finally:
            _stop(proc)
    return res


def calibrate(h: Harness, rates: list[float]) -> None:
    """The harness alone (sender straight into the receiver): its lossless limit."""
    a = h.args
    _progress("harness alone (sender → receiver, no router):")
    p = h.phase(a.steady_rate, a.phase_s, h.port_out, None)
    lat = sorted(p.lat_ms)
    best = 0.0
    for r in rates:
        q = h.phase(r, a.phase_s, h.port_out, None)
        _progress(f"    harness {a.phase_s:g} s {_describe(q)}, CPU sender "
                  f"{100 * q.sender_cpu_s / a.phase_s:.0f} % / receiver "
                  f"{100 * q.receiver_cpu_s / a.phase_s:.0f} % of a core")
        if q.harness_limited or not q.lossless:
            break
        best = r
    h.harness_limit = best or None
    h.harness_note = (f"Harness alone (sender straight into the receiver): lossless and on "
                      f"schedule up to {best:.0f} msg/s (of {rates[-1]:.0f} tried), latency "
                      f"p50 {1e3 * _pct(lat, 50):.0f} µs / p99 {1e3 * _pct(lat, 99):.0f} µs at "
                      f"{a.steady_rate:.0f} msg/s; router results at that limit print as ≥")
    _progress(h.harness_note)


# -- the report -------------------------------------------------------------------------------

def _fmt_s(s: float | None) -> str:
    return "none" if s is None else (f"{1e3 * s:.0f} ms" if s < 1 else f"{s:.2f} s")


def _fmt_rate(v: float | None, ceiling: bool, lowest: float) -> str:
    if v is None:
        return "n/a"
    if v == 0:
        return f"< {lowest / 1e3:g}k"
    return ("≥ " if ceiling else "") + f"{v / 1e3:g}k"


def _med(vals: Sequence[float | None]) -> float | None:
    got = [v for v in vals if v is not None and not math.isnan(v)]
    return statistics.median(got) if got else None


def _ratio(ours: Sequence[RunResult], peer: Sequence[RunResult],
           get: Callable[[RunResult], float | None]) -> float | None:
    rs = []
    for o, p in zip(ours, peer, strict=False):
        vo, vp = get(o), get(p)
        if vo is not None and vp is not None and not math.isnan(vo) and not math.isnan(vp) \
                and vp > 0:
            rs.append(vo / vp)
    return statistics.median(rs) if rs else None


def report(results: dict[str, list[RunResult]], rates: list[float], args: argparse.Namespace,
           header: list[str]) -> None:
    names = list(results)
    ours = results["aurora-gateway"]
    peer = results.get("mavlink-router")
    lowest = rates[0]

    def lat(q: float) -> Callable[[RunResult], float | None]:
        def get(r: RunResult) -> float | None:
            if r.steady is None or not r.steady.lat_ms:
                return None
            return _pct(sorted(r.steady.lat_ms), q)
        return get

    def cpu100k(r: RunResult) -> float | None:
        if r.steady is None or not r.steady.sent:
            return None
        return r.steady.cpu_s / r.steady.sent * 1e5

    def steady_loss(r: RunResult) -> float | None:
        return None if r.steady is None else r.steady.loss_pct

    def rate_cell(rs: list[RunResult], five: bool) -> str:
        vals = [(r.max5, r.max5_ceiling) if five else (r.max3, r.max3_ceiling) for r in rs]
        got = sorted((v, c) for v, c in vals if v is not None)
        if not got:
            return "n/a"
        v, c = got[(len(got) - 1) // 2]  # the lower median: a rate that was measured
        return _fmt_rate(v, c, lowest)

    def goal(ok: bool | None, text: str) -> str:
        return f"{text}: " + ("n/a" if ok is None else "met" if ok else "**NOT met**")

    rows: list[tuple[str, Callable[[list[RunResult]], str], str, str]] = []

    def num(get: Callable[[RunResult], float | None], fmt: str
            ) -> Callable[[list[RunResult]], str]:
        def cell(rs: list[RunResult]) -> str:
            v = _med([get(r) for r in rs])
            return "n/a" if v is None else fmt.format(v)
        return cell

    def ratio_of(get: Callable[[RunResult], float | None]) -> str:
        if peer is None:
            return ""
        v = _ratio(ours, peer, get)
        return "n/a" if v is None else f"{v:.2f}×"

    def rate_val(five: bool) -> Callable[[RunResult], float | None]:
        return lambda r: r.max5 if five else r.max3

    def rate_ratio(five: bool) -> str:
        """The median ratio of max lossless rates, "≥" when ours was at the ceiling there."""
        if peer is None:
            return ""
        rs = []
        for o, q in zip(ours, peer, strict=False):
            vo, vq = (o.max5, q.max5) if five else (o.max3, q.max3)
            co, cq = (o.max5_ceiling, q.max5_ceiling) if five else (o.max3_ceiling,
                                                                      q.max3_ceiling)
            if vo is not None and vq:
                rs.append((vo / vq, "≥ " if co and not cq else "≤ " if cq and not co else ""))
        if not rs:
            return "n/a"
        v, mark = sorted(rs)[(len(rs) - 1) // 2]
        return f"{mark}{v:.2f}×"

    r3 = _ratio(ours, peer, rate_val(False)) if peer else None
    rcpu = _ratio(ours, peer, cpu100k) if peer else None
    p99 = _med([lat(99)(r) for r in ours])
    rss = _med([r.rss_mb for r in ours])
    warm = _med([r.start_warm_s for r in ours])
    # forwarded nothing at all: the latency and start goals are failed, not "n/a"
    dead = bool(ours) and all(r.start_warm_s is None
                              and (r.steady is None or not r.steady.received) for r in ours)
    rows.append(("max lossless rate, 3 s phases", lambda rs: rate_cell(rs, False),
                 rate_ratio(False),
                 goal(None if r3 is None else r3 >= 1, "≥ mavlink-router's")))
    if not args.quick:
        rows.append(("max lossless rate, 5 s phases", lambda rs: rate_cell(rs, True),
                     rate_ratio(True), ""))
    rows.append(("loss at 2× own max (3 s)", num(lambda r: r.loss2x, "{:.1f} %"), "", ""))
    rows.append((f"CPU s per 100k messages at {args.steady_rate / 1e3:g}k msg/s",
                 num(cpu100k, "{:.2f}"), ratio_of(cpu100k),
                 goal(None if rcpu is None else rcpu <= 2, "≤ 2× mavlink-router's")))
    rows.append((f"latency p50 at {args.steady_rate / 1e3:g}k msg/s",
                 num(lat(50), "{:.2f} ms"), ratio_of(lat(50)), ""))
    rows.append((f"latency p99 at {args.steady_rate / 1e3:g}k msg/s",
                 num(lat(99), "{:.2f} ms"), ratio_of(lat(99)),
                 goal(False if dead else None if p99 is None else p99 <= 2.0, "≤ 2 ms")))
    rows.append((f"lost at {args.steady_rate / 1e3:g}k msg/s ({args.long_phase_s:g} s)",
                 num(steady_loss, "{:.2f} %"), "", ""))
    rows.append(("resident memory VmRSS (peak VmHWM)",
                 lambda rs: (f"{_opt(_med([r.rss_mb for r in rs]), '{:.1f}')} MB "
                             f"({_opt(_med([r.hwm_mb for r in rs]), '{:.1f}')})"),
                 ratio_of(lambda r: r.rss_mb),
                 goal(None if rss is None else rss <= 40, "≤ 40 MB")))
    def start_cell(get: Callable[[RunResult], float | None]
                   ) -> Callable[[list[RunResult]], str]:
        def cell(rs: list[RunResult]) -> str:
            v = _med([get(r) for r in rs])
            nones = sum(get(r) is None for r in rs)
            if v is None:
                return f"none within {args.start_timeout:g} s"
            return f"{v:.3f} s" + (f" ({nones} of {len(rs)} none)" if nones else "")
        return cell

    rows.append(("start to first forwarded frame, first start",
                 start_cell(lambda r: r.start_first_s),
                 ratio_of(lambda r: r.start_first_s), ""))
    rows.append(("start to first forwarded frame, warm (2nd)",
                 start_cell(lambda r: r.start_warm_s),
                 ratio_of(lambda r: r.start_warm_s),
                 goal(False if dead else None if warm is None else warm <= 0.3, "≤ 0.3 s")))

    cols = [n for n in ("mavlink-router", "aurora-gateway") if n in results]
    extra = [n for n in names if n not in cols]
    head = ["metric", *cols] + (["ratio", "goal"] if peer else ["goal"]) + extra
    print()
    for line in header:
        print(line)
    print()
    print("| " + " | ".join(head) + " |")
    print("|" + "|".join("---" for _ in head) + "|")
    for name, cell, ratio, g in rows:
        cells = [name] + [cell(results[c]) for c in cols]
        cells += [ratio, g] if peer else [g]
        cells += [cell(results[c]) for c in extra]
        print("| " + " | ".join(cells) + " |")
    print()
    if peer is not None:
        print("ratio: aurora-gateway / mavlink-router inside each repetition, then the median.")
    print("Per repetition (3 s max / 5 s max / CPU s per 100k / p99 ms / warm start s):")
    for n in names:
        parts = []
        for r in results[n]:
            parts.append(f"{_fmt_rate(r.max3, r.max3_ceiling, lowest)} / "
                         f"{_fmt_rate(r.max5, r.max5_ceiling, lowest)} / "
                         f"{_opt(cpu100k(r), '{:.2f}')} / {_opt(lat(99)(r), '{:.2f}')} / "
                         f"{_opt(r.start_warm_s, '{:.3f}')}")
        print(f"- {n}: " + "; ".join(parts))
        notes = sorted({note for r in results[n] for note in r.notes})
        for note in notes:
            print(f"  - note: {note}")


def _opt(v: float | None, fmt: str) -> str:
    return "n/a" if v is None or math.isnan(v) else fmt.format(v)


# -- main -------------------------------------------------------------------------------------

def _rates(text: str) -> list[float]:
    out = []
    for part in text.split(","):
        part = part.strip().lower()
        mult = 1000.0 if part.endswith("k") else 1.0
        out.append(float(part.rstrip("k")) * mult)
    if not out or any(r <= 0 for r in out) or out != sorted(out):
        raise argparse.ArgumentTypeError("rates: positive and ascending, e.g. 5k,10k,20k")
    return out


def _cpu_model() -> str:
    with contextlib.suppress(OSError), open("/proc/cpuinfo") as f:
        for line in f:
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.machine()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=(__doc__ or "").splitlines()[0],
        epilog=BUILD_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeat", type=int, default=3, help="repetitions per router (median)")
    p.add_argument("--phase-s", type=float, default=3.0, help="short phase length (s)")
    p.add_argument("--long-phase-s", type=float, default=5.0,
                   help="long phase length (s): second series and the steady phase")
    p.add_argument("--rates", type=_rates,
                   default=_rates("5k,7.5k,10k,15k,20k,30k,40k,60k,80k,100k"),
                   help="stepped rates, msg/s, ascending (default %(default)s)")
    p.add_argument("--steady-rate", type=float, default=10_000.0,
                   help="rate of the CPU / latency / memory phase (msg/s)")
    p.add_argument("--quick", action="store_true",
                   help="smoke run: 1 repetition, 1 s phases, no 5 s series, fewer rates")
    p.add_argument("--no-peer", action="store_true", help="measure aurora-gateway only")
    p.add_argument("--ours-form", choices=("cli", "config"), default="cli",
                   help="aurora-gateway from flags (the issue's interface) or a config file")
    p.add_argument("--aurora-gateway", metavar="PATH",
                   default=str(Path(sys.executable).parent / "aurora-gateway"),
                   help="the gateway's console script (default: next to this Python)")
    p.add_argument("--mavlink-routerd", metavar="PATH", help="mavlink-routerd (default: PATH)")
    p.add_argument("--mavproxy", metavar="PATH",
                   help="mavproxy.py (default: next to this Python, else PATH)")
    p.add_argument("--no-harness-check", action="store_true",
                   help="skip measuring the harness alone first")
    p.add_argument("--start-timeout", type=float, default=10.0,
                   help="longest wait for a router's first forwarded frame (s)")
    p.add_argument("--seed", type=int, default=11)
    args = p.parse_args(argv)
    if args.quick:
        args.repeat, args.phase_s, args.long_phase_s = 1, 1.0, 2.0
        args.rates = [r for r in args.rates if r in (5e3, 10e3, 20e3, 40e3)] or args.rates
    if not Path("/proc/self/stat").exists():
        print("needs Linux /proc", file=sys.stderr)
        return 2

    routers: list[Router] = []
    skipped: list[str] = []
    if not args.no_peer:
        exe = args.mavlink_routerd or shutil.which("mavlink-routerd")
        if exe and Path(exe).exists():
            routers.append(_mavlink_router(exe))
        else:
            skipped.append("mavlink-router: mavlink-routerd not found (see --help to build it)")
    if not Path(args.aurora_gateway).exists():
        print(f"{args.aurora_gateway}: not found (pip install -e . into this venv)",
              file=sys.stderr)
        return 2
    gw = _gateway_router(args.aurora_gateway, args.ours_form)
    routers.append(gw)
    if not args.no_peer:
        exe = (args.mavproxy or shutil.which("mavproxy.py", path=str(Path(sys.executable).parent))
               or shutil.which("mavproxy.py"))
        if exe and Path(exe).exists():
            routers.append(_mavproxy(exe))
        else:
            skipped.append("mavproxy: mavproxy.py not found (pip install MAVProxy)")
    for s in skipped:
        print(f"# skipped {s}", file=sys.stderr)

    tr = _templates(args.seed)
    share = sum(c for n, c in MIX if n in TRANSLATED) / sum(c for _, c in MIX)
    import pymavlink

    cmdline = " ".join([os.path.relpath(sys.executable), *sys.argv]) if argv is None else \
        " ".join(["bench_mavlink_router.py", *argv])
    load0 = os.getloadavg()
    t_start = time.monotonic()
    h = Harness(tr, args)
    results: dict[str, list[RunResult]] = {r.name: [] for r in routers}
    try:
        _progress(f"receiver SO_RCVBUF {h.rcvbuf} bytes; mix of {len(tr.order)} frames/cycle, "
                  f"{tr.mean_len():.1f} bytes/frame, {100 * share:.0f} % translated types")
        if not args.no_harness_check:
            calibrate(h, args.rates)
        for rep in range(args.repeat):
            for router in routers:
                label = f"[{rep + 1}/{args.repeat}] {router.name}"
                _progress(f"{label}:")
                results[router.name].append(measure_router(h, router, args.rates, label))
    finally:
        h.close()
    elapsed = time.monotonic() - t_start
    load1 = os.getloadavg()
    form = args.ours_form
    header = [
        f"Command: `{cmdline}`",
        f"Machine: {os.cpu_count()} cores ({_cpu_model()}), {platform.system()} "
        f"{platform.release()}, {platform.python_implementation()} "
        f"{platform.python_version()}, pymavlink {getattr(pymavlink, '__version__', '?')}; "
        f"load average {load0[0]:.1f} at start, {load1[0]:.1f} at end; {elapsed / 60:.1f} min",
        (f"aurora-gateway form: cli (`aurora-gateway {' '.join(gw.argv(14551, 14550, '')[1:])}`"
         ", other ports)") if form == "cli" else
        "aurora-gateway form: config (temporary TOML: one mavlink source, url udpin:A, "
        "endpoints [udpout:B]; no backend)",
        f"Traffic: ArduPilot-like mix, {tr.mean_len():.1f} bytes/frame, one frame per datagram, "
        f"{100 * share:.0f} % of frames of the types a GCS translator reads; medians of "
        f"{args.repeat} repetition(s); phases {args.phase_s:g} s / {args.long_phase_s:g} s",
    ]
    header += [f"Skipped {s}" for s in skipped]
    header.append(h.harness_note)
    report(results, args.rates, args, header)
    return 0


if __name__ == "__main__":
    sys.exit(main())
