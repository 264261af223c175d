"""User files: exact .npz/.csv round trips, overwrite refusal, refused pickles
and every malformed-file error."""

import numpy as np
import pytest

from lmpromp_ppl.data import Demonstrations, load_csv, load_dataset, load_npz, save_csv, save_npz
from lmpromp_ppl.errors import DataError


def _awkward_floats(rng, shape):
    """Values whose decimal representation needs all 17 digits, plus tiny and huge ones."""
    values = rng.standard_normal(shape) * np.exp(rng.uniform(-30, 30, shape))
    values.flat[0] = 0.1 + 0.2
    values.flat[-1] = 5e-324
    return values


def _equal(rng, labels=True, shared_times=True):
    L, T, D = 3, 5, 2
    times = np.cumsum(rng.uniform(0.1, 1.0, (L, T)), axis=1) + np.pi
    if shared_times:
        times[:] = times[0]
    return Demonstrations(
        times=tuple(times),
        positions=tuple(_awkward_floats(rng, (L, T, D))),
        labels=np.array(["left", "right, with comma", 'quo"te']) if labels else None,
        dof_names=("x", "y position"),
        name="original",
    )


def _ragged(rng, labels=True):
    lengths = [4, 2, 7]
    return Demonstrations(
        times=tuple(np.cumsum(rng.uniform(0.01, 1.0, n)) / 3.0 for n in lengths),
        positions=tuple(_awkward_floats(rng, (n, 3)) for n in lengths),
        labels=np.array(["a", "b", "a"]) if labels else None,
        dof_names=("q1", "q2", "ünïcode"),
    )


def _assert_identical(a: Demonstrations, b: Demonstrations):
    assert a.num_demos == b.num_demos
    for ta, tb, ya, yb in zip(a.times, b.times, a.positions, b.positions):
        assert ta.tobytes() == tb.tobytes()
        assert ya.shape == yb.shape and ya.tobytes() == yb.tobytes()
    assert a.dof_names == b.dof_names
    if a.labels is None:
        assert b.labels is None
    else:
        assert a.labels.tolist() == b.labels.tolist()


CASES = {
    "equal-shared-times-labelled": lambda rng: _equal(rng),
    "equal-own-times-unlabelled": lambda rng: _equal(rng, labels=False, shared_times=False),
    "ragged-labelled": lambda rng: _ragged(rng),
    "ragged-unlabelled": lambda rng: _ragged(rng, labels=False),
}


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("suffix, save, load", [(".npz", save_npz, load_npz), (".csv", save_csv, load_csv)])
def test_round_trip_is_exact(tmp_path, case, suffix, save, load):
    demos = CASES[case](np.random.default_rng(0))
    path = tmp_path / f"demos{suffix}"
    assert save(demos, path) == path
    loaded = load(path)
    _assert_identical(demos, loaded)
    assert loaded.name == str(path)
    # the registry dispatches on the suffix
    _assert_identical(demos, load_dataset(str(path)))


def test_npz_layout_follows_the_contract(tmp_path):
    rng = np.random.default_rng(1)
    save_npz(_equal(rng), tmp_path / "shared.npz")
    save_npz(_equal(rng, labels=False, shared_times=False), tmp_path / "own.npz")
    save_npz(_ragged(rng), tmp_path / "ragged.npz")
    with np.load(tmp_path / "shared.npz") as f:
        assert f["t"].shape == (5,) and f["y"].shape == (3, 5, 2) and f["labels"].dtype.kind == "U"
        assert f["dof_names"].tolist() == ["x", "y position"] and "lengths" not in f.files
    with np.load(tmp_path / "own.npz") as f:
        assert f["t"].shape == (3, 5) and "labels" not in f.files
    with np.load(tmp_path / "ragged.npz") as f:
        assert f["t"].shape == (13,) and f["y"].shape == (13, 3) and f["lengths"].tolist() == [4, 2, 7]


