"""Every validation error of :class:`Demonstrations`, directly and through the loaders."""

import numpy as np
import pytest

from lmpromp_ppl.data import Demonstrations, load_dataset
from lmpromp_ppl.errors import DataError, LmprompError

T3 = np.array([0.0, 1.0, 2.0])
Y3 = np.ones((3, 2))


def _make(times=(T3, T3), positions=(Y3, Y3), **kwargs):
    return Demonstrations(times=times, positions=positions, **kwargs)


def test_valid_demonstrations_are_read_only_float_arrays():
    demos = _make(times=([0, 1, 2], T3), positions=(Y3.astype(int), Y3), labels=[1, 2])
    assert demos.times[0].dtype == np.float64 and demos.positions[0].dtype == np.float64
    assert demos.labels.tolist() == ["1", "2"] and demos.dof_names == ("dof0", "dof1")
    with pytest.raises(ValueError):
        demos.positions[0][0, 0] = 5.0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(times=(T3,), positions=(Y3,)), "need at least 2 demonstrations, got 1"),
        (dict(times=(), positions=()), "need at least 2 demonstrations, got 0"),
        (dict(times=(T3, T3, T3)), "got 3 time arrays but 2 position arrays"),
        (dict(positions=(Y3, np.full((3, 2), np.nan))), "positions of demonstration 1 contain NaN or inf"),
        (dict(positions=(np.array([[0.0, np.inf]] * 3), Y3)), "positions of demonstration 0 contain NaN or inf"),
        (dict(times=(T3, np.array([0.0, np.nan, 2.0]))), "times of demonstration 1 contain NaN or inf"),
        (dict(times=(np.array([-np.inf, 0.0, 1.0]), T3)), "times of demonstration 0 contain NaN or inf"),
        (dict(positions=(Y3, np.ones((3, 3)))), "ragged DoF: demonstration 1 has 3 DoF, demonstration 0 has 2"),
        (dict(times=(T3, np.array([0.0, 2.0, 1.0]))), "times of demonstration 1 are not strictly increasing"),
        (dict(times=(np.array([0.0, 1.0, 1.0]), T3)), "times of demonstration 0 are not strictly increasing"),
        (dict(times=(T3, np.zeros(0)), positions=(Y3, np.zeros((0, 2)))), "demonstration 1 is empty"),
        (dict(positions=(Y3, np.zeros((3, 0)))), "demonstration 1 is empty"),
        (dict(times=(T3, np.zeros(1)), positions=(Y3, np.zeros((1, 2)))), "demonstration 1 has fewer than 2 samples"),
        (dict(positions=(Y3, np.ones((2, 2)))), "demonstration 1 has 3 times but 2 positions"),
        (dict(positions=(Y3, np.ones(3))), r"positions of demonstration 1 must have 2 dimension\(s\)"),
        (dict(times=(T3[:, None], T3)), r"times of demonstration 0 must have 1 dimension\(s\)"),
        (dict(positions=(Y3, np.array([["a", "b"]] * 3))), "positions of demonstration 1 is not numeric"),
        (dict(labels=["a"]), r"labels must have shape \(2,\), got \(1,\)"),
        (dict(labels=[["a", "b"]]), r"labels must have shape \(2,\), got \(1, 2\)"),
        (dict(dof_names=("x",)), "1 DoF names given for 2 DoF"),
    ],
)
def test_invalid_demonstrations_raise_a_data_error_naming_the_problem(kwargs, match):
    with pytest.raises(DataError, match=match) as info:
        _make(**kwargs)
    # a user error: the CLI prints it on one line and exits with status 2
    assert isinstance(info.value, LmprompError)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    "content, match",
    [
        ("demo,t,x\n0,0,1\n0,1,2\n1,0,1\n1,1,2\n1,2,3\n2,0,1\n2,0,2\n", "times of demonstration 2 are not strictly increasing"),
        ("demo,t,x\n0,0,1\n0,1,2\n", "need at least 2 demonstrations, got 1"),
    ],
)
def test_validation_errors_through_a_loader_name_the_file(tmp_path, content, match):
    path = tmp_path / "user.csv"
    path.write_text(content)
    with pytest.raises(DataError, match=match) as info:
        load_dataset(str(path))
    assert str(info.value).startswith(f"{path}: ")


def test_ragged_dof_in_a_ts_file_cannot_happen_and_nan_is_dropped(tmp_path):
    # a .ts file cannot express ragged DoF (dimension count is checked per line),
    # and its missing values become irregular sampling rather than NaN positions
    path = tmp_path / "x.ts"
    path.write_text("@data\n1,2,?,4:1,2,3,4\n1,2,3:4,5,6\n")
    demos = load_dataset(str(path))
    assert all(np.all(np.isfinite(y)) for y in demos.positions)
    np.testing.assert_array_equal(demos.times[0], [0.0, 1.0, 3.0])
    path.write_text("@data\n1,2,3:1,2,3\n1,2,3\n")
    with pytest.raises(DataError, match="line 3: expected 2 dimensions, got 1"):
        load_dataset(str(path))
