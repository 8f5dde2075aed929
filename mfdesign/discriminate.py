"""Experiments that tell hypotheses apart: rank rig experiments by how far the hypotheses'
posterior predictives separate, measurement noise included.

Given two or more calibrated hypotheses (each a multi-fidelity model fitted to the same
data with a different effect set, :class:`~mfdesign.models.predictive.MultiFidelity`),
each candidate :class:`Experiment` (a force sweep at fixed plate heights [mm] over
pressures [Pa], or a mass lift with a given load [N]: height reached vs pressure, on an
existing or a new membrane) is scored by Box & Hill's criterion:

    G. E. P. Box and W. J. Hill (1967), "Discrimination among mechanistic models",
    Technometrics 9(1):57-71,

the expected log Bayes factor of the true hypothesis against each rival when the
experiment's result ``y`` is drawn from the true hypothesis's posterior predictive,
``E_{y ~ p_i}[ln p_i(y) - ln p_j(y)]`` (the Kullback-Leibler divergence of the
predictives). Each predictive is the Gaussian mixture of its ``S`` posterior draws
(physics draw + discrepancy member) with the model's noise::

    p_k(y) = (1 / S) sum_s N(y; f_k,s, diag sigma_k^2)

over the experiment's rows jointly (a draw moves every row at once). The expectation is
a Monte-Carlo average over the draws of the true hypothesis plus noise. The hypotheses'
draws share their random numbers (thinning order, new membranes' thickness, discrepancy
members: common random numbers), and the draw index that generated ``y`` is left out of
every mixture (else the estimate is biased towards certainty); equal predictives then
score exactly 0. The score of an experiment is ``sum_i pi_i min_{j != i} E_i[ln BF_ij]``: the
expected log Bayes factor of the true hypothesis against its closest rival, averaged over
which one is true (weights ``pi``: the hypotheses' current probabilities, default equal).
Also reported: the expected posterior probability of the true hypothesis after the
experiment, ``sum_i pi_i E_{y ~ p_i}[P(i | y)]``.

Observables: a force row's recorded force [N] (noise: the model's ``noise_n``); a lift
row's plate height [mm] at a pressure, the first height (quasi-static inflation from
``h = 0``) where the draw's force falls to the load, interpolated on a height grid (noise:
the height sensor's ``height_sd_mm`` and the force noise through the force's slope).

The scoring is one JAX program: the draws of every candidate's rows in one call per
hypothesis, the criterion ``jax.vmap``-ed over candidates (``jax.lax.map`` in batches, to
bound memory). :func:`outside_rig` names the measurements off the rig that decide between
hypotheses the rig cannot tell apart (each effect's ``direct_check``). Units: mm, Pa, N.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping, Sequence

import numpy as np

from mfdesign.errors import InputError

__all__ = [
    "BOX_HILL_1967",
    "Experiment",
    "Hypothesis",
    "Ranking",
    "candidate_experiments",
    "decisive",
    "hypothesis_probabilities",
    "outside_rig",
    "parse_hypotheses",
    "rank_experiments",
]

BOX_HILL_1967 = (
    'G. E. P. Box and W. J. Hill (1967), "Discrimination among mechanistic models", Technometrics 9(1):57-71'
)
G_N_PER_KG = 9.80665
MATERIALS = ("free", "coupons", "coupons-jm")  # mfdesign.calibration.workflow.MATERIALS
NO_EFFECTS = ("none", "plain", "free rubber", "")
PER_MEMBRANE = "[m]"  # an effect written "fabric_inset[m]" varies from membrane to membrane

# Measurements off the rig for hypotheses the rig cannot tell apart (the effects' stories).
# An effect not named here falls back to its own ``direct_check``.
OUTSIDE_RIG: dict[str, str] = {
    "thickness_deviation": "measure each membrane's thickness (micrometer, several radii): a thicker membrane and a stiffer rubber give the same forces on the rig (the energy scales with mu x thickness)",
    "thickness_gradient": "measure each membrane's thickness near the disk and near the clamp",
    "ring_stiffening": "a hoop test of a ring cut from a bonded membrane (its hoop stiffness against the modelled 1 MPa fabric)",
    "ring_softening": "a hoop test of a ring cut from a bonded membrane (a partly delaminated ring is softer than the modelled 1 MPa)",
    "fabric_inset": "section a bonded ring (or the disk) and measure where the fabric starts to carry load; a hoop test of a bonded ring",
    "contact_offset": "photograph the disk's rim under pressure and measure where the membrane leaves the plate",
    "material": "a uniaxial (and equibiaxial) coupon test of the rubber: mu [Pa] and J_m apart from any membrane",
}


# --------------------------------------------------------------------------- hypotheses
@dataclasses.dataclass(frozen=True)
class Hypothesis:
    """A named effect set (registered effect names), the rubber's priors (``material``:
    ``free``, ``coupons``, ``coupons-jm``; :func:`mfdesign.calibration.workflow.material_priors`),
    whether each membrane has a thickness latent (``latents``), and which effects vary from
    membrane to membrane (``per_membrane``: a hierarchical random effect,
    :class:`~mfdesign.models.hierarchical.HierarchicalModel`)."""

    name: str
    effects: tuple[str, ...] = ()
    material: str = "free"
    latents: bool = True
    per_membrane: tuple[str, ...] = ()

    @classmethod
    def parse(cls, text: str) -> "Hypothesis":
        """``"fabric_inset+ring_stiffening"``, ``"none"`` (no effect); an effect written
        ``"fabric_inset[m]"`` varies per membrane; after ``":"`` comma-separated options:
        a material (``coupons``, ``coupons-jm``, ``free``) and ``no-latents``, e.g.
        ``"fabric_inset[m]+ring_stiffening:coupons,no-latents"``. Raises
        :class:`InputError` naming an unknown effect, material or option."""
        from mfdesign.physics import effects as fx

        raw = str(text).strip()
        body, _, opts = raw.partition(":")
        material, latents = "free", True
        for opt in (o.strip() for o in opts.split(",") if o.strip()):
            if opt in MATERIALS:
                material = opt
            elif opt == "no-latents":
                latents = False
            else:
                raise InputError(
                    f"hypothesis {raw!r}: option {opt!r}; allowed after ':' (comma-separated): "
                    f"a material ({', '.join(MATERIALS)}) and no-latents"
                )
        names = [] if body.strip().lower() in NO_EFFECTS else [n.strip() for n in body.split("+")]
        per = tuple(n[: -len(PER_MEMBRANE)] for n in names if n.endswith(PER_MEMBRANE))
        names = [n[: -len(PER_MEMBRANE)] if n.endswith(PER_MEMBRANE) else n for n in names]
        for n in names:
            if n not in fx.EFFECTS:
                raise InputError(
                    f"hypothesis {raw!r}: unknown effect {n!r}; allowed: none, or effects joined by '+' "
                    f"from {', '.join(sorted(fx.EFFECTS))} (one written NAME{PER_MEMBRANE} varies per membrane)"
                )
        if len(set(names)) != len(names):
            raise InputError(f"hypothesis {raw!r} names an effect twice")
        return cls(raw or "none", tuple(names), material, latents, per)

    @property
    def key(self) -> tuple:
        """What makes two hypotheses the same model."""
        return (frozenset(self.effects), self.material, self.latents, frozenset(self.per_membrane))


def parse_hypotheses(texts: Sequence[str]) -> list[Hypothesis]:
    """At least two distinct hypotheses (:meth:`Hypothesis.parse`); :class:`InputError` else."""
    hyps = [Hypothesis.parse(t) for t in texts]
    if len(hyps) < 2:
        raise InputError(f"need at least two hypotheses to tell apart, got {len(hyps)}")
    seen: dict = {}
    for h in hyps:
        if h.key in seen:
            raise InputError(f"hypotheses {seen[h.key]!r} and {h.name!r} are the same model")
        seen[h.key] = h.name
    return hyps


def outside_rig(hypotheses: Sequence[Hypothesis]) -> list[dict]:
    """Per pair of hypotheses, the off-rig measurements that would decide between them:
    the sentence of every effect in one but not the other (and of the rubber when their
    materials differ)."""
    from mfdesign.physics import effects as fx

    out = []
    for a_i, a in enumerate(hypotheses):
        for b in hypotheses[a_i + 1 :]:
            differ = sorted(set(a.effects) ^ set(b.effects))
            checks = {n: OUTSIDE_RIG.get(n) or fx.effect(n).direct_check for n in differ}
            if a.material != b.material:
                checks["material"] = OUTSIDE_RIG["material"]
            if a.latents != b.latents:
                checks["thickness"] = OUTSIDE_RIG["thickness_deviation"]
            for n in sorted(set(a.per_membrane) ^ set(b.per_membrane)):
                checks.setdefault(n, OUTSIDE_RIG.get(n) or fx.effect(n).direct_check)
                checks[n] += " (on several membranes: does it differ from one to the next?)"
            out.append({"pair": [a.name, b.name], "measurements": {k: v for k, v in checks.items() if v}})
    return out


def hypothesis_probabilities(bics: Sequence[float], prior: Sequence[float] | None = None) -> np.ndarray:
    """Posterior probabilities of hypotheses from their BIC (Schwarz 1978: ln p(D | H) ~ -BIC / 2)."""
    b = np.asarray(bics, float)
    if not np.all(np.isfinite(b)):
        raise ValueError(f"non-finite BIC {b.tolist()}")
    lp = -0.5 * b + (np.log(np.asarray(prior, float)) if prior is not None else 0.0)
    lp = lp - lp.max()
    w = np.exp(lp)
    return w / w.sum()


# --------------------------------------------------------------------------- experiments
@dataclasses.dataclass(frozen=True)
class Experiment:
    """One rig experiment: a membrane ``design`` ``[t, c, r1, w1, r2, w2]`` mm (NaN: no
    ring), ``kind`` ``"force"`` (plate held at each of ``heights_mm``, pressure ramped to
    ``p_max_pa``) or ``"lift"`` (a free plate loaded with ``load_n`` N, height recorded
    while the pressure ramps to ``p_max_pa``); ``new_membrane``: the membrane must be made;
    ``cost``: in trials (plus a membrane's making)."""

    design: tuple[float, ...]
    kind: str
    p_max_pa: float
    heights_mm: tuple[float, ...] = ()
    load_n: float = float("nan")
    new_membrane: bool = False
    cost: float = 1.0

    def __post_init__(self):
        if self.kind not in ("force", "lift"):
            raise InputError(f"experiment kind {self.kind!r}; allowed force, lift")
        if len(self.design) != 6:
            raise InputError(f"a design is 6 numbers [t, c, r1, w1, r2, w2] mm, got {len(self.design)}")
        if not (np.isfinite(self.p_max_pa) and self.p_max_pa > 0):
            raise InputError(f"p_max_pa must be a positive number of pascals, got {self.p_max_pa}")
        if self.kind == "force" and (not self.heights_mm or min(self.heights_mm) < 0):
            raise InputError(f"a force sweep needs plate heights >= 0 mm, got {list(self.heights_mm)}")
        if self.kind == "lift" and not (np.isfinite(self.load_n) and self.load_n > 0):
            raise InputError(f"a mass lift needs a positive load in N, got {self.load_n}")
        if not (np.isfinite(self.cost) and self.cost > 0):
            raise InputError(f"an experiment's cost must be positive, got {self.cost}")

    @property
    def design_key(self) -> str:
        from mfdesign.design import Membrane

        return Membrane.from_array(self.design).key()

    def label(self) -> str:
        what = (
            f"force sweep at h = {', '.join(f'{h:g}' for h in self.heights_mm)} mm"
            if self.kind == "force"
            else f"mass lift, load {self.load_n:.1f} N ({self.load_n / G_N_PER_KG:.2f} kg)"
        )
        return f"{'NEW ' if self.new_membrane else ''}{self.design_key}: {what}, to {self.p_max_pa:.0f} Pa"

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["design"] = self.design_key
        d["heights_mm"] = list(self.heights_mm)
        d["load_n"] = None if not np.isfinite(self.load_n) else self.load_n
        return d


def candidate_experiments(
    existing: Sequence[str],
    new_designs: Sequence[str] = (),
    *,
    height_sets_mm: Sequence[Sequence[float]] = ((0.0,), (20.0,), (40.0,), (0.0, 20.0, 40.0)),
    masses_kg: Sequence[float] = (1.5, 2.5, 4.0),
    ringed_p_max_pa: float = 4300.0,
    ringless_p_max_pa: float = 6000.0,
    lift_p_max_pa: float = 10000.0,
    cost_trial: float = 1.0,
    cost_membrane: float = 3.0,
) -> list[Experiment]:
    """Every (membrane, trial) pair: force sweeps at each set of ``height_sets_mm`` (cost one
    trial per height) and lifts with each mass of ``masses_kg`` (load ``m g`` N, one trial),
    on the ``existing`` membranes (design keys) and on ``new_designs`` (plus
    ``cost_membrane`` for making one). Pressures rise to the rig's limits (ringed force
    trials ``ringed_p_max_pa``, ringless ``ringless_p_max_pa``, lifts ``lift_p_max_pa``)."""
    from mfdesign.design import Membrane

    out = []
    seen = set()
    for new, keys in ((False, existing), (True, new_designs)):
        for key in keys:
            try:
                m = Membrane.from_key(str(key))
            except Exception as err:  # noqa: BLE001 -- a malformed key names itself
                raise InputError(f"design {key!r}: {err}") from None
            if m.key() in seen:
                continue
            seen.add(m.key())
            design = tuple(float(v) for v in m.to_array())
            extra = cost_membrane if new else 0.0
            p_force = ringed_p_max_pa if m.n_rings else ringless_p_max_pa
            for hs in height_sets_mm:
                hs = tuple(float(h) for h in hs)
                out.append(
                    Experiment(design, "force", p_force, hs, new_membrane=new, cost=extra + cost_trial * len(hs))
                )
            for kg in masses_kg:
                out.append(
                    Experiment(
                        design,
                        "lift",
                        lift_p_max_pa,
                        load_n=float(kg) * G_N_PER_KG,
                        new_membrane=new,
                        cost=extra + cost_trial,
                    )
                )
    if not out:
        raise InputError("no candidate experiments: give at least one existing or new membrane")
    return out


# --------------------------------------------------------------------------- scoring
@dataclasses.dataclass(frozen=True)
class Ranking:
    """The candidates ranked (best first). ``order``: indices into ``experiments``;
    ``score``: Box & Hill's expected log Bayes factor of the truth against its closest
    rival [nats], per candidate; ``pairwise``: ``[C, K, K]``, ``E_{y~p_i}[ln p_i - ln p_j]``;
    ``p_truth``: the expected posterior probability of the true hypothesis after the
    experiment; ``predictions``: per candidate and hypothesis, the observable's mean and
    central ``level`` interval at each row (force [N] at (h mm, p Pa), or lift height [mm]
    at p Pa); ``prior``: the weights pi."""

    hypotheses: tuple[str, ...]
    experiments: tuple[Experiment, ...]
    score: np.ndarray
    pairwise: np.ndarray
    p_truth: np.ndarray
    order: np.ndarray
    predictions: tuple
    prior: np.ndarray
    level: float
    method: str = BOX_HILL_1967
    # candidates no hypothesis has a number for at any of their rows (every row outside the
    # physical model or off the exact model's planes): left out of ``order``, said
    unscored: tuple[int, ...] = ()

    def top(self, n: int = 5) -> list[int]:
        return [int(i) for i in self.order[:n]]

    def entry(self, i: int) -> dict:
        """JSON of candidate ``i``: the experiment, its scores and each hypothesis's predictions."""
        e = self.experiments[i]
        return {
            "experiment": e.to_json(),
            "label": e.label(),
            "score_expected_log_bf": float(self.score[i]),
            "score_per_cost": float(self.score[i] / e.cost),
            "expected_p_truth": float(self.p_truth[i]),
            "pairwise_expected_log_bf": {
                f"{a} vs {b}": float(self.pairwise[i, ia, ib])
                for ia, a in enumerate(self.hypotheses)
                for ib, b in enumerate(self.hypotheses)
                if ia != ib
            },
            "predictions": self.predictions[i],
        }

    def lines(self, n: int = 5) -> list[str]:
        out = []
        for rank, i in enumerate(self.top(n), 1):
            e = self.experiments[i]
            out.append(
                f"{rank}. {e.label()}  cost {e.cost:g}; E[ln BF] {self.score[i]:.2f}, E[P(truth)] {self.p_truth[i]:.3f}"
            )
            preds = self.predictions[i]
            for h, p in preds["by_hypothesis"].items():
                pick = _summary_points(preds, p)
                out.append(f"     {h}: " + "; ".join(pick))
        return out


def _summary_points(preds: dict, p: dict, n: int = 3) -> list[str]:
    rows = preds["rows"]
    idx = np.unique(np.linspace(0, len(rows) - 1, min(n, len(rows))).round().astype(int))
    unit = "N" if preds["observable"] == "force_n" else "mm"
    out = []
    for j in idx:
        r = rows[j]
        where = f"h {r['height_mm']:g} mm, " if r.get("height_mm") is not None else ""
        out.append(
            f"{where}p {r['pressure_pa']:.0f} Pa: {p['mean'][j]:.1f} [{p['lo'][j]:.1f}, {p['hi'][j]:.1f}] {unit}"
        )
    return out


def _criterion(obs, sig, mask, eps, prior):
    """Box & Hill's expectations for ONE candidate: ``obs`` [K, S, R] mean observables,
    ``sig`` [K, R] noise sd, ``mask`` [R] rows that count, ``eps`` [S, R] N(0, 1),
    ``prior`` [K]. Returns ``E[i, j]`` [K, K] and ``E_i[P(i | y)]`` [K]."""
    import jax
    import jax.numpy as jnp

    k, s, _ = obs.shape
    y = obs + sig[:, None, :] * eps[None]  # [K(i), S(m), R]
    z = (y[:, :, None, None, :] - obs[None, None, :, :, :]) / sig[None, None, :, None, :]
    ll = -0.5 * jnp.sum(mask * (z**2 + jnp.log(2 * jnp.pi * sig[None, None, :, None, :] ** 2)), -1)  # [K, S, K, S]
    # draw m of every hypothesis is left out of its mixture when y came from draw m: the
    # draws share their random numbers across hypotheses (common random numbers), so
    # equal predictives score exactly 0
    ll = jnp.where(jnp.eye(s, dtype=bool)[None, :, None, :], -jnp.inf, ll)
    log_p = jax.scipy.special.logsumexp(ll, axis=-1) - jnp.log(s - 1)  # [K(i), S(m), K(j)]
    own = jnp.take_along_axis(log_p, jnp.arange(k)[:, None, None], axis=2)  # [K, S, 1]
    pair = jnp.mean(own - log_p, axis=1)  # [K(i), K(j)]
    post = jax.nn.log_softmax(log_p + jnp.log(prior)[None, None, :], axis=-1)
    p_true = jnp.mean(jnp.exp(jnp.take_along_axis(post, jnp.arange(k)[:, None, None], axis=2))[..., 0], axis=1)
    return pair, p_true


def _lift_heights(f, load, h_grid, sigma_f, height_sd):
    """Plate height [mm] of each draw at each pressure: ``f`` [S, G, P] force [N] on the
    height grid; the first height from 0 where the force falls to ``load``. Returns heights
    [S, P] and the noise sd [P] (sensor + force noise through the median slope)."""
    import jax.numpy as jnp

    above = f > load
    g = h_grid.shape[0]
    first = jnp.argmin(above, axis=1)  # first grid index not above the load (0 if none above... see below)
    all_above = jnp.all(above, axis=1)
    resting = ~above[:, 0, :]
    lo = jnp.clip(first - 1, 0, g - 1)
    f_lo = jnp.take_along_axis(f, lo[:, None, :], 1)[:, 0]
    f_hi = jnp.take_along_axis(f, first[:, None, :], 1)[:, 0]
    dh = h_grid[1] - h_grid[0]
    drop = jnp.maximum(f_lo - f_hi, 1e-9)
    h = h_grid[lo] + jnp.clip((f_lo - load) / drop, 0.0, 1.0) * dh
    h = jnp.where(resting, 0.0, jnp.where(all_above, h_grid[-1], h))
    slope = jnp.where(resting | all_above, jnp.inf, drop / dh)  # N/mm
    slope_med = jnp.median(slope, axis=0)
    sd = jnp.sqrt(height_sd**2 + (sigma_f / slope_med) ** 2)
    return h, sd


def _draws(mf, design, h_mm, p_pa, is_force: bool, key):
    """``F_s`` [S, N] of ``mf`` (a MultiFidelity) at rows ``design`` [N, 6] mm, ``h_mm``,
    ``p_pa``: force rows (the recorded force, measurement effects of force trials
    included) or lift rows (``is_force=False``: the force the free plate feels, what must
    equal the load; a load cell's errors do not enter). A calibrated membrane's row takes
    its own latent thickness, a new one draws from the population (as ``mf.members``)."""
    import jax.numpy as jnp

    from mfdesign.design import Membrane
    from mfdesign.models.hierarchical import CalibrationData
    from mfdesign.physics.effects import Rows

    index = {key_: i for i, key_ in enumerate(mf.design_keys)}
    member = np.array([index.get(Membrane.from_array(d).key(), len(index)) for d in design], dtype=np.int32)
    n = len(design)
    rows = Rows(
        jnp.asarray(h_mm),
        jnp.asarray(p_pa),
        jnp.full(n, bool(is_force)),
        jnp.zeros(n, bool),
        jnp.zeros(n, bool),
        jnp.asarray(member),
    )
    data = CalibrationData(
        jnp.asarray(design), rows, jnp.zeros(n), jnp.ones(n), tuple(mf.design_keys) + ("<new membrane>",)
    )
    return mf.sample_data(data, key)


def rank_experiments(
    predictives: Mapping[str, object],
    experiments: Sequence[Experiment],
    *,
    prior: Sequence[float] | None = None,
    n_pressures: int = 10,
    n_draws: int = 32,
    seed: int = 0,
    level: float = 0.9,
    height_sd_mm: float = 0.5,
    lift_grid_mm: tuple[float, float, float] = (0.0, 75.0, 2.5),
    batch_size: int = 16,
    min_lift_height_mm: float = 2.0,
) -> Ranking:
    """Rank ``experiments`` by Box & Hill's expected log Bayes factor (module doc).

    **Arguments:**

    - `predictives`: ``{hypothesis name: MultiFidelity}`` (each calibrated on the same data;
      an ``MFFit`` is taken for its ``mf``), at least two.
    - `experiments`: the candidates (:func:`candidate_experiments`).
    - `prior`: the hypotheses' current probabilities (default equal;
      :func:`hypothesis_probabilities` of their BIC).
    - `n_pressures`: pressures per trial, evenly up to the trial's ``p_max_pa``.
    - `n_draws`: posterior draws per hypothesis (the mixtures' components).
    - `seed`: the draws' and the noise's random key (the ranking is a deterministic
      function of it).
    - `level`: the predictions' central interval (0.9: 90 %).
    - `height_sd_mm`: the height sensor's noise [mm] (lift rows).
    - `lift_grid_mm`: (start, stop, step) of the height grid [mm] a lift height is found on.
    - `batch_size`: candidates per vmapped batch (bounds memory).
    - `min_lift_height_mm`: a lift row counts only where every hypothesis's every draw has
      the plate floating at least this far above its support and below the rig's top (as
      the calibration keeps lift rows, :func:`mfdesign.calibration.workflow.lifted_rows`).

    **Returns:**

    A :class:`Ranking` (best first), with each hypothesis's predictions of each candidate.
    """
    from mfdesign._x64 import enable_x64

    enable_x64()  # float64 physics: mfdesign._x64
    import jax
    import jax.numpy as jnp

    names = tuple(predictives)
    if len(names) < 2:
        raise InputError(f"need at least two hypotheses to tell apart, got {len(names)}")
    exps = tuple(experiments)
    if not exps:
        raise InputError("no candidate experiments to rank")
    if not 0 < level < 1:
        raise InputError(f"level must be in (0, 1), got {level}")
    if n_draws < 2 or n_pressures < 1:
        raise InputError(f"n_draws must be >= 2 and n_pressures >= 1, got {n_draws}, {n_pressures}")
    mfs: list[Any] = [getattr(m, "mf", m) for m in predictives.values()]
    k = len(mfs)
    pi = np.full(k, 1.0 / k) if prior is None else np.asarray(prior, float)
    if pi.shape != (k,) or not np.all(pi > 0):
        raise InputError(f"prior must be {k} positive weights, got {list(np.atleast_1d(pi))}")
    pi = pi / pi.sum()

    frac = np.arange(1, n_pressures + 1) / n_pressures
    force_i = [i for i, e in enumerate(exps) if e.kind == "force"]
    lift_i = [i for i, e in enumerate(exps) if e.kind == "lift"]
    n_h = max([len(exps[i].heights_mm) for i in force_i], default=1)
    r_obs = max(n_h * n_pressures if force_i else 0, n_pressures if lift_i else 0)
    h_grid = np.arange(lift_grid_mm[0], lift_grid_mm[1] + 1e-9, lift_grid_mm[2])

    # rows: force [Cf, n_h, P] (heights padded by repeating, masked); lift [Cl, G, P]
    def force_rows():
        d = np.array([exps[i].design for i in force_i]).reshape(-1, 6)
        hs = np.array(
            [list(exps[i].heights_mm) + [exps[i].heights_mm[-1]] * (n_h - len(exps[i].heights_mm)) for i in force_i]
        ).reshape(-1, n_h)
        p = np.array([exps[i].p_max_pa * frac for i in force_i]).reshape(-1, n_pressures)
        H = np.broadcast_to(hs[:, :, None], (len(force_i), n_h, n_pressures))
        P = np.broadcast_to(p[:, None, :], H.shape)
        D = np.broadcast_to(d[:, None, None, :], H.shape + (6,))
        return D.reshape(-1, 6), H.reshape(-1), P.reshape(-1)

    def lift_rows():
        d = np.array([exps[i].design for i in lift_i]).reshape(-1, 6)
        p = np.array([exps[i].p_max_pa * frac for i in lift_i]).reshape(-1, n_pressures)
        shape = (len(lift_i), len(h_grid), n_pressures)
        H = np.broadcast_to(h_grid[None, :, None], shape)
        P = np.broadcast_to(p[:, None, :], shape)
        D = np.broadcast_to(d[:, None, None, :], shape + (6,))
        return D.reshape(-1, 6), H.reshape(-1), P.reshape(-1)

    key = jax.random.PRNGKey(seed)
    obs = np.zeros((len(exps), k, n_draws, r_obs))
    sig = np.ones((len(exps), k, r_obs))
    mask = np.zeros((len(exps), r_obs))
    rows_of: list[list[dict]] = [[] for _ in exps]
    for i in force_i:
        e = exps[i]
        n = len(e.heights_mm)
        mask[i, : n * n_pressures] = 1.0
        rows_of[i] = [{"height_mm": float(h), "pressure_pa": float(e.p_max_pa * f)} for h in e.heights_mm for f in frac]
    for i in lift_i:
        mask[i, :n_pressures] = 1.0
        rows_of[i] = [{"height_mm": None, "pressure_pa": float(exps[i].p_max_pa * f)} for f in frac]
    for j, mf in enumerate(mfs):
        thin = mf.thinned(n_draws)
        if thin.theta.shape[0] < n_draws:
            raise InputError(
                f"hypothesis {names[j]!r} holds {thin.theta.shape[0]} posterior draws, fewer than n_draws={n_draws}"
            )
        sigma_f = float(thin.noise_n)
        k_j = key  # common random numbers across hypotheses (see _criterion)
        if force_i:
            D, H, P = force_rows()
            f_force = np.asarray(_draws(thin, D, H, P, True, k_j))
            f_force = f_force.reshape(n_draws, len(force_i), n_h * n_pressures)
            obs[force_i, j, :, : n_h * n_pressures] = np.transpose(f_force, (1, 0, 2))
            sig[force_i, j, :] = sigma_f
        if lift_i:
            D, H, P = lift_rows()
            f = _draws(thin, D, H, P, False, jax.random.fold_in(k_j, 1))
            f = jnp.transpose(f.reshape(n_draws, len(lift_i), len(h_grid), n_pressures), (1, 0, 2, 3))
            loads = jnp.asarray([exps[i].load_n for i in lift_i])
            h, sd = jax.vmap(_lift_heights, in_axes=(0, 0, None, None, None))(
                f, loads, jnp.asarray(h_grid), sigma_f, height_sd_mm
            )
            obs[lift_i, j, :, :n_pressures] = np.asarray(h)
            sig[lift_i, j, :n_pressures] = np.asarray(sd)
    # a lift row counts only where every draw of every hypothesis has the plate floating:
    # the likelihood drops resting and pinned rows (a resting row records the weight, not
    # the membrane's force), so a difference there is nothing the calibration would see
    for i in lift_i:
        floating = np.all(
            (obs[i, :, :, :n_pressures] >= min_lift_height_mm)
            & (obs[i, :, :, :n_pressures] <= h_grid[-1] - min_lift_height_mm),
            axis=(0, 1),
        )
        mask[i, :n_pressures] = floating.astype(float)
    # A row some hypothesis has no number for (outside the physical model: a force above
    # p pi R^2; off the exact model's planes) is not counted, as the calibration leaves such
    # rows out; a candidate left with no row is not scored (Ranking.unscored), not ranked last.
    raw = obs.copy()
    mask = mask * np.all(np.isfinite(obs), axis=(1, 2))
    obs = np.where(np.isfinite(obs), obs, 0.0)  # a masked row must not poison the sums
    unscored = tuple(i for i in range(len(exps)) if not mask[i].any())
    if len(unscored) == len(exps):
        raise InputError(
            f"the models have no finite prediction for any of the {len(exps)} candidates, e.g. {exps[0].label()}"
        )

    eps = np.asarray(jax.random.normal(jax.random.fold_in(key, 10_000), (len(exps), n_draws, r_obs)))
    crit = jax.jit(
        lambda xs: jax.lax.map(lambda x: _criterion(x[0], x[1], x[2], x[3], jnp.asarray(pi)), xs, batch_size=batch_size)
    )
    pair, p_true = crit((jnp.asarray(obs), jnp.asarray(sig), jnp.asarray(mask), jnp.asarray(eps)))
    pair, p_true = np.asarray(pair), np.asarray(p_true)
    off = np.where(np.eye(k, dtype=bool)[None], np.inf, pair)
    score = np.sum(pi[None] * off.min(axis=2), axis=1)
    exp_p = np.sum(pi[None] * p_true, axis=1)
    order = np.lexsort((np.arange(len(exps)), -np.round(score, 9)))
    order = np.array([i for i in order if i not in unscored], dtype=int)

    # predictions: observable mean and central interval with the noise, per hypothesis
    rng = np.random.default_rng(seed)
    a = (1 - level) / 2
    preds = []
    for i, e in enumerate(exps):
        m = np.arange(r_obs) < len(rows_of[i])  # every row of the trial (counted or not)
        by = {}
        for j, nm in enumerate(names):
            y = raw[i, j][:, m][None] + sig[i, j][m] * rng.standard_normal((8, n_draws, int(m.sum())))
            y = y.reshape(-1, int(m.sum()))
            lo, hi = np.quantile(y, [a, 1 - a], axis=0)
            by[nm] = {
                "mean": raw[i, j][:, m].mean(0).round(3).tolist(),
                "lo": lo.round(3).tolist(),
                "hi": hi.round(3).tolist(),
            }
        preds.append(
            {
                "observable": "force_n" if e.kind == "force" else "height_mm",
                "level": level,
                "rows": rows_of[i],
                "counted": (mask[i][m] > 0).tolist(),  # lift rows: only where every draw floats
                "by_hypothesis": by,
            }
        )
    return Ranking(names, exps, score, pair, exp_p, order, tuple(preds), pi, level, unscored=unscored)


def decisive(ranking: Ranking, i: int) -> bool:
    """Whether candidate ``i`` is expected to decide: E[ln BF] against the closest rival above ln 19 (P 0.95)."""
    return bool(ranking.score[i] > math.log(19.0))