def test_csv_layout_follows_the_contract(tmp_path):
    demos = Demonstrations(
        times=(np.array([0.0, 0.5]), np.array([0.0, 1.0])),
        positions=(np.array([[1.0], [0.1]]), np.array([[2.0], [3.0]])),
        labels=np.array(["a", "b"]),
        dof_names=("x",),
    )
    save_csv(demos, tmp_path / "d.csv")
    assert (tmp_path / "d.csv").read_text().splitlines() == [
        "demo,t,x,label",
        "0,0.0,1.0,a",
        "0,0.5,0.1,a",
        "1,0.0,2.0,b",
        "1,1.0,3.0,b",
    ]


def test_hand_written_csv_with_interleaved_rows_and_string_ids(tmp_path):
    path = tmp_path / "hand.csv"
    path.write_text("\ufefft,demo,y,label\n0,trial-b,1,x\n0,trial-a,5,y\n1,trial-b,2,x\n2,trial-a,6,y\n\n")
    demos = load_csv(path)
    assert demos.dof_names == ("y",)
    assert demos.labels.tolist() == ["x", "y"]  # order of first appearance
    np.testing.assert_array_equal(demos.times[1], [0.0, 2.0])
    np.testing.assert_array_equal(demos.positions[0][:, 0], [1.0, 2.0])


@pytest.mark.parametrize("suffix, save", [(".npz", save_npz), (".csv", save_csv)])
def test_save_refuses_existing_file_unless_overwrite(tmp_path, suffix, save):
    demos = _ragged(np.random.default_rng(2))
    path = tmp_path / f"d{suffix}"
    path.write_bytes(b"precious")
    with pytest.raises(DataError, match="exists; pass overwrite=True"):
        save(demos, path)
    assert path.read_bytes() == b"precious"
    save(demos, path, overwrite=True)
    _assert_identical(demos, load_dataset(str(path)))
    with pytest.raises(DataError, match="is a directory"):
        save(demos, tmp_path, overwrite=True)
    with pytest.raises(DataError, match="cannot write"):
        save(demos, tmp_path / "no" / "such" / f"dir{suffix}")


def test_save_csv_refuses_unreadable_dof_names(tmp_path):
    base = _equal(np.random.default_rng(3), labels=False)
    for names in [("t", "x"), ("x", "x"), ("label", "y"), ("", "y"), (" x", "y")]:
        demos = Demonstrations(base.times, base.positions, dof_names=names)
        with pytest.raises(DataError, match="cannot save DoF names"):
            save_csv(demos, tmp_path / "d.csv")
    assert not (tmp_path / "d.csv").exists()


# ---------------------------------------------------------------- malicious / malformed .npz
class _Exploit:
    def __reduce__(self):
        return (exec, ("import pathlib; pathlib.Path('PWNED').write_text('x')",))


def test_pickle_bearing_npz_is_refused_and_nothing_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "evil.npz"
    payload = np.empty(1, dtype=object)
    payload[0] = _Exploit()
    np.savez(path, t=np.arange(3.0), y=payload)
    with pytest.raises(DataError, match="evil.npz: holds object arrays"):
        load_dataset(str(path))
    # a raw pickle disguised as .npz
    import pickle

    disguised = tmp_path / "disguised.npz"
    disguised.write_bytes(pickle.dumps(_Exploit()))
    with pytest.raises(DataError, match="disguised.npz: not an .npz"):
        load_npz(disguised)
    assert not (tmp_path / "PWNED").exists()


def _write_npz(path, **arrays):
    np.savez(path, **arrays)
    return path


Y = np.zeros((2, 3, 1))
T = np.arange(3.0)


