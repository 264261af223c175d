r"""One result layout for every engine (docs/cli.md, "Files written").

A :class:`FitResult` holds what an engine produced on one model and dataset.
:meth:`FitResult.to_datatree` turns it into an ArviZ-style
:class:`xarray.DataTree` with groups

* ``posterior``: draws with dims (``chain``, ``draw``, ...) and the site names
  and dims of :data:`SITE_DIMS` (VI engines: draws from q, one chain);
* ``derived``: identifiable quantities (``gram_eig``, ``pred_mean``, ``pred_sd``);
* ``sample_stats``: NUTS statistics (divergences, tree depth, step size, ...);
* ``optimization``: ELBO or loss traces with dim ``iteration``;
* ``point_estimate``: posterior means used for plug-in prediction;
* ``observed_data``: the demonstrations in data units, ``t`` (``demo``,
  ``sample``) and ``y`` (``demo``, ``sample``, ``dof``), NaN-padded when
  lengths differ, and ``aligned_phase`` (``demo``, ``sample``) when the
  phases were aligned before fitting (``fit(..., align="dtw")``);
* ``posterior_predictive`` (on request): replicated demonstrations ``y``
  (``chain``, ``draw``, ``demo``, ``sample``, ``dof``) drawn from
  :math:`N(\Psi_i w_i, \beta^{-1} I)` for each posterior draw of ``w``.

Attributes record the model, engine, dataset, hyperparameters, engine options,
seed, timing, the per-DoF scaling, the basis and the package versions.

:meth:`FitResult.save` writes ``posterior.nc`` (netCDF through h5netcdf) and
``summary.json``; :func:`load` reads them back.  Both carry
:data:`FORMAT_VERSION`.

What is saved, and how big it gets:

* every array is stored in float64 (no rounding) with zlib compression, and
  :func:`load` gives back exactly the arrays that were saved;
* CAVI results also store the variational parameters, the engine state, in the
  group ``variational``; a loaded CAVI fit rebuilds the state, so q can be
  re-sampled (``result.sampler(key, n)`` gives the same draws as before saving
  for the same key) and predicted from;
* the draw-indexed groups (``posterior``, ``derived``, ``sample_stats``,
  ``posterior_predictive``) are thinned evenly along ``draw`` when the
  posterior draws would exceed ``max_draw_bytes`` (default
  :data:`MAX_DRAW_BYTES`, uncompressed) -- the per-demonstration sites ``w``
  and ``h`` grow with the number of demonstrations.  At least
  :data:`MIN_SAVED_DRAWS` draws per chain are kept; the ``draw`` coordinate
  holds the indices of the kept draws.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np
import xarray as xr

from lmpromp_ppl.basis import DEFAULT_WIDTH
from lmpromp_ppl.data.core import Demonstrations, Scaling
from lmpromp_ppl.quantities import derived_quantities
from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.models.hyper import Hyperparameters

__all__ = [
    "FORMAT_VERSION", "MAX_DRAW_BYTES", "MIN_SAVED_DRAWS", "SITE_DIMS", "FitResult", "load", "package_version",
    "package_versions", "site_dims", "to_json_value",
]

FORMAT_VERSION = 1

#: Default bound, in bytes before compression, on the posterior draws a saved fit stores.
MAX_DRAW_BYTES = 8_000_000
#: Draws per chain kept however large the per-demonstration sites are.
MIN_SAVED_DRAWS = 20
#: zlib level of every stored array.
COMPRESSION_LEVEL = 4

#: Dims of each site after the sample dims; ``component`` only in the mixture.
SITE_DIMS: dict[str, tuple[str, ...]] = {
    "b": ("component", "weight"),
    "M": ("component", "weight", "latent"),
    "h": ("demo", "component", "latent"),
    "w": ("demo", "weight"),
    "alpha": ("component",),
    "lam": ("component", "latent"),
    "beta": (),
    "pi": ("component",),
    "z": ("demo",),
    "mu_w": ("weight",),
    "Sigma_w": ("weight", "weight2"),
    "gram_eig": ("component", "latent"),
    "pred_mean": ("phase", "dof"),
    "pred_sd": ("phase", "dof"),
    "t": ("demo", "sample"),
    "y": ("demo", "sample", "dof"),
    "aligned_phase": ("demo", "sample"),
}


def site_dims(name: str, ndim: int) -> tuple[str, ...]:
    """Dims of a site with ``ndim`` non-sample axes (drops ``component`` when absent)."""
    dims = SITE_DIMS.get(name)
    if dims is None:
        return tuple(f"{name}_dim_{i}" for i in range(ndim))
    if len(dims) == ndim:
        return dims
    dims = tuple(d for d in dims if d != "component")
    if len(dims) != ndim:
        raise ValueError(f"site {name!r} has {ndim} axes, expected {SITE_DIMS[name]}")
    return dims


def package_version(name: str) -> str | None:
    """Installed version of a distribution package, or ``None`` when it is not installed."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return None


