"""The command line with a newcomer's mistakes: bad numbers, missing inputs, seeds, warnings, progress output."""

from __future__ import annotations

import dataclasses
import io
import subprocess
import sys

import numpy as np
import pytest
import xarray as xr

import lmpromp_ppl as lp
from lmpromp_ppl._progress import line_reporter, show_progress_bars
from lmpromp_ppl.cli import main
from lmpromp_ppl.reports.render import format_ess, format_number, format_rhat

# the data and sizes of test_cli_fit_predict.py: compiled functions are shared in one test run
DATASET = "synthetic:latent?L=8&D=2&J=4&V=2&T=20&seed=3"
SMALL = ["--latent-dim", "2", "--num-basis", "4"]


def _one_error_line(err: str) -> str:
    assert "Traceback" not in err and "Warning" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("lmpromp: error:"), err
    return lines[0]


# --------------------------------------------------------------------------- bad numbers
@pytest.mark.parametrize(
    "args, option",
    [
        (["fit", DATASET, "--samples", "-1"], "--samples"),
        (["fit", DATASET, "--samples", "0"], "--samples"),
        (["fit", DATASET, "--max-iter", "0"], "--max-iter"),
        (["fit", DATASET, "--accelerate", "fast"], "--accelerate"),
        (["fit", DATASET, "--tol", "nan"], "--tol"),
        (["fit", DATASET, "--beta", "0"], "--beta"),
        (["fit", DATASET, "--learning-rate", "-0.1"], "--learning-rate"),
        (["fit", DATASET, "--num-basis", "1"], "--num-basis"),
        (["fit", DATASET, "--num-basis", "many"], "--num-basis"),
        (["fit", DATASET, "--latent-dim", "0"], "--latent-dim"),
        (["fit", DATASET, "--warmup", "-5"], "--warmup"),
        (["fit", DATASET, "--seed", "-1"], "--seed"),
        (["fit", DATASET, "--seed", str(2**32)], "--seed"),
        (["predict", "{tmp}", "--observe", "{tmp}/o.npz", "--samples", "-1"], "--samples"),
        (["predict", "{tmp}", "--observe", "{tmp}/o.npz", "--samples", "0"], "--samples"),
        (["predict", "{tmp}", "--observe", "{tmp}/o.npz", "--noise-sd", "-1"], "--noise-sd"),
        (["predict", "{tmp}", "--observe", "{tmp}/o.npz", "--duration", "inf"], "--duration"),
        (["compare", DATASET, "--draws", "50"], "--draws"),
        (["compare", DATASET, "--chains", "0"], "--chains"),
        (["compare", DATASET, "--steps", "-3"], "--steps"),
        (["demo", "--latent-dim", "0"], "--latent-dim"),
        (["reproduce", "priors", "--seed", "-2"], "--seed"),
        (["sbc", "--replicates", "0"], "--replicates"),
        (["sbc", "--beta", "-1"], "--beta"),
        (["sbc", "--workers", "0"], "--workers"),
        (["sweep", DATASET, "--grid", "beta=10,100", "--test-fraction", "1.5"], "--test-fraction"),
        (["sweep", DATASET, "--grid", "beta=10,100", "--max-iter", "0"], "--max-iter"),
        (["bench", "--svi-budget", "0"], "--svi-budget"),
        (["bench", "--batch-size", "-1"], "--batch-size"),
    ],
)
def test_a_bad_number_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys, args, option):
    target = tmp_path / "out" / ("result.json" if args[0] == "bench" else "dir")
    argv = [a.format(tmp=tmp_path) for a in args] + ["--out", str(target), "--quiet"]
    assert main(argv) == 2
    captured = capsys.readouterr()
    line = _one_error_line(captured.err)
    assert option in line
    assert captured.out == ""
    assert not (tmp_path / "out").exists()


def test_data_show_rejects_a_negative_seed(tmp_path, capsys):
    assert main(["data", "show", DATASET, "--out", str(tmp_path / "d" / "x.png"), "--seed", "-1"]) == 2
    assert "--seed" in _one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "d").exists()