@pytest.mark.parametrize(
    "arrays, match",
    [
        (dict(y=Y), "missing key 't'"),
        (dict(t=T), "missing key 'y'"),
        (dict(t=T, y=Y, weights=T), r"unknown key\(s\) weights; valid keys: t, y, lengths, labels, dof_names"),
        (dict(t=T, y=np.zeros((2, 3))), r"y must have shape \(L, T, D\)"),
        (dict(t=np.arange(4.0), y=Y), r"t must have shape \(3,\) or \(2, 3\)"),
        (dict(t=np.array(["a", "b", "c"]), y=Y), "t must be numeric"),
        (dict(t=T, y=Y, labels=np.array(["a"])), r"labels must have shape \(2,\)"),
        (dict(t=T, y=Y, labels=np.array([1, 2])), "labels must be a unicode string array"),
        (dict(t=T, y=Y, dof_names=np.array(["a", "b"])), r"dof_names must have shape \(1,\)"),
        (dict(t=T, y=Y, dof_names=np.array([b"x"])), "dof_names must be a unicode string array"),
        (dict(t=np.arange(5.0), y=np.zeros((5, 1)), lengths=np.array([2.0, 3.0])), "lengths must be a 1-D integer"),
        (dict(t=np.arange(5.0), y=np.zeros((5, 1)), lengths=np.array([2, 2])), "lengths sum to 4"),
        (dict(t=np.arange(5.0), y=np.zeros((5, 1)), lengths=np.array([5, 0])), "lengths must be positive"),
        (dict(t=np.arange(5.0), y=np.zeros((1, 5, 1)), lengths=np.array([5])), r"ragged files need t \(N,\) and y \(N, D\)"),
        (dict(t=T, y=np.full((2, 3, 1), np.nan)), "positions of demonstration 0 contain NaN or inf"),
        (dict(t=np.array([0.0, 2.0, 1.0]), y=Y), "not strictly increasing"),
        (dict(t=T[:0], y=Y[:, :0]), "demonstration 0 is empty"),
        (dict(t=T, y=Y[:1]), "need at least 2 demonstrations"),
    ],
)
def test_malformed_npz_errors_name_the_file(tmp_path, arrays, match):
    path = _write_npz(tmp_path / "bad.npz", **arrays)
    with pytest.raises(DataError, match=match) as info:
        load_npz(path)
    assert str(path) in str(info.value)


def test_unreadable_npz(tmp_path):
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip file at all")
    with pytest.raises(DataError, match="cannot read .*garbage.npz"):
        load_npz(garbage)
    npy = tmp_path / "single.npz"
    with open(npy, "wb") as handle:
        np.save(handle, np.zeros(3))
    with pytest.raises(DataError, match="single.npz: not an .npz"):
        load_npz(npy)
    with pytest.raises(DataError, match="cannot read .*absent.npz"):
        load_npz(tmp_path / "absent.npz")


# ---------------------------------------------------------------- malformed .csv
@pytest.mark.parametrize(
    "text, match",
    [
        ("", "empty file"),
        ("t,x\n0,1\n", "no 'demo' column"),
        ("demo,x\n0,1\n", "no 't' column"),
        ("demo,t,label\n0,0,a\n", "no DoF columns"),
        ("demo,t,x,x\n0,0,1,1\n", "repeated column names"),
        ("demo,t,x\n0,0,1\n0,1\n", "line 3: 2 fields, the header has 3"),
        ("demo,t,x\n0,0,1\n0,1,abc\n", "line 3: column 'x': 'abc' is not a number"),
        ("demo,t,x\n0,0,1\n0,1,nan\n", "line 3: column 'x': value 'nan' is not finite"),
        ("demo,t,x\n0,zero,1\n", "line 2: column 't'"),
        ("demo,t,x,label\n0,0,1,a\n0,1,1,b\n1,0,1,a\n1,1,1,a\n", "line 3: label 'b' differs from 'a'"),
        ("demo,t,x\n", "no data rows"),
        ("demo,t,x\n0,0,1\n0,1,2\n", "need at least 2 demonstrations"),
        ("demo,t,x\n0,0,1\n0,1,2\n1,1,1\n1,0,2\n", "times of demonstration 1 are not strictly increasing"),
        ("demo,t,x\n0,0,1\n0,1,2\n1,0,1\n", "demonstration 1 has fewer than 2 samples"),
    ],
)
def test_malformed_csv_errors_name_the_file(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(DataError, match=match) as info:
        load_csv(path)
    assert str(path) in str(info.value)


def test_unreadable_csv(tmp_path):
    binary = tmp_path / "binary.csv"
    binary.write_bytes(b"demo,t,x\n\xff\xfe\x81")
    with pytest.raises(DataError, match="cannot read .*binary.csv"):
        load_csv(binary)
