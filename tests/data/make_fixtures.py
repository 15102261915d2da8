"""Writes tests/data/flight-v1.aur and flight-v2.aur with main's recorder before issue 24."""
import itertools
from pathlib import Path

from gateway.flight import FlightModel
from gateway.recorder import Recorder
from gateway.recording import HEADER_V1, encode_record_v1
from gateway.sources.sim import flight_frames

T0 = 1_790_000_000.0
out = Path("tests/data")
model = FlightModel()
frames = list(itertools.takewhile(lambda tf: tf[0] <= 40.0,
                                  flight_frames(model, rate_hz=2.0, status_hz=0.5)))
print(len(frames), model.cycle_s)
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
print(v1.stat().st_size, v2.stat().st_size)
