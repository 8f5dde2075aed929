"""The result of a calibration: posterior samples, summary table with units, MAP, evidence.

Model comparison (with vs without an effect) uses two numbers computed at the MAP
``x*`` (unconstrained ``u*``, Hessian ``H`` of the negative log posterior in ``u``):

* ``bic = k ln n - 2 ln L(x*)`` (Schwarz 1978), ``k`` parameters, ``n`` rows (sum of
  weights); lower is better;
* ``log_evidence_laplace = ln p(u*, D) + (k / 2) ln 2 pi - (1 / 2) ln det H`` (Laplace's
  approximation of ``ln p(D)``, Kass & Raftery 1995); higher is better; the evidence is
  invariant to the reparameterisation, so the unconstrained ``u`` is the right place.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from mfdesign.models.hierarchical import LATENT, membrane_block

__all__ = [
    "Posterior",
    "arviz_diagnostics",
    "convergence_rows",
    "convergence_rule",
    "load_inference_data",
    "save_inference_data",
]

NETCDF_NAME = "posterior.nc"


MIN_TAU_RATIO = 50.0
# Independence proposals fitted to the posterior are accepted most of the time (that is
# their point); a random-walk-like chain below 0.2 or a frozen one at 1 is what this flags.
ACCEPTANCE_RANGE = (0.2, 0.9)


def convergence_rule() -> str:
    """The one convergence rule, in words: every report (``posterior.json`` ``convergence.rule``,
    the demo's page, docs/calibration.md) states this sentence and no other threshold.

    Why R-hat and ESS are not part of it: the walkers of an ensemble sampler are not
    independent chains (each move uses the others), so R-hat across walkers checks mixing
    but does not prove convergence; emcee's integrated autocorrelation time is the criterion
    of its authors (Foreman-Mackey et al. 2013, and emcee's "autocorrelation analysis" guide)."""
    lo, hi = ACCEPTANCE_RANGE
    return (
        f"A chain has converged when, after its adaptation steps, it is at least {MIN_TAU_RATIO:g} times its "
        f"longest integrated autocorrelation time tau long (emcee), its mean acceptance lies in {lo:g}-{hi:g}, "
        "and no draw presses on the edge of the force model's lattice. R-hat and bulk / tail ESS (ArviZ, "
        "computed on the draws posterior.nc holds) are reported beside it as checks of mixing, not as part "
        "of the rule: emcee's walkers are not independent chains."
    )


def _nc_name(var: str) -> str:
    """The ``posterior.nc`` variable of a per-membrane block (one value per ``membrane``):
    ``thickness``, or ``membrane.<effect.param>`` for a per-membrane effect parameter (its
    population centre keeps the parameter's own name)."""
    return "thickness" if var + "[" == LATENT else f"membrane.{var}"


@dataclasses.dataclass(frozen=True)
class Posterior:
    """Posterior of a :class:`~mfdesign.models.hierarchical.HierarchicalModel`.

    ``names``/``units`` of the parameters; ``samples`` [S, dim] physical values after
    burn-in and thinning; ``log_prob`` [S]; ``x_map`` [dim] physical MAP; ``log_lik_map``
    (weighted log-likelihood at the MAP); ``n_rows``; ``bic``; ``log_evidence_laplace``;
    ``convergence`` (dict, see :func:`mfdesign.calibration.mcmc.convergence_report`);
    ``design_keys`` (membrane order of the latents); ``effects``;
    ``chain`` [draw, walker, dim] the same samples per walker (physical units, before
    flattening; ``None`` for a posterior saved before it was kept) and ``log_prob_chain``
    [draw, walker]: what :meth:`to_inference_data` turns into ArviZ's ``chain x draw``.
    """

    names: tuple[str, ...]
    units: tuple[str, ...]
    samples: np.ndarray
    log_prob: np.ndarray
    x_map: np.ndarray
    log_lik_map: float
    n_rows: float
    bic: float
    log_evidence_laplace: float
    convergence: dict[str, Any]
    design_keys: tuple[str, ...] = ()
    effects: tuple[str, ...] = ()
    chain: np.ndarray | None = None
    log_prob_chain: np.ndarray | None = None
    # The force model the chain was sampled with (the exact model's lattice grows during
    # calibration); not saved: a reloaded posterior rebuilds its model from the data.
    force_model: Any = dataclasses.field(default=None, compare=False, repr=False)

    @property
    def dim(self) -> int:
        return len(self.names)

    def median(self) -> np.ndarray:
        return np.median(self.samples, axis=0)

    def _blocks(self) -> dict[str, list[int]]:
        """Per-membrane parameters grouped: ``{variable: [column of membrane 0, 1, ...]}``
        (``"thickness"``, and each per-membrane effect parameter ``"effect.param"``)."""
        out: dict[str, list[int]] = {}
        for i, name in enumerate(self.names):
            b = membrane_block(name)
            if b is not None:
                out.setdefault(b[0], []).append(i)
        return out

    def derived(self) -> tuple[list[str], list[str], np.ndarray]:
        """Per-membrane values [S, M] named by design key: the relative thickness
        (``thickness_rel KEY``) where latent, and each per-membrane effect parameter
        (``effect.param KEY``, its own unit)."""
        names: list[str] = []
        units: list[str] = []
        cols: list[int] = []
        for var, idx in self._blocks().items():
            label = "thickness_rel" if var + "[" == LATENT else var
            keys = self.design_keys if len(self.design_keys) == len(idx) else [str(m) for m in range(len(idx))]
            names += [f"{label} {key}" for key in keys]
            units += ["1" if label == "thickness_rel" else self.units[idx[0]]] * len(idx)
            cols += idx
        return names, units, self.samples[:, cols] if cols else np.zeros((len(self.samples), 0))

    def _derived_columns(self) -> list[int]:
        return [i for idx in self._blocks().values() for i in idx]

    def summary(self) -> pd.DataFrame:
        """One row per parameter (and derived per-membrane values): unit, median, 5 / 95 %
        and 2.5 / 97.5 % quantiles, MAP."""
        d_names, d_units, d_samples = self.derived()
        keep = [i for i, n in enumerate(self.names) if membrane_block(n) is None]
        names = [self.names[i] for i in keep] + d_names
        units = [self.units[i] for i in keep] + d_units
        samples = np.concatenate([self.samples[:, keep], d_samples], axis=1)
        x_map = list(self.x_map[keep]) + list(self.x_map[self._derived_columns()])
        q = np.quantile(samples, [0.5, 0.05, 0.95, 0.025, 0.975], axis=0)
        return pd.DataFrame(
            {
                "parameter": names,
                "unit": units,
                "median": q[0],
                "q05": q[1],
                "q95": q[2],
                "q025": q[3],
                "q975": q[4],
                "map": x_map,
            }
        )

    def interval(self, name: str, level: float = 0.95) -> tuple[float, float]:
        """Central ``level`` credible interval of one parameter."""
        if name not in self.names:
            raise KeyError(f"no parameter {name!r}; parameters: {list(self.names)}")
        x = self.samples[:, self.names.index(name)]
        a = (1.0 - level) / 2.0
        lo, hi = np.quantile(x, [a, 1.0 - a])
        return float(lo), float(hi)

    def format_table(self) -> str:
        """The summary as aligned text (for the terminal)."""
        t = self.summary()
        lines = [f"{'parameter':<44} {'unit':>5} {'median':>11} {'5 %':>11} {'95 %':>11} {'MAP':>11}"]
        for r in t.itertuples():
            lines.append(
                f"{r.parameter:<44} {r.unit:>5} {r.median:>11.4g} {r.q05:>11.4g} {r.q95:>11.4g} {r.map:>11.4g}"
            )
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        return {
            "parameters": self.summary().to_dict(orient="records"),
            "names": list(self.names),
            "units": list(self.units),
            "x_map": self.x_map.tolist(),
            "log_lik_map": self.log_lik_map,
            "n_rows": self.n_rows,
            "bic": self.bic,
            "log_evidence_laplace": self.log_evidence_laplace,
            "convergence": self.convergence,
            "design_keys": list(self.design_keys),
            "effects": list(self.effects),
            "n_samples": int(len(self.samples)),
        }

    # -- ArviZ ------------------------------------------------------------------------------
    def chains(self) -> tuple[np.ndarray, np.ndarray]:
        """``(x [chain, draw, dim], log_prob [chain, draw])``: one ArviZ chain per emcee
        walker; a posterior without a stored chain (an old ``posterior.npz``) is one chain."""
        if self.chain is not None:
            return np.swapaxes(self.chain, 0, 1), np.swapaxes(self.log_prob_chain, 0, 1)
        return self.samples[None], self.log_prob[None]

    def tau_step(self) -> int:
        """Every how many stored draws one is about one autocorrelation time apart:
        ``ceil(tau_max / thin)`` (the stored chain is thinned by ``thin`` = tau_min / 2
        steps, :func:`~mfdesign.calibration.mcmc.calibrate`); 1 when the report lacks them."""
        c = self.convergence or {}
        tau, thin = c.get("tau_max"), c.get("thin") or 1
        if not (isinstance(tau, (int, float)) and np.isfinite(tau) and tau > 0):
            return 1
        return max(1, int(np.ceil(float(tau) / float(thin))))

    def file_chains(self) -> tuple[np.ndarray, np.ndarray]:
        """What ``posterior.nc`` holds: :meth:`chains` thinned to one draw per autocorrelation
        time (:meth:`tau_step`), every walker and every kept draw otherwise. Draws closer than
        tau carry little new information and would multiply the pointwise groups' cost (draws
        x rows force evaluations) for nothing."""
        x, lp = self.chains()
        step = self.tau_step() if self.chain is not None else 1
        return x[:, ::step], lp[:, ::step]

    def to_inference_data(
        self, model=None, data=None, *, max_draws: int | None = None, seed: int = 0, max_rows: int | None = 3000
    ):
        """An ``arviz.InferenceData`` in physical units, dims ``chain x draw`` (walkers as chains).

        Groups: ``posterior`` (one variable per parameter, ``thickness`` (the per-membrane latents) as one variable
        over ``membrane``; each with its ``units`` attribute), ``sample_stats`` (``lp``: the
        log posterior). With ``model`` (the :class:`~mfdesign.models.hierarchical.HierarchicalModel`
        that was sampled) and ``data`` (its ``CalibrationData``, or Measurements: then the
        rows are drawn as :meth:`CalibrationData.from_measurements` draws them with
        ``max_rows`` and ``seed``, i.e. the rows the calibration used) also:

        * ``log_likelihood``: ``force_n`` [chain, draw, row], each row's weighted term
          ``w_i log p(F_i | x)`` of the log-likelihood the sampler saw (sums to
          ``model.log_lik``), for ``az.loo`` / ``az.waic``;
        * ``posterior_predictive``: ``force_n`` [chain, draw, row], a replicated force
          [N]: ``model.sample_force`` plus the model's noise (Gaussian or Student-t);
        * ``observed_data``: ``force_n`` [row]; ``constant_data``: ``height_mm``,
          ``pressure_pa``, ``weight``, ``membrane`` (index into ``design_keys``).

        Rows of weight 0 (padding) are left out. Draws: every walker's kept draws, one per
        autocorrelation time (:meth:`file_chains`); ``max_draws`` (default ``None``: all of
        them) thins them further, evenly, so that chains x draws <= ``max_draws`` when a model
        is given (the pointwise groups cost draws x rows force evaluations).
        """
        import arviz as az

        x, lp = self.file_chains()
        n_chain, n_draw = x.shape[:2]
        if model is not None and data is not None and max_draws is not None and n_chain * n_draw > max_draws:
            step = int(np.ceil(n_chain * n_draw / max_draws))
            x, lp = x[:, ::step], lp[:, ::step]
            n_draw = x.shape[1]
        posterior, dims, units = {}, {}, {}
        blocks = self._blocks()
        for i, name in enumerate(self.names):
            if membrane_block(name) is None:
                posterior[name], units[name] = x[..., i], self.units[i]
        coords: dict[str, Any] = {}
        for var, z in blocks.items():
            key = _nc_name(var)
            posterior[key], units[key] = x[..., z], self.units[z[0]]
            dims[key] = ["membrane"]
            coords["membrane"] = list(self.design_keys) if len(self.design_keys) == len(z) else list(range(len(z)))
        groups: dict[str, Any] = {"posterior": posterior, "sample_stats": {"lp": lp}}
        if model is not None and data is not None:
            groups.update(
                _pointwise_groups(
                    model,
                    data,
                    x.reshape(n_chain * n_draw, -1),
                    (n_chain, n_draw),
                    seed=seed,
                    max_rows=max_rows,
                    design_keys=self.design_keys,
                )
            )
            dims.update(
                {
                    "force_n": ["row"],
                    "height_mm": ["row"],
                    "pressure_pa": ["row"],
                    "weight": ["row"],
                    "membrane_index": ["row"],
                }
            )
        import warnings

        with warnings.catch_warnings():  # "more chains than draws": many walkers, short thinned chains
            warnings.filterwarnings("ignore", message="More chains", category=UserWarning)
            idata = az.from_dict(**groups, coords=coords or None, dims=dims or None)
        for name, unit in units.items():
            idata.posterior[name].attrs["units"] = unit
        for group in ("observed_data", "posterior_predictive"):
            if hasattr(idata, group):
                getattr(idata, group)["force_n"].attrs["units"] = "N"
        idata.posterior.attrs.update(
            {
                "effects": ",".join(self.effects),
                "design_keys": json.dumps(list(self.design_keys)),
                "chains_are": "emcee walkers (not independent chains)",
                "draws_are": f"every {self.tau_step() if self.chain is not None else 1} stored draw(s): "
                "about one autocorrelation time apart",
                "n_samples_in_npz": int(len(self.samples)),
            }
        )
        return idata

    def save(self, path, *, call: str = "", seeds: dict | None = None, inputs: dict | None = None) -> Path:
        """``path.json`` (summary, diagnostics, provenance) and ``path.npz`` (samples), each
        written atomically.

        The JSON's ``"provenance"`` (:func:`mfdesign.provenance.provenance`): the version,
        ``call`` (default: the command line when run as ``mfdesign ...``, else
        ``Posterior.save()``), ``seeds`` (e.g. ``{"seed": 0}``), ``inputs`` (name -> sha256
        of the input files, as the caller knows them) and the machine. :meth:`load` ignores it."""
        from mfdesign import outputs
        from mfdesign.provenance import call_line, provenance

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with outputs.atomic_path(path.with_suffix(".npz")) as tmp:
            extra = {} if self.chain is None else {"chain": self.chain, "log_prob_chain": self.log_prob_chain}
            np.savez(tmp, samples=self.samples, log_prob=self.log_prob, x_map=self.x_map, **extra)
        record = provenance(call or call_line("Posterior.save()"), seeds, inputs)
        outputs.write_json(path.with_suffix(".json"), self.to_json() | {"provenance": record}, default=float)
        return path.with_suffix(".json")

    @classmethod
    def load(cls, path) -> "Posterior":
        """Inverse of :meth:`save`. A missing, corrupt or inconsistent pair of files, or
        non-finite samples or MAP, raise ``InputError`` saying which."""
        from mfdesign.errors import InputError, one_line

        path = Path(path)
        js, npz = path.with_suffix(".json"), path.with_suffix(".npz")
        for f in (js, npz):
            if not f.is_file():
                raise InputError(
                    f"posterior file {f} is missing; allowed: posterior.json + posterior.npz "
                    "as `mfdesign calibrate` writes them"
                )
        try:
            meta = json.loads(js.read_text())
            if not isinstance(meta, dict):
                raise InputError(f"{js}: expected a JSON object, got {type(meta).__name__}")
            arrays = _read_npz_bounded(npz, ("samples", "log_prob", "x_map"), optional=("chain", "log_prob_chain"))
            samples, log_prob, x_map = (
                np.asarray(arrays[k], dtype=np.float64) for k in ("samples", "log_prob", "x_map")
            )
            chain, lp_chain = (
                np.asarray(arrays[k], dtype=np.float64) if k in arrays else None for k in ("chain", "log_prob_chain")
            )
            post = cls(
                tuple(map(str, meta["names"])),
                tuple(map(str, meta["units"])),
                samples,
                log_prob,
                x_map,
                float(meta["log_lik_map"]),
                float(meta["n_rows"]),
                float(meta["bic"]),
                float(meta["log_evidence_laplace"]),
                dict(meta["convergence"]),
                tuple(map(str, meta["design_keys"])),
                tuple(map(str, meta["effects"])),
                chain,
                lp_chain,
            )
        except InputError:
            raise
        except Exception as err:  # noqa: BLE001 -- corrupt JSON / zip / npy fail in many ways
            raise InputError(
                f"{path}.json/.npz: not a readable posterior ({type(err).__name__}: "
                f"{one_line(err, 200)}); allowed: the files `mfdesign calibrate` writes"
            ) from None
        dim = len(post.names)
        if (
            samples.ndim != 2
            or samples.shape[1] != dim
            or len(samples) < 1
            or log_prob.shape != (len(samples),)
            or x_map.shape != (dim,)
            or len(post.units) != dim
        ):
            raise InputError(
                f"{path}: samples {samples.shape}, log_prob {log_prob.shape}, x_map {x_map.shape} and "
                f"{dim} names / {len(post.units)} units do not fit; allowed: samples [S, dim], "
                "log_prob [S], x_map [dim]"
            )
        if chain is not None and (
            chain.ndim != 3
            or chain.shape[2] != dim
            or lp_chain is None
            or lp_chain.shape != chain.shape[:2]
            or not np.isfinite(chain).all()
        ):
            raise InputError(
                f"{npz}: chain {chain.shape} / log_prob_chain "
                f"{None if lp_chain is None else lp_chain.shape} do not fit {dim} parameters; "
                "allowed: finite chain [draw, walker, dim] and log_prob_chain [draw, walker]"
            )
        for name, a in (("samples", samples), ("x_map", x_map)):
            if not np.isfinite(a).all():
                raise InputError(
                    f"{npz}: {int((~np.isfinite(a)).sum())} {name} values are NaN or infinite; "
                    "allowed: finite parameters (rerun the calibration)"
                )
        return post


def _read_npz_bounded(path: Path, names: tuple[str, ...], optional: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Arrays of an ``np.savez`` file, each header checked first: a corrupt header may
    declare a shape of terabytes, which ``np.load`` would allocate before reading."""
    import zipfile

    from mfdesign.errors import InputError

    limit = path.stat().st_size  # np.savez stores uncompressed: no array is larger than the file
    out = {}
    with zipfile.ZipFile(path) as z:
        present = {n[:-4] for n in z.namelist() if n.endswith(".npy")}
        names = tuple(names) + tuple(n for n in optional if n in present)
        for name in names:
            with z.open(f"{name}.npy") as fh:
                version = np.lib.format.read_magic(fh)
                read_header = (
                    np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                )
                shape, _, dtype = read_header(fh)
                if dtype.hasobject or int(np.prod(shape, dtype=object)) * dtype.itemsize > limit:
                    raise InputError(
                        f"{path}: array {name!r} declares shape {shape} {dtype}, more than the "
                        f"file holds ({limit} bytes); allowed: the file as np.savez wrote it"
                    )
        with np.load(path, allow_pickle=False) as z:
            for name in names:
                out[name] = z[name]
    return out


def _pointwise_groups(
    model, data, x_flat: np.ndarray, shape: tuple[int, int], *, seed: int, max_rows: int | None, design_keys
) -> dict[str, dict[str, np.ndarray]]:
    """``log_likelihood``, ``posterior_predictive``, ``observed_data``, ``constant_data``
    (see :meth:`Posterior.to_inference_data`); calls the model's own ``pointwise_log_lik``
    and ``sample_force``."""
    import jax
    import jax.numpy as jnp

    from mfdesign.models.hierarchical import CalibrationData

    if not isinstance(data, CalibrationData):
        data = CalibrationData.from_measurements(
            data, max_rows=max_rows, seed=seed, design_keys=tuple(design_keys) or None
        )
    w = np.asarray(data.weight, float)
    keep = np.flatnonzero(w > 0)
    xs = jnp.asarray(x_flat)
    ll = np.asarray(jax.lax.map(lambda xi: model.pointwise_log_lik(xi, data), xs, batch_size=16))
    mean_force = np.asarray(model.sample_force(xs, data, jax.random.PRNGKey(seed)))
    rng = np.random.default_rng(seed)
    sigma = np.asarray(xs[:, model.names.index("noise_n")])[:, None]
    eps = (
        rng.standard_normal(mean_force.shape)
        if model.likelihood == "gaussian"
        else rng.standard_t(model.nu, mean_force.shape)
    )
    replicated = mean_force + sigma * eps

    def shaped(a):
        return a[:, keep].reshape(*shape, len(keep))

    return {
        "log_likelihood": {"force_n": shaped(w[None, :] * ll)},
        "posterior_predictive": {"force_n": shaped(replicated)},
        "observed_data": {"force_n": np.asarray(data.force_n, float)[keep]},
        "constant_data": {
            "height_mm": np.asarray(data.rows.h_mm, float)[keep],
            "pressure_pa": np.asarray(data.rows.p_pa, float)[keep],
            "weight": w[keep],
            "membrane_index": np.asarray(data.rows.membrane)[keep],
        },
    }


def arviz_diagnostics(chain: np.ndarray, names) -> dict[str, Any]:
    """R-hat and bulk / tail ESS (ArviZ; Vehtari et al. 2021) of a physical chain
    [draw, walker, dim], walkers taken as chains. The walkers of an ensemble sampler are
    not independent chains, so R-hat is a check of mixing across walkers, not a proof of
    convergence; the autocorrelation time stays the primary criterion."""
    import arviz as az

    chain = np.asarray(chain, float)
    out: dict[str, Any] = {"rhat": {}, "ess_bulk": {}, "ess_tail": {}}
    if chain.ndim != 3 or chain.shape[0] < 4:  # ArviZ needs a few draws per chain
        return out | {"rhat_max": float("nan"), "ess_bulk_min": float("nan"), "ess_tail_min": float("nan")}
    per_chain = np.swapaxes(chain, 0, 1)  # [chain, draw, dim]
    for i, name in enumerate(names):
        a = per_chain[..., i]
        out["rhat"][name] = float(az.rhat(a))
        out["ess_bulk"][name] = float(az.ess(a, method="bulk"))
        out["ess_tail"][name] = float(az.ess(a, method="tail"))

    def _agg(values, fn):
        v = np.asarray(list(values), float)
        v = v[np.isfinite(v)]
        return float(fn(v)) if len(v) else float("nan")

    out["rhat_max"] = _agg(out["rhat"].values(), np.max)
    out["ess_bulk_min"] = _agg(out["ess_bulk"].values(), np.min)
    out["ess_tail_min"] = _agg(out["ess_tail"].values(), np.min)
    return out


def convergence_rows(convergence: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per parameter of a convergence report (``Posterior.convergence``, as
    :func:`~mfdesign.calibration.mcmc.convergence_report` and :func:`arviz_diagnostics` fill
    it): emcee's integrated autocorrelation time ``tau`` [steps] beside ArviZ's R-hat and
    bulk / tail ESS [draws]. Nothing is recomputed (the report shows what the chain's check
    saw); a number the report lacks (an old ``posterior.json``) is None."""
    parts = {k: convergence.get(k) or {} for k in ("tau", "rhat", "ess_bulk", "ess_tail")}
    names = list(dict.fromkeys(name for part in parts.values() for name in part))
    return [
        {
            "parameter": name,
            "tau [steps]": parts["tau"].get(name),
            "R-hat": parts["rhat"].get(name),
            "ESS bulk": parts["ess_bulk"].get(name),
            "ESS tail": parts["ess_tail"].get(name),
        }
        for name in names
    ]


def file_diagnostics(idata, names) -> dict[str, Any]:
    """:func:`arviz_diagnostics` of the ``posterior`` group of ``idata`` (the draws a
    ``posterior.nc`` holds), per parameter of ``names`` (``thickness[i]`` is the variable
    ``thickness`` at membrane ``i``): what ``az.summary`` on the file reports."""
    post = idata.posterior
    cols = []
    for name in names:
        b = membrane_block(name)
        if b is None:
            cols.append(np.asarray(post[name]))
        else:
            cols.append(np.asarray(post[_nc_name(b[0])])[..., b[1]])
    x = np.stack(cols, axis=-1)  # [chain, draw, dim]
    return arviz_diagnostics(np.swapaxes(x, 0, 1), names)


def save_inference_data(post: Posterior, path, model=None, data=None, **kwargs) -> Path:
    """``post.to_inference_data(model, data, **kwargs)`` written atomically as netCDF
    (``posterior.nc``; engine h5netcdf). Reload: :func:`load_inference_data`.

    The R-hat and ESS in ``post.convergence`` are then replaced by those ArviZ computes on
    the draws just written (:func:`file_diagnostics`), with ``draws_in_file`` and the
    :func:`convergence_rule`: a report shows the numbers ``az.summary`` gives on the file,
    not those of other draws. Save ``post`` (:meth:`Posterior.save`) after this."""
    from mfdesign import outputs

    path = Path(path)
    if path.suffix != ".nc":
        path = path / NETCDF_NAME
    path.parent.mkdir(parents=True, exist_ok=True)
    idata = post.to_inference_data(model, data, **kwargs)
    post.convergence.update(file_diagnostics(idata, post.names))
    post.convergence["draws_in_file"] = {
        "file": path.name,
        "chains": int(idata.posterior.sizes["chain"]),
        "draws": int(idata.posterior.sizes["draw"]),
    }
    post.convergence["rule"] = convergence_rule()
    with outputs.atomic_path(path) as tmp:
        try:
            idata.to_netcdf(str(tmp), engine="h5netcdf")
        except ValueError as err:  # older h5netcdf / xarray pairs know no "zlib" filter: store uncompressed
            if "ompression" not in str(err):
                raise
            idata.to_netcdf(str(tmp), engine="h5netcdf", compress=False)
    return path


def load_inference_data(folder):
    """The ``arviz.InferenceData`` a sampling command wrote into ``folder`` (``posterior.nc``)."""
    import arviz as az

    from mfdesign.errors import InputError

    path = Path(folder)
    path = path if path.suffix == ".nc" else path / NETCDF_NAME
    if not path.is_file():
        raise InputError(f"no {path}; allowed: the --out folder of `mfdesign calibrate` / `mfdesign fit-mf`")
    return az.from_netcdf(str(path), engine="h5netcdf")
