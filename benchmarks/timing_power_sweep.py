"""Could any tempering of the timing likelihood meet the 1.2x goal on LASA?  The prediction's RMSE at fixed powers.

``lmpromp predict --duration estimate`` tempers the timing's likelihood by a power kappa in [0, 1]
chosen by cross-validation over the training demonstrations (``calibrate_timing``).  This asks
what the best *fixed* power per shape, chosen with hindsight on the test folds themselves, would
give: leave-one-out as in ``lmpromp timing`` (the LMProMP fitted by CAVI with the default settings
to the other demonstrations, the first third of the held-out one observed in time, the rest
predicted at its true times), the duration estimated with each power in ``POWERS``; the table gives
the mean RMSE over the folds divided by the true duration's.  A power chosen on the test folds is
an optimistic bound for any rule that chooses it without them.  Run from the repository root
(about 20 minutes on 2 cores)::

    python benchmarks/timing_power_sweep.py --out benchmarks/timing_power_sweep.json
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from timing_sensitivity import held_out_folds  # the same folds (run from the repository root)

DATASETS = tuple(f"lasa:{s}" for s in ("GShape", "Angle", "Sshape", "Worm", "CShape", "NShape", "Trapezoid", "Spoon"))
POWERS = (0.0, 0.03125, 0.125, 0.5, 1.0)


def dataset_row(name: str, seed: int = 0) -> dict:
    true_rmse, rmse = [], []
    for duration, error_of in held_out_folds(name, seed):
        true_rmse.append(error_of(duration=duration))
        rmse.append([error_of(duration="estimate", timing_power=power) for power in POWERS])
    ratio = np.mean(rmse, axis=0) / np.mean(true_rmse)
    return {"dataset": name, "folds": len(rmse), "rmse_true": float(np.mean(true_rmse)),
            "ratio": [float(r) for r in ratio], "best_power": POWERS[int(np.argmin(ratio))],
            "best_ratio": float(ratio.min())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/timing_power_sweep.json")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rows = []
    print("dataset          " + " ".join(f"{p:>8g}" for p in POWERS) + "     best", flush=True)
    for name in DATASETS:
        row = dataset_row(name, args.seed)
        rows.append(row)
        print(f"{name:<16} " + " ".join(f"{r:8.2f}" for r in row["ratio"]) + f" {row['best_ratio']:8.2f}", flush=True)
    with open(args.out, "w") as f:
        json.dump({"seed": args.seed, "powers": list(POWERS), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
