"""Calibration report: PIT-ECDF figures, the uniformity table and ``calibration.json``.

:func:`write_sbc_report` turns the task records of an SBC run into

* ``DIR/pit_ecdf_MODEL_ENGINE.png``: arviz-plots ``plot_ecdf_pit`` of the
  PIT values of every quantity: the difference between the empirical CDF and
  the uniform CDF, annotated with the simultaneous ``pot_c`` uniformity test's
  p-value and the points that test flags (arviz-plots deprecates its
  ``"envelope"`` band method because it assumes independent PIT values);
* ``DIR/uniformity.md``: one row per (model, engine, quantity) of
  :func:`lmpromp_ppl.calibration.sbc.summarize`;
* ``DIR/calibration.json``: ``{"problem", "num_replicates", "rows", "vsbc_numpyro", "failed"}``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lmpromp_ppl.calibration.sbc import collect, pit_values, summarize
from lmpromp_ppl.results import to_json_value

__all__ = ["plot_pit_ecdf", "uniformity_markdown", "write_sbc_report"]


def plot_pit_ecdf(pit: Mapping[str, np.ndarray], path: Path, title: str) -> None:
    """arviz-plots PIT-ECDF (difference form, ``pot_c`` test) of ``pit`` (name -> (R, k)) into ``path``."""
    import arviz_plots as azp
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import xarray as xr

    variables = {}
    coords = {}
    for name, values in pit.items():
        values = np.asarray(values)
        if values.shape[1] == 1:
            variables[name] = (("replicate",), values[:, 0])
        else:
            variables[name] = (("replicate", f"{name}_dim"), values)
            coords[f"{name}_dim"] = np.arange(values.shape[1])
    tree = xr.DataTree.from_dict({"prior_sbc": xr.Dataset(variables, coords=coords)})
    collection = azp.plot_ecdf_pit(tree, sample_dims=["replicate"], method="pot_c",
                                   backend="matplotlib")
    plt.gcf().suptitle(title)
    collection.savefig(str(path))
    plt.close("all")


def uniformity_markdown(rows: list[Mapping[str, Any]]) -> str:
    """The summary rows as a Markdown table."""
    header = ("| model | engine | quantity | k | R | min p (pot_c) | Bonferroni p | cov50 | cov90 | "
              "sd/rmse | VSBC min p |\n|---|---|---|---|---|---|---|---|---|---|---|\n")
    fmt = lambda x: "n/a" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.3g}"  # noqa: E731
    lines = [
        f"| {r['model']} | {r['engine']} | {r['quantity']} | {r['components']} | {r['replicates']} | "
        f"{fmt(r['pvalue_min'])} | {fmt(r['pvalue_bonferroni'])} | {fmt(r['coverage50'])} | "
        f"{fmt(r['coverage90'])} | {fmt(r['sd_ratio'])} | {fmt(r['vsbc_pvalue_min'])} |"
        for r in rows
    ]
    return header + "\n".join(lines) + "\n"


def write_sbc_report(
    records: Mapping[str, Mapping[str, Any]], out_dir: Path, *, problems: Mapping[str, dict],
    num_draws: int, seed: int = 0, figures: bool = True,
) -> dict[str, Any]:
    """Write the figures, ``uniformity.md`` and ``calibration.json``; returns the JSON content.

    Parameters
    ----------
    records : task id -> record of :func:`lmpromp_ppl.calibration.runner.run_tasks`
    out_dir : report directory
    problems : model -> ``SbcProblem.to_dict()``, stored in the JSON
    num_draws : N, posterior draws per replicate
    seed : seed of the PIT jitter
    figures : write the PIT-ECDF figures
    """
    out_dir = Path(out_dir)
    ok = [r for r in records.values() if r.get("status") == "ok"]
    sbc_results = [r["result"] for r in ok if r["spec"].get("kind") == "sbc"]
    collected = collect(sbc_results)
    rows = summarize(collected, num_draws, seed=seed)
    if figures:
        for number, ((model, engine), entry) in enumerate(sorted(collected.items())):
            rng = np.random.default_rng([seed, 7919, number])
            pit = {name: pit_values(ranks, num_draws, rng) for name, ranks in entry["ranks"].items()}
            if next(iter(pit.values())).shape[0] >= 2:
                plot_pit_ecdf(pit, out_dir / f"pit_ecdf_{model}_{engine}.png",
                              f"SBC PIT-ECDF: {model} / {engine} (R = {len(entry['indices'])})")
    vsbc = {r["result"]["model"]: {"ks_pvalues": r["result"]["ks_pvalues"], "ks_stats": r["result"]["ks_stats"]}
            for r in ok if r["spec"].get("kind") == "vsbc_numpyro"}
    content = to_json_value({
        "problem": dict(problems),
        "num_draws": int(num_draws),
        "engines": {f"{m}/{e}": {"replicates": int(len(v["indices"])), "seconds": v["seconds"],
                                 "not_converged": v["not_converged"], "divergences": v["divergences"],
                                 **({"importance": v["importance"]} if "importance" in v else {})}
                    for (m, e), v in sorted(collected.items())},
        "rows": rows,
        "vsbc_numpyro": vsbc,
        "failed": {task_id: r.get("error") for task_id, r in records.items() if r.get("status") != "ok"},
    })
    (out_dir / "uniformity.md").write_text(uniformity_markdown(rows))
    (out_dir / "calibration.json").write_text(json.dumps(content, indent=1, allow_nan=False))
    return content
