"""What a new user waits for first: ``lmpromp demo`` (``make demo`` after its install), in a fresh process.

Each repeat runs ``lmpromp demo --quiet --out DIR`` as a new process, so every
program compiles from a cold cache as on a user's first run, and records:

* ``wall_s``: the whole command (imports, data, five engines, diagnostics, report);
* per engine, the fit's own ``seconds`` (run) and ``compile_seconds`` from the report's
  ``metrics.json`` (the rest of an engine's time is its start, its draws and checks);
* the machine's float64 matrix-product rate (:func:`lmpromp_ppl.bench.matmul_rate`) and
  load average, since compilation time follows the processor, not the core count.

Run from the repository root (about 1.5 minutes per repeat on 2 cores)::

    python benchmarks/demo_time.py --out benchmarks/demo_time.json

Target (issue 18, 2 cores): ``make demo`` (all engines, the report written) under 90 s
after installation, i.e. ``wall_s`` below 90.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TARGET_S = 90.0


def _lmpromp() -> list[str]:
    """The command line of this interpreter's ``lmpromp`` entry point."""
    script = Path(sys.executable).with_name("lmpromp")
    return [str(script)] if script.exists() else [sys.executable, "-m", "lmpromp_ppl.cli"]


def one_run(seed: int) -> dict:
    """One ``lmpromp demo`` in a fresh process; its wall time and the engines' own timings."""
    out = Path(tempfile.mkdtemp(prefix="lmpromp-demo-bench-")) / "demo"
    try:
        start = time.perf_counter()
        subprocess.run(_lmpromp() + ["demo", "--quiet", "--seed", str(seed), "--out", str(out)], check=True)
        wall = time.perf_counter() - start
        metrics = json.loads((out / "compare" / "metrics.json").read_text())
    finally:
        shutil.rmtree(out.parent, ignore_errors=True)
    engines = {name: {"seconds": e.get("seconds"), "compile_seconds": e.get("compile_seconds")}
               for name, e in metrics["engines"].items()}
    return {"wall_s": wall, "engines": engines, "nuts_rhat_max": metrics["engines"]["nuts"].get("rhat_max")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="output JSON file")
    parser.add_argument("--repeats", type=int, default=2, help="fresh-process runs (default 2)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from lmpromp_ppl.bench import machine_info, matmul_rate

    machine = machine_info()
    machine["matmul_flop_rate"] = matmul_rate()
    runs = []
    for i in range(args.repeats):
        runs.append(one_run(args.seed))
        print(f"run {i + 1}/{args.repeats}: {runs[-1]['wall_s']:.1f} s", file=sys.stderr, flush=True)
    walls = [r["wall_s"] for r in runs]
    machine["load_average_after"] = list(os.getloadavg())
    document = {
        "format": "lmpromp-demo-time/1",
        "command": "lmpromp demo --quiet (a fresh process per run)",
        "machine": machine,
        "runs": runs,
        "wall_s_min": min(walls),
        "wall_s_median": statistics.median(walls),
        "wall_s_max": max(walls),
        "target_s": TARGET_S,
        "met": max(walls) < TARGET_S,
    }
    args.out.write_text(json.dumps(document, indent=2) + "\n")
    print(f"{'run':>4} {'wall s':>8}  " + "  ".join(f"{n:>16}" for n in runs[0]["engines"]))
    for i, r in enumerate(runs):
        cells = "  ".join(f"{e['seconds']:7.1f} +{e['compile_seconds']:6.1f}c" for e in r["engines"].values())
        print(f"{i + 1:>4} {r['wall_s']:8.1f}  {cells}")
    print(f"matmul rate {machine['matmul_flop_rate'] / 1e9:.0f} GFLOP/s; target {TARGET_S:g} s: "
          f"{'met' if document['met'] else 'not met'}; wrote {args.out}")


if __name__ == "__main__":
    main()
