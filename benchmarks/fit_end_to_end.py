"""What a user waits for: `lmpromp fit` end to end on large synthetic datasets, with peak memory.

Each row writes a synthetic latent-manifold dataset (thesis eq. 4.1; L
demonstrations, D = 7 DoF, T = 120 samples, generated with J = 60 and V = 10)
to an ``.npz`` file, then runs in a fresh process what ``lmpromp fit FILE
--engine cavi --num-basis 60 --latent-dim 10 --out DIR`` runs, timing each
stage a user waits for:

* ``import_s``: importing lmpromp_ppl (JAX, NumPyro, ArviZ);
* ``load_s``: reading and validating the file (:func:`lmpromp_ppl.data.load_dataset`);
* ``prepare_s``: standardising and building the model inputs (:func:`lmpromp_ppl.prepare_dataset`);
* ``fit_s``: :func:`lmpromp_ppl.fit` on the prepared data, of which ``compile_s``
  is compilation and ``loop_s`` the compiled sweeps (the fit's own ``compile_seconds``
  and ``seconds``); the rest is the start (ridge + PCA), the restarts' bookkeeping and
  the degeneracy checks;
* ``save_s``: writing ``posterior.nc`` and ``summary.json`` (draws from q thinned to the
  saved size);
* ``peak_rss_gb``: the process's peak resident memory (``ru_maxrss``), JAX's runtime included;
  ``baseline_rss_gb`` is the same figure right after the imports.

Run from the repository root (about 2 minutes for both rows on 2 cores)::

    python benchmarks/fit_end_to_end.py --out benchmarks/fit_end_to_end.json
    python benchmarks/fit_end_to_end.py --rows 1000 --out /tmp/e2e.json   # one row

Targets (issue 18, 2 cores): L = 1000 converged, under 5 s after compilation
(``fit_s - compile_s + prepare_s``), peak memory under 1 GB; L = 10 000 under 60 s and
4 GB.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

NUM_DOFS, NUM_STEPS, NUM_BASIS, LATENT_DIM = 7, 120, 60, 10


def _rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2  # kB on Linux


def child(path: str, out_dir: str) -> dict:
    """One end-to-end fit in this process (the stages of the module docstring)."""
    start = time.perf_counter()
    import lmpromp_ppl as lp

    row = {"import_s": time.perf_counter() - start, "baseline_rss_gb": _rss_gb()}
    t = time.perf_counter()
    demos = lp.data.load_dataset(path)
    row["load_s"] = time.perf_counter() - t
    t = time.perf_counter()
    prepared = lp.prepare_dataset(demos, NUM_BASIS)
    row["prepare_s"] = time.perf_counter() - t
    t = time.perf_counter()
    result = lp.fit(prepared, model="lmpromp", engine="cavi", hyper=lp.preset("default", latent_dim=LATENT_DIM))
    row["fit_s"] = time.perf_counter() - t
    t = time.perf_counter()
    result.save(out_dir, force=True)
    row["save_s"] = time.perf_counter() - t
    summary = result.summary
    row.update(
        compile_s=summary.get("compile_seconds"),
        loop_s=summary.get("seconds"),
        iterations=summary.get("iterations"),
        converged=summary.get("converged"),
        elbo=summary.get("elbo"),
        peak_rss_gb=_rss_gb(),
        total_s=time.perf_counter() - start,
    )
    row["after_compile_s"] = row["prepare_s"] + row["fit_s"] - (row["compile_s"] or 0.0)
    return row


def write_dataset(num_demos: int, path: Path) -> float:
    from lmpromp_ppl.data.files import save_npz
    from lmpromp_ppl.data.synthetic import latent_manifold

    t = time.perf_counter()
    demos = latent_manifold(L=num_demos, D=NUM_DOFS, J=NUM_BASIS, V=LATENT_DIM, T=NUM_STEPS, seed=0)
    save_npz(demos, path, overwrite=True)
    return time.perf_counter() - t


TARGETS = {1000: {"after_compile_s": 5.0, "peak_rss_gb": 1.0}, 10000: {"after_compile_s": 60.0, "peak_rss_gb": 4.0}}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", default="1000,10000", help="numbers of demonstrations, comma-separated")
    parser.add_argument("--out", type=Path, default=None, help="JSON file to write")
    parser.add_argument("--child", nargs=2, metavar=("DATA", "OUT_DIR"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(*args.child)))
        return
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for num_demos in (int(x) for x in args.rows.split(",")):
            path = Path(tmp) / f"latent-{num_demos}.npz"
            generate_s = write_dataset(num_demos, path)
            proc = subprocess.run(
                [sys.executable, __file__, "--child", str(path), str(Path(tmp) / f"fit-{num_demos}")],
                capture_output=True, text=True,
            )
            if proc.returncode != 0:
                row = {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"exit {proc.returncode}"}
            else:
                row = json.loads(proc.stdout.strip().splitlines()[-1])
            row.update(L=num_demos, D=NUM_DOFS, T=NUM_STEPS, J=NUM_BASIS, V=LATENT_DIM, d=NUM_DOFS * NUM_BASIS,
                       generate_s=generate_s)
            goal = TARGETS.get(num_demos)
            if goal and "error" not in row:
                row["targets"] = goal
                row["met"] = bool(row["converged"]) and all(row[k] <= v for k, v in goal.items())
            rows.append(row)
            print(_line(row), flush=True)
    from lmpromp_ppl.bench.machine import machine_info

    report = {"benchmark": "fit_end_to_end", "machine": machine_info(), "rows": rows}
    if args.out is not None:
        args.out.write_text(json.dumps(report, indent=2) + "\n")


COLUMNS = ("L", "load_s", "prepare_s", "compile_s", "loop_s", "fit_s", "save_s", "after_compile_s", "iterations",
           "converged", "peak_rss_gb", "met")


def _line(row: dict) -> str:
    if "error" in row:
        return f"L={row['L']}: failed: {row['error']}"
    cells = []
    for k in COLUMNS:
        v = row.get(k)
        cells.append(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}")
    return "  ".join(cells)


if __name__ == "__main__":
    main()
