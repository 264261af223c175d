"""The library's figures: no backend switching, every axis labelled, the LASA path in the plane."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

from lmpromp_ppl.cli.data import plot_demonstrations
from lmpromp_ppl.data import Demonstrations
from lmpromp_ppl.reports import figures

ROOT = Path(__file__).resolve().parent.parent


def test_importing_and_using_the_figures_keeps_the_users_backend(tmp_path):
    """A session on the svg backend stays on it after importing and drawing the report figures."""
    code = f"""
import matplotlib
matplotlib.use("svg")
import matplotlib.pyplot as plt
import numpy as np
before = matplotlib.get_backend()
mine = plt.figure()
import lmpromp_ppl.reports.figures as f
import lmpromp_ppl.reproduce._common
f.plot_traces({{"cavi": {{"elbo": np.arange(5.0)}}}}, {str(tmp_path / "t.png")!r})
print(before, matplotlib.get_backend(), plt.fignum_exists(mine.number))
"""
    env = {k: v for k, v in os.environ.items() if k != "MPLBACKEND"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    before, after, still_open = out.stdout.split()
    assert before.lower() == "svg" and after.lower() == "svg"
    assert still_open == "True"
    assert (tmp_path / "t.png").stat().st_size > 0


def _demos(num_dofs=2, L=3, T=40, labels=None):
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 2.0, T)
    pos = [np.c_[[np.sin(t + i) * (k + 1) + rng.normal(0, 0.01, T) for k in range(num_dofs)]].T for i in range(L)]
    return Demonstrations([t] * L, pos, labels=labels, dof_names=tuple("xyzabcd"[:num_dofs]), name="test")


def _assert_labelled(fig: Figure):
    visible = [ax for ax in fig.axes if ax.get_visible()]
    assert visible
    for ax in visible:
        assert ax.get_xlabel().strip() and ax.get_ylabel().strip(), (ax.get_title(), ax.get_xlabel(), ax.get_ylabel())


@pytest.fixture
def saved_figures(monkeypatch):
    """Capture the Figure objects the report functions save."""
    seen = []
    original = Figure.savefig

    def spy(self, *args, **kwargs):
        seen.append(self)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", spy)
    return seen


def test_every_report_figure_labels_every_axis(tmp_path, saved_figures):
    demos = _demos(labels=np.array(["a", "b", "a"]))
    rng = np.random.default_rng(1)
    phase = np.linspace(0, 1, 20)
    bands = {"nuts": (np.ones((20, 2)), 0.1 * np.ones((20, 2))), "cavi": (np.zeros((20, 2)), 0.2 * np.ones((20, 2)))}
    figures.plot_traces({"cavi": {"elbo": np.arange(10.0)}, "svi_meanfield": {"loss": np.arange(1.0, 9.0)}}, tmp_path / "a.png")
    figures.plot_sd_ratios({"cavi": {"b": rng.uniform(0.5, 1.5, 6), "alpha": np.array([0.9])}}, tmp_path / "b.png")
    figures.plot_predictive(bands, phase, demos, tmp_path / "c.png")
    figures.plot_latent({"nuts": rng.normal(size=(3, 2)), "cavi": rng.normal(size=(3, 2))}, demos.labels,
                        tmp_path / "d.png", "latent", ("h, latent dim 1", "h, latent dim 2"))
    q = {e: {"alpha": rng.gamma(5, size=200), "b": rng.normal(size=(200, 3))} for e in ("nuts", "cavi")}
    figures.plot_marginals(q, tmp_path / "e.png")
    assert len(saved_figures) == 5
    for fig in saved_figures:
        _assert_labelled(fig)
    pred = saved_figures[2]
    assert [ax.get_ylabel() for ax in pred.axes] == ["x (data units)", "y (data units)"]
    assert all(ax.get_xlabel() == "phase" for ax in pred.axes)
    assert pred.get_layout_engine() is not None  # constrained: titles clear of tick labels


@pytest.mark.parametrize("num_dofs", [1, 2, 5])
def test_data_show_labels_every_axis(num_dofs):
    _assert_labelled(plot_demonstrations(_demos(num_dofs)))


def test_data_show_draws_two_dof_paths_in_the_plane():
    demos = _demos(2)
    fig = plot_demonstrations(demos)
    plane = fig.axes[0]
    lines = [line for line in plane.get_lines() if len(line.get_xdata()) > 1]
    assert len(lines) == demos.num_demos
    for line, y in zip(lines, demos.positions):
        np.testing.assert_array_equal(line.get_xdata(), y[:, 0])
        np.testing.assert_array_equal(line.get_ydata(), y[:, 1])
    assert plane.get_aspect() == 1.0
    assert (plane.get_xlabel(), plane.get_ylabel()) == ("x (data units)", "y (data units)")
    # the per-DoF panels are still there, over time
    assert [ax.get_xlabel() for ax in fig.axes[1:3]] == ["time", "time"]
    # and the plane panel can be left out
    assert len(plot_demonstrations(demos, plane=False).get_axes()) == 2
