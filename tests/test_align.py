"""Aligning demonstrations' phases before fitting (lmpromp_ppl.data.align)."""

import numpy as np
import pytest

from lmpromp_ppl.data import Demonstrations
from lmpromp_ppl.data.align import align_phases, dtw_path
from lmpromp_ppl.errors import DataError


def _brute_force_cost(cost):
    n, m = cost.shape
    table = np.full((n + 1, m + 1), np.inf)
    table[0, 0] = 0.0
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            table[i, j] = cost[i - 1, j - 1] + min(table[i - 1, j - 1], table[i - 1, j], table[i, j - 1])
    return table[n, m]


@pytest.mark.parametrize("shape", [(5, 7), (9, 9), (12, 6)])
def test_dtw_path_is_the_minimum_cost_monotone_path(shape):
    cost = np.random.default_rng(sum(shape)).random(shape)
    rows, cols = dtw_path(cost)
    assert (rows[0], cols[0]) == (0, 0) and (rows[-1], cols[-1]) == (shape[0] - 1, shape[1] - 1)
    steps = np.stack([np.diff(rows), np.diff(cols)], axis=1)
    assert np.all((steps >= 0) & (steps <= 1)) and np.all(steps.sum(axis=1) >= 1)
    np.testing.assert_allclose(cost[rows, cols].sum(), _brute_force_cost(cost), rtol=1e-12)


def test_dtw_band_excludes_far_cells():
    cost = np.ones((20, 20))
    cost[np.arange(20), np.arange(20)] = 5.0  # the diagonal is dear, a detour is cheap without a band
    rows, cols = dtw_path(cost, band=2)
    assert np.max(np.abs(rows - cols)) <= 2


def _warped(seed=0, num=150):
    """Demonstrations of one movement f at known phase warps g_i (the middle one the identity)."""
    u = np.linspace(0.0, 1.0, num)
    shifts = (-0.15, 0.0, 0.15)  # g(u) = u + a sin(pi u): monotone, |g - u| up to 0.15
    f = lambda z: np.column_stack([np.sin(2 * np.pi * z), np.cos(3 * np.pi * z)])
    rng = np.random.default_rng(seed)
    times = [u * (2.0 + 0.3 * k) for k in range(3)]
    warps = [u + a * np.sin(np.pi * u) for a in shifts]
    positions = [f(g) + 0.01 * rng.standard_normal((num, 2)) for g in warps]
    return Demonstrations(times, positions, name="warped"), warps


def test_align_phases_recovers_known_warps():
    demos, warps = _warped()
    aligned = align_phases(demos)
    for z, g in zip(aligned.phases(), warps):
        assert z[0] == 0.0 and z[-1] == 1.0 and np.all(np.diff(z) >= 0)
        assert np.max(np.abs(z - g)) < 0.04
    # the linear phases are far from the warps: the test could fail
    assert max(np.max(np.abs(z - g)) for z, g in zip(demos.phases(), warps)) > 0.14
    assert aligned.subset([0, 2]).phases()[1] is aligned.phases()[2]


def test_aligned_fit_stores_its_phases_and_sharpens_the_movement_distribution(tmp_path):
    from lmpromp_ppl import load
    from lmpromp_ppl.api import fit
    from lmpromp_ppl.predict.from_fit import population_prediction

    demos, _ = _warped()
    demos = Demonstrations(demos.times * 3, [y + 0.05 * k for k in range(3) for y in demos.positions], name="warped")
    linear = fit(demos, num_basis=10)
    aligned = fit(demos, num_basis=10, align="dtw")
    assert "aligned_phase" not in linear.observed
    np.testing.assert_array_equal(aligned.observed["aligned_phase"], np.stack(align_phases(demos).phases()))
    aligned.save(tmp_path / "fit")
    again = load(tmp_path / "fit")
    np.testing.assert_array_equal(again.training_phases()[4], aligned.training_phases()[4])
    back = again.training_demonstrations()  # what calibrate_timing refits on
    assert back.num_demos == demos.num_demos and back.dof_names == demos.dof_names
    for a, b, z, g in zip(back.times, demos.times, back.warp, align_phases(demos).phases()):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(z, g)
    assert linear.training_demonstrations().warp is None
    # the warps blur the linear-phase distribution; aligned, only the offsets of 0.05 remain
    assert np.mean(population_prediction(aligned).sd) < 0.6 * np.mean(population_prediction(linear).sd)
    assert again.posterior_predictive(num_draws=2).shape[2:] == (9, 150, 2)


def test_bad_alignment_input():
    demos, _ = _warped()
    with pytest.raises(DataError, match="unknown alignment"):
        align_phases(demos, "warp")
    with pytest.raises(DataError, match="band"):
        align_phases(demos, band=0.0)
    with pytest.raises(DataError, match="non-decreasing from 0 to 1"):
        demos.with_warp([z[::-1] for z in demos.phases()])
    with pytest.raises(DataError, match="aligned phases"):
        demos.with_warp([z[:-1] for z in demos.phases()])


def test_cli_fit_align(tmp_path, capsys):
    from lmpromp_ppl.cli import main

    demos, _ = _warped()
    from lmpromp_ppl.data import save_npz

    save_npz(demos, tmp_path / "demos.npz")
    assert main(["fit", str(tmp_path / "demos.npz"), "--num-basis", "8", "--align", "dtw",
                 "--out", str(tmp_path / "fit")]) == 0
    assert "phases aligned (dtw)" in capsys.readouterr().out
    assert main(["fit", str(tmp_path / "demos.npz"), "--align", "stretch", "--out", str(tmp_path / "bad")]) == 2
    assert "--align" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
