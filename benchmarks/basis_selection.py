"""What does choosing J by the bound change on real data?  A table per dataset.

For every dataset of ``reports/real-data/`` (default: all 30 LASA shapes,
GunPoint and two synthetic sets) the script chooses the number of basis
functions per DoF with :func:`lmpromp_ppl.select_num_basis` (single-type
LMProMP, CAVI, default preset) on all demonstrations, then measures the
leave-one-demonstration-out figures of ``lmpromp real-data``
(:func:`lmpromp_ppl.reports.real_data.dataset_row`) at that J, and prints them
beside the committed rows at the default J = 20 (``reports/real-data/real-data.json``).
docs/defaults.md (*Choosing J by the bound*) quotes the result.

    PYTHONPATH=. python benchmarks/basis_selection.py --out benchmarks/basis_selection.json
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np

from lmpromp_ppl.api import select_num_basis
from lmpromp_ppl.data import load_dataset
from lmpromp_ppl.reports import real_data

FIGURES = ("pop_rmse", "coverage90", "halfwidth", "cond_rmse_observed", "cond_rmse_rest", "uncond_rmse_rest",
           "max_abs_w")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", nargs="*", default=real_data.default_datasets())
    parser.add_argument("--reference", default="reports/real-data/real-data.json")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="benchmarks/basis_selection.json")
    args = parser.parse_args()
    reference = {}
    if Path(args.reference).is_file():
        rows = json.loads(Path(args.reference).read_text())["rows"]
        reference = {r["dataset"]: r for r in rows if r["engine"] == "cavi"}
    out = {"seed": args.seed, "rows": {}}
    print(f"{'dataset':45s} {'J':>3s} {'coverage J / 20':>16s} {'half-width J / 20':>18s} {'cond. rest':>10s} {'max abs(w)':>11s}")
    for name in args.datasets:
        start = time.perf_counter()
        demos = load_dataset(name)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            choice = select_num_basis(demos, seed=args.seed)
        row = real_data.dataset_row(name, "cavi", options={"num_basis": choice["num_basis"]}, demos=demos,
                                    seed=args.seed)
        entry = {k: row[k] for k in FIGURES}
        entry.update(num_basis=choice["num_basis"], grid=choice["grid"], elbo=choice["elbo"],
                     passes=row["passes"], seconds=time.perf_counter() - start)
        out["rows"][name] = entry
        ref = reference.get(name, {})
        print(f"{name[:45]:45s} {choice['num_basis']:3d} {entry['coverage90']:7.3f} / {ref.get('coverage90', np.nan):6.3f} "
              f"{entry['halfwidth']:8.3f} / {ref.get('halfwidth', np.nan):6.3f} {entry['cond_rmse_rest']:10.3f} "
              f"{entry['max_abs_w']:11.2f}", flush=True)
        Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    lasa = [v for k, v in out["rows"].items() if k.startswith("lasa:")]
    if lasa:
        cov = np.array([v["coverage90"] for v in lasa])
        print(f"LASA: mean coverage {cov.mean():.3f}, in [0.80, 0.98]: {int(np.sum((cov >= 0.8) & (cov <= 0.98)))} of {len(cov)}")


if __name__ == "__main__":
    main()
