"""The benchmark driver: every row, the batch and the baseline, timed as a user waits for them."""

from __future__ import annotations

import dataclasses
import datetime
import os
import warnings
from typing import Any, Callable

import jax
import numpy as np

from lmpromp_ppl.bench.config import DEFAULT_ROW, BenchConfig, RowSpec, log, row_hyper
from lmpromp_ppl.bench.data import row_demonstrations, shared_cavi_data
from lmpromp_ppl.bench.engines import bench_batch, bench_cavi, bench_nuts, bench_promp_baseline, bench_svi
from lmpromp_ppl.bench.machine import machine_info, matmul_rate
from lmpromp_ppl.bench.report import evaluate_goals
from lmpromp_ppl.data.prepared import prepare_dataset
from lmpromp_ppl.errors import ConvergenceWarning, LmprompError
from lmpromp_ppl.results import to_json_value

__all__ = ["run_benchmark"]


def _not_run(reason: str) -> dict:
    return {"run": False, "reason": reason}


def _bench_row(row: RowSpec, config: BenchConfig, peak_rate: float) -> dict:
    hyper = row_hyper(row)
    demos = row_demonstrations(row)
    data = shared_cavi_data(demos, row.J)
    out: dict[str, Any] = {
        "name": row.name, "L": row.L, "D": row.D, "J": row.J, "d": row.d, "V": row.V, "K": row.K,
        "T": row.T, "seed": row.seed, "cores": machine_info()["cores"],
        "data": demos.name, "hyperparameters": "preset proper: " + str(hyper.to_dict()),
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        out["cavi"], _ = bench_cavi(row, data, config, peak_rate)
    log(config, f"{row.name}: cavi {out['cavi']['fit_s'] * 1e3:.2f} ms, {out['cavi']['iterations']} iterations")
    # the engines other than CAVI read padded model inputs from the one data path (already standardised)
    md = prepare_dataset(demos, row.J, standardise=False).model_data if row.engines else None
    key = jax.random.key(config.seed)
    for engine in ("svi_meanfield", "svi_autonormal"):
        if engine not in row.engines:
            out[engine] = _not_run("not run on this row: outside the stated SVI budget")
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            out[engine] = bench_svi(engine, md, hyper, key, out["cavi"]["elbo"], out["cavi"]["elbo_init"],
                                    config.svi)
        log(config, f"{row.name}: {engine} {out[engine]['fit_s']:.2f} s, {out[engine]['steps']} steps, "
                     f"gap {out[engine]['elbo_gap']:.3g} (target {out[engine]['gap_target']:.3g})")
    if "nuts" in row.engines:
        out["nuts"] = bench_nuts(md, hyper, key, config.nuts)
        log(config, f"{row.name}: nuts {out['nuts']['fit_s']:.1f} s, min bulk ESS {out['nuts']['ess_bulk_min']:.0f}")
    else:
        out["nuts"] = _not_run("not run on this row: NUTS needs minutes per problem; it runs on the default row only")
    fit = out["cavi"]["fit_s"]
    ratio = lambda e: out[e]["fit_s"] / fit if out[e].get("run", True) else None  # noqa: E731
    out["ratios"] = {
        "nuts_over_cavi": ratio("nuts"),
        "svi_over_cavi": ratio("svi_meanfield"),
        "svi_autonormal_over_cavi": ratio("svi_autonormal"),
        "note": "wall time excluding compilation over CAVI's fit_s; svi_over_cavi is svi_meanfield "
                "(CAVI's family, the same ELBO); an SVI ratio is a lower bound when it did not reach the target",
    }
    return out


def _scaling_exponent(rows: list[dict]) -> dict | None:
    """Least-squares slope of log(seconds per sweep) on log L over the rows that vary only L."""
    series = sorted((r for r in rows if r["K"] == 1 and r["D"] == 2 and r["J"] == 10 and r["V"] == 3),
                    key=lambda r: r["L"])
    if len({r["L"] for r in series}) < 2:
        return None
    L = np.array([r["L"] for r in series], float)
    per_iter = np.array([r["cavi"]["s_per_iteration"] for r in series])
    slope_all = float(np.polyfit(np.log(L), np.log(per_iter), 1)[0])
    large = L >= 100
    slope_large = float(np.polyfit(np.log(L[large]), np.log(per_iter[large]), 1)[0]) if large.sum() >= 2 else None
    flops = [r["cavi"]["flops_per_iteration"] for r in series]
    flop_slope = (float(np.polyfit(np.log(L), np.log(np.asarray(flops, float)), 1)[0])
                  if all(f is not None for f in flops) else None)
    return {
        "L": L.tolist(),
        "s_per_iteration": per_iter.tolist(),
        "flops_per_iteration": flops,
        "flops_exponent": flop_slope,
        "exponent": slope_all,
        "exponent_L_ge_100": slope_large,
        "goal": "linear (exponent 1); at small L the fixed cost of a sweep dominates; "
                "flops_exponent is the same fit to XLA's operation count (free of timing noise)",
    }


def run_benchmark(config: BenchConfig, device: str = "cpu", gpu_note: str = "",
                  on_update: Callable[[dict], None] | None = None) -> dict:
    """Run every row, the batch row and the ProMP baseline; return the JSON document.

    Parameters
    ----------
    config : rows and settings
    device : ``"cpu"`` or ``"gpu"`` (jax's default backend must match)
    gpu_note : on a CPU run, why no GPU run accompanies it (the ``gpu`` entry's ``reason``)
    on_update : called with the document so far (``"complete": false``) after every row,
        so that a caller can save partial results of a long run
    """
    if device not in ("cpu", "gpu"):
        raise LmprompError(f"device must be 'cpu' or 'gpu', got {device!r}")
    if jax.default_backend() != device:
        raise LmprompError(
            f"--device {device} asked for, but jax's default backend is {jax.default_backend()!r}"
        )
    started = datetime.datetime.now(datetime.timezone.utc)
    machine = machine_info()
    peak = matmul_rate(config.matmul_size)
    machine["matmul_flop_rate"] = peak
    machine["matmul"] = f"float64 {config.matmul_size} x {config.matmul_size} matrix product, best of 5"
    log(config, f"matmul rate {peak / 1e9:.1f} GFLOP/s")
    gpu = ({"run": True, "device": machine["jax_devices"]} if device == "gpu" else
           _not_run(gpu_note or "this is a CPU run; run `lmpromp bench --device gpu` on a GPU machine"))
    rows: list[dict] = []
    batch = None
    baseline: dict = _not_run("not reached yet")

    def document(complete: bool) -> dict:
        machine["load_average_now"] = list(os.getloadavg()) if hasattr(os, "getloadavg") else None
        return to_json_value({
            "format": "lmpromp-bench/1",
            "complete": complete,
            "created": started.isoformat(timespec="seconds"),
            "device": device,
            "machine": machine,
            "settings": {
                "model": "lmpromp (mixture of K LMProMPs when K > 1), hyperparameter preset 'proper'",
                "data": "standardised synthetic:latent (thesis eq. 4.1), one time grid per row",
                "cavi": {"tol": config.tol, "max_iter": config.max_iter, "timing_sweeps": config.timing_sweeps,
                         "repeats": config.repeats, "budget_s": config.cavi_budget_s},
                "svi": dataclasses.asdict(config.svi),
                "nuts": dataclasses.asdict(config.nuts),
                "seed": config.seed,
            },
            "rows": rows,
            "scaling": _scaling_exponent(rows),
            "batch": batch,
            "promp_baseline": baseline,
            "gpu": gpu,
            "goals": evaluate_goals(rows, batch),
        })

    for row in config.rows:
        rows.append(_bench_row(row, config, peak))
        if on_update is not None:
            on_update(document(False))
    if config.batch_size > 0:
        batch = bench_batch(config.batch_row or DEFAULT_ROW, config.batch_size, config)
        log(config, f"batch: {batch['datasets']} datasets in {batch['fit_s']:.2f} s")
        if on_update is not None:
            on_update(document(False))
    baseline = (bench_promp_baseline(config.baseline_dataset, config.baseline_num_basis)
                if config.baseline_dataset else _not_run("not requested"))
    return document(True)
