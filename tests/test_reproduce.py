"""Every thesis experiment runs in --quick mode and writes finite numbers, a figure, a section and claims."""

from __future__ import annotations

import json
import math

import pytest

from lmpromp_ppl.cli import main
from lmpromp_ppl.reproduce import EXPERIMENTS, VERDICTS, Context, run_many
from lmpromp_ppl.reproduce.prediction import effective_rank
from lmpromp_ppl.reproduce.latent_analysis import nearest_mean_accuracy

#: Keys each experiment's ``numbers`` must hold.
EXPECTED = {
    "priors": {"promp", "lmpromp", "mixture", "cluster_plane_variance"},
    "noise": {"noise", "train_size"},
    "sparsity": {"interval"},
    "beta": {"rows", "learned_beta", "spearman_rank", "spearman_train"},
    "c0": {"rows", "nonfinite_total"},
    "semantics": {"LASA GShape", "GunPoint"},
    "latent-analysis": {"active_dims", "class_accuracy_latent", "class_accuracy_pca", "first_two_share"},
    "bimodal": {"reaching", "lasa"},
}


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("reproduction")
    documents = run_many(list(EXPERIMENTS), Context(out=out, quick=True, seed=0, progress=False))
    return out, {d["experiment"]: d for d in documents}


def _numbers(value, where="numbers"):
    """Yield (path, value) for every number in a JSON document."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _numbers(v, f"{where}.{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _numbers(v, f"{where}[{i}]")
    else:
        yield where, value


@pytest.mark.parametrize("name", list(EXPERIMENTS))
def test_experiment_writes_finite_json_figure_and_section(quick_run, name):
    out, documents = quick_run
    document = json.loads((out / f"{name}.json").read_text())
    assert document == documents[name]
    assert EXPECTED[name] <= set(document["numbers"])
    values = list(_numbers(document["numbers"]))
    numeric = [(p, v) for p, v in values if isinstance(v, (int, float)) and not isinstance(v, bool)]
    assert numeric, name
    missing = [p for p, v in values if v is None and not p.endswith("train_size")]
    assert not missing, missing
    assert all(math.isfinite(v) for _, v in numeric)
    assert document["claims"] and all(c["verdict"] in VERDICTS for c in document["claims"])
    for figure in document["figures"]:
        assert (out / figure).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / f"{name}.md").read_text().startswith("## ")


def test_c0_has_no_nonfinite_results(quick_run):
    _, documents = quick_run
    numbers = documents["c0"]["numbers"]
    assert numbers["nonfinite_total"] == 0
    assert all(row["nonfinite"] == 0 for row in numbers["rows"])
    assert [row["c0"] for row in numbers["rows"]] == [0.05, 1.0, 500.0]


def test_prediction_scores_cover_every_model_and_setting(quick_run):
    _, documents = quick_run
    rows = documents["sparsity"]["numbers"]["interval"]["LASA GShape"]
    assert [r["setting"]["interval"] for r in rows] == [1, 3]
    for row in rows:
        assert set(row["models"]) == {"promp", "lmpromp", "mixture"}
        assert all(m["folds"] == 3 and m["rmse_mean"] > 0 for m in row["models"].values())


def test_claims_table_has_one_row_per_claim(quick_run):
    out, documents = quick_run
    text = (out / "claims.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| ") and line[2].isdigit()]
    assert len(rows) == sum(len(d["claims"]) for d in documents.values())
    report = (out / "report.md").read_text()
    assert all(f"({d['thesis']})" in report for d in documents.values())


def test_cli_reproduce_single_experiment_and_errors(quick_run, tmp_path, capsys):
    out, _ = quick_run
    target = tmp_path / "c0"
    assert main(["reproduce", "c0", "--out", str(target), "--quick", "--quiet", "--seed", "1"]) == 0
    document = json.loads((target / "c0.json").read_text())
    assert document["seed"] == 1 and document["quick"] is True
    assert main(["reproduce", "c0", "--out", str(target), "--quick", "--quiet"]) == 2  # exists, no --force
    assert main(["reproduce", "nonsense", "--out", str(tmp_path / "x"), "--quick", "--quiet"]) == 2
    assert "unknown experiment" in capsys.readouterr().err


def test_effective_rank_counts_independent_directions():
    import numpy as np

    rng = np.random.default_rng(0)
    M = rng.standard_normal((6, 3))
    h = rng.standard_normal((20, 3))
    h[:, 2] = 0.0
    rank = effective_rank(M, h)
    assert rank["numerical"] == 2
    assert 1.0 < rank["entropy"] <= 2.0


def test_nearest_mean_accuracy_separates_and_fails_on_shuffled_labels():
    import numpy as np

    x = np.concatenate([np.zeros((10, 2)), np.ones((10, 2)) * 5]) + np.random.default_rng(1).normal(0, 0.1, (20, 2))
    labels = np.array(["a"] * 10 + ["b"] * 10)
    assert nearest_mean_accuracy(x, labels) == 1.0
    assert nearest_mean_accuracy(x, np.array(["a", "b"] * 10)) < 0.8


def test_preset_default_runs_with_the_library_defaults(quick_run, tmp_path, capsys):
    """``--preset default``: learned beta, twice the thesis's J, width 1; recorded in the JSON and claims.md."""
    _, documents = quick_run
    target = tmp_path / "semantics-default"
    assert main(["reproduce", "semantics", "--out", str(target), "--quick", "--quiet", "--preset", "default"]) == 0
    document = json.loads((target / "semantics.json").read_text())
    thesis = documents["semantics"]
    assert thesis["preset"] == "thesis" and thesis["width"] == 2.0
    assert document["preset"] == "default" and document["width"] == 1.0
    for label, size in document["sizes"].items():
        assert size["num_basis"] == 2 * thesis["sizes"][label]["num_basis"]
    # a different basis and noise model: the measured effects are not the thesis run's
    assert document["numbers"]["GunPoint"] != thesis["numbers"]["GunPoint"]
    assert "--preset default" in (target / "claims.md").read_text()
    assert main(["reproduce", "c0", "--out", str(tmp_path / "y"), "--quick", "--quiet", "--preset", "nope"]) == 2
    assert "unknown preset" in capsys.readouterr().err
