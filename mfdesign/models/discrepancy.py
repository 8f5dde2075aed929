"""The sim-to-real discrepancy delta of the multi-fidelity model, and what it knows it does not know.

An ensemble fitted to the residuals of a few membranes has no reason to be right on a
membrane it never saw: on the real rig's seven membranes an ungated discrepancy made
held-out membranes worse than the calibrated physics alone (issue 5: folds 3 and 4 by
4-8 N; issue 18: pooled 7.9 vs 5.9 N). Here delta is read as a Gaussian-process-like
posterior around the training membranes (Kennedy & O'Hagan 2001 use a GP; the ensemble
carries the shape near the data)::

    delta_s(x) = g(x) delta_m(s)(x) + sqrt(1 - g(x)^2) sigma (p / p_ref) z_s(design)
    g(x)       = exp(-d(x)^2 / (2 l^2)),   d = distance to the nearest training membrane

* ``delta_m`` is member ``m`` of the RPN ensemble (all training membranes);
* ``d`` is measured in :func:`~mfdesign.design.membrane_features` (1 = a feature over its
  whole product range, or one ring more); at a training membrane ``g = 1``;
* far from every training membrane the mean shrinks to zero (the calibrated physics) and
  the spread grows to ``sigma``, the discrepancy's prior scale;
* ``z_s`` is a draw of a unit Gaussian process over the design features with the same
  length scale ``l`` (random Fourier features, Rahimi & Recht 2007): one smooth random
  offset per posterior draw, correlated between nearby designs, constant over h;
  drawn in antithetic pairs, so that the predictive mean is not moved by them;
* no pressure, no force, on the rig as in the simulator: delta is 0 at ``p = 0`` (the
  ensemble has no constant term, the prior term grows as ``p / p_ref`` with ``p_ref`` the
  training rows' RMS pressure, so ``sigma`` is the spread at a typical pressure).

``l`` and ``sigma`` come from the training data by leave-one-membrane-out (beyond
:data:`GATE_FOLDS` membranes, folds of several: every K-th membrane)
(:func:`fit_gated`): every fold's ensemble is trained at once, with the full one
(``member_weight`` masks the held-out membranes), ``l`` is the shortest candidate whose held-out mean square of the
residual is within one standard error of the best, the error of the paired difference
over the held-out membranes (``0``: no transfer between membranes, a reference row;
``inf``: the ungated ensemble), and
``sigma^2`` the held-out excess variance per unit of ``1 - g^2`` (method of moments).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from mfdesign._x64 import enable_x64
from mfdesign.design import membrane_features
from mfdesign.models.ensemble import Ensemble

__all__ = ["LENGTHS", "Discrepancy", "fit_gated"]

# Candidate length scales (feature units). 0: the discrepancy stays on its own membranes;
# inf: the ensemble everywhere (the model before the gate).
LENGTHS = (0.0, 0.05, 0.1, 0.2, 0.35, 0.5, 0.75, 1.0, 1.5, 2.5, math.inf)
TIE_REL = 0.005  # held-out RMSEs this close are a tie (in words: "about zero")
N_FEATURES_RFF = 128  # random Fourier features of the prior draw z_s
GATE_FILE = "gate.json"
# Folds of the gate's cross-validation at most: membranes beyond this many share folds
# (round-robin over their ids, so a fold holds every K-th membrane), as Campbell et al. 2025
# cross-validated 22 membranes 11-fold. Every fold is M ensemble members trained at once:
# leave-one-membrane-out on a round of 22 membranes trained 23 x 8 = 184 members, 2.5 x the
# time of 12 x 8 (~33-37 against ~80 training steps/s on 2 cores; issue 40).
GATE_FOLDS = 11


class Discrepancy(eqx.Module):
    """Gated discrepancy (module docstring): ``ensemble`` (an RPN
    :class:`~mfdesign.models.ensemble.Ensemble` of the residuals [N]), ``anchors`` [K, 6]
    the training membranes (mm), ``length`` the gate's length scale (feature units; inf =
    no gate), ``sigma_n`` the prior scale [N] at ``p_ref_pa`` [Pa], ``report`` the
    selection's figures."""

    ensemble: Ensemble
    anchors: jax.Array
    length: float = eqx.field(static=True)
    sigma_n: float = eqx.field(static=True)
    report: tuple = eqx.field(static=True, default=())
    p_ref_pa: float = eqx.field(static=True, default=0.0)  # 0: prior term constant in p (gates before it)

    def gate(self, design) -> jax.Array:
        """``g`` [N] in [0, 1] at design rows [N, 6] mm (1 at a training membrane)."""
        f = membrane_features(design)
        a = membrane_features(self.anchors)
        d2 = jnp.min(jnp.sum((f[:, None, :] - a[None, :, :]) ** 2, -1), axis=1)
        if math.isinf(self.length):
            return jnp.ones_like(d2)
        if self.length == 0.0:
            return (d2 < 1e-12).astype(d2.dtype)
        return jnp.exp(-0.5 * d2 / self.length**2)

    def mean(self, design, h_mm, p_pa) -> jax.Array:
        """The discrepancy's mean [N] in N (the gated ensemble mean)."""
        return self.gate(design) * jnp.mean(self.ensemble.predict(design, h_mm, p_pa), axis=0)

    def draws(self, design, h_mm, p_pa, n_draws: int, key) -> jax.Array:
        """``delta_s`` [n_draws, N] in N at rows ``design`` [N, 6] mm, ``h_mm``, ``p_pa``:
        draw ``s`` takes ensemble member ``s mod M`` (module docstring). Traceable."""
        members = self.ensemble.predict(design, h_mm, p_pa)
        g = self.gate(design)
        out = g * members[jnp.arange(n_draws) % members.shape[0]]
        if self.sigma_n > 0 and not math.isinf(self.length):
            scale = jnp.sqrt(jnp.clip(1 - g**2, 0.0, 1.0)) * self.sigma_n
            if self.p_ref_pa > 0:
                scale = scale * jnp.asarray(p_pa) / self.p_ref_pa
            out = out + scale * self._prior_draws(design, n_draws, key)
        return out

    def _prior_draws(self, design, n_draws, key) -> jax.Array:
        """Unit-variance GP draws [n_draws, N] over the design features (random Fourier
        features of a squared-exponential kernel with the gate's length scale)."""
        k_w, k_b, k_a = jax.random.split(key, 3)
        ell = max(self.length, 1e-3)
        f = membrane_features(design)
        omega = jax.random.normal(k_w, (N_FEATURES_RFF, f.shape[-1]), f.dtype) / ell
        phase = jax.random.uniform(k_b, (N_FEATURES_RFF,), f.dtype, 0.0, 2 * jnp.pi)
        phi = jnp.sqrt(2.0 / N_FEATURES_RFF) * jnp.cos(f @ omega.T + phase)  # [N, F]
        # antithetic pairs (a, -a): the draws' mean is exactly zero for an even count, so
        # the predictive mean far from the data IS the calibrated physics (32 independent
        # draws of a 3 N spread would move it by ~0.5 N per design)
        half = jax.random.normal(k_a, ((n_draws + 1) // 2, N_FEATURES_RFF), f.dtype)
        a = jnp.concatenate([half, -half])[:n_draws]
        return a @ phi.T

    def save(self, path) -> Path:
        """``path/ensemble.*`` (the ensemble) and ``path/gate.json`` (anchors, length, sigma)."""
        from mfdesign import outputs

        path = Path(path)
        self.ensemble.save(path)
        outputs.write_json(
            path / GATE_FILE,
            {
                "kind": "gated_discrepancy",
                "anchors_mm": np.asarray(self.anchors).tolist(),
                "length": None if math.isinf(self.length) else self.length,
                "sigma_n": self.sigma_n,
                "p_ref_pa": self.p_ref_pa,
                "report": [dict(r) for r in self.report],
            },
        )
        return path

    @classmethod
    def load(cls, path) -> "Discrepancy":
        """Read :meth:`save`'s folder. A folder without ``gate.json`` (fits before the gate)
        loads as the ungated ensemble, as it was fitted. Raises ``InputError`` on a
        malformed gate file."""
        from mfdesign.errors import InputError

        path = Path(path)
        ens = Ensemble.load(path)
        gate = path / GATE_FILE
        if not gate.is_file():
            return cls(ens, jnp.full((1, 6), jnp.nan), math.inf, 0.0)
        try:
            meta = json.loads(gate.read_text())
            anchors = np.asarray(meta["anchors_mm"], dtype=np.float64).reshape(-1, 6)
            length = math.inf if meta["length"] is None else float(meta["length"])
            sigma = float(meta["sigma_n"])
            p_ref = float(meta.get("p_ref_pa", 0.0))  # absent: a gate fitted before the pressure scaling
            report = tuple(tuple(sorted(r.items())) for r in meta.get("report", []))
        except (ValueError, KeyError, TypeError) as err:
            raise InputError(f"{gate} is not a valid gate file ({err!r}); rerun mfdesign fit-mf") from None
        if not (
            len(anchors) and length >= 0 and math.isfinite(sigma) and sigma >= 0 and math.isfinite(p_ref) and p_ref >= 0
        ):
            raise InputError(
                f"{gate}: length {length}, sigma_n {sigma}, p_ref_pa {p_ref}, {len(anchors)} anchors; "
                "allowed: length >= 0 or null, sigma_n >= 0, p_ref_pa >= 0, at least one anchor"
            )
        return cls(ens, jnp.asarray(anchors), length, sigma, report, p_ref)

    def selection(self) -> list[dict]:
        """The leave-one-membrane-out table behind ``length``: one dict per candidate."""
        return [dict(r) for r in self.report]

    def describe(self) -> str:
        """One sentence: how far the discrepancy reaches beyond its training membranes."""
        rows = {r.get("length"): r for r in self.selection() if "heldout_rmse_n" in r}
        if math.isinf(self.length):
            if not rows:
                return "discrepancy ungated (too few membranes to hold one out): it extrapolates to new designs"
            if rows[None]["heldout_rmse_n"] >= rows[0.0]["heldout_rmse_n"] * (1 - TIE_REL):
                return (
                    "discrepancy about zero: held-out membranes are predicted alike with or without it "
                    f"({rows[None]['heldout_rmse_n']:.2f} N RMS)"
                )
            return (
                "discrepancy ungated: it transfers to held-out membranes "
                f"(held-out RMSE {rows[None]['heldout_rmse_n']:.2f} N vs {rows[0.0]['heldout_rmse_n']:.2f} N without it)"
            )
        cv = rows.get(self.length)
        extra = (
            f", held-out RMSE {cv['heldout_rmse_n']:.2f} N (ungated {rows[None]['heldout_rmse_n']:.2f} N, "
            f"none {rows[0.0]['heldout_rmse_n']:.2f} N)"
            if cv and None in rows and 0.0 in rows
            else ""
        )
        return (
            f"discrepancy gated: length {self.length:g} (design-feature units), prior spread "
            f"{self.sigma_n:.2f} N for a membrane far from the training ones{extra}"
        )


def _one_se_choice(mse, per_membrane) -> int:
    """Index into :data:`LENGTHS` of the gate's length, from the pooled held-out mean squares
    ``mse`` [lengths] and the per-membrane ones ``per_membrane`` [lengths, membranes] N^2.

    One-standard-error rule (Breiman et al. 1984; Hastie, Tibshirani & Friedman 2009,
    sec. 7.10): the least transfer (shortest length > 0) whose held-out mean square is
    within one standard error of the best. Six or seven membranes rank lengths noisily: a
    transfer must win clearly to be kept (on the real rig's data a 1 % inner gain picked a
    transfer that hurt the held-out membrane). The error is that of the paired difference
    over the held-out membranes: every length is scored on the same ones, and the spread of
    their own difficulty is no evidence against a transfer (one extreme membrane at 18 N^2
    made any length "within one SE" of a transfer that won on 8 of 10, and a campaign's
    round kept no transfer at 1.01 N against 0.65 N; issue 41)."""
    mse, pm = np.asarray(mse, float), np.asarray(per_membrane, float)
    top = int(np.argmin(mse))
    se = np.nan_to_num(np.std(pm - pm[top], axis=1, ddof=1) / math.sqrt(pm.shape[1]))
    within = [i for i, ell in enumerate(LENGTHS) if ell > 0 and mse[i] - mse[top] <= se[i]]
    # no transfer at all the best, and clearly (every length > 0 worse by more than its
    # error): the least transfer there is
    return min(within) if within else next(i for i, ell in enumerate(LENGTHS) if ell > 0)


def _fit_with_folds(config, design, h_mm, p_pa, r, w, row_fold, n_folds, key, progress):
    """The full ensemble and every cross-validation fold's, in ONE training run of
    ``(K + 1) M`` members: block 0 sees every row (weight 1), block ``j + 1`` is blind to
    the rows of fold ``j`` (``row_fold`` [n] in 0..K-1). Members train independently
    (their own minibatches, Adam element-wise), so block 0 is an ordinary M-member fit;
    one shape compiles once, where two runs of M and K M members compiled every training
    program twice (issue 40: ``_nets``, ``_train_chunk``, ``_training_data``, ~12 s a cold
    demo). Returns the full ensemble (M members) and the blocks' mean predictions
    [K + 1, n] N at the rows."""
    from mfdesign.models.ensemble import fit_ensemble

    m = config.n_members
    seen = np.concatenate([np.ones((1, len(r))), row_fold[None, :] != np.arange(n_folds)[:, None]])
    mask = np.repeat(seen.astype(float), m, axis=0)  # [(K + 1) M, n]
    both_cfg = dataclasses.replace(config, n_members=m * (n_folds + 1))
    both = fit_ensemble(both_cfg, design, h_mm, p_pa, r, w, member_weight=mask, key=key, progress=progress)
    pred = np.asarray(both.predict(design, h_mm, p_pa)).reshape(n_folds + 1, m, -1).mean(1)
    return both.subset(0, m), pred


def fit_gated(config, design, h_mm, p_pa, resid_n, weight, membrane, noise_n=None, *, key=0, progress=False):
    """Fit the gated discrepancy to residuals ``resid_n`` [n] N at rows (``design`` [n, 6]
    mm, ``h_mm``, ``p_pa``), ``weight`` [n], ``membrane`` [n] integer ids of the rows'
    membranes.

    One ensemble on every row (the discrepancy near the data). With three or more
    membranes, the same training run also holds ``K x M`` members, member block ``j`` blind
    to membrane ``j`` (leave-one-membrane-out; one run, one compile: :func:`_fit_with_folds`;
    with more than :data:`GATE_FOLDS` membranes, ``K = GATE_FOLDS`` folds, fold ``j``
    holding out every membrane whose index is ``j`` modulo ``K``, and a row's gate distance
    is to the nearest membrane its fold saw): each candidate of
    :data:`LENGTHS` is scored by the held-out RMSE of ``resid - g delta_j``; the shortest
    length within one standard error of the best wins (the one-standard-error rule, on the
    membranes' paired differences to the best), and
    ``sigma^2 = sum(w ((r - g delta_j)^2 - noise^2)) / sum(w (1 - g^2) (p / p_ref)^2)`` (>= 0)
    with ``noise`` the within-membrane residual scale after the full ensemble (or
    ``noise_n``). The ensemble has no constant term (``config.intercept`` is set False):
    delta(p = 0) = 0. With fewer membranes nothing can be held out: ``length`` = inf (the
    ensemble everywhere), said in the report.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    from mfdesign.models.ensemble import fit_ensemble

    # no pressure, no force, on the rig as in the simulator: the discrepancy is 0 at p = 0 (a
    # constant term would invent force at rest, +24 N at h = 50 mm on a known membrane)
    config = dataclasses.replace(config, intercept=False)
    design = np.asarray(design, np.float64)
    r, w = np.asarray(resid_n, np.float64), np.asarray(weight, np.float64)
    membrane = np.asarray(membrane)
    p = np.asarray(p_pa, np.float64)
    p_ref = float(np.sqrt(np.average(p**2, weights=w)))
    shape2 = (p / p_ref) ** 2 if p_ref > 0 else np.ones_like(p)  # the prior term's variance grows as p^2
    ids = np.unique(membrane)
    first = np.array([np.flatnonzero(membrane == i)[0] for i in ids])
    anchors = design[first]
    k0, _ = jax.random.split(jax.random.PRNGKey(key) if isinstance(key, int) else key)
    if len(ids) < 3:
        full = fit_ensemble(config, design, h_mm, p_pa, r, w, key=k0, progress=progress)
        report = ({"length": None, "note": f"{len(ids)} membrane(s): nothing to hold out, no gate"},)
        return Discrepancy(
            full, jnp.asarray(anchors), math.inf, 0.0, tuple(tuple(sorted(x.items())) for x in report), p_ref
        )
    row_membrane = np.searchsorted(ids, membrane)
    n_folds = min(len(ids), GATE_FOLDS)
    membrane_fold = np.arange(len(ids)) % n_folds  # one membrane a fold up to GATE_FOLDS
    row_fold = membrane_fold[row_membrane]
    full, pred = _fit_with_folds(config, design, h_mm, p_pa, r, w, row_fold, n_folds, k0, progress)
    if noise_n is None:
        noise_n = float(np.sqrt(np.average((r - pred[0]) ** 2, weights=w)))
    d_held = pred[1:][row_fold, np.arange(len(r))]  # each row by the fold blind to its membrane
    feats = np.asarray(membrane_features(design))
    fa = np.asarray(membrane_features(anchors))
    d2 = np.sum((feats[:, None, :] - fa[None, :, :]) ** 2, -1)
    # the nearest membrane its fold saw: not its own, nor one held out beside it
    d2[row_fold[:, None] == membrane_fold[None, :]] = np.inf
    d2 = d2.min(1)
    rows, per_membrane = [], []
    for ell in LENGTHS:
        g = np.ones_like(d2) if math.isinf(ell) else (np.zeros_like(d2) if ell == 0 else np.exp(-0.5 * d2 / ell**2))
        e2 = (r - g * d_held) ** 2
        rmse = float(np.sqrt(np.average(e2, weights=w)))
        room = float(np.sum(w * (1 - g**2) * shape2))
        s2 = float(np.sum(w * (e2 - noise_n**2)) / room) if room > 1e-9 * w.sum() else 0.0
        rows.append(
            {"length": None if math.isinf(ell) else ell, "heldout_rmse_n": rmse, "sigma_n": math.sqrt(max(s2, 0.0))}
        )
        per_membrane.append([np.average(e2[row_membrane == j], weights=w[row_membrane == j]) for j in range(len(ids))])
    best = _one_se_choice(np.array([r_["heldout_rmse_n"] ** 2 for r_ in rows]), np.asarray(per_membrane))
    ell = LENGTHS[best]
    sigma = rows[best]["sigma_n"] if not math.isinf(ell) else 0.0
    for i, x in enumerate(rows):
        x["chosen"] = i == best
    report = tuple(tuple(sorted(x.items())) for x in rows)
    return Discrepancy(full, jnp.asarray(anchors), ell, sigma, report, p_ref)
