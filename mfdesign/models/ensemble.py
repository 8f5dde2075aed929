"""Randomised-prior-network ensemble of operator networks for membrane force.

The paper's data-driven model (Campbell et al. 2025, "Active Learning Design: Modeling
Force Output for Axisymmetric Soft Pneumatic Actuators"): for a design
``[t, c, r1, w1, r2, w2]`` (mm, NaN for an absent ring), plate height ``h`` (mm) and
gauge pressure ``p`` (Pa) it predicts the plate force ``F`` (N) as a polynomial in
pressure whose coefficients depend on the design and the height::

    e_k   = where(ring k present, phi((r_k, w_k)_norm), e_none)      ring encoder
    z     = MLP([e_1 + e_2, onehot(n_rings), t_norm, c_norm, h_norm]) latent
    a     = A z + b                                                  head, degree D
    F/s_F = a_0 + sum_{k=1..D} g(a_k) p_norm^k,   p_norm = p / s_p >= 0

with ``g`` the identity, or ``softplus`` in the monotone option (then dF/dp >= 0 for
p >= 0). Summing the ring embeddings makes the prediction independent of ring order; the
learned ``e_none`` stands for "no ring", and NaN inputs are replaced before the ring MLP
so that NaN reaches neither values nor gradients.

Uncertainty: an ensemble of randomised prior networks (Osband, Aslanides & Cassirer 2018,
"Randomized prior functions for deep reinforcement learning"): member m predicts
``f_m(x) = g_m(x; theta_m) + beta * stop_gradient(q_m(x; theta0_m))`` with ``q_m`` a
frozen random network of the same architecture. Every member is fitted to the data with a
weighted Huber loss on its own random minibatch; their spread is the epistemic
uncertainty. All members train together in one jitted step over stacked parameters
(``eqx.filter_vmap``), and ``lax.scan`` runs many steps per call.

Normalisation (stored in the model): t, c, h and ring (r, w) are standardised, the ring
statistics using present rings only; ``p_norm = p / s_p`` with ``s_p`` the largest
training |p|; forces are divided by their training standard deviation ``s_F``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from mfdesign._x64 import enable_x64
from mfdesign.models.predictor import EnsemblePredictor
from mfdesign.physics._traces import stored_jit

FORMAT_VERSION = 1
MAX_RINGS = 2


# --------------------------------------------------------------------------- config
@dataclasses.dataclass(frozen=True)
class EnsembleConfig:
    """Hyper-parameters. Defaults follow the paper (32 members, 10,000 steps, batch 100).

    ``ring_depth``/``ring_width``: hidden layers of the ring encoder (0 = one linear map);
    ``latent_depth``/``latent_width``: the latent MLP; ``degree``: polynomial degree in p;
    ``beta``: prior scale; ``huber_delta_n``: Huber threshold in newtons; learning rate
    ``lr`` decays by ``lr_decay`` every ``lr_decay_steps`` down to ``lr_min`` (the
    authors' schedule); ``chunk``: steps per compiled ``lax.scan`` call; ``intercept=False``
    drops the head's constant ``a_0``, so that ``F(p = 0) = 0`` exactly (a sim-to-real
    discrepancy: neither the rubber nor the simulator pushes without pressure).
    """

    n_members: int = 32
    steps: int = 10_000
    batch: int = 100
    ring_embed_dim: int = 12
    ring_depth: int = 0
    ring_width: int = 16
    latent_depth: int = 3
    latent_width: int = 32
    degree: int = 2
    monotone: bool = False
    intercept: bool = True
    beta: float = 1.0
    huber_delta_n: float = 1.0
    lr: float = 5e-3
    lr_decay: float = 0.1
    lr_decay_steps: int = 5_000
    lr_min: float = 1e-4
    chunk: int = 500
    dtype: str = "float32"

    def __post_init__(self):
        ints = dict(
            n_members=1,
            steps=0,
            batch=1,
            ring_embed_dim=1,
            ring_depth=0,
            ring_width=1,
            latent_depth=0,
            latent_width=1,
            chunk=1,
            lr_decay_steps=1,
        )
        for name, low in ints.items():
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < low:
                raise ValueError(f"EnsembleConfig.{name} must be an integer >= {low}, got {v!r}")
        if self.degree not in (1, 2, 3):
            raise ValueError(f"EnsembleConfig.degree must be 1, 2 or 3, got {self.degree!r}")
        for name in ("beta", "huber_delta_n", "lr", "lr_min"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"EnsembleConfig.{name} must be a finite number >= 0, got {v!r}")
        for name in ("monotone", "intercept"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"EnsembleConfig.{name} must be true or false, got {getattr(self, name)!r}")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"EnsembleConfig.dtype must be 'float32' or 'float64', got {self.dtype!r}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "EnsembleConfig":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown EnsembleConfig fields: {sorted(unknown)}")
        return cls(**d)

    def fit(self, design, h_mm, p_pa, force_n, weight=None, *, key=None, progress=True) -> EnsemblePredictor:
        """:class:`~mfdesign.models.cv.ForceModelSpec` interface: :func:`fit_ensemble` with this
        config, as a predictor (its ``ensemble`` is the fitted :class:`Ensemble`)."""
        enable_x64()  # float64 physics: mfdesign._x64
        return EnsemblePredictor(fit_ensemble(self, design, h_mm, p_pa, force_n, weight, key=key, progress=progress))


# --------------------------------------------------------------------------- inputs
def check_inputs(design, h_mm, p_pa, force_n=None, weight=None):
    """Validate and convert to float64 NumPy arrays: design [n, 6], the rest [n].

    Raises ``ValueError`` naming the array on wrong shapes, NaN outside absent-ring
    slots, half-specified rings or negative weights.
    """
    design = np.atleast_2d(np.asarray(design, dtype=np.float64))
    n = design.shape[0]
    if design.ndim != 2 or design.shape[1] != 6:
        raise ValueError(f"design must be [n, 6] = [t, c, r1, w1, r2, w2] in mm, got shape {design.shape}")
    if not np.all(np.isfinite(design[:, :2])):
        raise ValueError("design thickness and contact radius (columns 0, 1) must be finite")
    rings = design[:, 2:].reshape(n, MAX_RINGS, 2)
    if np.any(np.isnan(rings).any(-1) != np.isnan(rings).all(-1)):
        raise ValueError("a ring needs both radius and half-width (or both NaN for no ring)")
    if np.any(np.isinf(rings)):
        raise ValueError("ring radii and half-widths must be finite or NaN")
    out = [design]
    for name, arr in (("h_mm", h_mm), ("p_pa", p_pa), ("force_n", force_n), ("weight", weight)):
        if arr is None:
            out.append(None)
            continue
        arr = (
            np.broadcast_to(np.asarray(arr, dtype=np.float64), (n,))
            if np.ndim(arr) == 0
            else np.asarray(arr, dtype=np.float64).reshape(-1)
        )
        if arr.shape != (n,):
            raise ValueError(f"{name} must have {n} entries (one per design row), got {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must be finite")
        if name == "weight" and np.any(arr < 0):
            raise ValueError("weight must be >= 0")
        out.append(arr)
    return tuple(out)


class Normaliser(eqx.Module):
    """Affine input/output scalings fitted on training data (see the module docstring)."""

    mu_tch: jax.Array  # [3] means of t, c, h
    sd_tch: jax.Array
    mu_ring: jax.Array  # [2] means of (r, w) over present rings
    sd_ring: jax.Array
    p_scale: jax.Array  # scalar, Pa
    f_scale: jax.Array  # scalar, N

    @classmethod
    def fit(cls, design, h, p, force):
        tch = np.column_stack([design[:, 0], design[:, 1], h])
        rings = design[:, 2:].reshape(-1, 2)
        rings = rings[~np.isnan(rings).any(1)]
        mu_r = rings.mean(0) if len(rings) else np.zeros(2)
        sd_r = rings.std(0) if len(rings) > 1 else np.ones(2)
        pos = lambda s: np.where(s > 1e-12, s, 1.0)  # noqa: E731
        p_scale = float(np.max(np.abs(p))) or 1.0
        f_scale = float(np.std(force)) or 1.0
        return cls(
            jnp.asarray(tch.mean(0)),
            jnp.asarray(pos(tch.std(0))),
            jnp.asarray(mu_r),
            jnp.asarray(pos(sd_r)),
            jnp.asarray(p_scale),
            jnp.asarray(f_scale),
        )


# --------------------------------------------------------------------------- network
class ForceNet(eqx.Module):
    """One operator network (Campbell et al. 2025) on one normalised point -> F / s_F."""

    ring_mlp: eqx.nn.MLP
    no_ring: jax.Array
    latent: eqx.nn.MLP
    head: eqx.nn.Linear
    monotone: bool = eqx.field(static=True)
    intercept: bool = eqx.field(static=True)

    def __init__(self, cfg: EnsembleConfig, key):
        k1, k2, k3, k4 = jax.random.split(key, 4)
        dt = jnp.dtype(cfg.dtype)
        e = cfg.ring_embed_dim
        self.ring_mlp = eqx.nn.MLP(
            2, e, cfg.ring_width, cfg.ring_depth, activation=jnp.tanh, final_activation=jnp.tanh, key=k1, dtype=dt
        )
        self.no_ring = 0.5 * jax.random.normal(k2, (e,), dt)
        self.latent = eqx.nn.MLP(
            e + MAX_RINGS + 1 + 3,
            cfg.latent_width,
            cfg.latent_width,
            cfg.latent_depth,
            activation=jax.nn.gelu,
            final_activation=jax.nn.gelu,
            key=k3,
            dtype=dt,
        )
        self.head = eqx.nn.Linear(cfg.latent_width, cfg.degree + 1, key=k4, dtype=dt)
        self.monotone = cfg.monotone
        self.intercept = cfg.intercept

    def __call__(self, tch, rings, present, p):
        """``tch`` [3] normalised (t, c, h); ``rings`` [2, 2] normalised, finite;
        ``present`` [2] bool; ``p`` normalised pressure (scalar, >= 0 for monotone)."""
        emb = jax.vmap(self.ring_mlp)(rings)
        emb = jnp.where(present[:, None], emb, self.no_ring[None, :]).sum(0)
        count = jax.nn.one_hot(present.sum(), MAX_RINGS + 1, dtype=emb.dtype)
        a = self.head(self.latent(jnp.concatenate([emb, count, tch.astype(emb.dtype)])))
        slopes = jax.nn.softplus(a[1:]) if self.monotone else a[1:]
        powers = p.astype(a.dtype) ** jnp.arange(1, a.shape[0])
        return (a[0] if self.intercept else 0.0) + jnp.dot(slopes, powers)


def _features(norm: Normaliser, design, h, p):
    """Normalised, NaN-free features of one point (design [6], h, p in mm, mm, Pa)."""
    tch = (jnp.stack([design[0], design[1], h]) - norm.mu_tch) / norm.sd_tch
    raw = design[2:].reshape(MAX_RINGS, 2)
    present = ~jnp.isnan(raw).any(-1)
    safe = jnp.where(present[:, None], raw, norm.mu_ring)  # NaN never enters arithmetic
    rings = (safe - norm.mu_ring) / norm.sd_ring
    return tch, rings, present, p / norm.p_scale


class Ensemble(eqx.Module):
    """Trained RPN ensemble: ``predict(design [n,6], h_mm [n], p_pa [n]) -> F [members, n]`` N.

    ``trainable`` and ``prior`` are :class:`ForceNet` pytrees stacked along a leading
    member axis; the prior is frozen (``stop_gradient``) and scaled by ``beta``.
    """

    trainable: ForceNet
    prior: ForceNet
    norm: Normaliser
    beta: float = eqx.field(static=True)
    config: EnsembleConfig = eqx.field(static=True)

    @property
    def n_members(self) -> int:
        return self.config.n_members

    def _member(self, net, prior, design, h, p):
        x = _features(self.norm, design, h, p)
        f = net(*x) + self.beta * jax.lax.stop_gradient(prior(*x))
        return f * self.norm.f_scale

    def predict(self, design, h_mm, p_pa):
        """Force [members, n] in N at design rows [n, 6] (mm), heights [n] mm, pressures [n] Pa.

        Pure and traceable: jit-, vmap- and grad-able in every numeric input.
        """
        h_mm, p_pa = jnp.broadcast_arrays(jnp.asarray(h_mm), jnp.asarray(p_pa))
        return _predict(self, jnp.asarray(design), h_mm, p_pa)

    def subset(self, start: int, stop: int) -> "Ensemble":
        """Members ``start .. stop - 1`` as an ensemble of their own (same normalisation):
        one training run of several ensembles' members (``member_weight``) split apart."""
        if not 0 <= start < stop <= self.n_members:
            raise ValueError(f"members {start}..{stop - 1} of {self.n_members}: allowed 0 <= start < stop <= members")
        cut = lambda t: jax.tree.map(lambda a: a[start:stop] if eqx.is_array(a) else a, t)  # noqa: E731
        cfg = dataclasses.replace(self.config, n_members=stop - start)
        return Ensemble(cut(self.trainable), cut(self.prior), self.norm, self.beta, cfg)

    def mean_std(self, design, h_mm, p_pa):
        """Ensemble mean and standard deviation [n] of the force (N)."""
        f = self.predict(design, h_mm, p_pa)
        return f.mean(0), f.std(0)

    def save(self, path) -> Path:
        """Write ``path/ensemble.eqx`` (leaves) and ``path/ensemble.json`` (format, config, norm)."""
        from mfdesign import outputs

        path = Path(path)
        path.mkdir(parents=True, exist_ok=True)
        with outputs.atomic_path(path / "ensemble.eqx") as tmp:
            eqx.tree_serialise_leaves(tmp, self)
        meta = {
            "format_version": FORMAT_VERSION,
            "kind": "rpn_ensemble",
            "beta": self.beta,
            "config": self.config.to_dict(),
            "normalisation": {
                k: np.asarray(getattr(self.norm, k)).tolist()
                for k in ("mu_tch", "sd_tch", "mu_ring", "sd_ring", "p_scale", "f_scale")
            },
        }
        outputs.write_json(path / "ensemble.json", meta)
        return path

    @classmethod
    def load(cls, path) -> "Ensemble":
        """Inverse of :meth:`save`; checks the format version, the sizes in the config (before
        allocating anything) and that every weight is finite. A folder that is not a saved
        ensemble raises ``FileNotFoundError``; a corrupt or mismatched one ``InputError``
        saying what was wrong."""
        enable_x64()  # float64 physics: mfdesign._x64
        from mfdesign.errors import InputError, one_line

        path = Path(path)
        meta_file = path / "ensemble.json"
        if not meta_file.is_file():
            raise FileNotFoundError(f"no ensemble.json in {path}: not a saved Ensemble")
        try:
            model = cls._load_checked(path, meta_file)
        except InputError:
            raise
        except Exception as err:  # noqa: BLE001 -- a corrupt file fails in many ways (equinox TreePathError, ...)
            raise InputError(
                f"{path}: not a loadable ensemble ({type(err).__name__}: {one_line(err, 200)}); "
                "allowed: a folder written by `mfdesign fit` (refit it)"
            ) from None
        leaves = [np.asarray(a) for a in jax.tree.leaves(eqx.filter(model, eqx.is_inexact_array))]
        bad = sum(int((~np.isfinite(a)).sum()) for a in leaves)
        if bad:
            raise InputError(
                f"{path / 'ensemble.eqx'}: {bad} of {sum(a.size for a in leaves)} weights are NaN or "
                "infinite; allowed: finite weights (refit the model)"
            )
        return model

    @classmethod
    def _load_checked(cls, path: Path, meta_file: Path) -> "Ensemble":
        from mfdesign.errors import InputError

        meta = json.loads(meta_file.read_text())
        if not isinstance(meta, dict):
            raise InputError(f"{meta_file}: expected a JSON object, got {type(meta).__name__}")
        if meta.get("format_version") != FORMAT_VERSION:
            raise InputError(f"{path}: format_version {meta.get('format_version')} != {FORMAT_VERSION}")
        cfg = EnsembleConfig.from_dict(meta["config"])
        too_big = {k: getattr(cfg, k) for k, top in LOAD_LIMITS.items() if getattr(cfg, k) > top}
        if too_big:
            raise InputError(
                f"{meta_file}: config sizes {too_big} exceed what a saved ensemble may declare "
                f"({ {k: LOAD_LIMITS[k] for k in too_big} })"
            )
        beta = float(meta["beta"])
        n = meta["normalisation"]
        norm = Normaliser(
            *(
                jnp.asarray(n[k], dtype=jnp.float64)
                for k in ("mu_tch", "sd_tch", "mu_ring", "sd_ring", "p_scale", "f_scale")
            )
        )
        if not (math.isfinite(beta) and all(np.isfinite(np.asarray(a)).all() for a in jax.tree.leaves(norm))):
            raise InputError(f"{meta_file}: beta or the normalisation holds NaN or infinity; allowed: finite numbers")
        if not (path / "ensemble.eqx").is_file():
            raise InputError(
                f"{path}: ensemble.json without ensemble.eqx; allowed: both, as `mfdesign fit` writes them"
            )
        # shapes only (eval_shape): every weight is read from the file, and running the
        # members' initialisers op by op under vmap took 30 s for 4 members (issue 40)
        skeleton = eqx.filter_eval_shape(init_ensemble, cfg, norm, jax.random.PRNGKey(0), beta=beta)
        return eqx.tree_deserialise_leaves(path / "ensemble.eqx", skeleton)