def test_the_console_command_prints_no_traceback():
    """The same error in a fresh process: status 2, one line, as a user sees it."""
    proc = subprocess.run([sys.executable, "-m", "lmpromp_ppl.cli", "predict", "no-such-fit", "--observe", "o.npz",
                           "--out", "p", "--samples", "-1"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "--samples" in _one_error_line(proc.stderr)


# --------------------------------------------------------------------------- output directories
def test_a_failed_command_removes_the_directories_it_created(tmp_path, capsys):
    out = tmp_path / "new" / "deeper" / "run"
    assert main(["fit", "lasa:NoSuchShape", "--out", str(out), "--quiet"]) == 2
    assert "NoSuchShape" in _one_error_line(capsys.readouterr().err)
    assert not (tmp_path / "new").exists()
    assert tmp_path.is_dir()  # what existed before is kept


def test_a_failed_command_keeps_a_directory_the_user_had(tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    assert main(["fit", "lasa:NoSuchShape", "--out", str(mine), "--quiet"]) == 2
    _one_error_line(capsys.readouterr().err)
    assert mine.is_dir()


def test_predict_on_a_missing_fit_directory_says_so(tmp_path, capsys):
    np.savez(tmp_path / "o.npz", t=np.array([0.0, 0.1]), y=np.zeros((2, 2)))
    missing = tmp_path / "no-fit-here"
    assert main(["predict", str(missing), "--observe", str(tmp_path / "o.npz"), "--out", str(tmp_path / "p")]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert str(missing) in line and "does not exist" in line
    assert not (tmp_path / "p").exists()


# --------------------------------------------------------------------------- seeds
def _posterior(path) -> xr.Dataset:
    with xr.open_datatree(path / "posterior.nc", engine="h5netcdf") as tree:
        return tree["posterior"].to_dataset().load()


@pytest.fixture(scope="module")
def seeded_fits(tmp_path_factory):
    root = tmp_path_factory.mktemp("seeds")
    dirs = {}
    for name, seed in (("7a", 7), ("7b", 7), ("8", 8)):
        dirs[name] = root / name
        assert main(["fit", DATASET, *SMALL, "--engine", "cavi", "--seed", str(seed), "--out", str(dirs[name]),
                     "--quiet"]) == 0
    return dirs


def test_the_seed_changes_the_saved_draws(seeded_fits):
    a, b = _posterior(seeded_fits["7a"]), _posterior(seeded_fits["8"])
    assert set(a.data_vars) == set(b.data_vars) and "w" in a
    for name in a.data_vars:
        assert a[name].shape == b[name].shape
        assert not np.array_equal(a[name].values, b[name].values), name


def test_one_seed_twice_saves_identical_draws(seeded_fits):
    xr.testing.assert_identical(_posterior(seeded_fits["7a"]), _posterior(seeded_fits["7b"]))


def test_replicated_data_follow_the_fits_seed(seeded_fits):
    fit = lp.load(seeded_fits["7a"])
    assert fit.seed == 7
    same = fit.posterior_predictive(num_draws=5)
    np.testing.assert_array_equal(same, fit.posterior_predictive(num_draws=5))
    other = dataclasses.replace(fit, seed=8).posterior_predictive(num_draws=5)  # same draws, other seed
    ok = np.isfinite(same)
    assert not np.allclose(same[ok], other[ok])


# --------------------------------------------------------------------------- warnings and progress
def test_a_fit_that_stops_early_says_so_in_its_result_line(tmp_path, capsys):
    assert main(["fit", DATASET, *SMALL, "--max-iter", "2", "--out", str(tmp_path / "f")]) == 0
    captured = capsys.readouterr()
    lines = captured.out.strip().splitlines()
    assert len(lines) == 1, captured.out
    assert "did not converge in 2 sweeps" in lines[0] and "> tol" in lines[0] and str(tmp_path / "f") in lines[0]
    assert "Warning" not in captured.err and "warn" not in captured.err and ".py" not in captured.err
    assert "\r" not in captured.out + captured.err


def test_quiet_silences_the_non_convergence_line(tmp_path, capsys):
    assert main(["fit", DATASET, *SMALL, "--max-iter", "2", "--out", str(tmp_path / "f"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""


def test_a_converged_fit_prints_no_convergence_note(tmp_path, capsys):
    assert main(["fit", DATASET, *SMALL, "--out", str(tmp_path / "f")]) == 0
    out = capsys.readouterr().out
    assert "did not converge" not in out and "ELBO" in out


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bars_only_on_a_terminal(monkeypatch, tmp_path, capsys):
    assert show_progress_bars(True) is False  # pytest's captured stderr is no terminal
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    assert show_progress_bars(True) is True and show_progress_bars(False) is False
    assert main(["fit", DATASET, *SMALL, "--max-iter", "2", "--out", str(tmp_path / "tty")]) == 0
    assert "\r" in terminal.getvalue() and "CAVI" in terminal.getvalue()  # the bar is drawn on a terminal
    terminal.truncate(0)
    assert main(["fit", DATASET, *SMALL, "--max-iter", "2", "--out", str(tmp_path / "quiet"), "--quiet"]) == 0
    assert terminal.getvalue() == ""


def test_chunk_lines_only_on_a_terminal(monkeypatch):
    assert line_reporter(True, "svi_x") is None  # a log keeps the per-stage lines only
    mine = lambda done, value: None  # noqa: E731
    assert line_reporter(mine, "svi_x") is mine and line_reporter(False, "svi_x") is None
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    line_reporter(True, "svi_x")(500, -1.25)
    assert terminal.getvalue() == "svi_x: step 500, mean loss -1.25\n"


def test_report_numbers_are_rounded():
    assert format_rhat(1.0189393368003983) == "1.019" and format_rhat(1.0) == "1.000" and format_rhat(None) == "–"
    assert format_ess(271.83) == "272" and format_ess(12345.6) == "12346" and format_ess(float("nan")) == "–"
    assert format_number(0.0030512345) == "0.00305" and format_number(1234.56) == "1235"
    assert format_number(-449.48812, 6) == "-449.488" and format_number(3) == "3" and format_number(True) == "yes"
