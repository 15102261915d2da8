"""Run a benchmark on two checkouts alternately, in one invocation: before and after a change.

``fanout``: each tree's own ``tools/bench/bench_fanout.py`` under its own ``.venv``; the
per-case µs/update (the bench's own median of its repetitions) and the ratio lines.
``router``: this checkout's ``tools/bench/bench_mavlink_router.py`` (one harness) with
``--no-peer --aurora-gateway <tree>/.venv/bin/aurora-gateway``: the same sender and receiver,
each tree's gateway; the rows of its summary table.

Rounds alternate before, after, before, after …; per figure the median over the rounds is
printed (with every round's value).  Arguments after ``--`` go to the benchmark.  Prints
figures; asserts nothing about time.

Run: ``.venv/bin/python tools/bench/compare_trees.py --before /path/to/old/checkout
[--rounds N] {fanout,router} [-- bench arguments]``
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_TABLE_ROW = re.compile(r"^(\S.*?\S)\s{2,}([\d.]+)\s")  # bench_fanout: case, µs/update, …
_RATIO = re.compile(r"^(.*?)\s*:\s*([\d.]+)x")  # bench_fanout: "dispatcher / floor …: 4.72x"
_MD_ROW = re.compile(r"^\| (.+?) \| (.+?) \|")  # the router bench's summary table


def _python(tree: Path) -> str:
    return str(tree / ".venv" / "bin" / "python")


def _command(kind: str, tree: Path, extra: list[str]) -> list[str]:
    if kind == "fanout":
        return [_python(tree), str(tree / "tools" / "bench" / "bench_fanout.py"), *extra]
    return [_python(ROOT), str(ROOT / "tools" / "bench" / "bench_mavlink_router.py"),
            "--no-peer", "--aurora-gateway", str(tree / ".venv" / "bin" / "aurora-gateway"),
            *extra]


def _figures(kind: str, text: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for line in text.splitlines():
        if kind == "fanout":
            m = _RATIO.match(line) or _TABLE_ROW.match(line)
            if m and not line.startswith(("case", "Python")):
                out[m.group(1).strip()] = m.group(2)
        else:
            m = _MD_ROW.match(line)
            if m and m.group(1) not in ("metric", "---"):
                out[m.group(1).strip()] = m.group(2).strip()
    return out


def _number(value: str) -> tuple[float, str] | None:
    """``"7.5k"`` → (7500, "k"), ``"2.84"`` → (2.84, ""), ``"0.54 ms"`` → (0.54, "ms");
    a lower bound (``"≥ 10k"``) counts as its bound; None when there is no number."""
    m = re.match(r"(?:[≥<]\s*)?([-+]?[\d.]+)\s*(k\b)?\s*(.*)$", value.strip())
    if m is None:
        return None
    scale = 1000.0 if m.group(2) else 1.0
    return float(m.group(1)) * scale, (m.group(2) or "") + (m.group(3) or "")


def _median(values: list[str]) -> str:
    nums = [_number(v) for v in values]
    if any(n is None for n in nums):
        return " / ".join(values)
    med = statistics.median(n[0] for n in nums if n is not None)
    unit = nums[0][1] if nums[0] is not None else ""
    if unit.startswith("k"):
        return f"{med / 1000:g}k{unit[1:]}"
    return f"{med:g}{(' ' + unit) if unit else ''}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--before", type=Path, required=True, help="the old checkout (its .venv)")
    ap.add_argument("--rounds", type=int, default=2, help="rounds per tree, alternating (2)")
    ap.add_argument("kind", choices=("fanout", "router"))
    ap.add_argument("extra", nargs=argparse.REMAINDER, help="-- then the bench's arguments")
    args = ap.parse_args(argv)
    extra = args.extra[1:] if args.extra[:1] == ["--"] else args.extra
    trees = {"before": args.before.resolve(), "after": ROOT}
    for label, tree in trees.items():
        head = subprocess.run(["git", "-C", str(tree), "log", "-1", "--format=%h %s"],
                              capture_output=True, text=True, check=False).stdout.strip()
        print(f"{label:6}: {tree} @ {head[:72]}")
    runs: dict[str, list[dict[str, str]]] = {label: [] for label in trees}
    for k in range(args.rounds):
        for label, tree in trees.items():
            cmd = _command(args.kind, tree, extra)
            print(f"[round {k + 1}] {label}: {' '.join(cmd)}", flush=True)
            res = subprocess.run(cmd, capture_output=True, text=True, cwd=tree, check=False)
            if res.returncode != 0:
                print(res.stdout[-3000:], res.stderr[-3000:], sep="\n")
                return 1
            runs[label].append(_figures(args.kind, res.stdout))
    keys = list(runs["after"][0])
    width = max(len(k) for k in keys)
    print(f"\n{'figure':{width}}  {'before (median)':>16}  {'after (median)':>16}   rounds")
    for key in keys:
        b = [r.get(key, "?") for r in runs["before"]]
        a = [r.get(key, "?") for r in runs["after"]]
        print(f"{key:{width}}  {_median(b):>16}  {_median(a):>16}   "
              f"before {', '.join(b)}; after {', '.join(a)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
