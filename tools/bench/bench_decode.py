"""Benchmark: the Aurora wire decoder against pymavlink's MAVLink 2 parser.

Builds two deterministic streams of the same number of frames:

* Aurora: a flight-like mix made with :func:`gateway.wire.encode` — 7 in 10 SM_UPDATE in the
  64-byte (f64) revision, 2 in 10 in the 36-byte (f32) revision, 1 in 10 STATUS — with varied
  values (seeded, so every run decodes the same bytes);
* MAVLink 2: packed with pymavlink's generated ``common`` dialect (never ``mavutil``, which
  rewrites the process environment): by default 7 in 10 ATTITUDE (40 bytes on the wire),
  2 in 10 GLOBAL_POSITION_INT (40), 1 in 10 HEARTBEAT (21); ``--mavlink attitude`` sends
  ATTITUDE only.

and times, in every repetition and in this order:

(a) ``Decoder().feed(stream)`` + ``flush()`` on the whole stream;
(b) ``MAVLink(None).parse_buffer(stream)`` on the whole stream (fresh parser each time,
    default ``robust_parsing``);
(c) our decoder fed 4 KiB chunks (a realistic serial read), then flushed;
(d) pymavlink ``parse_buffer`` fed the same 4 KiB chunks; (c) and (d) stream (each chunk's
    messages are counted and dropped) and are timed in alternating blocks of chunks, so a
    change of machine load mid-run hits both.

Both sides must decode exactly ``--frames`` messages (checked before anything is printed).
The machine is shared and noisy, so each figure is the median of ``--repeat`` runs (min and
max shown too) and the ours/pymavlink ratios are taken per repetition, i.e. between runs that
saw the same machine load, then their median is printed.  The cyclic garbage collector is
off while the clock runs, as in :mod:`timeit` (``--gc`` leaves it on).  Prints figures;
asserts nothing about time.

Run: ``.venv/bin/python tools/bench/bench_decode.py [--frames N] [--repeat N]``
"""

from __future__ import annotations

import argparse
import gc
import platform
import random
import statistics
import struct
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # run as a script from anywhere, without installing
    sys.path.insert(0, str(ROOT))

from pymavlink.dialects.v20 import common as mav  # noqa: E402

from gateway import wire  # noqa: E402
from gateway.model import SM_UPDATE_F32_LEN, SM_UPDATE_F64_LEN, SmUpdate, Status  # noqa: E402

TARGET_RATIO = 5.0  # the target: our decoder at least 5x pymavlink's parse_buffer
CHUNK = 4096
_F32 = struct.Struct("<f")


def _f32(x: float) -> float:
    """``x`` rounded to single precision (what the 36-byte revision carries)."""
    return _F32.unpack(_F32.pack(x))[0]


# -- streams ----------------------------------------------------------------------------------


def aurora_stream(frames: int, seed: int) -> bytes:
    """``frames`` Aurora frames: 7/10 SM_UPDATE f64, 2/10 SM_UPDATE f32, 1/10 STATUS."""
    rng = random.Random(seed)
    out = []
    t_ms = 0
    alt = vel = 0.0
    for k in range(frames):
        t_ms += rng.randint(8, 12)
        slot = k % 10
        if slot == 9:
            msg: SmUpdate | Status = Status(
                t_ms, rng.randrange(8), 0, Status.make_flags(
                    armed=rng.random() < 0.5, imu_ok=True, baro_ok=rng.random() < 0.9,
                    calibrated=True, log_ready=rng.random() < 0.7))
        else:
            vel += rng.uniform(-2.0, 3.0)
            alt = max(0.0, alt + vel * 0.01)
            vals = [alt, rng.uniform(-5.0, 60.0), rng.uniform(-12.0, 50.0), vel,
                    rng.uniform(-3.14, 3.14), rng.uniform(-1.5, 1.5), rng.uniform(-3.14, 3.14)]
            plen = SM_UPDATE_F32_LEN if slot in (3, 7) else SM_UPDATE_F64_LEN
            if plen == SM_UPDATE_F32_LEN:
                vals = [_f32(v) for v in vals]
            msg = SmUpdate(t_ms, rng.randrange(8), rng.random() < 0.5, 0, *vals,
                           payload_len=plen)
        out.append(wire.encode(msg))
    return b"".join(out)


