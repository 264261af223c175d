"""Sweeps to convergence of CAVI with and without its accelerations (issue 18, items 2 and 3).

For each problem, ``cavi.fit`` from the thesis initialisation with every
acceleration of ``lmpromp_ppl.inference.cavi.ACCELERATIONS`` (``none`` is the
thesis's plain sweeps), tol = 1e-8, max_iter = 3000.  Reported: sweeps, whether
the fit converged, the final bound, whether the bound never fell from one sweep
to the next, the loop's seconds and seconds per sweep, and the compilation
seconds (the first fit of each problem compiles; the others reuse it).

Problems: the synthetic ``latent`` rows of ``lmpromp bench`` (``proper`` preset,
shared design) and real recordings with the package defaults (``default``
preset, the default basis, standardised).

    PYTHONPATH=. python benchmarks/cavi_sweeps.py --out benchmarks/cavi_sweeps.json
"""

from __future__ import annotations

import argparse
import json
import platform
import time
import warnings

import jax
import numpy as np

from lmpromp_ppl.basis import DEFAULT_NUM_BASIS
from lmpromp_ppl.bench.config import DEFAULT_ROW, SCALING_ROWS, row_hyper
from lmpromp_ppl.bench.data import row_demonstrations, shared_cavi_data
from lmpromp_ppl.data import prepare_dataset
from lmpromp_ppl.errors import ConvergenceWarning
from lmpromp_ppl.inference import cavi
from lmpromp_ppl.inference.compiled import clear
from lmpromp_ppl.models.hyper import preset

ROWS = ("default", "L1000", "L10000", "d420", "V10", "L1000_d420_V10")
REAL = ("lasa:GShape", "lasa:Angle", "lasa:Sshape", "lasa:Multi_Models_1", "gunpoint", "synthetic:latent")
MODES = ("none", "overrelax", "scale")


def _problems(rows, real):
    by_name = {row.name: row for row in SCALING_ROWS + (DEFAULT_ROW,)}
    for name in rows:
        row = by_name[name]
        start = time.perf_counter()
        data = shared_cavi_data(row_demonstrations(row), row.J)
        yield f"synthetic row {name} (L={row.L}, d={row.D * row.J}, V={row.V})", data, row_hyper(row), \
            time.perf_counter() - start
    for spec in real:
        start = time.perf_counter()
        data = cavi.sufficient_statistics(prepare_dataset(spec, DEFAULT_NUM_BASIS).model_data)
        yield spec, data, preset("default"), time.perf_counter() - start


def _fit(data, hyper, mode):
    state = cavi.init_state(data, hyper)
    arrays = cavi.hyper_arrays(hyper, 0.0, mode)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        result = cavi.run(state, data, arrays, 1e-8, 3000)
    trace = result.elbo_trace
    steps = np.diff(trace)
    return {
        "mode": mode,
        "sweeps": int(result.iterations),
        "converged": bool(result.converged),
        "elbo": float(trace[-1]),
        "monotone": bool(np.all(steps >= -1e-10 * np.abs(trace[1:]))),
        "fit_s": round(result.seconds, 4),
        "s_per_sweep": round(result.seconds / max(result.iterations, 1), 6),
        "compile_s": round(result.compile_seconds, 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/cavi_sweeps.json")
    parser.add_argument("--rows", default=",".join(ROWS))
    parser.add_argument("--real", default=",".join(REAL))
    args = parser.parse_args()
    rows = [r for r in args.rows.split(",") if r]
    real = [r for r in args.real.split(",") if r]
    results = []
    header = f"{'problem':<48} {'mode':<10} {'sweeps':>6} {'conv':>5} {'bound':>16} {'mono':>5} {'fit s':>8} {'ms/sweep':>9} {'compile s':>9}"
    print(header)
    for name, data, hyper, prepare_s in _problems(rows, real):
        clear()  # every problem compiles from a cold cache, measured on its first mode
        for mode in MODES:
            row = {"problem": name, "prepare_s": round(prepare_s, 3), **_fit(data, hyper, mode)}
            results.append(row)
            print(f"{name:<48} {mode:<10} {row['sweeps']:>6} {str(row['converged']):>5} {row['elbo']:>16.4f} "
                  f"{str(row['monotone']):>5} {row['fit_s']:>8.3f} {1000 * row['s_per_sweep']:>9.3f} {row['compile_s']:>9.2f}",
                  flush=True)
    for name in dict.fromkeys(r["problem"] for r in results):
        by_mode = {r["mode"]: r for r in results if r["problem"] == name}
        by_mode["scale"]["sweeps_ratio_to_none"] = round(by_mode["none"]["sweeps"] / by_mode["scale"]["sweeps"], 2)
    out = {
        "machine": {"python": platform.python_version(), "jax": jax.__version__, "cpu": platform.processor(),
                    "devices": [str(d) for d in jax.devices()]},
        "tol": 1e-8, "max_iter": 3000,
        "results": results,
    }
    with open(args.out, "w") as f:
        json.dump(out, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
