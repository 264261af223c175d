"""What ``cavi_lr`` costs against the mean-field CAVI fit (issue 19: at most 10x on the default row).

For each row (the default problem of ``lmpromp bench`` and three larger ones) this times,
in one process, on the same standardised synthetic demonstrations and hyperparameters
(``lmpromp_ppl.bench.row_hyper``):

* ``cavi``: ``cavi.fit`` (mean-field family, column-wise q(M), the engine's defaults);
* ``cavi_lr``: ``cavi.fit_lr`` (joint local family, row-wise q(M), the linear response
  and the importance ratios of 4000 draws on the collapsed model with their k-hat).

``cold_s`` is the first call (compilation included), ``fit_s`` the best of ``--repeats``
later calls (compiled programs reused): the wall time of the whole call, as a user
waits for it.  ``ratio`` is cavi_lr's ``fit_s`` over cavi's.  ``draws_s`` times
``--draws`` draws after the fit, as ``FitResult.to_datatree`` takes them: ``cavi.sample_q``
for CAVI, and ``CaviLrFit.sample`` for ``cavi_lr``, whose draws end with
``REFRESH_SWEEPS`` exact-conditional sweeps each (:mod:`lmpromp_ppl.inference.refresh`);
``total_ratio`` is (fit + draws) of cavi_lr over (fit + draws) of cavi, ``cold_total_ratio`` the
same for the first calls (compilation included, what a user of a fresh process waits for).  Run from the repository
root (about 2 minutes on 2 cores)::

    python benchmarks/cavi_lr_cost.py --out benchmarks/cavi_lr_cost.json
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import jax

from lmpromp_ppl.bench.config import DEFAULT_ROW, SCALING_ROWS, row_hyper
from lmpromp_ppl.bench.data import row_demonstrations
from lmpromp_ppl.bench.machine import machine_info
from lmpromp_ppl.data import model_data
from lmpromp_ppl.inference import cavi

TARGET_RATIO = 10.0
ROWS = (DEFAULT_ROW,) + tuple(r for r in SCALING_ROWS if r.name in ("L100", "d120", "V10"))


def _time(call, repeats: int) -> tuple[float, float, object]:
    start = time.perf_counter()
    out = call()
    cold = time.perf_counter() - start
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        out = call()
        best = min(best, time.perf_counter() - start)
    return cold, best, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/cavi_lr_cost.json")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--draws", type=int, default=1000)
    args = parser.parse_args()
    rows = []
    print(f"{'row':8s} {'L':>5s} {'d':>4s} {'V':>3s} {'cavi s':>8s} {'cavi_lr s':>10s} {'ratio':>6s} "
          f"{'cold cavi':>10s} {'cold lr':>8s} {'k-hat':>6s} {'draws cavi':>10s} {'draws lr':>9s} {'total':>6s} {'cold total':>10s}")
    for row in ROWS:
        data = model_data(row_demonstrations(row), row.J)
        hyper = row_hyper(row)
        key = jax.random.key(0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cold_c, fit_c, _ = _time(lambda: cavi.fit(data, hyper, key), args.repeats)
            cold_l, fit_l, lr = _time(lambda: cavi.fit_lr(data, hyper, key), args.repeats)
            fitted = cavi.fit(data, hyper, key)
            cold_dc, draws_c, _ = _time(lambda: jax.block_until_ready(cavi.sample_q(key, fitted.state, args.draws)),
                                        args.repeats)
            cold_dl, draws_l, _ = _time(lambda: jax.block_until_ready(lr.sample(key, args.draws)), args.repeats)
        entry = {"row": row.name, "L": row.L, "d": row.d, "V": row.V,
                 "cavi": {"fit_s": fit_c, "cold_s": cold_c},
                 "cavi_lr": {"fit_s": fit_l, "cold_s": cold_l, "lr_seconds": lr.lr_seconds,
                             "lr_compile_seconds": lr.lr_compile_seconds, "psis_khat": lr.psis_khat,
                             "cg_residual": float(lr.lr.residual), "iterations": int(lr.fit.iterations)},
                 "ratio": fit_l / fit_c, "draws": args.draws, "refresh_sweeps": lr.refresh,
                 "draws_s": {"cavi": draws_c, "cavi_lr": draws_l},
                 "cold_draws_s": {"cavi": cold_dc, "cavi_lr": cold_dl},
                 "total_ratio": (fit_l + draws_l) / (fit_c + draws_c),
                 "cold_total_ratio": (cold_l + cold_dl) / (cold_c + cold_dc)}
        rows.append(entry)
        khat = "-" if lr.psis_khat is None else f"{lr.psis_khat:.2f}"
        print(f"{row.name:8s} {row.L:5d} {row.d:4d} {row.V:3d} {fit_c:8.3f} {fit_l:10.3f} {fit_l / fit_c:6.1f} "
              f"{cold_c:10.1f} {cold_l:8.1f} {khat:>6s} {draws_c:10.3f} {draws_l:9.3f} {entry['total_ratio']:6.1f} {entry['cold_total_ratio']:10.1f}")
    default = rows[0]
    verdict = "met" if default["ratio"] <= TARGET_RATIO else "missed"
    print(f"default row: cavi_lr / cavi = {default['ratio']:.1f} (target <= {TARGET_RATIO:g}: {verdict}); "
          f"with {args.draws} draws ({default['refresh_sweeps']} sweeps each): {default['total_ratio']:.1f}; "
          f"first calls in a fresh process, compilation included: {default['cold_total_ratio']:.1f}")
    with open(args.out, "w") as f:
        json.dump({"machine": machine_info(), "repeats": args.repeats, "draws": args.draws, "target_ratio": TARGET_RATIO,
                   "rows": rows}, f, indent=2)
        f.write("\n")


if __name__ == "__main__":
    main()
