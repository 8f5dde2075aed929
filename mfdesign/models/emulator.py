"""Neural emulator of the membrane simulator: F(design, h, p; SimParams), differentiable.

Replaces :func:`mfdesign.physics.solve.force_at` inside sampling loops and optimisers
(calibration, diagnosis, acquisition). Inputs: ``design`` ``[N, 6]`` =
``[t, c, r1, w1, r2, w2]`` mm (NaN for an absent ring; the encoding of
:meth:`Measurements.design_array`), plate height ``h_mm`` ``[N]``, gauge pressure
``p_pa`` ``[N]`` and a :class:`SimParams` whose fields are scalars or arrays that
broadcast to ``[N]``. Output: plate force [N], ``>= 0``.

Physics built in (exact for the simulator's equations, checked numerically): stresses
of a Gent membrane scale with ``mu t`` and the fabric's with ``ring_mu t``, so the
equilibrium shape depends on the rubber through ``q = p / (mu t_eff)`` [1/mm]
(``t_eff = t * thickness_factor``) and ``ring_mu / mu`` only; the disk's vertical balance
``F = p pi r0^2 + 2 pi r0 t W1 sin(phi0)`` then makes ``F / (p pi r0^2)`` a function of the
shape alone; ``c`` and ``contact_offset_mm`` enter only through the effective disk radius
``r0 = c + offset``. The network therefore learns the dimensionless

    y = F / (p pi r0^2) = g(q^(1/3), h, r0, ring edges relative to r0, ln J_m,
                            thickness_gradient, clamp_prestretch, ln(ring_mu / mu))

and returns ``F = p pi r0^2 softplus(z)`` (0 at ``p = 0``, >= 0 everywhere, near 0 in the
no-contact region). ``mu``, ``t`` and ``thickness_factor`` are exactly free.

Network: an ensemble of ``n_members`` MLPs (equinox) trained together in one jitted step
(``eqx.filter_vmap``) with Adam (Kingma & Ba 2015, optax) on bootstrap-free independent
initialisations (Lakshminarayanan et al. 2017, "Simple and scalable predictive
uncertainty estimation using deep ensembles"); the mean is the prediction, the spread a
rough "emulator fidelity" signal. Computations in float64 (``import mfdesign`` enables it).

Training ranges (design space, h, p, every SimParams field) are stored with the model;
:meth:`Emulator.in_range` flags queries outside them (use the simulator there).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from mfdesign._x64 import enable_x64
from mfdesign.data.shipped import emulator_dir
from mfdesign.design import OUTER_RADIUS_MM, DesignSpace
from mfdesign.models.emulator_data import PARAM_FIELDS  # the constants the emulator takes
from mfdesign.models.force import ForceModel
from mfdesign.physics.params import SimParams

FORMAT_VERSION = 1
DEFAULT_DIR = emulator_dir()  # shipped in the package (mfdesign.data.shipped)
N_FEATURES = 14
Q_SCALE = 1.0  # 1/mm: q = p / (mu t_eff) is at most ~1 in the training ranges
MIN_RUBBER_MM = 0.5  # the effective disk edge must stay this far inside the first ring


def default_ranges() -> dict[str, tuple[float, float]]:
    """Training ranges of the default data generator (:mod:`emulator_data`)."""
    from mfdesign.models import emulator_data as ed

    space = DesignSpace()
    rng = {k: (lo, hi) for k, (lo, hi, _) in ed.PARAM_RANGES.items()}
    rng["ring_jm"] = (ed.RING_JM, ed.RING_JM)
    rng.update(
        height_mm=ed.H_RANGE_MM,
        pressure_pa=ed.P_RANGE_PA,
        thickness_mm=space.thickness_mm,
        contact_radius_mm=space.contact_radius_mm,
        half_width_mm=space.half_width_mm,
    )
    return rng


# --------------------------------------------------------------------------- config
@dataclasses.dataclass(frozen=True)
class EmulatorConfig:
    """Network and training hyper-parameters (``lr`` peak of a cosine schedule)."""

    n_members: int = 4
    width: int = 128
    depth: int = 4
    steps: int = 20_000
    batch: int = 512
    lr: float = 3e-3
    lr_final: float = 3e-5
    weight_decay: float = 0.0
    y_weight: float = 0.05  # weight of the dimensionless error (fits low pressures too)
    seed: int = 0

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "EmulatorConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"EmulatorConfig: unknown fields {sorted(unknown)}; allowed {sorted(names)}")
        return cls(**d)


# --------------------------------------------------------------------------- features
def _broadcast_inputs(design, h_mm, p_pa, params: SimParams):
    h = jnp.asarray(h_mm, dtype=float)
    p = jnp.asarray(p_pa, dtype=float)
    d = jnp.asarray(design, dtype=float)
    if d.shape[-1:] != (6,):
        raise ValueError(f"design must be [N, 6] = [t, c, r1, w1, r2, w2] mm, got shape {d.shape}")
    shape = jnp.broadcast_shapes(h.shape, p.shape, d.shape[:-1], *(jnp.shape(getattr(params, f)) for f in PARAM_FIELDS))
    h, p = jnp.broadcast_to(h, shape), jnp.broadcast_to(p, shape)
    d = jnp.broadcast_to(d, shape + (6,))
    par = {f: jnp.broadcast_to(jnp.asarray(getattr(params, f), dtype=float), shape) for f in PARAM_FIELDS}
    return d, h, p, par


def features(design, h_mm, p_pa, params: SimParams) -> tuple[jax.Array, jax.Array]:
    """Raw features ``[..., N_FEATURES]`` and the force scale ``p pi r0^2`` [N].

    NaN ring entries are replaced before any arithmetic (the double-``where`` trick), so
    no NaN reaches values or gradients.
    """
    d, h, p, par = _broadcast_inputs(design, h_mm, p_pa, params)
    t_eff = d[..., 0] * par["thickness_factor"]
    r0 = d[..., 1] + par["contact_offset_mm"]
    span = OUTER_RADIUS_MM - r0
    q = jnp.maximum(p, 0.0) / (par["mu_pa"] * t_eff)
    cube = jnp.cbrt(jnp.maximum(q, 0.0) / Q_SCALE + 1e-12)
    ring = []
    for k in range(2):
        r, w = d[..., 2 + 2 * k], d[..., 3 + 2 * k]
        present = ~(jnp.isnan(r) | jnp.isnan(w))
        r_s = jnp.where(present, r, 0.0)
        w_s = jnp.where(present, w, 0.0)
        inner = jnp.where(present, (r_s - w_s - r0) / span, 0.0)
        outer = jnp.where(present, (r_s + w_s - r0) / span, 0.0)
        ring += [present.astype(float), inner, outer]
    feats = jnp.stack(
        [
            cube,
            h / 80.0,
            r0 / 40.0,
            jnp.log(par["jm"]),
            par["thickness_gradient"],
            (par["clamp_prestretch"] - 1.0) * 10.0,
            jnp.log(par["ring_mu_pa"] / par["mu_pa"]),
            jnp.log(par["ring_jm"]),
        ]
        + ring,
        axis=-1,
    )
    scale = jnp.maximum(p, 0.0) * 1e-6 * jnp.pi * r0**2  # MPa mm^2 = N
    return feats, scale


# --------------------------------------------------------------------------- model
def _mlp(key, width: int, depth: int) -> eqx.nn.MLP:
    return eqx.nn.MLP(N_FEATURES, "scalar", width, depth, activation=jax.nn.silu, key=key)


class Emulator(ForceModel):
    """Ensemble of MLPs for ``y = F / (p pi r0^2)``; call it for the mean force [N]."""

    name = "emulator"

    members: eqx.nn.MLP  # stacked: every array leaf has a leading axis n_members
    feat_mean: jax.Array
    feat_std: jax.Array
    config: EmulatorConfig = eqx.field(static=True)
    ranges: tuple = eqx.field(static=True)  # ((name, low, high), ...)

    # -- prediction ---------------------------------------------------------------------
    def _z(self, feats):
        x = (feats - self.feat_mean) / self.feat_std
        flat = x.reshape(-1, N_FEATURES)
        z = eqx.filter_vmap(lambda m: jax.vmap(m)(flat))(self.members)
        return z.reshape((z.shape[0],) + feats.shape[:-1])

    def members_force(self, design, h_mm, p_pa, params: SimParams = SimParams()) -> jax.Array:
        """Force of every member [n_members, N] (N)."""
        feats, scale = features(design, h_mm, p_pa, params)
        f = scale * jax.nn.softplus(self._z(feats))
        # constants it was not trained on (a fabric inset, any field added to SimParams after
        # its training): NaN, never a silently ignored effect
        return jnp.where(self._untrained_set(params), jnp.nan, f)

    def __call__(self, design, h_mm, p_pa, params: SimParams = SimParams()) -> jax.Array:
        """Mean force over the members [N] (N)."""
        return jnp.mean(self.members_force(design, h_mm, p_pa, params), axis=0)

    def mean_std(self, design, h_mm, p_pa, params: SimParams = SimParams()):
        """Mean and spread (std over members) of the force [N] (N)."""
        f = self.members_force(design, h_mm, p_pa, params)
        return jnp.mean(f, axis=0), jnp.std(f, axis=0)

    # -- ranges -------------------------------------------------------------------------
    @property
    def range_dict(self) -> dict[str, tuple[float, float]]:
        return {n: (lo, hi) for n, lo, hi in self.ranges}

    def untrained_fields(self) -> dict[str, float]:
        """SimParams fields it has no training range for, with the only value it knows: the default.

        Read from the stored ranges, so an emulator saved before a field existed pins that
        field too (its features never saw it vary).
        """
        return {f.name: f.default for f in dataclasses.fields(SimParams) if f.name not in self.range_dict}

    def _untrained_set(self, params: SimParams) -> jax.Array:
        off = jnp.asarray(False)
        for name, default in self.untrained_fields().items():
            off = off | (jnp.asarray(getattr(params, name)) != default)
        return off

    def support(self) -> dict[str, tuple[float, float]]:
        """The training ranges; a field it was never trained on is pinned at its default."""
        return {**self.range_dict, **{n: (v, v) for n, v in self.untrained_fields().items()}}

    def input_ranges(self) -> dict[str, tuple[float, float]]:
        rg = self.range_dict
        return {
            "height_mm": tuple(rg.get("height_mm", (0.0, 80.0))),
            "pressure_pa": tuple(rg.get("pressure_pa", (0.0, 1.0e4))),
        }

    def in_range(self, design, h_mm, p_pa, params: SimParams = SimParams()) -> jax.Array:
        """True where the query lies inside the training ranges (bool [N]).

        Checked: thickness, contact radius, ring half-widths, h, p and every SimParams
        field against their stored ranges (relative tolerance 1e-6), ring geometry valid
        (rings >= 3 mm apart, inside the clamp) and the effective disk edge ``c + offset``
        at least 0.5 mm inside the first ring. NaN anywhere -> False.
        """
        d, h, p, par = _broadcast_inputs(design, h_mm, p_pa, params)
        rg = self.range_dict

        def within(x, name):
            lo, hi = rg[name]
            tol = 1e-6 * max(abs(lo), abs(hi), 1.0)
            return (x >= lo - tol) & (x <= hi + tol)

        ok = within(d[..., 0], "thickness_mm") & within(d[..., 1], "contact_radius_mm")
        ok &= within(h, "height_mm") & within(p, "pressure_pa")
        for f in PARAM_FIELDS:
            ok &= within(par[f], f)
        ok &= ~self._untrained_set(params)
        r1, w1, r2, w2 = (d[..., k] for k in range(2, 6))
        has1 = ~jnp.isnan(r1) & ~jnp.isnan(w1)
        has2 = ~jnp.isnan(r2) & ~jnp.isnan(w2)
        half = lambda w, has: jnp.where(has, within(w, "half_width_mm"), True)
        ok &= half(w1, has1) & half(w2, has2)
        ok &= ~(jnp.isnan(r1) ^ jnp.isnan(w1)) & ~(jnp.isnan(r2) ^ jnp.isnan(w2))
        ok &= ~(has2 & ~has1)  # slot 2 without slot 1 is not the encoding
        r0 = d[..., 1] + par["contact_offset_mm"]
        gap = 3.0 - 1e-6
        ok &= jnp.where(has1, (r1 - w1 >= d[..., 1] + gap) & (r1 - w1 >= r0 + MIN_RUBBER_MM), True)
        last = jnp.where(has2, r2 + w2, jnp.where(has1, r1 + w1, -jnp.inf))
        ok &= jnp.where(has2, r2 - w2 >= r1 + w1 + gap, True)
        ok &= last <= OUTER_RADIUS_MM - gap
        return ok

    # -- persistence --------------------------------------------------------------------
    def save(self, path=DEFAULT_DIR, extra: dict | None = None) -> Path:
        """Write ``path/emulator.eqx`` (leaves) and ``path/emulator.json`` (format version,
        config, ranges, normalisation, ``extra`` such as accuracy)."""
        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        eqx.tree_serialise_leaves(path / "emulator.eqx", self)
        meta = {
            "format_version": FORMAT_VERSION,
            "kind": "simulator_emulator",
            "dtype": "float64",
            "config": self.config.to_dict(),
            "ranges": {n: [lo, hi] for n, lo, hi in self.ranges},
            "feat_mean": np.asarray(self.feat_mean).tolist(),
            "feat_std": np.asarray(self.feat_std).tolist(),
            "extra": extra or {},
        }
        (path / "emulator.json").write_text(json.dumps(meta, indent=2))
        return path

    @classmethod
    def load(cls, path=DEFAULT_DIR) -> "Emulator":
        """Inverse of :meth:`save`; checks the format version."""
        enable_x64()  # float64 physics: mfdesign._x64
        path = Path(path)
        meta_file = path / "emulator.json"
        if not meta_file.exists():
            raise FileNotFoundError(f"no emulator.json in {path}: not a saved Emulator")
        meta = json.loads(meta_file.read_text())
        if meta.get("format_version") != FORMAT_VERSION:
            raise ValueError(
                f"{path}: emulator format_version {meta.get('format_version')}, this code reads {FORMAT_VERSION}"
            )
        cfg = EmulatorConfig.from_dict(meta["config"])
        ranges = {k: tuple(v) for k, v in meta["ranges"].items()}
        # shapes only (eval_shape): every weight is read from the file, and running the
        # members' initialisers eagerly under vmap compiled one random program per layer
        # shape (5 of them, ~2.9 s of a cold demo, issue 40)
        skeleton = eqx.filter_eval_shape(
            init_emulator, cfg, np.asarray(meta["feat_mean"]), np.asarray(meta["feat_std"]), ranges
        )
        return eqx.tree_deserialise_leaves(path / "emulator.eqx", skeleton)


def init_emulator(config: EmulatorConfig, feat_mean, feat_std, ranges: dict) -> Emulator:
    keys = jax.random.split(jax.random.PRNGKey(config.seed), config.n_members)
    members = eqx.filter_vmap(lambda k: _mlp(k, config.width, config.depth))(keys)
    return Emulator(
        members=members,
        feat_mean=jnp.asarray(feat_mean, dtype=float),
        feat_std=jnp.asarray(feat_std, dtype=float),
        config=config,
        ranges=tuple((k, float(lo), float(hi)) for k, (lo, hi) in sorted(ranges.items())),
    )


_DEFAULT: Emulator | None = None


def load_default() -> Emulator:
    """The trained artifact shipped in the package (``mfdesign/data/files/emulator``; loaded once, then cached)."""
    enable_x64()  # float64 physics: mfdesign._x64
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = Emulator.load(DEFAULT_DIR)
    return _DEFAULT


# --------------------------------------------------------------------------- data -> arrays
def table_arrays(df) -> dict[str, np.ndarray]:
    """Simulator table (see :mod:`emulator_data`) -> design [N,6], h, p, F, params fields."""
    from mfdesign.models.emulator_data import DESIGN_COLS

    out = {
        "design": df[list(DESIGN_COLS)].to_numpy(float),
        "h": df["height_mm"].to_numpy(float),
        "p": df["pressure_pa"].to_numpy(float),
        "F": df["force_n"].to_numpy(float),
    }
    for f in PARAM_FIELDS:
        out[f] = df[f].to_numpy(float)
    return out


def params_of(arrays: dict[str, np.ndarray]) -> SimParams:
    return SimParams(**{f: jnp.asarray(arrays[f]) for f in PARAM_FIELDS})


# --------------------------------------------------------------------------- training
def fit_emulator(
    arrays: dict[str, np.ndarray],
    config: EmulatorConfig = EmulatorConfig(),
    ranges: dict | None = None,
    progress: bool = True,
) -> tuple[Emulator, dict]:
    """Train on simulator points (``table_arrays`` output). Points with ``p = 0`` carry no
    information (F = 0 by construction) and are skipped.

    Loss per point: ``((y_hat - y) s / F_ref)^2 + y_weight (y_hat - y)^2``, with
    ``s = p pi r0^2`` (so the first term is the squared force error over the typical
    force ``F_ref``, the RMS training force). Adam with a cosine learning-rate decay;
    each member draws its own minibatches.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    from tqdm.auto import tqdm

    keep = arrays["p"] > 0
    a = {k: v[keep] for k, v in arrays.items()}
    feats, scale = features(a["design"], a["h"], a["p"], params_of(a))
    feats, scale = np.asarray(feats), np.asarray(scale)
    y = a["F"] / scale
    f_ref = float(np.sqrt(np.mean(a["F"] ** 2)))
    mean, std = feats.mean(0), feats.std(0)
    std = np.where(std > 1e-9, std, 1.0)
    emu = init_emulator(config, mean, std, ranges or default_ranges())
    X = jnp.asarray((feats - mean) / std)
    Y, S = jnp.asarray(y), jnp.asarray(scale / f_ref)
    n = X.shape[0]
    sched = optax.cosine_decay_schedule(config.lr, config.steps, config.lr_final / config.lr)
    opt = optax.adamw(sched, weight_decay=config.weight_decay)
    params, static = eqx.partition(emu.members, eqx.is_inexact_array)
    opt_state = eqx.filter_vmap(opt.init)(params)

    def member_loss(p, idx):
        m = eqx.combine(p, static)
        z = jax.vmap(m)(X[idx])
        err = jax.nn.softplus(z) - Y[idx]
        return jnp.mean((err * S[idx]) ** 2 + config.y_weight * err**2)

    def member_step(p, s, key):
        idx = jax.random.randint(key, (config.batch,), 0, n)
        loss, g = jax.value_and_grad(member_loss)(p, idx)
        upd, s = opt.update(g, s, p)
        return optax.apply_updates(p, upd), s, loss

    chunk = 500

    @eqx.filter_jit
    def run(p, s, key):
        def body(carry, k):
            p, s = carry
            ks = jax.random.split(k, config.n_members)
            p, s, loss = eqx.filter_vmap(member_step)(p, s, ks)
            return (p, s), loss

        (p, s), losses = jax.lax.scan(body, (p, s), jax.random.split(key, chunk))
        return p, s, losses.mean(0)

    key = jax.random.PRNGKey(config.seed + 1)
    history = []
    bar = tqdm(range(0, config.steps, chunk), desc="emulator training", disable=not progress, mininterval=10)
    for _ in bar:
        key, sub = jax.random.split(key)
        params, opt_state, loss = run(params, opt_state, sub)
        history.append(np.asarray(loss).tolist())
        bar.set_postfix(loss=f"{float(np.mean(loss)):.2e}")
    emu = eqx.tree_at(lambda e: e.members, emu, eqx.combine(params, static))
    return emu, {"loss": history, "f_ref_n": f_ref, "n_points": int(n)}


