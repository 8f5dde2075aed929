"""The default moves of the calibration (adaptation rounds of independence proposals mixed
with differential evolution) mix a near-Gaussian posterior of ~30 parameters: the 22
membranes' round (28 parameters) ran at acceptance 0.07-0.09 and tau ~25-40 with one
refit of a 5-dof Student-t, 14 tau in 2000 steps (issue 40)."""

import emcee
import jax.numpy as jnp
import numpy as np

from mfdesign.calibration import mcmc

DIM, WALKERS, AFTER = 30, 62, 200


def _target(seed: int = 0):
    """A Gaussian with a non-diagonal covariance (correlations up to ~0.9, scales over two
    decades) and a Laplace approximation that misjudges it (half the widths' curvature)."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.standard_normal((DIM, DIM)))
    eig = np.geomspace(0.02, 1.0, DIM)  # the smallest like the round's 0.009-0.03
    corr = q @ np.diag(eig) @ q.T
    s = np.sqrt(np.diag(corr))
    corr /= np.outer(s, s)
    sd = np.geomspace(0.01, 1.0, DIM)
    cov = corr * np.outer(sd, sd)
    mean = rng.standard_normal(DIM)
    prec = np.linalg.inv(cov)
    widen = np.diag(np.r_[np.ones(6), np.full(DIM - 6, 1 / 2.0)])  # latents' Laplace sd 2x (as on the round)
    laplace = mcmc.MapResult(
        jnp.asarray(mean + 0.3 * sd), jnp.asarray(mean), jnp.asarray(0.0), jnp.asarray(widen @ prec @ widen), True
    )
    return mean, cov, prec, laplace


def test_default_moves_mix_a_correlated_30_dimensional_gaussian():
    mean, cov, prec, laplace = _target()

    def log_p(x):
        r = x - mean
        return -0.5 * np.einsum("ij,jk,ik->i", r, prec, r)

    backend = emcee.backends.Backend()
    backend.reset(WALKERS, DIM)
    start = mcmc._laplace_start(laplace, WALKERS, np.random.default_rng(1))
    # the schedule of calibrate: walkers drawn from the Laplace approximation, round 1 with
    # its independence proposal, each later round
    # refitted to the round before, then the last refit fixed
    moves, begin = mcmc.default_moves(laplace), 0
    for end in mcmc.ADAPT_ROUNDS:
        sampler = emcee.EnsembleSampler(WALKERS, DIM, log_p, vectorize=True, backend=backend, moves=moves)
        if begin == 0:
            sampler.random_state = np.random.RandomState(0).get_state()
        sampler.run_mcmc(start, end - begin, progress=False)
        start = sampler.get_last_sample()
        moves = mcmc.adapted_moves(backend.get_chain(discard=begin, flat=True))
        begin = end
    sampler = emcee.EnsembleSampler(WALKERS, DIM, log_p, vectorize=True, backend=backend, moves=moves)
    sampler.run_mcmc(start, AFTER, progress=False)

    chain = backend.get_chain(discard=mcmc.ADAPT_STEPS)
    acc = np.mean(np.any(chain[1:] != chain[:-1], axis=2))  # a walker moves iff accepted
    assert 0.2 <= acc <= 0.9, acc
    tau = emcee.autocorr.integrated_time(chain, tol=0, quiet=True)
    # 50 tau within the 2000-step ceiling with room (the old moves: tau 35-40 on this kind of target)
    assert np.max(tau) < 12, tau
    draws = chain.reshape(-1, DIM)
    sd = np.sqrt(np.diag(cov))
    np.testing.assert_allclose(np.std(draws, 0) / sd, 1.0, atol=0.12)
    np.testing.assert_allclose((np.mean(draws, 0) - mean) / sd, 0.0, atol=0.12)
    corr = np.corrcoef(draws.T)
    assert np.max(np.abs(corr - cov / np.outer(sd, sd))) < 0.12


def test_adapted_proposal_dof_and_scale_follow_dimension():
    moves = mcmc.adapted_moves(np.random.default_rng(0).standard_normal((500, 12)))
    lap = moves[0][0]
    assert lap.df == mcmc.adapted_df(12) == 24.0 and abs(moves[0][1] - mcmc.ADAPTED_SHARE) < 1e-12
    assert abs(sum(w for _, w in moves) - 1.0) < 1e-12
    # a covariance that is not positive definite leaves differential evolution alone
    flat = mcmc.adapted_moves(np.ones((50, 3)))
    assert all(type(m).__name__.startswith("DE") for m, _ in flat)