class _Sink:
    """A write-only file for ``MAVLink(file=...)``: collects what ``send()`` writes."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.parts.append(bytes(data))


def mavlink_stream(frames: int, seed: int, kind: str) -> bytes:
    """``frames`` MAVLink 2 frames from sysid 1 / compid 1, packed by pymavlink's ``send()``."""
    rng = random.Random(seed)
    sink = _Sink()
    link = mav.MAVLink(sink, srcSystem=1, srcComponent=1)
    t_ms = 0

    def nz(lo: float, hi: float) -> float:
        # v2 trims trailing zero bytes of the payload; keep every frame its full size
        return rng.uniform(lo, hi) or 1e-3

    for k in range(frames):
        t_ms += rng.randint(8, 12)
        slot = k % 10 if kind == "mix" else 0
        if slot == 9:
            m: Any = link.heartbeat_encode(
                mav.MAV_TYPE_ROCKET, mav.MAV_AUTOPILOT_GENERIC,
                mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (128 if rng.random() < 0.5 else 0),
                rng.randrange(1, 8), mav.MAV_STATE_ACTIVE)
        elif slot in (3, 7):
            m = link.global_position_int_encode(
                t_ms, 473977418 + rng.randrange(-10000, 10000),
                85455939 + rng.randrange(-10000, 10000), rng.randrange(400000, 3000000),
                rng.randrange(1, 2500000), rng.randrange(-3000, 3000),
                rng.randrange(-3000, 3000), rng.randrange(-30000, 30000) or 1,
                rng.randrange(1, 36000))
        else:
            m = link.attitude_encode(t_ms, nz(-3.1, 3.1), nz(-1.5, 1.5), nz(-3.1, 3.1),
                                     nz(-2.0, 2.0), nz(-2.0, 2.0), nz(-2.0, 2.0))
        link.send(m)
    return b"".join(sink.parts)


def chunks(data: bytes, size: int) -> list[bytes]:
    return [data[i:i + size] for i in range(0, len(data), size)]


# -- the four timed cases ---------------------------------------------------------------------


def ours_whole(stream: bytes) -> list[Any]:
    dec = wire.Decoder("bench")
    out = dec.feed(stream)
    out += dec.flush()
    return out


def mav_whole(stream: bytes) -> list[Any]:
    return mav.MAVLink(None).parse_buffer(stream) or []


class _Timer:
    """Collect earlier garbage, then keep the cyclic GC off (unless asked) while timing.

    As in :mod:`timeit`: the whole-stream cases hold 100k live results, which makes the
    collector rescan them again and again, a cost a streaming gateway (messages die young,
    by reference count) does not pay.
    """

    def __init__(self, keep_gc: bool) -> None:
        self.keep_gc = keep_gc

    def __enter__(self) -> _Timer:
        gc.collect()
        if not self.keep_gc:
            gc.disable()
        return self

    def __exit__(self, *exc: object) -> None:
        gc.enable()


def time_whole(fn: Callable[[bytes], list[Any]], stream: bytes,
               keep_gc: bool) -> tuple[float, int]:
    """Seconds to decode ``stream`` in one call, and the message count (freeing not timed)."""
    with _Timer(keep_gc):
        t0 = time.perf_counter()
        out = fn(stream)
        dt = time.perf_counter() - t0
    n = len(out)
    del out
    return dt, n


