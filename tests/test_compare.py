"""``lmpromp compare`` end to end on a tiny synthetic problem, and its user errors."""

from __future__ import annotations

import contextlib
import io
import json
import re

import numpy as np
import pytest

import lmpromp_ppl
from lmpromp_ppl.cli import main

DATASET = "synthetic:latent?L=6&D=2&J=3&V=2&T=15&seed=0"
TINY = ["--model", "lmpromp", "--latent-dim", "2", "--num-basis", "3", "--chains", "2", "--warmup", "200",
        "--samples", "300", "--seed", "0", "--draws", "600"]
SIX = {"b", "alpha", "lam", "gram_eig", "pred_mean", "w"}
FOUR = {"smd_max_abs", "sd_ratio_median", "wasserstein_max", "coverage90"}
FIGURES = ("traces.png", "marginals.png", "sd_ratios.png", "predictive.png", "latent.png")


def _strict_json(text: str) -> dict:
    def reject(name):
        raise AssertionError(f"metrics.json holds {name}")

    return json.loads(text, parse_constant=reject)


@pytest.fixture(scope="module")
def compare_run(tmp_path_factory):
    """One run with its progress output (stdout, stderr: no terminal)."""
    out = tmp_path_factory.mktemp("compare") / "report"
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        rc = main(["compare", DATASET, "--engines", "cavi,nuts", "--out", str(out), *TINY])
    assert rc == 0, stderr.getvalue()
    return out, stdout.getvalue(), stderr.getvalue()


@pytest.fixture(scope="module")
def report_dir(compare_run):
    return compare_run[0]


def test_progress_says_done_for_every_engine_and_ends_once(compare_run):
    out, stdout, stderr = compare_run
    assert "\r" not in stdout + stderr  # no progress bars outside a terminal
    assert "Traceback" not in stderr and "Warning:" not in stderr
    for engine in ("cavi", "nuts"):
        assert len(re.findall(rf"\] {engine} done in \d+\.\d s$", stderr, flags=re.M)) == 1, (engine, stderr)
    lines = stdout.strip().splitlines()
    assert len(lines) == 1 and f"report in {out}/report.html" in lines[0]
    assert "report.html" not in stderr and "wrote" not in stderr  # the final line is said once, on stdout
    assert re.search(r"NUTS max R-hat \d\.\d{3}, \d+ divergences", lines[0]), lines[0]


def test_report_rounds_rhat_and_ess(report_dir):
    md = (report_dir / "report.md").read_text()
    start = md.index("| quantity | max R-hat | min bulk ESS | min tail ESS |")
    rows = md[start:].split("\n\n")[0].splitlines()[2:]  # the NUTS reliability table's body
    assert len(rows) >= 2 and all(re.fullmatch(r"\| \S+ \| \d\.\d{3} \| \d+ \| \d+ \|", r) for r in rows), rows
    assert not re.search(r"\d\.\d{7,}", md + (report_dir / "report.html").read_text())


def test_compare_writes_every_file(report_dir):
    for name in ("report.md", "report.html", "metrics.json", *FIGURES):
        assert (report_dir / name).is_file(), name
    for engine in ("cavi", "nuts"):
        assert (report_dir / engine / "posterior.nc").is_file()
        fit = lmpromp_ppl.load(report_dir / engine)
        assert fit.engine == engine and fit.hyper.a0 == lmpromp_ppl.PROPER.a0  # one shared preset


def test_metrics_json_follows_the_contract(report_dir):
    metrics = _strict_json((report_dir / "metrics.json").read_text())
    assert {"dataset", "model", "hyperparameters", "engines"} <= set(metrics)
    assert metrics["dataset"] == DATASET and metrics["model"] == "lmpromp"
    assert metrics["hyperparameters"]["latent_dim"] == 2
    engines = metrics["engines"]
    assert set(engines) == {"cavi", "nuts"}
    for e in engines.values():
        assert e["seconds"] > 0 and e["compile_seconds"] >= 0
    nuts = engines["nuts"]
    assert {"rhat_max", "ess_bulk_min", "ess_tail_min", "divergences"} <= set(nuts)
    assert nuts["rhat_max"] >= 1.0 - 0.05 and nuts["ess_bulk_min"] > 0 and nuts["divergences"] >= 0
    cavi = engines["cavi"]
    assert np.isfinite(cavi["elbo"]) and "psis_khat" in cavi
    # CAVI's log q is available, so k-hat is a number (mean-field q in ~100 dims: typically large)
    assert cavi["psis_khat"] is not None and cavi["psis_khat_note"] == ""
    # numpyro's Pareto fit of the same ratios cross-checks the arviz-stats one
    assert cavi["psis_khat"] == pytest.approx(cavi["psis_khat_numpyro"], abs=0.05)
    assert set(cavi["vs_nuts"]) == SIX
    for q, summary in cavi["vs_nuts"].items():
        assert set(summary) == FOUR, q
        assert summary["sd_ratio_median"] > 0 and 0.0 <= summary["coverage90"] <= 1.0
        assert summary["smd_max_abs"] >= 0 and summary["wasserstein_max"] >= 0


