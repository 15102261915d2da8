"""How tests/data's recordings of the previous release were made (kept for the record; the
tests read the files, they never run this).

Run with the package as it was before issue 24 (commit 7c8f6f5), not the working tree's::

    git archive 7c8f6f5 gateway dialects | tar -x -C OLD
    # then run this file with OLD first on the import path (and the editable install's
    # finder out of sys.meta_path), from the repository root

It writes flight-v1.aur (version 1) and flight-v2.aur (version 2 of frames only: rocket
"alpha", and "beta" every other frame) from the simulated flight's first 40 s at 2 Hz, then
that release's ``export`` (csv, jsonl) and ``decode`` of each: what tests/
test_recording_kinds.py compares today's output with, byte for byte.
"""

import contextlib
import itertools
from pathlib import Path

from gateway.commands.cli import main
from gateway.flight import FlightModel
from gateway.recorder import Recorder
from gateway.recording import HEADER_V1, encode_record_v1
from gateway.sources.sim import flight_frames

T0 = 1_790_000_000.0
out = Path("tests/data")
model = FlightModel()
frames = list(itertools.takewhile(lambda tf: tf[0] <= 40.0,
                                  flight_frames(model, rate_hz=2.0, status_hz=0.5)))
v1 = out / "flight-v1.aur"
v1.write_bytes(HEADER_V1 + b"".join(encode_record_v1(T0 + t, f) for t, f in frames))
v2 = out / "flight-v2.aur"
v2.unlink(missing_ok=True)
rec = Recorder(v2)
for i, (t, f) in enumerate(frames):
    rec.write(f, t=T0 + t, vehicle="alpha", source="alpha")
    if i % 2 == 0:
        rec.write(f, t=T0 + t + 0.01, vehicle="beta", source="serial-b")
rec.close()

for name in ("flight-v1", "flight-v2"):
    src = f"tests/data/{name}.aur"
    for fmt in ("csv", "jsonl"):
        assert main(["export", src, "--format", fmt, "-o", f"tests/data/{name}.{fmt}"]) == 0
    with open(f"tests/data/{name}.decode.jsonl", "w") as f, contextlib.redirect_stdout(f):
        assert main(["decode", src]) == 0
