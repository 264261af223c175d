"""The goals a benchmark run is judged on, and its table."""

from __future__ import annotations

from typing import Any

from lmpromp_ppl.bench.config import GOAL_ROW_NAME

__all__ = ["evaluate_goals", "format_table"]


def _goal(target: str, measured: float | None, met: bool | None, note: str = "") -> dict:
    out = {"target": target, "measured": measured, "met": met}
    if note:
        out["note"] = note
    return out


def evaluate_goals(rows: list[dict], batch: dict | None) -> dict:
    """The issue's goals with their measured figures (``met`` is null when not measured)."""
    by_name = {r["name"]: r for r in rows}
    default = by_name.get("default")
    goals: dict[str, dict] = {}
    if default is not None:
        fit = default["cavi"]["fit_s"]
        goals["default_cavi_under_20ms"] = _goal("CAVI fit_s < 0.020 s on the default problem", fit, fit < 0.020)
        ratio = default["ratios"]["nuts_over_cavi"]
        goals["default_1000x_faster_than_nuts"] = _goal(
            "NUTS fit_s / CAVI fit_s >= 1000", ratio, None if ratio is None else ratio >= 1000)
        ratio = default["ratios"]["svi_over_cavi"]
        svi = default.get("svi_meanfield", {})
        lower = isinstance(svi, dict) and not svi.get("reached", True)
        goals["default_100x_faster_than_svi"] = _goal(
            "svi_meanfield time to the CAVI ELBO (gap < 1 %) / CAVI fit_s >= 100", ratio,
            None if ratio is None else ratio >= 100,
            "SVI did not reach the target within its budget: the ratio is a lower bound" if lower else "")
    goal_row = by_name.get(GOAL_ROW_NAME)
    if goal_row is not None:
        fit = goal_row["cavi"]["fit_s"]
        goals["L1000_d420_V10_under_5s"] = _goal(
            f"CAVI fit_s < 5 s for L = 1000, d = 420, V = 10 on {goal_row['cores']} cores", fit, fit < 5.0)
    if batch is not None:
        goals["batch_1000_under_60s"] = _goal(
            f"{batch['datasets']} batched default datasets in < 60 s (initialisation included)",
            batch["fit_s"], batch["fit_s"] < 60.0 if batch["datasets"] >= 1000 else None,
            "" if batch["datasets"] >= 1000 else "fewer than 1000 datasets were run")
    return goals


# --------------------------------------------------------------------------- table
def _fmt(value: Any, spec: str) -> str:
    if value is None:
        return "-"
    return format(value, spec)


def _engine_cell(row: dict, engine: str) -> str:
    entry = row[engine]
    if not entry.get("run", True):
        return "not run"
    if engine == "nuts":
        return f"{entry['fit_s']:.1f} s, {entry['s_per_ess'] * 1e3:.0f} ms/ESS"
    mark = "" if entry["reached"] else " (budget, not reached)"
    return f"{entry['fit_s']:.2f} s, {entry['steps']} steps{mark}"


def format_table(result: dict) -> str:
    """A Markdown table of the rows, then the batch, baseline and goals."""
    lines = [
        "| row | L | d | V | K | CAVI compile s | CAVI fit ms | iters | ms/iter | GFLOP/s | "
        "svi_meanfield | svi_autonormal | NUTS | NUTS/CAVI | SVI/CAVI |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---|---:|---:|",
    ]
    for r in result["rows"]:
        c = r["cavi"]
        rate = None if c["flop_rate"] is None else c["flop_rate"] / 1e9
        lines.append(
            f"| {r['name']} | {r['L']} | {r['d']} | {r['V']} | {r['K']} | {c['compile_s']:.2f} | "
            f"{c['fit_s'] * 1e3:.2f} | {c['iterations']}{'' if c['converged'] else ' (' + c['stopped'] + ')'} | {c['s_per_iteration'] * 1e3:.3f} | "
            f"{_fmt(rate, '.2f')} | {_engine_cell(r, 'svi_meanfield')} | {_engine_cell(r, 'svi_autonormal')} | "
            f"{_engine_cell(r, 'nuts')} | {_fmt(r['ratios']['nuts_over_cavi'], '.3g')} | "
            f"{_fmt(r['ratios']['svi_over_cavi'], '.3g')} |"
        )
    out = "\n".join(lines)
    machine = result["machine"]
    out += f"\n\nMatrix-product rate: {machine['matmul_flop_rate'] / 1e9:.1f} GFLOP/s ({machine['matmul']})."
    scaling = result.get("scaling")
    if scaling:
        out += (f"\nCAVI cost per sweep ~ L^{scaling['exponent']:.2f} over L = "
                f"{', '.join(str(int(v)) for v in scaling['L'])}"
                + ("" if scaling["exponent_L_ge_100"] is None else
                   f" (L^{scaling['exponent_L_ge_100']:.2f} for L >= 100)")
                + ("" if scaling.get("flops_exponent") is None else
                   f"; operations per sweep ~ L^{scaling['flops_exponent']:.2f}") + ".")
    batch = result.get("batch")
    if batch:
        out += (f"\nBatch: {batch['datasets']} default datasets in {batch['fit_s']:.2f} s "
                f"({batch['datasets_per_s']:.0f} datasets/s, compile {batch['compile_s']:.1f} s, "
                f"{batch['converged_fraction']:.1%} converged).")
    base = result.get("promp_baseline", {})
    if base.get("run", True) and "lmpromp_ppl" in base:
        theirs = base["movement_primitives"]
        theirs_text = theirs if isinstance(theirs, str) else (
            f"movement_primitives {theirs['fit_s'] * 1e3:.1f} ms, mean RMSE / range "
            f"{base['mean_rmse_over_range']:.2e}")
        out += (f"\nProMP baseline on {base['dataset']} ({base['num_demos']} x {base['num_steps']} x "
                f"{base['num_dofs']}, J = {base['num_basis']}): lmpromp_ppl "
                f"{base['lmpromp_ppl']['fit_s'] * 1e3:.1f} ms; {theirs_text}.")
    gpu = result["gpu"]
    if not gpu["run"]:
        out += f"\nGPU: not run ({gpu['reason']})."
    out += "\n\n| goal | target | measured | met |\n|---|---|---:|---|"
    for name, g in result["goals"].items():
        out += f"\n| {name} | {g['target']} | {_fmt(g['measured'], '.4g')} | {g['met']} |"
    return out