def test_report_is_self_contained_and_explains(report_dir):
    html = (report_dir / "report.html").read_text()
    assert html.count("src='data:image/png;base64,") == len(FIGURES)
    assert not re.search(r"src='(?!data:)", html)  # no external resource
    md = (report_dir / "report.md").read_text()
    for fig in FIGURES:
        assert f"({fig})" in md
    for phrase in ("rotation", "label switching", "Procrustes", "sd ratio", "k-hat", "proper",
                   "<engine>/posterior.nc"):
        assert phrase in md, phrase


def test_existing_output_is_refused_without_force(report_dir, capsys):
    rc = main(["compare", DATASET, "--engines", "cavi,nuts", "--out", str(report_dir), "--quiet", *TINY])
    err = capsys.readouterr().err
    assert rc == 2 and "--force" in err and err.count("\n") == 1


@pytest.mark.parametrize(
    "args, message",
    [
        (["--engines", "cavi,svi_meanfield"], "must include nuts"),
        (["--engines", "cavi,hmc,nuts"], "unknown engine 'hmc'"),
        (["--engines", "nuts"], "besides nuts"),
        (["--engines", "cavi,nuts", "--model", "promp"], "CAVI is offered"),
        (["--engines", "cavi,nuts", "--model", "tree"], "unknown model"),
        (["--engines", "cavi,nuts", "--preset", "wild"], "unknown hyperparameter preset"),
    ],
)
def test_user_errors_exit_2_with_one_line(tmp_path, capsys, args, message):
    rc = main(["compare", DATASET, "--out", str(tmp_path / "r"), "--quiet", *args])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert message in err and err.count("\n") == 1
    assert not (tmp_path / "r").exists()  # refused before anything was written


def test_unknown_dataset_exits_2(tmp_path, capsys):
    rc = main(["compare", "nosuchdata:x", "--out", str(tmp_path / "r"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1


@pytest.mark.slow
def test_compare_with_svi_guides_and_numpyro_khat_cross_check(tmp_path):
    """All three SVI guides: k-hat from the Pareto fits of arviz-stats and numpyro are both computed."""
    out = tmp_path / "svi"
    assert main(["compare", DATASET, "--engines", "cavi,svi,nuts", "--out", str(out), "--quiet", "--steps", "2000",
                 *TINY]) == 0
    metrics = _strict_json((out / "metrics.json").read_text())
    for engine in ("svi_meanfield", "svi_autonormal", "svi_lowrank"):
        e = metrics["engines"][engine]
        assert set(e["vs_nuts"]) == SIX
        assert e["psis_khat"] is not None and e["psis_khat_numpyro"] is not None
        # same particles (same key): arviz-stats' and numpyro's generalized Pareto fits agree
        assert e["psis_khat"] == pytest.approx(e["psis_khat_numpyro"], abs=0.05)


def test_the_mixture_chooses_its_basis_once_before_any_fit(monkeypatch, tmp_path):
    """compare with the mixture (or --num-basis auto) asks the bound for J once, before any engine runs."""
    import lmpromp_ppl.api as api
    from lmpromp_ppl.reports.compare import compare

    class Chosen(Exception):
        pass

    calls = []

    def choose(data, **options):
        calls.append(data)
        raise Chosen

    monkeypatch.setattr(api, "select_num_basis", choose)
    for model, options in (("mixture", {}), ("lmpromp", {"num_basis": "auto"})):
        with pytest.raises(Chosen):
            compare(DATASET, model, "cavi,nuts", out_dir=tmp_path / model, **options)
        assert not (tmp_path / model).exists()
    assert calls == [DATASET, DATASET]
    with pytest.raises(lmpromp_ppl.errors.LmprompError, match="'auto'"):
        compare(DATASET, "lmpromp", "cavi,nuts", out_dir=tmp_path / "bad", num_basis="many")
    assert main(["compare", DATASET, "--num-basis", "many", "--out", str(tmp_path / "cli")]) == 2
