"""``lmpromp data list`` and ``lmpromp data show`` through :func:`lmpromp_ppl.cli.main`."""

import numpy as np
import pytest
from matplotlib.image import imread

from lmpromp_ppl.cli import main
from lmpromp_ppl.data import Demonstrations, save_npz


def _one_line_error(capsys, *fragments):
    err = capsys.readouterr().err
    assert err.startswith("lmpromp: error: ") and err.count("\n") == 1, err
    for fragment in fragments:
        assert fragment in err, err
    assert "Traceback" not in err


def test_data_list_prints_every_dataset(capsys):
    assert main(["data", "list"]) == 0
    names = capsys.readouterr().out.splitlines()
    assert len(names) == 36
    assert names[0] == "lasa:Angle" and "gunpoint:test" in names and names[-1] == "synthetic:reaching"


def test_data_show_writes_a_png_and_one_summary_line(tmp_path, capsys):
    out = tmp_path / "figs" / "lasa.png"
    assert main(["data", "show", "lasa:Angle?every=20", "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines == [f"lasa:Angle?every=20: 7 demonstrations, 2 DoF (x, y), 51 samples each, no labels -> {out}"]
    image = imread(out)
    # two panels side by side: wider than tall, and not blank
    assert image.shape[1] > image.shape[0] > 100
    assert image[..., :3].std() > 0.05


def test_data_show_colours_by_label_one_panel_per_dof(tmp_path, capsys):
    out = tmp_path / "reach.png"
    code = main(["data", "show", "synthetic:reaching", "--seed", "4", "--out", str(out), "--quiet", "--phase"])
    assert code == 0
    assert capsys.readouterr().out == ""
    image = imread(out)[..., :3]
    # tab10 blue (C0) and orange (C1) lines for the two labels
    blue = np.all(np.abs(image - np.array([0x1F, 0x77, 0xB4]) / 255) < 0.02, axis=-1)
    orange = np.all(np.abs(image - np.array([0xFF, 0x7F, 0x0E]) / 255) < 0.02, axis=-1)
    assert blue.sum() > 100 and orange.sum() > 100
    # 7 DoF in a 3-column grid: 3 rows
    assert image.shape[0] > image.shape[1] * 0.6


def test_data_show_refuses_an_existing_out_unless_force(tmp_path, capsys):
    out = tmp_path / "x.png"
    out.write_bytes(b"keep")
    assert main(["data", "show", "gunpoint", "--out", str(out)]) == 2
    _one_line_error(capsys, "exists; pass --force")
    assert out.read_bytes() == b"keep"
    assert main(["data", "show", "gunpoint", "--out", str(out), "--force"]) == 0
    assert "gunpoint:train: 50 demonstrations, 1 DoF (x), 150 samples each, labels Gun-Draw (24), Point (26)" in (
        capsys.readouterr().out
    )
    assert out.read_bytes()[:4] == b"\x89PNG"


def test_data_show_reads_user_files(tmp_path, capsys):
    demos = Demonstrations(
        times=(np.arange(4.0), np.arange(6.0)),
        positions=(np.ones((4, 1)), np.zeros((6, 1))),
        labels=np.array(["a", "b"]),
        dof_names=("angle",),
    )
    path = save_npz(demos, tmp_path / "mine.npz")
    assert main(["data", "show", str(path), "--out", str(tmp_path / "mine.png")]) == 0
    assert "2 demonstrations, 1 DoF (angle), 4-6 samples, labels a (1), b (1)" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, fragments",
    [
        (["data", "show", "lasa:Nope", "--out", "{tmp}/a.png"], ["unknown LASA shape 'Nope'", "Angle"]),
        (["data", "show", "cifar", "--out", "{tmp}/a.png"], ["unknown dataset 'cifar'", "gunpoint"]),
        (["data", "show", "synthetic:latent?Q=1", "--out", "{tmp}/a.png"], ["unknown option 'Q'", "alpha"]),
        (["data", "show", "{tmp}/missing.csv", "--out", "{tmp}/a.png"], ["cannot read", "missing.csv"]),
        (["data", "show", "lasa:Angle", "--out", "{tmp}/a.figure"], ["unknown image type 'figure'", "png"]),
        (["data", "show", "lasa:Angle"], ["Missing option '--out'"]),
        (["data", "show", "lasa:Angle", "--out", "{tmp}/a.png", "--seed", "x"], ["--seed"]),
        (["data", "frobnicate"], ["No such command 'frobnicate'"]),
    ],
)
def test_data_user_errors_exit_2_with_one_line(tmp_path, capsys, argv, fragments):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert main(argv) == 2
    _one_line_error(capsys, *fragments)
    assert not (tmp_path / "a.png").exists()


def test_data_help(capsys):
    assert main(["data", "show", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--out" in out and "--force" in out and "--quiet" in out and "lasa:<Shape>" in out