# Largest sizes a saved ensemble may declare: checked before the skeleton is allocated, so
# a corrupt ensemble.json cannot ask for gigabytes (the paper's model: 32 members, width 32).
LOAD_LIMITS = {
    "n_members": 1024,
    "ring_embed_dim": 512,
    "ring_depth": 16,
    "ring_width": 4096,
    "latent_depth": 16,
    "latent_width": 4096,
}


# Rows one compiled pass evaluates at once. Every member's activations are [members, rows,
# width]: the discrepancy's cross-validation (48 members) on the 150,503 bundled rows at once
# peaked at 7.5 GB RSS in predict and 2.3 GB in _training_data (issue 40, the demo's 10 GB);
# 8,192 rows keep them near 0.1 GB a layer. Rows are independent: the values do not change.
ROW_CHUNK = 8192


def _by_rows(fn, *rows, chunk: int = ROW_CHUNK):
    """``fn(*rows)`` whose every output has the members first and the rows second, in
    passes of ``chunk`` rows (``jax.lax.map``, traceable and differentiable); the last
    pass is padded by repeating the last row, and the padding cut off."""
    n = rows[0].shape[0]
    if n <= chunk:
        return fn(*rows)
    k = -(-n // chunk)

    def split(a):
        a = jnp.concatenate([a, jnp.repeat(a[-1:], k * chunk - n, axis=0)])
        return a.reshape(k, chunk, *a.shape[1:])

    out = jax.lax.map(lambda xs: fn(*xs), tuple(split(a) for a in rows))  # [k, members, chunk, ...]
    return jax.tree.map(lambda o: jnp.moveaxis(o, 0, 1).reshape(o.shape[1], k * chunk, *o.shape[3:])[:, :n], out)


@stored_jit
def _predict(model: Ensemble, design, h_mm, p_pa):
    """All members at all points: vmap over points inside vmap over stacked members, in
    passes of :data:`ROW_CHUNK` rows."""
    points = eqx.filter_vmap(model._member, in_axes=(None, None, 0, 0, 0))
    members = eqx.filter_vmap(points, in_axes=(eqx.if_array(0), eqx.if_array(0), None, None, None))
    out = _by_rows(lambda d, h, p: members(model.trainable, model.prior, d, h, p), design, h_mm, p_pa)
    return out.astype(jnp.result_type(float))


@eqx.filter_jit
def _nets(cfg: EnsembleConfig, keys) -> "ForceNet":
    # one compiled program (cfg static): eagerly, every layer's initialiser compiled its own
    # small program (~21 jax.random programs a demo, issue 40); the weights are bit-identical
    return eqx.filter_vmap(lambda k: ForceNet(cfg, k))(keys)


def init_ensemble(cfg: EnsembleConfig, norm: Normaliser, key, beta: float | None = None) -> Ensemble:
    """Random initial ensemble: trainable and prior nets, each stacked over members."""
    kt, kp = jax.random.split(key)
    trainable = _nets(cfg, jax.random.split(kt, cfg.n_members))
    prior = _nets(cfg, jax.random.split(kp, cfg.n_members))
    return Ensemble(trainable, prior, norm, float(cfg.beta if beta is None else beta), cfg)


# --------------------------------------------------------------------------- training
@functools.lru_cache(maxsize=32)
def _optimiser(cfg: EnsembleConfig):
    """Adam on the authors' exponentially decaying learning rate (cached: one compile per config)."""
    schedule = optax.exponential_decay(
        cfg.lr, transition_steps=cfg.lr_decay_steps, decay_rate=cfg.lr_decay, end_value=cfg.lr_min
    )
    return optax.adam(schedule)


def _loss(trainable, static_model, data, idx):
    """Sum over members of the weighted Huber loss on each member's own minibatch.

    ``data`` = (features, prior outputs [members, n], F / s_F, weights [members, n]): the features and
    the frozen priors' outputs do not change in training, so they are computed once per fit
    (the prior's forward pass would otherwise cost a quarter of every step). ``idx``
    [members, batch]; the members' parameters are disjoint, so the gradient of the sum is
    every member's own gradient (Adam is element-wise: one optimiser state serves all).
    """
    feats, prior_out, f, w = data
    delta = static_model.config.huber_delta_n / static_model.norm.f_scale

    def member_loss(net, prior_row, w_row, rows):
        x = jax.tree.map(lambda a: a[rows], feats)
        pred = jax.vmap(net)(*x) + prior_row[rows]
        err = optax.huber_loss(pred, f[rows], delta=delta)
        return jnp.mean(w_row[rows] * err)

    losses = eqx.filter_vmap(member_loss)(trainable, prior_out, w, idx)
    return losses.sum(), losses


@eqx.filter_jit
def _training_data(model: Ensemble, design, h, p, f, w):
    """Normalised features of every row and the frozen priors' scaled outputs [members, n]."""
    feats = jax.vmap(_features, in_axes=(None, 0, 0, 0))(model.norm, design, h, p)
    prior_all = _by_rows(lambda *x: eqx.filter_vmap(lambda net: jax.vmap(net)(*x))(model.prior), *feats)
    return feats, model.beta * prior_all, f / model.norm.f_scale, w


@eqx.filter_jit
def _train_chunk(trainable, opt_state, static_model, data, key, n_steps: int, optimiser):
    """``n_steps`` Adam steps of all members at once (``lax.scan``); returns member losses."""
    n, m, b = data[2].shape[0], static_model.config.n_members, static_model.config.batch
    params, static = eqx.partition(trainable, eqx.is_inexact_array)

    def step(carry, k):
        params, opt_state = carry
        idx = jax.random.randint(k, (m, b), 0, n)
        grads, losses = jax.grad(lambda q: _loss(eqx.combine(q, static), static_model, data, idx), has_aux=True)(params)
        updates, opt_state = optimiser.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), losses

    (params, opt_state), losses = jax.lax.scan(step, (params, opt_state), jax.random.split(key, n_steps))
    return eqx.combine(params, static), opt_state, losses[-1]


