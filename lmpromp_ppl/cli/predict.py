"""``lmpromp predict``: condition a saved fit on a (partial) demonstration."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import typer

from lmpromp_ppl.cli import app
from lmpromp_ppl.cli._common import SEED_MAX, positive, claim_out_dir
from lmpromp_ppl.errors import DataError, LmprompError

__all__ = ["predict_command", "read_observation", "read_via"]


def _read_columns(path: Path, what: str) -> dict[str, np.ndarray]:
    """The named arrays of a ``.npz`` (read without pickle) or the columns of a ``.csv`` with a header, in order."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"cannot read {what} file {path}: no such file")
    if path.suffix not in (".npz", ".csv"):
        raise DataError(f"{what} file {path} must end in .npz or .csv")
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as f:
                return {name: np.asarray(f[name], dtype=float) for name in f.files}
        table = np.atleast_1d(np.genfromtxt(path, delimiter=",", names=True, dtype=float))
    except (OSError, ValueError) as exc:
        raise DataError(f"cannot read {what} file {path}: {exc}") from None
    return {name: np.asarray(table[name], dtype=float) for name in table.dtype.names or ()}


def _stack(columns: list[np.ndarray], size: int) -> np.ndarray:
    return np.stack(columns, axis=-1) if columns else np.empty((size, 0))


def read_observation(path: Path, num_dofs: int) -> tuple[np.ndarray, np.ndarray]:
    """Read one demonstration ``t`` (T,), ``y`` (T, D) from ``.npz`` or ``.csv``.

    NaN in ``y`` marks an unobserved entry.  ``.npz`` is read without pickle;
    ``.csv`` has a header with ``t`` then one column per DoF.
    """
    path = Path(path)
    columns = _read_columns(path, "observation")
    if path.suffix == ".npz":
        if "t" not in columns or "y" not in columns:
            raise DataError(f"{path}: needs arrays 't' (T,) and 'y' (T, D), found {sorted(columns)}")
        t, y = columns["t"], columns["y"]
    else:
        names = list(columns)
        if not names or names[0] != "t":
            raise DataError(f"{path}: the first column must be 't', found {names}")
        t = columns["t"]
        y = _stack([columns[n] for n in names[1:]], t.size)
    if y.ndim == 1 and num_dofs == 1:
        y = y[:, None]
    if t.ndim != 1 or y.ndim != 2 or y.shape[0] != t.shape[0]:
        raise DataError(f"{path}: 't' must be (T,) and 'y' (T, D), got {t.shape} and {y.shape}")
    if y.shape[1] != num_dofs:
        raise DataError(f"{path}: the fit has {num_dofs} DoF but 'y' has {y.shape[1]} columns")
    if not np.all(np.isfinite(t)):
        raise DataError(f"{path}: 't' contains NaN or inf")
    return t, y


def _parse_duration(text: str | None):
    if text is None:
        return None
    if text == "estimate":
        return "estimate"
    try:
        value = float(text)
    except ValueError:
        raise DataError(f"--duration must be a positive number of seconds or 'estimate', got {text!r}") from None
    if not np.isfinite(value) or value <= 0:
        raise DataError(f"--duration must be positive and finite, got {text!r}")
    return value


def read_via(path: Path, num_dofs: int):
    """Read via-points (``--via``): see the option's help; the sd defaults to 0 (pass exactly)."""
    from lmpromp_ppl.predict.timing import ViaPoints

    path = Path(path)
    columns = _read_columns(path, "via-point")
    sd = 0.0
    if path.suffix == ".npz":
        where = "phase" if "phase" in columns else "t" if "t" in columns else None
        if where is None or "y" not in columns:
            raise DataError(f"{path}: needs 'phase' (V,) or 't' (V,), and 'y' (V, D); found {sorted(columns)}")
        at, pos, vel = columns[where], columns["y"], columns.get("dy")
        sd = columns.get("sd", 0.0)
    else:
        names = list(columns)
        if not names or names[0] not in ("phase", "t") or len(names) not in (1 + num_dofs, 1 + 2 * num_dofs):
            raise DataError(f"{path}: columns must be phase or t, then {num_dofs} positions and optionally "
                            f"{num_dofs} velocities; found {names}")
        where = names[0]
        at = columns[where]
        pos = _stack([columns[n] for n in names[1:1 + num_dofs]], at.size)
        vel = _stack([columns[n] for n in names[1 + num_dofs:]], at.size) if len(names) > 1 + num_dofs else None
    if pos.ndim == 1 and num_dofs == 1:
        pos = pos[:, None]
        vel = None if vel is None else vel.reshape(-1, 1)
    if at.ndim != 1 or pos.shape != (at.shape[0], num_dofs):
        raise DataError(f"{path}: needs {where} (V,) and y (V, {num_dofs}), got {at.shape} and {pos.shape}")
    return ViaPoints(at, pos, vel, sd, sd, timed=where == "t")


