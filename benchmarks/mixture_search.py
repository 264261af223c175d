"""Does the CAVI mixture find the movement types?  A table over datasets, hyperparameters and seeds.

For each labelled dataset and hyperparameter setting the mixture (K = 6 unless
given) is fitted with ``lmpromp_ppl.fit(..., engine="cavi")`` for every seed,
with the split-and-merge search (default) and, with ``--compare-none``, without
it.  Reported per fit: the ELBO, the active components, the adjusted Rand
index (ARI) of the MAP responsibilities against the labels, and seconds.  Per
dataset and setting the script also reports the *oracle* bound: CAVI started
from the true labels (one component per label, the others removed), which tells
whether the labelled partition is where the bound is highest.

    PYTHONPATH=. python benchmarks/mixture_search.py --seeds 10 --out benchmarks/mixture_search.json
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import jax
import numpy as np

from lmpromp_ppl.basis import DEFAULT_NUM_BASIS

DATASETS = (
    "lasa:GShape+Angle+Sshape?every=20",
    "lasa:CShape+Worm+Zshape+Leaf_1?every=20",
    "lasa:JShape+Snake+Trapezoid?every=20",
    "lasa:Khamesh+Spoon+NShape+Sine?every=20",
    "synthetic:clusters",
    "gunpoint:train",
)
#: name: (preset, changes); every setting learns beta except ``thesis``.
SETTINGS = {
    "default,V=2": ("default", dict(num_components=6, latent_dim=2)),
    "default,V=3": ("default", dict(num_components=6, latent_dim=3)),
    "l0=0.01,V=2": ("default", dict(lambda0=0.01, num_components=6, latent_dim=2)),
    "l0=0.01,V=1": ("default", dict(lambda0=0.01, num_components=6, latent_dim=1)),
    "c0=d0=2,V=2": ("default", dict(c0=2.0, d0=2.0, num_components=6, latent_dim=2)),
    "thesis,V=2": ("thesis", dict(num_components=6, latent_dim=2)),
}


def oracle_elbo(spec: str, hyper, num_basis: int) -> float:
    """Final bound of plain CAVI started at the labels (one component per label)."""
    from lmpromp_ppl.data import prepare_dataset
    from lmpromp_ppl.inference import cavi
    from lmpromp_ppl.inference.cavi import search

    prepared = prepare_dataset(spec, num_basis)
    raw, data = prepared.raw, cavi.sufficient_statistics(prepared.model_data)
    hyper_arr = cavi.hyper_arrays(hyper)
    _, codes = np.unique(raw.labels, return_inverse=True)
    if codes.max() >= hyper.num_components:
        return float("nan")
    start = cavi.init_mixture_state(data, hyper, jax.random.key(0))
    state = search.state_from_labels(start, hyper_arr, codes)
    return float(cavi.run(state, data, hyper_arr, 1e-8, 3000).elbo_trace[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--datasets", nargs="*", default=list(DATASETS))
    parser.add_argument("--settings", nargs="*", default=list(SETTINGS), choices=list(SETTINGS))
    parser.add_argument("--num-basis", type=int, default=DEFAULT_NUM_BASIS)
    parser.add_argument("--compare-none", action="store_true", help="also fit with search='none'")
    parser.add_argument("--out", default="benchmarks/mixture_search.json")
    args = parser.parse_args()

    import lmpromp_ppl
    from lmpromp_ppl.models.hyper import preset

    warnings.simplefilter("ignore")
    searches = ["split_merge"] + (["none"] if args.compare_none else [])
    rows = []
    print(f"{'dataset':44s} {'setting':13s} {'search':11s} {'types':>5s} {'ok/seeds':>8s} "
          f"{'ARI mean':>8s} {'ARI min':>7s} {'#active':>9s} {'ELBO best':>10s} {'oracle':>10s} {'s/fit':>6s}")
    for spec in args.datasets:
        labels = lmpromp_ppl.data.load_dataset(spec).labels
        types = len(set(labels))
        for name in args.settings:
            base, changes = SETTINGS[name]
            hyper = preset(base, **changes)
            oracle = oracle_elbo(spec, hyper, args.num_basis)
            for search in searches:
                fits = []
                for seed in range(args.seeds):
                    start = time.perf_counter()
                    res = lmpromp_ppl.fit(spec, model="mixture", hyper=hyper, num_basis=args.num_basis,
                                          seed=seed, search=search)
                    s = res.summary
                    fits.append({"seed": seed, "elbo": s["elbo"], "ari": s["ari"],
                                 "active_components": s["active_components"],
                                 "seconds": time.perf_counter() - start})
                aris = np.array([f["ari"] for f in fits])
                counts = [len(f["active_components"]) for f in fits]
                ok = sum(f["ari"] >= 0.9 and len(f["active_components"]) == types for f in fits)
                row = {"dataset": spec, "setting": name, "hyperparameters": hyper.to_dict(), "search": search,
                       "num_types": types, "num_ok": ok, "ari_mean": float(aris.mean()), "ari_min": float(aris.min()),
                       "oracle_elbo": oracle, "best_elbo": max(f["elbo"] for f in fits), "fits": fits}
                rows.append(row)
                print(f"{spec:44s} {name:13s} {search:11s} {types:5d} {ok:4d}/{len(fits):<3d} {aris.mean():8.3f} "
                      f"{aris.min():7.3f} {min(counts):4d}-{max(counts):<4d} {row['best_elbo']:10.1f} {oracle:10.1f} "
                      f"{np.mean([f['seconds'] for f in fits]):6.1f}", flush=True)
                with open(args.out, "w") as fh:
                    json.dump({"ok_means": "ARI >= 0.9 and as many active components as labels", "rows": rows},
                              fh, indent=1)


if __name__ == "__main__":
    main()