def fit_ensemble(
    config: EnsembleConfig,
    design,
    h_mm,
    p_pa,
    force_n,
    weight=None,
    *,
    member_weight=None,
    key=None,
    progress: bool = True,
) -> Ensemble:
    """Fit an RPN ensemble (Osband et al. 2018) to points ``(design, h, p) -> F``.

    ``design`` [n, 6] mm (NaN = no ring), ``h_mm`` [n], ``p_pa`` [n] (>= 0 for the
    monotone head), ``force_n`` [n] N, ``weight`` [n] per-sample weights (normalised to
    mean 1; default equal). ``member_weight`` [members, n] (>= 0, optional) multiplies the
    weights member by member: members that never see some rows (weight 0) are held-out
    fits sharing one compiled training run, e.g. every fold of a cross-validation at once.
    ``key``: a ``jax.random`` key or an int seed (default 0).
    """
    enable_x64()  # float64 physics: mfdesign._x64
    design, h, p, f, w = check_inputs(design, h_mm, p_pa, force_n, weight)
    if config.monotone and np.any(p < 0):
        raise ValueError("the monotone head needs pressures p_pa >= 0")
    w = np.ones_like(f) if w is None else w
    if w.sum() <= 0:
        raise ValueError("weights sum to zero: nothing to fit")
    w = np.broadcast_to(w, (config.n_members, len(w)))
    if member_weight is not None:
        mw = np.asarray(member_weight, dtype=np.float64)
        if mw.shape != w.shape or not np.all(np.isfinite(mw)) or np.any(mw < 0):
            raise ValueError(f"member_weight must be finite, >= 0, of shape {w.shape} (members, rows), got {mw.shape}")
        w = w * mw
        if np.any(w.sum(1) <= 0):
            raise ValueError("a member's weights sum to zero: it has nothing to fit")
    w = w / w.mean(1, keepdims=True)
    key = jax.random.PRNGKey(0 if key is None else key) if isinstance(key, (int, type(None))) else key
    k_init, k_train = jax.random.split(key)
    norm = Normaliser.fit(design, h, p, f)
    model = init_ensemble(config, norm, k_init)
    dt = jnp.dtype(config.dtype)
    model = eqx.tree_at(lambda m: m.norm, model, jax.tree.map(lambda a: a.astype(dt), norm))
    data = _training_data(model, *(jnp.asarray(a, dtype=dt) for a in (design, h, p, f, w)))
    optimiser = _optimiser(config)
    trainable = model.trainable
    opt_state = optimiser.init(eqx.filter(trainable, eqx.is_inexact_array))
    done, keys = 0, jax.random.split(k_train, max(1, -(-config.steps // config.chunk)))
    with tqdm(total=config.steps, desc="ensemble fit", unit="step", disable=not progress) as bar:
        for k in keys:
            n_steps = min(config.chunk, config.steps - done)
            if n_steps <= 0:
                break
            trainable, opt_state, losses = _train_chunk(trainable, opt_state, model, data, k, n_steps, optimiser)
            done += n_steps
            bar.update(n_steps)
            bar.set_postfix(loss=f"{float(losses.mean()):.4g}")
    model = eqx.tree_at(lambda m: m.trainable, model, trainable)
    return eqx.tree_at(lambda m: m.norm, model, norm)