def _parse_power(text: str | None):
    """``--timing-power``: ``calibrate`` (also when not given) or a number in [0, 1]."""
    if text is None or text == "calibrate":
        return "calibrate"
    try:
        value = float(text)
    except ValueError:
        raise DataError(f"--timing-power must be 'calibrate' or a number in [0, 1], got {text!r}") from None
    if not 0.0 <= value <= 1.0:
        raise DataError(f"--timing-power must lie in [0, 1], got {text}")
    return value


@app.command("predict")
def predict_command(
    fit_dir: Path = typer.Argument(..., help="Directory written by `lmpromp fit`."),
    observe: Path = typer.Option(..., "--observe", help="Observed (partial) demonstration: .npz with t (T,), y (T, D) or .csv; NaN = unobserved."),
    out: Path = typer.Option(..., "--out", help="Output directory (prediction.npz, prediction.png)."),
    duration: Optional[str] = typer.Option(None, help="SECONDS: map times to phases as t / duration; estimate: infer the duration (times in seconds from the movement's start). Default: t are phases."),
    max_start: float = typer.Option(0.0, "--max-start", help="With --duration estimate: the observation may have begun after the movement, at any phase up to this one (in [0, 1); times then count from the observation's start); its start phase is estimated too. Default 0: it began with the movement."),
    timing_power: Optional[str] = typer.Option(None, "--timing-power", help="With --duration estimate: the power in [0, 1] of the timing's likelihood (1: the model's posterior, 0: the duration prior alone), or calibrate (default): the candidate powers averaged with weights by how well refits without each of up to 8 folds of the training demonstrations predict the held-out durations, each observed from its start for as long as this observation (lmpromp_ppl.calibrate_timing; the refits use CAVI)."),
    via: Optional[Path] = typer.Option(None, "--via", help="Via-points: .npz with phase (V,) or t (V,) seconds, y (V, D), optional dy (V, D) and sd; or .csv with a phase or t column then D position and optionally D velocity columns; NaN = free."),
    noise_sd: Optional[float] = typer.Option(None, "--noise-sd", callback=positive, help="Observation noise s.d. in data units (default: the fit's, from its learned beta)."),
    bayesian: bool = typer.Option(True, "--bayesian/--plug-in", help="Average over posterior draws (default) or plug in the posterior mean."),
    exact: bool = typer.Option(True, "--exact/--thesis-approximation", help="Exact p(w|o) (default) or the thesis's approximation, eqs. 4.6-4.7."),
    samples: int = typer.Option(20, min=1, help="Sampled trajectories to store."),
    seed: int = typer.Option(0, min=0, max=SEED_MAX, help=f"Seed for the sampled trajectories (0 to {SEED_MAX})."),
    force: bool = typer.Option(False, "--force", help="Overwrite existing output files."),
    quiet: bool = typer.Option(False, "--quiet", help="No output but errors."),
) -> None:
    """Predict the whole movement from a partial observation, with a saved fit."""
    import jax
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from lmpromp_ppl.predict.from_fit import predict_from_fit
    from lmpromp_ppl.results import load

    timing = _parse_duration(duration)
    if not 0.0 <= max_start < 1.0:
        raise DataError(f"--max-start must lie in [0, 1), got {max_start:g}")
    if max_start > 0 and timing != "estimate":
        raise DataError("--max-start needs --duration estimate")
    if timing_power is not None and timing != "estimate":
        raise DataError("--timing-power needs --duration estimate")
    power = _parse_power(timing_power)
    if not fit_dir.exists():
        raise LmprompError(f"fit directory {fit_dir} does not exist; write one with `lmpromp fit ... --out {fit_dir}`")
    if not fit_dir.is_dir():
        raise LmprompError(f"{fit_dir} is not a directory; pass the directory written by `lmpromp fit`")
    result = load(fit_dir)
    t, y = read_observation(observe, result.num_dofs)
    if timing is None and (np.any(t < 0) or np.any(t > 1)):
        raise DataError("observation phases must lie in [0, 1]; pass --duration to map times to phases")
    via_points = None if via is None else read_via(via, result.num_dofs)
    calibration = None
    if timing == "estimate" and power == "calibrate":
        from lmpromp_ppl.api import calibrate_timing

        seen = np.any(np.isfinite(y), axis=1)
        if not np.any(seen):
            raise DataError("estimating the timing needs observed values at times (seconds)")
        calibration = calibrate_timing(result, float(np.max(t[seen])), max_start=max_start, progress=not quiet)
        powers, power_weights, power = calibration.powers, calibration.weights, calibration.mean_power
    else:
        powers, power_weights = (1.0 if timing != "estimate" else power), None
    pred = predict_from_fit(result, t, y, duration=timing, max_start=max_start, via=via_points, noise_sd=noise_sd, bayesian=bayesian,
                            exact=exact, num_samples=samples, key=jax.random.key(seed),
                            timing_power=powers, timing_weights=power_weights)
    out_dir = claim_out_dir(out, force)
    extra = {}
    if timing is not None:
        extra = dict(time=pred.time, time_mean=pred.time_mean, time_sd=pred.time_sd)
    if timing == "estimate":
        extra.update(duration=np.asarray(pred.duration), duration_interval=np.asarray(pred.duration_interval),
                     timing_power=np.asarray(power))
        if calibration is not None:
            extra.update(timing_powers=calibration.powers, timing_weights=calibration.weights)
    if max_start > 0:
        extra.update(start_phase=np.asarray(pred.timing.start_estimate))
    np.savez(out_dir / "prediction.npz", phase=pred.phase, mean=pred.mean, sd=pred.sd, sd_obs=pred.sd_obs,
             samples=pred.samples, **extra)
    fig = Figure(figsize=(4.5 * result.num_dofs, 3.2), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, result.num_dofs, squeeze=False)[0]
    for k, ax in enumerate(axes):
        ok = np.isfinite(y[:, k])
        if timing is None:
            for path in pred.samples[:, :, k]:
                ax.plot(pred.phase, path, color="tab:blue", alpha=0.15, lw=0.8)
            ax.fill_between(pred.phase, pred.mean[:, k] - 1.645 * pred.sd_obs[:, k],
                            pred.mean[:, k] + 1.645 * pred.sd_obs[:, k], color="tab:blue", alpha=0.12,
                            label="90 % band, new observation")
            x, mean, sd = pred.phase, pred.mean[:, k], pred.sd[:, k]
        else:  # real time: the observation, the predicted rest, the end's interval
            x, mean, sd = pred.time, pred.time_mean[:, k], pred.time_sd[:, k]
            if timing == "estimate":
                # the end lies T (1 - z0) after the observation's start (z0 = 0 unless --max-start)
                end = np.asarray(pred.duration_interval) * (1.0 - pred.timing.start_estimate)
                ax.axvspan(*end, color="tab:orange", alpha=0.15, label="90 % interval of the end")
        ax.fill_between(x, mean - 1.645 * sd, mean + 1.645 * sd, color="tab:blue", alpha=0.25, label="90 % band, movement")
        ax.plot(x, mean, color="tab:blue", lw=2, label="predicted mean")
        ax.plot(t[ok], y[ok, k], "o", color="black", ms=3, label="observed")
        if via_points is not None:
            start = pred.timing.start_estimate if pred.timing is not None else 0.0
            at = via_points.at if timing is None or via_points.timed else (via_points.at - start) * pred.duration
            okv = np.isfinite(via_points.position[:, k])
            ax.plot(at[okv], via_points.position[okv, k], "D", color="tab:red", ms=6, label="via-points")
        name = result.dof_names[k] if result.dof_names else f"DoF {k}"
        ax.set_xlabel("phase" if timing is None else
                      "time from the observation's start" if max_start > 0 else "time from the movement's start")
        ax.set_ylabel(f"{name} (data units)")
        ax.set_title(name)
    axes[0].legend(fontsize=8)
    fig.savefig(out_dir / "prediction.png", dpi=110)
    if not quiet and timing == "estimate":
        lo, hi = pred.duration_interval
        typer.echo(f"estimated duration {pred.duration:.4g} (90 % interval {lo:.4g} to {hi:.4g}), in the observation's time unit")
        if calibration is None:
            typer.echo(f"power of the timing's likelihood {power:.3g} (as given)")
        else:
            how = (f"weighed by refits without each of {calibration.num_folds} folds, {calibration.num_scored} "
                   f"held-out durations scored; best single power {calibration.power:.3g}")
            if calibration.num_unconverged:
                how += f"; {calibration.num_unconverged} refits stopped at CAVI's iteration limit"
            typer.echo(f"power of the timing's likelihood averaged over {calibration.powers.size} candidates, "
                       f"mean {power:.3g} ({how})")
        if max_start > 0:
            typer.echo(f"estimated start phase of the observation {pred.timing.start_estimate:.3g}")
    if not quiet:
        typer.echo(f"predicted {result.model}/{result.engine} from {int(np.isfinite(y).sum())} observed values; wrote {out_dir}")