def evaluate(emu: Emulator, arrays: dict[str, np.ndarray], f_range_n: float | None = None) -> dict:
    """Held-out accuracy against the simulator: RMSE, RMSE / force range, max error,
    overall and per ring count (force range = max - min simulator force, or given)."""
    pred = np.asarray(jax.jit(emu.__call__)(arrays["design"], arrays["h"], arrays["p"], params_of(arrays)))
    err = pred - arrays["F"]
    rng = float(f_range_n if f_range_n is not None else arrays["F"].max() - arrays["F"].min())
    n_rings = (~np.isnan(arrays["design"][:, [2, 4]])).sum(1)

    def stats(mask):
        e = err[mask]
        if e.size == 0:
            return {"n": 0}
        rmse = float(np.sqrt(np.mean(e**2)))
        return {
            "n": int(e.size),
            "rmse_n": rmse,
            "rmse_over_range": rmse / rng,
            "max_abs_err_n": float(np.max(np.abs(e))),
            "mae_n": float(np.mean(np.abs(e))),
            "p99_abs_err_n": float(np.quantile(np.abs(e), 0.99)),
        }

    out = {"force_range_n": rng, "all": stats(np.ones_like(err, bool))}
    for k in range(3):
        out[f"rings_{k}"] = stats(n_rings == k)
    out["_pred"] = pred
    return out
