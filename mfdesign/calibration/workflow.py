"""The multi-fidelity fit end to end: calibrate theta, fit the discrepancy, build the predictive.

Shared by ``mfdesign calibrate`` / ``mfdesign fit-mf`` and the experiments:

1. :func:`force_model_named`: ``"emulator"`` (the trained emulator of the simulator,
   ``mfdesign.models.emulator.load_default``) or ``"standin"`` (the analytic stand-in);
2. :func:`model_for`: a :class:`HierarchicalModel` whose priors of mu [Pa] and J_m are
   truncated to the emulator's training ranges (outside them it extrapolates);
3. :func:`fit_multi_fidelity`: emcee calibration, then the RPN discrepancy on the
   residuals at the posterior median, then the residual noise and the
   :class:`~mfdesign.models.predictive.MultiFidelity` predictive.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import equinox as eqx

import numpy as np

from mfdesign._x64 import enable_x64
from mfdesign.models.hierarchical import HierarchicalModel
from mfdesign.physics.effects import LogNormal
from mfdesign.materials import ECOFLEX_JM, ECOFLEX_MU_PA

__all__ = [
    "MFFit",
    "authors_sim_params",
    "calibrated_sim_params",
    "for_search",
    "for_table",
    "fit_multi_fidelity",
    "force_model_named",
    "lifted_rows",
    "load_multi_fidelity",
    "material_priors",
    "model_for",
]

# The paper's uniaxial coupon tests (Campbell et al. 2025): the rubber's mu and J_m measured
# apart from any membrane.
COUPON_MU_PA = 31.5e3
MATERIALS = ("free", "coupons", "coupons-jm")


def material_priors(material: str = "free") -> dict:
    """Priors of the rubber for :func:`fit_multi_fidelity` / :func:`model_for` (keyword
    arguments ``mu_prior``, ``jm_prior``).

    - ``"free"``: none given (the defaults: the data calibrate mu [Pa] and J_m).
    - ``"coupons"``: both held at the coupons' values, mu 31.5 kPa and J_m 39.6 (uniform
      priors +-0.2 kPa and +-0.2: held, with room for the sampler to move): the data then
      calibrate the effects and the membranes' latents only (on the real lifts, without
      latents: the best trajectories of a new membrane, docs/real_data_log.md section 7).
    - ``"coupons-jm"``: J_m held, mu calibrated.
    """
    from mfdesign.errors import InputError
    from mfdesign.physics.effects import Uniform

    if material not in MATERIALS:
        raise InputError(f"material {material!r}: allowed {', '.join(MATERIALS)}")
    out = {}
    if material in ("coupons", "coupons-jm"):
        out["jm_prior"] = Uniform(ECOFLEX_JM - 0.2, ECOFLEX_JM + 0.2)
    if material == "coupons":
        out["mu_prior"] = Uniform(COUPON_MU_PA - 200.0, COUPON_MU_PA + 200.0)
    return out


EFFECT_AXES = ("tensor", "tensor-jm", "additive")
# the axes each choice starts with (node 0 only; a calibration grows them where it goes)
_LATTICE_START: dict[str, dict[str, dict[str, tuple[float, float]]]] = {
    "tensor": {},
    "tensor-jm": {"tensor": {"jm": (0.0, 0.0)}, "additive": {"ring": (0.0, 0.0)}},
    "additive": {"tensor": {"jm": (0.0, 0.0), "ring": (0.0, 0.0)}},
}


def force_model_named(
    name: str, table=None, progress: bool = False, effect_axes: str = "tensor", extra_designs: Sequence[str] = ()
):
    """The force model ``name`` (:data:`~mfdesign.models.force.FORCE_MODELS`) for the rows of
    ``table`` (Measurements; the exact model needs its designs, heights and pressures) and,
    for the exact model, the planes of ``extra_designs`` too (design keys not measured yet,
    e.g. membranes a lab could make: predicted on the simulator itself).

    ``effect_axes`` (exact only): where a calibrated effect's lattice axis goes.

    - ``"tensor"``: crossed with J_m and the ring ratio (exact cross terms; a calibrated
      mechanical effect multiplies the planes by its node count).
    - ``"tensor-jm"``: crossed with J_m, the ring ratio's axis added at the reference (the
      fabric is 30-40 times the rubber, so the ring ratio's cross terms are small; one
      J_m node costs 7x fewer planes of a ringed membrane than ``"tensor"``;
      ``experiments/bench_effect_axes.py`` measures it against the simulator).
    - ``"additive"``: J_m and the ring ratio crossed, each effect's axis added at the
      reference material (first order in the cross terms, fewest planes).
    """
    if effect_axes not in EFFECT_AXES:
        raise ValueError(f"effect_axes must be one of {EFFECT_AXES}, got {effect_axes!r}")
    enable_x64()  # float64 physics: mfdesign._x64
    from mfdesign.models.backends import force_model_for

    if name == "exact":
        if table is None:
            raise ValueError("the exact force model needs the data's designs")
        df = table.df
        return force_model_for(
            "exact",
            tuple(dict.fromkeys([*df["design_key"], *extra_designs])),
            h_max_mm=float(
                max(
                    df["height_mm"].max(),
                    df["height_set_mm"].max(skipna=True) if df["height_set_mm"].notna().any() else 0.0,
                )
            ),
            p_max_pa=float(df["pressure_pa"].max()),
            progress=progress,
            grow="additive" if effect_axes == "additive" else "tensor",
            tensor=_LATTICE_START[effect_axes].get("tensor"),
            additive=_LATTICE_START[effect_axes].get("additive"),
        )
    return force_model_for(name)


def model_for(force_model, design_keys: Sequence[str], effects=(), **kwargs):
    """A hierarchical model with one thickness latent per membrane of ``design_keys``; the priors
    of mu [Pa], J_m and the thickness spread stay inside the force model's support (an
    emulator extrapolates outside its training ranges; the exact model's planes reach a
    stated range of reduced pressure and J_m)."""
    from mfdesign.models.force import ForceModel

    ranges = force_model.support() if isinstance(force_model, ForceModel) else {}
    if ranges:
        mu_lo, mu_hi = ranges.get("mu_pa", (15e3, 50e3))
        jm_lo, jm_hi = ranges.get("jm", (10.0, 100.0))
        tf_lo, tf_hi = ranges.get("thickness_factor", (0.7, 1.3))
        kwargs.setdefault("mu_prior", LogNormal(ECOFLEX_MU_PA, 0.3, float(mu_lo), float(mu_hi)))
        kwargs.setdefault("jm_prior", LogNormal(ECOFLEX_JM, 0.5, float(jm_lo), float(jm_hi)))
        kwargs.setdefault("thickness_sd_prior", LogNormal(0.05, 0.8, 1e-3, float(min(1 - tf_lo, tf_hi - 1) / 3)))
    return HierarchicalModel(force_model=force_model, effects=tuple(effects), n_membranes=len(design_keys), **kwargs)


@dataclasses.dataclass(frozen=True)
class MFFit:
    """A fitted multi-fidelity model: hierarchical ``model``, ``posterior``, discrepancy
    ``delta`` (gated RPN ensemble, :class:`~mfdesign.models.discrepancy.Discrepancy`), residual noise ``noise_n`` [N], predictive ``mf``."""

    model: object
    posterior: object
    delta: object
    noise_n: float
    mf: object
    design_keys: tuple[str, ...]
    # the seed that thinned the posterior into ``mf``: a reloaded fit must thin alike, or
    # its predictions differ from the fit's whenever the posterior holds over 128 draws
    seed: int = 0

    def save(
        self, folder, *, physics: str, material: str = "free", table=None, call: str = "", inputs: dict | None = None
    ) -> dict:
        """Write the fit into ``folder``: ``posterior.json`` + ``posterior.npz``, the
        discrepancy ``delta/`` and ``mf.json`` (what :meth:`load` needs to rebuild the
        model: effects, physics, likelihood, material, latents, the thinning seed; and its
        ``"provenance"``, which :meth:`load` ignores), each file atomically
        (:mod:`mfdesign.outputs`).

        **Arguments:**

        - `folder`: the folder (created).
        - `physics`: the force model's name where the model met the data (`"exact"`,
          `"emulator"`, `"standin"`); a reloaded fit runs on the search physics
          (`"emulator"` for `"exact"`: the exact model holds planes of the calibrated
          membranes only).
        - `material`: the name of the rubber priors used (:func:`material_priors`).
        - `table`: the calibrated measurements; given, ``mf.json`` records the training
          RMSE [N] and 90 % coverage on them.
        - `call`: the command line or Python call, for the provenance of ``mf.json`` and
          ``posterior.json`` (default: the command line when run as ``mfdesign ...``, else
          ``MFFit.save()``); their seed is the fit's.
        - `inputs`: name -> sha256 of the input files, when the caller knows them
          (:func:`mfdesign.provenance.input_hashes`).

        **Returns:**

        The dict written as ``mf.json``.
        """
        from pathlib import Path

        from mfdesign import outputs
        from mfdesign.provenance import call_line, provenance

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        call = call or call_line("MFFit.save()")
        seeds = {"seed": int(self.seed)}
        self.posterior.save(folder / "posterior", call=call, seeds=seeds, inputs=inputs)  # type: ignore[attr-defined]
        self.delta.save(folder / "delta")  # type: ignore[attr-defined]
        meta = {
            "noise_n": self.noise_n,
            "effects": list(self.model.effects),  # type: ignore[attr-defined]
            "physics": physics,
            "search_physics": "emulator" if physics == "exact" else physics,
            "likelihood": self.model.likelihood,  # type: ignore[attr-defined]
            # the model's layout and priors, for load_multi_fidelity to rebuild it
            "material": material,
            "membrane_latents": bool(self.model.membrane_latents),  # type: ignore[attr-defined]
            "membrane_effects": list(self.model.membrane_effects),  # type: ignore[attr-defined]
            "thin_seed": int(self.seed),
            # how far the discrepancy reaches beyond its membranes (leave-one-membrane-out)
            "discrepancy_gate": {
                "length": self.delta.length if np.isfinite(self.delta.length) else None,  # type: ignore[attr-defined]
                "sigma_n": self.delta.sigma_n,  # type: ignore[attr-defined]
            },
        }
        if table is not None:
            from mfdesign.models.predictive import coverage

            cov = coverage(self.mf, table.subset(list(self.design_keys)), level=0.9, key=self.seed)  # type: ignore[arg-type]
            meta.update(train_rmse_n=cov["rmse_n"], train_coverage90=cov["coverage"])
        meta["provenance"] = provenance(call, seeds, inputs)
        outputs.write_json(folder / "mf.json", meta)
        return meta

    @classmethod
    def load(cls, folder) -> "MFFit":
        """The fit :meth:`save` wrote (:func:`load_multi_fidelity`)."""
        return load_multi_fidelity(folder)


def fit_multi_fidelity(
    table,
    force_model,
    effects=(),
    *,
    n_steps: int = 2000,
    n_walkers: int | None = None,
    max_rows: int = 1500,
    chain_path=None,
    ensemble_config=None,
    seed: int = 0,
    progress: bool = True,
    likelihood: str = "student_t",
    pool=None,
    stop_when_converged: bool = True,
    jm_prior=None,
    mu_prior=None,
    membrane_latents: bool = True,
    membrane_effects: Sequence[str] = (),
    release_memory: bool = False,
    grow_walkers: bool = False,
) -> MFFit:
    """The multi-fidelity model: calibrate the physics, then fit the sim-to-real discrepancy.

    emcee samples mu [Pa], J_m, the membranes' thickness latents and the parameters of
    ``effects`` (:func:`~mfdesign.calibration.mcmc.calibrate`); an ensemble of randomised
    prior networks (delta) is trained on the residuals at the posterior median, gated by
    the distance to the training membranes with a length scale and a prior spread chosen
    by leave-one-membrane-out (:mod:`mfdesign.models.discrepancy`); the predictive
    combines posterior draws with the discrepancy's draws.

    **Arguments:**

    - `table`: the measurements (:class:`~mfdesign.data.measurements.Measurements`).
    - `force_model`: the physics, a name of :data:`~mfdesign.models.force.FORCE_MODELS`
      (`"exact"`: simulator planes of the measured membranes, solved once and cached;
      `"emulator"`: the bundled neural emulator, fast, about 1 N RMS off the simulator;
      `"standin"`: tests) or a built force model.
    - `effects`: names (or instances) of the effects to calibrate with the material, e.g.
      what :func:`~mfdesign.diagnosis.pipeline.diagnose` found (`Diagnosis.found`).
    - `n_steps`: the most emcee steps (fewer when `stop_when_converged`).
    - `n_walkers`: emcee walkers (default `max(32, 2 dim + 2)`).
    - `grow_walkers`: `n_walkers` is a least number: a model with more parameters takes
      `2 dim + 2` (a campaign's model grows a latent per membrane, round after round).
    - `max_rows`: rows the likelihood uses (evenly within trials).
    - `chain_path`: HDF5 file of the chain (a rerun resumes it); `None`: in memory.
    - `ensemble_config`: the discrepancy ensemble's
      :class:`~mfdesign.models.ensemble.EnsembleConfig` (default 8 members, 3000 steps).
    - `seed`: random seed (rows, walkers, ensemble).
    - `progress`: progress bars.
    - `likelihood`: `"student_t"` or `"gaussian"` noise [N].
    - `pool`: anything with `map`, for emcee.
    - `stop_when_converged`: stop once the chain is 50 autocorrelation times long
      (:func:`~mfdesign.calibration.mcmc.calibrate`).
    - `jm_prior`: the prior of J_m (a :class:`~mfdesign.physics.effects.Prior`; default:
      log-normal around the coupons' 39.6, sd 0.5, inside the force model's support); a
      narrow one holds the locking at a measured value.
    - `mu_prior`: the prior of mu [Pa] (default: log-normal around the paper's 31.7 kPa, sd
      0.3, inside the force model's support); a narrow one holds the rubber's modulus at a
      measured value (the coupons'), so that the lifts calibrate the effects and the
      membranes' latents only.
    - `membrane_latents`: one thickness latent per membrane, drawn from a population
      (the hierarchy); `False`: none, every membrane at its nominal thickness (what the
      membranes share, e.g. an effect's geometry, is then not traded against each
      membrane's own scale; their differences go to the discrepancy and the noise).
    - `membrane_effects`: parameters of `effects` (`"effect.param"`, or an effect's name)
      that vary from membrane to membrane: a hierarchical random effect around the
      population centre, whose spread is calibrated; a new membrane's prediction draws its
      value from that population (:class:`~mfdesign.models.hierarchical.HierarchicalModel`).
    - `release_memory`: between the chain and the discrepancy, drop JAX's compiled programs
      and return the free heap (:func:`mfdesign._memory.release_memory`); for a process
      that owns JAX (the demo, a CLI command): it clears JAX's caches for everyone.

    **Returns:**

    An :class:`MFFit`: the hierarchical `model`, the `posterior`
    (:class:`~mfdesign.calibration.posterior.Posterior`: `summary()`, `convergence`), the
    discrepancy ensemble `delta`, the residual noise `noise_n` [N] and the predictive `mf`
    (:class:`~mfdesign.models.predictive.MultiFidelity`; `mf.predictor(n_draws)` is what
    :func:`~mfdesign.acquire.propose` and :func:`~mfdesign.optimization.optimize` take).
    """
    enable_x64()  # float64 physics: mfdesign._x64
    from mfdesign.calibration.mcmc import calibrate
    from mfdesign.models.ensemble import EnsembleConfig
    from mfdesign.models.hierarchical import DISCREPANCY_ROWS, CalibrationData, fit_discrepancy
    from mfdesign.models.predictive import MultiFidelity

    if isinstance(force_model, str):
        force_model = force_model_named(force_model, table, progress=progress)
    data = CalibrationData.from_measurements(table, max_rows=max_rows, seed=seed)
    n_trials = table.df.groupby(["design_key", "trial"]).ngroups
    data = data.padded(max(len(data), max_rows + n_trials))  # equal shapes across folds: one compile
    priors = {k: v for k, v in (("jm_prior", jm_prior), ("mu_prior", mu_prior)) if v is not None}
    model = model_for(
        force_model,
        data.design_keys,
        effects,
        likelihood=likelihood,
        membrane_latents=membrane_latents,
        membrane_effects=tuple(membrane_effects),
        **priors,
    )
    if grow_walkers and n_walkers is not None:
        n_walkers = max(int(n_walkers), 2 * model.dim + 2)
    post = calibrate(
        data,
        model,
        n_steps=n_steps,
        n_walkers=n_walkers,
        chain_path=chain_path,
        seed=seed,
        progress=progress,
        pool=pool,
        stop_when_converged=stop_when_converged,
    )
    if post.force_model is not None:  # the exact model's lattice grew to hold the posterior
        model = eqx.tree_at(lambda m: m.force_model, model, post.force_model)
    if release_memory:  # the chain's programs are done with (the demo's peak sat here, issue 40)
        from mfdesign._memory import release_memory as release

        release()
    cfg = ensemble_config or EnsembleConfig(n_members=8, steps=3000, monotone=False)
    x_ref = post.median()
    used = table.subset(list(data.design_keys))
    # the residual noise on the discrepancy's own rows (evenly along every trial, at most
    # DISCREPANCY_ROWS: the bundled 150k rows cost seconds and a GB for one number)
    full = CalibrationData.from_measurements(used, max_rows=DISCREPANCY_ROWS, design_keys=data.design_keys, seed=seed)
    delta = fit_discrepancy(model, x_ref, used, data.design_keys, cfg, key=seed, progress=progress)
    resid = np.asarray(full.force_n - model.expected_force(x_ref, full))
    d_mean = np.asarray(delta.mean(full.design, full.rows.h_mm, full.rows.p_pa))
    w = np.asarray(full.weight)
    # rows the simulator has no value for (NOT_CONVERGED at the posterior's constants) carry
    # no residual: one NaN row must not make the predictive's noise, hence every interval, NaN
    ok = np.isfinite(resid) & np.isfinite(d_mean)
    if not ok.any():
        raise ValueError("no calibrated row has a finite residual: the force model has no value at the posterior")
    noise = float(np.sqrt(np.average((resid[ok] - d_mean[ok]) ** 2, weights=w[ok])))
    mf = MultiFidelity.from_posterior(model, post, delta, noise_n=noise, seed=seed)
    return MFFit(model, post, delta, noise, mf, tuple(data.design_keys), seed)


def for_search(fit: MFFit, physics: str = "emulator"):
    """The fit's predictive with the force model of design searches (default: the emulator).

    The exact model holds planes of the calibrated membranes only; a search over new
    designs runs the same posterior and discrepancy on the emulator, whose error (about
    1 N RMS against the simulator) adds to the prediction there: say so where it is used
    and check winners with the simulator."""
    from mfdesign.models.backends import force_model_for
    from mfdesign.models.predictive import MultiFidelity

    model = eqx.tree_at(lambda m: m.force_model, fit.model, force_model_for(physics))
    return MultiFidelity.from_posterior(model, fit.posterior, fit.delta, noise_n=fit.noise_n, seed=fit.seed)


def for_table(fit: MFFit, table, physics: str = "exact", progress: bool = False):
    """The fit's predictive where it meets ``table``'s rows (Measurements), on ``physics``.

    For ``"exact"``: the simulator's planes of the calibrated membranes and of ``table``'s
    (cached ones read, new ones solved), the lattice grown to hold every posterior draw's
    constants at those rows; the same posterior and discrepancy. A fit saved for design
    searches (a campaign's round, :func:`for_search`) holds the emulator, whose error
    reaches the prediction of a membrane it never saw: on ``experiments/campaign_rounds.py``'s
    two test membranes 0.45 N RMS against the virtual rig's noise-free truth, where their
    planes give 0.05 N (issue 41). A held-out check is where the model meets data: run it
    here. Other ``physics`` (emulator, standin) hold every design, and a fit on them is
    saved on them: ``fit.mf`` itself.
    """
    from mfdesign.calibration.mcmc import _params_at
    from mfdesign.models.predictive import MultiFidelity

    mf: MultiFidelity = fit.mf  # type: ignore[assignment]
    if physics != "exact":
        return mf
    fm = force_model_named("exact", table, progress=progress, extra_designs=fit.design_keys)
    model = eqx.tree_at(lambda m: m.force_model, fit.model, fm)
    data = mf.data_for(None, None, None, table=table)
    u = np.asarray(model.to_unconstrained(np.asarray(mf.theta)))
    fm = fm.covering(_params_at(model, data, u), progress=progress, margin=1)
    model = eqx.tree_at(lambda m: m.force_model, model, fm)
    return MultiFidelity(model, mf.theta, mf.delta, mf.noise_n, mf.design_keys)


def load_multi_fidelity(folder) -> MFFit:
    """The fit saved by ``mfdesign fit-mf --out FOLDER`` (``mf.json``, ``posterior.*``,
    ``delta/``). Raises ``InputError`` (a ``ValueError``) saying what is missing, corrupt,
    non-finite or inconsistent."""
    enable_x64()  # float64 physics: mfdesign._x64
    import json
    from pathlib import Path

    from mfdesign.calibration.posterior import Posterior
    from mfdesign.errors import InputError, one_line
    from mfdesign.models.discrepancy import Discrepancy
    from mfdesign.models.predictive import MultiFidelity

    folder = Path(folder)
    need = [folder / "mf.json", folder / "posterior.json", folder / "delta" / "ensemble.json"]
    missing = [str(p.relative_to(folder)) for p in need if not p.is_file()]
    if missing:
        raise InputError(f"{folder} is not a multi-fidelity fit (mfdesign fit-mf --out): missing {missing}")
    try:
        meta = json.loads((folder / "mf.json").read_text())
        effects, noise = list(meta["effects"]), float(meta["noise_n"])
        # Searches over new designs run on the emulator: the exact model holds planes of
        # the calibrated membranes only (its error is stated in the commands that search).
        simulator = str(meta.get("search_physics", meta.get("simulator")))
        seed = int(meta.get("thin_seed", 0))  # absent: a fit saved before the seed was kept
    except (ValueError, KeyError, TypeError) as err:
        raise InputError(f"{folder / 'mf.json'} is not a valid fit summary ({err!r}); rerun mfdesign fit-mf") from None
    if not (np.isfinite(noise) and noise > 0):
        raise InputError(f"{folder / 'mf.json'}: noise_n = {noise}; allowed: a positive finite number of newtons")
    post = Posterior.load(folder / "posterior")  # InputError when corrupt or non-finite
    try:
        model = model_for(
            force_model_named(simulator),
            post.design_keys,
            effects,
            likelihood=meta.get("likelihood", "gaussian"),
            membrane_latents=bool(meta.get("membrane_latents", True)),
            membrane_effects=tuple(map(str, meta.get("membrane_effects", ()))),
            **material_priors(str(meta.get("material", "free"))),
        )
    except Exception as err:  # noqa: BLE001 -- unknown simulator / effect / likelihood named in the file
        raise InputError(
            f"{folder / 'mf.json'}: cannot rebuild the model ({type(err).__name__}: "
            f"{one_line(err, 200)}); rerun mfdesign fit-mf"
        ) from None
    if tuple(model.names) != tuple(post.names):
        raise InputError(
            f"{folder}: the posterior's parameters {list(post.names)} do not match the model "
            f"({list(model.names)}) of effects {effects} on {simulator!r}"
        )
    try:
        delta = Discrepancy.load(folder / "delta")
    except FileNotFoundError as err:
        raise InputError(f"{folder}: {err}") from None
    mf = MultiFidelity.from_posterior(model, post, delta, noise_n=noise, seed=seed)
    return MFFit(model, post, delta, noise, mf, tuple(post.design_keys), seed)


def calibrated_sim_params(fit: MFFit) -> tuple:
    """The simulator constants a fit stands for: :class:`~mfdesign.physics.params.SimParams`
    at the posterior median of every parameter (mu [Pa], J_m and each effect's mechanical
    constants), for a NEW membrane (nominal thickness: the population prior of the
    thickness latents is centred at 0), on a plain force row (inflating, plate held);
    effects that act only on the recorded force (``lift_preload``, sensor offsets) leave
    the simulator's constants alone. Returns ``(params, description)``, the description a
    JSON-ready dict (``constants``, ``rule``, the non-default fields)."""
    enable_x64()  # float64 physics: mfdesign._x64
    import jax
    import jax.numpy as jnp

    from mfdesign.physics.params import SimParams

    from mfdesign.calibration.posterior import Posterior
    from mfdesign.models.predictive import MultiFidelity

    post, mf, model = fit.posterior, fit.mf, fit.model
    assert isinstance(post, Posterior) and isinstance(mf, MultiFidelity) and isinstance(model, HierarchicalModel)
    x = np.median(np.asarray(post.samples, dtype=np.float64), axis=0)
    # One force row of a new membrane: any design serves (no effect reads the design).
    row = np.array([[2.0, 30.0, np.nan, np.nan, np.nan, np.nan]])
    data = mf.data_for(row, np.array([10.0]), np.array([4000.0]))
    params = model.sim_params(jnp.asarray(x), data, thickness_rel=jnp.zeros(1))
    params = jax.tree.map(lambda a: float(np.asarray(a).reshape(-1)[0]), params)
    authors = SimParams()
    fields = [f.name for f in dataclasses.fields(SimParams)]
    description = {
        "constants": "calibrated",
        "rule": "posterior median of each parameter; a new membrane at nominal thickness",
        **{k: getattr(params, k) for k in fields if k in ("mu_pa", "jm") or getattr(params, k) != getattr(authors, k)},
    }
    return params, description


def authors_sim_params() -> tuple:
    """The authors' constants (Ecoflex 00-30: mu 31.7 kPa, J_m 39.6) and their description,
    in the form of :func:`calibrated_sim_params`."""
    from mfdesign.physics.params import SimParams

    params = SimParams()
    return params, {"constants": "authors", "mu_pa": float(params.mu_pa), "jm": float(params.jm)}


def lifted_rows(table, min_lift_height_mm: float = 2.0):
    """The rows calibration uses, as Measurements: force rows, and mass-lift rows with the
    plate floating (:func:`~mfdesign.data.lifts.floating_rows`; resting or pinned, a lift
    row records the mass's weight, not the membrane's force F(h, p))."""
    from mfdesign.data.lifts import floating_rows
    from mfdesign.data.measurements import Measurements

    df = table.df
    return Measurements(df[floating_rows(df, resting_mm=min_lift_height_mm)].reset_index(drop=True))