def package_versions() -> dict[str, str | None]:
    """Versions of lmpromp-ppl and the libraries its results depend on."""
    names = ("lmpromp-ppl", "jax", "jaxlib", "numpyro", "arviz-base", "arviz-stats", "xarray", "numpy")
    return {name: package_version(name) for name in names}


def to_json_value(x):
    """JSON-safe value, recursively: mappings to dicts with string keys, tuples to lists,
    numpy and jax arrays and scalars to Python values, NaN and infinities to ``None``."""
    if isinstance(x, Mapping):
        return {str(k): to_json_value(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_json_value(v) for v in x]
    if hasattr(x, "tolist") and not isinstance(x, (str, bytes)):  # numpy / jax arrays and scalars
        return to_json_value(x.tolist())
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    return x


def kept_draws(draws: dict, max_bytes: float) -> np.ndarray | None:
    """Indices of the draws (per chain) a saved fit keeps, evenly spaced; ``None`` keeps them all.

    The posterior draws ``draws`` (leading dims chain, draw) are kept whole
    while they take at most ``max_bytes``; beyond that as many draws as fit,
    but at least :data:`MIN_SAVED_DRAWS`.
    """
    if not draws:
        return None
    n = np.shape(next(iter(draws.values())))[1]
    per_draw = sum(np.asarray(v).nbytes for v in draws.values()) / n
    if per_draw * n <= max_bytes:
        return None
    keep = min(n, max(MIN_SAVED_DRAWS, int(max_bytes // per_draw)))
    return np.unique(np.linspace(0, n - 1, keep).round().astype(int))


class SavedLinearResponse(NamedTuple):
    """What a saved ``cavi_lr`` fit holds: the joint-family CAVI state and the linear-response Gaussian."""

    state: object
    lr: object


def _state_dataset(state) -> xr.Dataset:
    """The CAVI state as a Dataset (one variable per array; nested covariances as ``w_cov__<field>``)."""
    data_vars, attrs = {}, {"state_type": type(state).__name__}
    for name, value in state._asdict().items():
        if value is None:
            continue
        if hasattr(value, "_asdict"):
            attrs[f"{name}_type"] = type(value).__name__
            items = [(f"{name}__{sub}", v) for sub, v in value._asdict().items()]
        else:
            items = [(name, value)]
        for var, v in items:
            arr = np.asarray(v)
            data_vars[var] = (tuple(f"{var}_dim_{i}" for i in range(arr.ndim)), arr)
    return xr.Dataset(data_vars, attrs=attrs)


def _state_from_dataset(ds: xr.Dataset):
    """Rebuild the CAVI state written by :func:`_state_dataset`.

    Files written before the engine had one state (``state_type`` ``MixtureState``, or a
    single-type ``CaviState`` without the component axis) are read into the current
    :class:`~lmpromp_ppl.inference.cavi.CaviState`.
    """
    import jax.numpy as jnp

    from lmpromp_ppl.inference import cavi

    if ds.attrs["state_type"] not in ("CaviState", "MixtureState"):  # (LinearResponse is read by load)
        raise LmprompError(f"unknown CAVI state type {ds.attrs['state_type']!r} in the saved fit")
    covs = {"FullCovariance": cavi.FullCovariance, "EigenCovariance": cavi.EigenCovariance}
    fields = {}
    for name in cavi.CaviState._fields:
        if f"{name}_type" in ds.attrs:
            cov_type = covs[ds.attrs[f"{name}_type"]]
            fields[name] = cov_type(**{sub: jnp.asarray(ds[f"{name}__{sub}"].values) for sub in cov_type._fields})
        elif name in ds.data_vars:
            fields[name] = jnp.asarray(ds[name].values)
        else:
            fields[name] = None
    if fields["active"] is None:  # a single-type state saved without the component axis
        return cavi.lift_single_type(fields)
    return cavi.CaviState(**fields)


def _encoding(tree: xr.DataTree) -> dict:
    """zlib compression (with byte shuffling) of every non-scalar array; values are stored unchanged."""
    encoding = {}
    for node in tree.subtree:
        enc = {
            name: {"zlib": True, "complevel": COMPRESSION_LEVEL, "shuffle": True}
            for name, var in node.to_dataset(inherit=False).variables.items()
            if var.ndim > 0 and var.dtype.kind in "biuf"
        }
        if enc:
            encoding[node.path] = enc
    return encoding


def _dataset(values: dict, sample_dims: tuple[str, ...]) -> xr.Dataset:
    data_vars = {}
    for name, value in values.items():
        arr = np.asarray(value)
        dims = sample_dims + site_dims(name, arr.ndim - len(sample_dims))
        data_vars[name] = (dims, arr)
    return xr.Dataset(data_vars)


@dataclass
class FitResult:
    """What an engine produced on one model and dataset.

    ``draws`` maps site names to arrays with leading (chain, draw) dims; VI
    engines instead give a ``sampler(key, num_draws) -> dict`` of draws from q
    (leading draw axis) and ``draws`` is filled on demand; CAVI also gives
    ``log_density(draws) -> (n,)``, log q at such draws (for PSIS k-hat).
    """

    model: str
    engine: str
    hyper: Hyperparameters
    num_basis: int
    num_dofs: int
    scaling: Scaling
    dataset: str = ""
    dof_names: tuple[str, ...] = ()
    width: float = DEFAULT_WIDTH
    draws: dict | None = None
    sampler: Callable | None = None
    log_density: Callable | None = None
    point: dict = field(default_factory=dict)
    sample_stats: dict = field(default_factory=dict)
    optimization: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)
    state: object = None
    observed: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)
    seed: int | None = None

    # ---------------------------------------------------------------- draws
    def posterior_draws(self, num_draws: int = 1000, key=None) -> dict:
        """Draws with (chain, draw) leading dims; VI results sample q once and cache."""
        if self.draws is not None:
            return self.draws
        if self.sampler is None:
            raise LmprompError("this result holds neither draws nor a sampler")
        from lmpromp_ppl._keys import DRAWS, seed_key

        key = seed_key(self.seed, DRAWS) if key is None else key
        raw = self.sampler(key, num_draws)
        self.draws = {k: np.asarray(v)[None] for k, v in raw.items()}
        return self.draws

    def _draws_to_keep(self, num_draws: int, key, max_draw_bytes: float | None) -> tuple[dict, np.ndarray | None]:
        """The draws a DataTree holds and the kept indices (:func:`kept_draws`).

        A VI result whose ``num_draws`` draws would exceed ``max_draw_bytes`` draws
        only as many as are kept (independent draws from q, so drawing fewer equals
        thinning) and caches those, as :meth:`posterior_draws` does: a thousand draws
        of ``w`` for a thousand demonstrations of 420 weights would take 3.4 GB.
        """
        if self.draws is None and self.sampler is not None and max_draw_bytes is not None:
            import jax

            from lmpromp_ppl._keys import DRAWS, seed_key

            key = seed_key(self.seed, DRAWS) if key is None else key
            shapes = jax.eval_shape(lambda k: self.sampler(k, 1), key)
            per_draw = sum(math.prod(v.shape) * np.dtype(v.dtype).itemsize for v in shapes.values())
            if per_draw * num_draws > max_draw_bytes:
                count = min(num_draws, max(MIN_SAVED_DRAWS, int(max_draw_bytes // per_draw)))
                self.draws = {k: np.asarray(v)[None] for k, v in self.sampler(key, count).items()}
                return self.draws, None
        draws = self.posterior_draws(num_draws, key)
        return draws, None if max_draw_bytes is None else kept_draws(draws, max_draw_bytes)

    @property
    def elbo(self) -> float | None:
        return self.summary.get("elbo")

    def training_phases(self) -> list[np.ndarray]:
        """Each training demonstration's phases: ``observed_data.aligned_phase`` when the fit
        aligned them, else its time mapped linearly to [0, 1] (padding dropped)."""
        return list(self.training_demonstrations().phases())

    def training_demonstrations(self) -> Demonstrations:
        """The demonstrations the fit saw, from ``observed_data`` (padding dropped; aligned phases kept as ``warp``)."""
        if not self.observed or "t" not in self.observed:
            raise LmprompError("this result holds no observed data")
        t = np.asarray(self.observed["t"], dtype=float)
        y = np.asarray(self.observed["y"], dtype=float)
        valid = [np.isfinite(row) for row in t]
        aligned = self.observed.get("aligned_phase")
        return Demonstrations(
            times=tuple(t[i, v] for i, v in enumerate(valid)),
            positions=tuple(y[i, v] for i, v in enumerate(valid)),
            dof_names=tuple(self.dof_names),
            name=self.dataset,
            warp=None if aligned is None else tuple(np.asarray(aligned, dtype=float)[i, v] for i, v in enumerate(valid)),
        )

    def posterior_predictive(self, key=None, num_draws: int | None = None, draws: dict | None = None) -> np.ndarray:
        r"""Replicated demonstrations ``(chain, draw, demo, sample, dof)`` in data units.

        For each posterior draw of ``w``: :math:`y_i = \Psi_i w_i + \epsilon`,
        :math:`\epsilon \sim N(0, \beta^{-1} I)` (standardised units, then
        mapped back), at the observed times; NaN where ``observed_data`` is padded.
        ``draws`` replaces :meth:`posterior_draws` (e.g. the thinned draws a saved fit keeps).
        """
        import jax

        from lmpromp_ppl._keys import POSTERIOR_PREDICTIVE, seed_key
        from lmpromp_ppl.basis import design_matrix

        if not self.observed:
            raise LmprompError("this result holds no observed data to replicate")
        draws = self.posterior_draws() if draws is None else draws
        w = np.asarray(draws["w"])  # (chain, draw, L, d)
        if num_draws is not None:
            w = w[:, :num_draws]
        beta = np.asarray(draws["beta"])[:, : w.shape[1], None, None] if "beta" in draws else self.hyper.beta
        t, y = np.asarray(self.observed["t"]), np.asarray(self.observed["y"])
        key = seed_key(self.seed, POSTERIOR_PREDICTIVE) if key is None else key
        noise = np.asarray(jax.random.normal(key, w.shape[:2] + y.shape))
        out = np.full(w.shape[:2] + y.shape, np.nan)
        for i, phase in enumerate(self.training_phases()):
            valid = np.isfinite(t[i])
            psi = np.asarray(design_matrix(phase, self.num_dofs, self.num_basis, self.width))
            mean = np.einsum("sd,cnd->cns", psi, w[:, :, i]).reshape(w.shape[:2] + (valid.sum(), self.num_dofs))
            rep = mean + noise[:, :, i, valid] / np.sqrt(beta)  # beta: scalar or (chain, draw, 1, 1)
            out[:, :, i, valid] = self.scaling.invert(rep)
        return out

    def to_datatree(
        self, num_draws: int = 1000, key=None, *, posterior_predictive: bool = False,
        max_draw_bytes: float | None = None,
    ) -> xr.DataTree:
        """The result in the common DataTree layout (module docstring).

        ``max_draw_bytes`` thins the draw-indexed groups evenly along ``draw``
        (:func:`kept_draws`); ``None`` keeps every draw.
        """
        import jax

        from lmpromp_ppl._keys import POSTERIOR_PREDICTIVE

        draws, keep = self._draws_to_keep(num_draws, key, max_draw_bytes)
        sample_stats = self.sample_stats
        if keep is not None:
            draws = {k: np.asarray(v)[:, keep] for k, v in draws.items()}
            sample_stats = {k: np.asarray(v)[:, keep] for k, v in sample_stats.items()}
        draw_coord = {"draw": np.arange(np.shape(next(iter(draws.values())))[1]) if keep is None else keep}
        groups = {"posterior": _dataset(draws, ("chain", "draw")).assign_coords(draw_coord)}
        derived = derived_quantities(
            self.model,
            draws,
            num_dofs=self.num_dofs,
            num_basis=self.num_basis,
            gamma=self.hyper.gamma,
            scaling=self.scaling,
            width=self.width,
        )
        phase = derived.pop("phase")
        ds = _dataset(derived, ("chain", "draw"))
        groups["derived"] = ds.assign_coords(phase=phase, dof=list(self.dof_names or range(self.num_dofs)), **draw_coord)
        if sample_stats:
            groups["sample_stats"] = _dataset(sample_stats, ("chain", "draw")).assign_coords(draw_coord)
        if self.optimization:
            groups["optimization"] = xr.Dataset(
                {k: (("iteration",), np.asarray(v, dtype=float)) for k, v in self.optimization.items()}
            )
        if self.point:
            groups["point_estimate"] = _dataset(self.point, ())
        if self.observed:
            groups["observed_data"] = _dataset(self.observed, ())
        if posterior_predictive:
            # not the key of the draws: the noise must be independent of them
            noise_key = None if key is None else jax.random.fold_in(key, POSTERIOR_PREDICTIVE)
            groups["posterior_predictive"] = _dataset(
                {"y": self.posterior_predictive(noise_key, draws=draws)}, ("chain", "draw")
            ).assign_coords(draw_coord)
        if self.engine == "cavi" and self.state is not None and hasattr(self.state, "_asdict"):
            groups["variational"] = _state_dataset(self.state)
        if self.engine == "cavi_lr" and self.state is not None and hasattr(self.state, "lr"):
            groups["variational"] = _state_dataset(self.state.state)
            groups["linear_response"] = _state_dataset(self.state.lr)
        tree = xr.DataTree.from_dict(groups)
        tree.attrs.update(self._attrs())
        return tree

    def _attrs(self) -> dict:
        return {
            "lmpromp_format_version": FORMAT_VERSION,
            "model": self.model,
            "engine": self.engine,
            "dataset": self.dataset,
            "hyperparameters": json.dumps(self.hyper.to_dict()),
            "scaling": json.dumps(self.scaling.to_dict()),
            "num_basis": self.num_basis,
            "num_dofs": self.num_dofs,
            "width": self.width,
            "dof_names": json.dumps(list(self.dof_names)),
            "engine_options": json.dumps(to_json_value(self.options)),
            "seed": -1 if self.seed is None else int(self.seed),
            "seconds": json.dumps(to_json_value(self.summary.get("seconds"))),
            "compile_seconds": json.dumps(to_json_value(self.summary.get("compile_seconds"))),
            "package_versions": json.dumps(package_versions()),
        }

    def summary_dict(self) -> dict:
        """The ``summary.json`` content (docs/cli.md)."""
        out = {
            "format_version": FORMAT_VERSION,
            "model": self.model,
            "engine": self.engine,
            "dataset": self.dataset,
            "hyperparameters": self.hyper.to_dict(),
            "num_basis": self.num_basis,
            "scaling": self.scaling.to_dict(),
            "elbo": None,
            "elbo_trace": [],
            "iterations": None,
            "converged": None,
            "seconds": None,
            "compile_seconds": None,
            "active_latent_dims": None,
            "warnings": [],
        }
        out.update(self.summary)
        return to_json_value(out)

    def save(
        self, out_dir: str | Path, *, force: bool = False, num_draws: int = 1000, key=None,
        max_draw_bytes: float = MAX_DRAW_BYTES,
    ) -> Path:
        """Write ``posterior.nc`` and ``summary.json`` into ``out_dir``.

        Arrays are stored in float64 with zlib compression; draws are thinned
        to about ``max_draw_bytes`` (module docstring).  VI engines draw
        ``num_draws`` from q with ``key`` first.
        """
        out_dir = Path(out_dir)
        targets = [out_dir / "posterior.nc", out_dir / "summary.json"]
        existing = [str(t) for t in targets if t.exists()]
        if existing and not force:
            raise LmprompError(f"refusing to overwrite {', '.join(existing)}; pass force=True (--force)")
        out_dir.mkdir(parents=True, exist_ok=True)
        tree = self.to_datatree(num_draws, key, max_draw_bytes=max_draw_bytes)
        tmp = out_dir / "posterior.nc.tmp"
        tree.to_netcdf(tmp, engine="h5netcdf", encoding=_encoding(tree))
        tmp.replace(targets[0])
        targets[1].write_text(json.dumps(self.summary_dict(), indent=2) + "\n")
        return out_dir


def load(path: str | Path) -> FitResult:
    """Load a fit written by :meth:`FitResult.save` (or ``lmpromp fit --out``)."""
    path = Path(path)
    nc, js = path / "posterior.nc", path / "summary.json"
    for f in (nc, js):
        if not f.is_file():
            raise LmprompError(f"{path} is not a saved fit: {f.name} is missing")
    try:
        summary = json.loads(js.read_text())
        tree = xr.open_datatree(nc, engine="h5netcdf").load()
    except (OSError, ValueError) as exc:
        raise LmprompError(f"cannot read the fit in {path}: {exc}") from None
    version = summary.get("format_version")
    if version != FORMAT_VERSION or tree.attrs.get("lmpromp_format_version") != FORMAT_VERSION:
        raise LmprompError(f"{path} has format version {version}; this lmpromp-ppl reads {FORMAT_VERSION}")
    attrs = tree.attrs

    def group(name):
        if name not in tree.children:
            return {}
        return {k: np.asarray(v.values) for k, v in tree[name].to_dataset().data_vars.items()}

    result = FitResult(
        model=attrs["model"],
        engine=attrs["engine"],
        hyper=Hyperparameters.from_dict(json.loads(attrs["hyperparameters"])),
        num_basis=int(attrs["num_basis"]),
        num_dofs=int(attrs["num_dofs"]),
        scaling=Scaling.from_dict(json.loads(attrs["scaling"])),
        dataset=attrs.get("dataset", ""),
        dof_names=tuple(json.loads(attrs["dof_names"])),
        width=float(attrs["width"]),
        draws=group("posterior"),
        point=group("point_estimate"),
        sample_stats=group("sample_stats"),
        optimization=group("optimization"),
        observed=group("observed_data"),
        options=json.loads(attrs.get("engine_options", "{}")),
        seed=None if int(attrs.get("seed", -1)) < 0 else int(attrs["seed"]),
        summary={k: v for k, v in summary.items() if k not in ("format_version",)},
    )
    if "variational" in tree.children:
        from lmpromp_ppl.inference import cavi

        state = _state_from_dataset(tree["variational"].to_dataset())
        result.state = state
        result.sampler = lambda k, n: cavi.sample_q(k, state, n)
        result.log_density = lambda draws: cavi.log_q(state, draws)
    if "linear_response" in tree.children:  # cavi_lr: new draws from the linear-response Gaussian
        from lmpromp_ppl.inference import cavi
        from lmpromp_ppl.inference.cavi.linear_response import log_q_lr

        ds = tree["linear_response"].to_dataset()
        lr = cavi.LinearResponse(**{name: np.asarray(ds[name].values) for name in cavi.LinearResponse._fields})
        result.state = SavedLinearResponse(state, lr)
        sweeps = int((summary.get("linear_response") or {}).get("refresh_sweeps", 0))
        result.sampler = _lr_sampler(result, lr, state, sweeps)
        result.log_density = lambda draws: log_q_lr(lr, state, draws)
    return result


def _lr_sampler(result: FitResult, lr, state, sweeps: int):
    """New draws of a loaded ``cavi_lr`` fit: the linear-response Gaussian, then ``sweeps`` exact-conditional
    sweeps on the training data rebuilt from ``observed_data`` (:mod:`lmpromp_ppl.inference.refresh`), as
    the fitted engine drew them (without its importance resampling)."""
    from lmpromp_ppl.inference import cavi
    from lmpromp_ppl.inference.refresh import refresh

    inputs = []  # the training data's model inputs, built on the first refreshed draw and kept

    def sample(key, num_draws):
        import jax

        key, key_refresh = jax.random.split(key)
        draws = cavi.sample_lr(key, lr, state, num_draws, bool(state.beta_learned))
        if not sweeps:
            return draws
        if not inputs:
            from lmpromp_ppl.data.prepared import prepare_dataset

            inputs.append(prepare_dataset(result.training_demonstrations(), result.num_basis, width=result.width,
                                          scaling=result.scaling).model_data)
        return refresh(key_refresh, draws, inputs[0], result.hyper, sweeps)

    return sample