def time_chunked(a_parts: Sequence[bytes], m_parts: Sequence[bytes], keep_gc: bool,
                 blocks: int = 16) -> tuple[float, float, int, int]:
    """Both decoders fed 4 KiB chunks, streaming: each chunk's messages are counted and
    dropped, as a live reader would.  The streams are cut into ``blocks`` blocks of chunks
    timed alternately (ours, pymavlink, ours, ...), so a change in machine load during the
    run falls on both sides alike.  Returns (our s, pymavlink s, our count, their count).
    """
    dec = wire.Decoder("bench")
    feed = dec.feed
    parse = mav.MAVLink(None).parse_buffer  # returns None when no message completed
    t_ours = t_mav = 0.0
    n_ours = n_mav = 0
    clock = time.perf_counter
    with _Timer(keep_gc):
        for b in range(blocks):
            mine = a_parts[len(a_parts) * b // blocks:len(a_parts) * (b + 1) // blocks]
            theirs = m_parts[len(m_parts) * b // blocks:len(m_parts) * (b + 1) // blocks]
            t0 = clock()
            for p in mine:
                n_ours += len(feed(p))
            if b == blocks - 1:
                n_ours += len(dec.flush())
            t1 = clock()
            for p in theirs:
                got = parse(p)
                if got:
                    n_mav += len(got)
            t2 = clock()
            t_ours += t1 - t0
            t_mav += t2 - t1
    return t_ours, t_mav, n_ours, n_mav


# -- checks and reporting ---------------------------------------------------------------------


def _collect_ours(parts: Sequence[bytes]) -> list[Any]:
    dec = wire.Decoder("bench")
    out: list[Any] = []
    for p in parts:
        out += dec.feed(p)
    return out + dec.flush()


def _collect_mav(parts: Sequence[bytes]) -> list[Any]:
    link = mav.MAVLink(None)
    out: list[Any] = []
    for p in parts:
        out += link.parse_buffer(p) or []
    return out


def verify(aurora: bytes, mavlink: bytes, frames: int) -> None:
    """Both decoders see exactly ``frames`` good messages, whole and chunked; exit otherwise."""
    problems = []
    for name, got in (("ours whole", ours_whole(aurora)),
                      ("ours 4 KiB", _collect_ours(chunks(aurora, CHUNK)))):
        if len(got) != frames:
            problems.append(f"{name}: {len(got)} messages, expected {frames}")
        elif b"".join(m.raw for m in got) != aurora:
            problems.append(f"{name}: decoded frames do not reproduce the stream")
        elif any(type(m) not in (SmUpdate, Status) for m in got):
            problems.append(f"{name}: undecoded frames")
    dec = wire.Decoder()
    dec.feed(aurora)
    dec.flush()
    st = dec.stats
    if st.crc_failures or st.bytes_skipped or st.frames != frames:
        problems.append(f"ours: stats {st.as_dict()}")
    for name, got in (("pymavlink whole", mav_whole(mavlink)),
                      ("pymavlink 4 KiB", _collect_mav(chunks(mavlink, CHUNK)))):
        if len(got) != frames:
            problems.append(f"{name}: {len(got)} messages, expected {frames}")
        elif any(m.get_type() == "BAD_DATA" for m in got):
            problems.append(f"{name}: BAD_DATA in the output")
    if problems:
        sys.exit("verification failed:\n  " + "\n  ".join(problems))


def crc_impl() -> str:
    """How the generated dialect computes its CRC (it tries fastcrc, else pure Python)."""
    if getattr(mav, "mcrf4xx", None) is not None and mav.x25crc is getattr(mav, "_x25crc_fast",
                                                                           None):
        return "fastcrc (crc16.mcrf4xx via x25crc = _x25crc_fast)"
    if hasattr(mav, "_x25crc_slow") and mav.x25crc is mav._x25crc_slow:
        return "pure Python (_x25crc_slow): fastcrc not importable"
    return f"unknown ({mav.x25crc!r})"


def pymavlink_version() -> str:
    try:
        from importlib.metadata import version

        return version("pymavlink")
    except Exception:
        return "?"


def summary(xs: Sequence[float]) -> tuple[float, float, float]:
    return statistics.median(xs), min(xs), max(xs)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=100_000, help="frames per stream (100000)")
    ap.add_argument("--repeat", type=int, default=7, help="repetitions; medians reported (7)")
    ap.add_argument("--seed", type=int, default=2024, help="stream seed (2024)")
    ap.add_argument("--mavlink", choices=("mix", "attitude"), default="mix",
                    help="MAVLink stream: ATTITUDE/GLOBAL_POSITION_INT/HEARTBEAT 7:2:1 (mix) "
                         "or ATTITUDE only")
    ap.add_argument("--gc", action="store_true",
                    help="leave the cyclic garbage collector on while timing (off by default, "
                         "as in timeit)")
    args = ap.parse_args(argv)
    if args.frames < 1 or args.repeat < 1:
        ap.error("--frames and --repeat must be positive")

    aurora = aurora_stream(args.frames, args.seed)
    mavlink = mavlink_stream(args.frames, args.seed, args.mavlink)
    a_parts, m_parts = chunks(aurora, CHUNK), chunks(mavlink, CHUNK)
    verify(aurora, mavlink, args.frames)

    names = ("ours, whole stream", "pymavlink, whole stream", "ours, 4 KiB chunks",
             "pymavlink, 4 KiB chunks")
    sizes = (len(aurora), len(mavlink), len(aurora), len(mavlink))
    times: list[list[float]] = [[] for _ in names]
    for rep in range(args.repeat + 1):  # repetition 0 warms up and is not counted
        t_a, n_a = time_whole(ours_whole, aurora, args.gc)
        t_b, n_b = time_whole(mav_whole, mavlink, args.gc)
        t_c, t_d, n_c, n_d = time_chunked(a_parts, m_parts, args.gc)
        for name, n in zip(names, (n_a, n_b, n_c, n_d), strict=True):
            if n != args.frames:  # cannot happen after verify(); never print a wrong figure
                sys.exit(f"{name}: decoded {n} messages, expected {args.frames}")
        if rep:
            for k, t in enumerate((t_a, t_b, t_c, t_d)):
                times[k].append(t)

    print(f"Python {platform.python_version()} ({platform.python_implementation()}), "
          f"{platform.machine()}, pymavlink {pymavlink_version()}, CRC: {crc_impl()}")
    print(f"{args.frames} frames per stream, {args.repeat} repetitions (+1 warm-up), "
          f"seed {args.seed}, cyclic GC {'on' if args.gc else 'off'} while timing")
    print(f"  Aurora : {len(aurora):>9} bytes, {len(aurora) / args.frames:5.1f} B/frame "
          "(SM_UPDATE f64:f32:STATUS = 7:2:1)")
    mix = "ATTITUDE:GLOBAL_POSITION_INT:HEARTBEAT = 7:2:1" if args.mavlink == "mix" \
        else "ATTITUDE only"
    print(f"  MAVLink: {len(mavlink):>9} bytes, {len(mavlink) / args.frames:5.1f} B/frame "
          f"(v2, {mix})")
    print()
    print(f"{'case':<26}{'frames/s (median)':>18}{'min':>11}{'max':>11}{'MB/s':>8}"
          f"{'ms/run':>9}")
    for name, size, ts in zip(names, sizes, times, strict=True):
        med, lo, hi = summary(ts)
        print(f"{name:<26}{args.frames / med:>18,.0f}{args.frames / hi:>11,.0f}"
              f"{args.frames / lo:>11,.0f}{size / med / 1e6:>8.1f}{med * 1e3:>9.1f}")
    print()
    for label, ours, theirs in (("whole stream", 0, 1), ("4 KiB chunks", 2, 3)):
        ratios = [t / o for o, t in zip(times[ours], times[theirs], strict=True)]
        med, lo, hi = summary(ratios)
        verdict = "meets" if med >= TARGET_RATIO else "BELOW"
        print(f"ours/pymavlink frames/s, {label}: median {med:.2f}x (min {lo:.2f}, "
              f"max {hi:.2f}) -- {verdict} the >= {TARGET_RATIO:g}x target")
    return 0


if __name__ == "__main__":
    sys.exit(main())
