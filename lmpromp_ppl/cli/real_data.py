"""``lmpromp real-data``: do the default settings fit real demonstrations? (reports/real-data/)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from lmpromp_ppl.cli import app
from lmpromp_ppl.cli._common import claim_out_dir

__all__ = ["real_data_command"]

_NUTS_DATASETS = "lasa:GShape?every=20,lasa:Angle?every=20,gunpoint:train"


def _split(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def nuts_names(nuts_datasets: str, names: list[str]) -> list[str]:
    """The datasets NUTS runs on: ``all`` is every dataset of the table, else the comma-separated list."""
    return list(names) if nuts_datasets.strip() == "all" else _split(nuts_datasets)


@app.command("real-data")
def real_data_command(
    out: Path = typer.Option(..., "--out", help="Output directory (real-data.md, real-data.json, predictive.png)."),
    datasets: Optional[str] = typer.Option(None, help="Comma-separated dataset strings (default: all 30 LASA shapes, GunPoint, two synthetic sets)."),
    engines: str = typer.Option("cavi,nuts", help="Engines, comma-separated (cavi, nuts, svi_*)."),
    nuts_datasets: str = typer.Option(_NUTS_DATASETS, "--nuts-datasets", help="The subsample that NUTS runs on (comma-separated), or all (every dataset of --datasets)."),
    max_folds: int = typer.Option(8, "--max-folds", min=1, help="Held-out demonstrations per dataset (CAVI, SVI)."),
    nuts_folds: int = typer.Option(3, "--nuts-folds", min=1, help="Held-out demonstrations per dataset for NUTS."),
    nuts_chains: int = typer.Option(4, "--nuts-chains", min=1, help="NUTS chains per fit."),
    nuts_draws: int = typer.Option(500, "--nuts-draws", min=10, help="NUTS warm-up and kept draws per chain (each)."),
    merge: bool = typer.Option(
        False, "--merge",
        help="Keep the rows of an existing real-data.json in --out for (dataset, engine) pairs not run now, "
             "and its mixture rows when --mixture-seeds is 0 (needs --force).",
    ),
    mixture_seeds: int = typer.Option(10, "--mixture-seeds", min=0, help="Seeds per pooled LASA set for the mixture check (0: skip)."),
    seed: int = typer.Option(0, "--seed", help="Seed for every random choice."),
    force: bool = typer.Option(False, "--force", help="Write into an existing non-empty directory."),
    quiet: bool = typer.Option(False, "--quiet", help="No progress output."),
) -> None:
    """Fit every dataset with the default settings and write the table of docs/defaults.md."""
    from lmpromp_ppl.errors import LmprompError
    from lmpromp_ppl.reports import real_data

    names = _split(datasets) if datasets else real_data.default_datasets()
    engine_list = _split(engines)
    from lmpromp_ppl.api import ENGINES

    unknown = [e for e in engine_list if e not in ENGINES]
    if unknown:
        raise LmprompError(f"unknown engine(s) {', '.join(unknown)}; choose from {', '.join(ENGINES)}")
    from lmpromp_ppl.data import load_dataset

    nuts_list = nuts_names(nuts_datasets, names)
    loaded = {name: load_dataset(name) for name in dict.fromkeys(names + (nuts_list if "nuts" in engine_list else []))}
    previous = None
    if merge:
        import json

        path = Path(out) / "real-data.json"
        if not path.is_file():
            raise LmprompError(f"--merge needs an existing {path}")
        try:
            previous = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise LmprompError(f"cannot read {path}: {exc}") from None
    target = claim_out_dir(out, force)
    echo = (lambda msg: None) if quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    rows = []
    for engine in engine_list:
        subset = nuts_list if engine == "nuts" else names
        folds = nuts_folds if engine == "nuts" else max_folds
        options = {"num_chains": nuts_chains, "num_warmup": nuts_draws, "num_samples": nuts_draws} \
            if engine == "nuts" else {}
        for name in subset:
            row = real_data.dataset_row(name, engine, max_folds=folds, seed=seed, options=options, demos=loaded[name])
            if options:
                row["engine_options"] = options
            rows.append(row)
            ok = "all criteria met" if all(row["passes"].values()) else \
                "fails " + ", ".join(k for k, v in row["passes"].items() if not v)
            echo(f"{engine} {name}: pop RMSE {row['pop_rmse']:.3f}, LOO coverage {row['coverage90']:.2f}, "
                 f"max |w| {row['max_abs_w']:.2g}; {ok} ({row['seconds']:.0f} s)")
    mixture = []
    if mixture_seeds:
        mixture = real_data.mixture_rows(
            list(real_data.POOLED_LASA) + ["synthetic:clusters", "gunpoint:train"],
            seeds=[seed + s for s in range(mixture_seeds)],
            on_row=lambda r: echo(f"mixture {r['dataset']} seed {r['seed']}: {r['active_components']} active, "
                                  f"ARI {r['ari'] if r['ari'] is None else round(r['ari'], 3)}"),
        )
    parts = ["lmpromp real-data", f"--out {out}", f"--engines {engines or repr('')}", f"--max-folds {max_folds}",
             f"--mixture-seeds {mixture_seeds}", f"--seed {seed}"]
    if datasets:
        parts.append(f"--datasets '{datasets}'")
    if "nuts" in engine_list:
        parts += [f"--nuts-datasets '{nuts_datasets}'", f"--nuts-folds {nuts_folds}",
                  f"--nuts-chains {nuts_chains}", f"--nuts-draws {nuts_draws}"]
    command = " ".join(parts)
    if previous is not None:
        parts.append("--merge --force")
        command = f"{previous.get('command', '')} && {' '.join(parts)}"
        done = {(r["dataset"], r["engine"]) for r in rows}
        rows = [r for r in previous.get("rows", []) if (r["dataset"], r["engine"]) not in done] + rows
        if not mixture_seeds:
            mixture = list(previous.get("mixture", []))
    real_data.write_report(target, rows, mixture, command=command,
                           figure=[n for n in names if n.startswith("lasa:")][:7] + [n for n in names if n.startswith("gunpoint")][:1])
    if not quiet:
        typer.echo(f"wrote {target / 'real-data.md'}")
