"""``calibration.workflow.for_table``: a fit's predictive where it meets a table's rows.

A campaign saves its rounds for design searches, on the emulator; a held-out check of a
membrane the fit never saw must run on that membrane's own simulator planes (issue 41: on
the campaign's test membranes the emulator was 0.45 N off the truth, the planes 0.05 N).
Here a small fit (on the stand-in, cheap) is moved onto exact physics for a new membrane:
its force model must hold that membrane's planes, cover every posterior draw, and give what
the simulator gives there at those draws."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from mfdesign.design import Membrane
from mfdesign.physics.solve import force_at

CALIBRATED = "[2.0, 25.4, nan, nan, nan, nan]"
NEW = "[1.75, 32.0, nan, nan, nan, nan]"


def _table(keys, seed):
    from mfdesign.models.standin import standin_plane
    from mfdesign.rig.virtual import Protocol, VirtualRig

    protocol = Protocol(sample_hz=0.2, trials_per_height=1, heights_mm=(10.0, 40.0))
    rig = VirtualRig(seed=seed, protocol=protocol, simulator=standin_plane)
    return rig.run([Membrane.from_key(k) for k in keys], lift=False, progress=False)


@pytest.mark.slow  # a minute or two of simulator planes on 2 cores
def test_a_fit_predicts_a_new_membrane_on_its_own_planes(tmp_path, monkeypatch):
    monkeypatch.setenv("MFDESIGN_CACHE_DIR", str(tmp_path))  # planes of this test only
    from mfdesign.calibration.workflow import fit_multi_fidelity, for_table, force_model_named
    from mfdesign.models.ensemble import EnsembleConfig
    from mfdesign.models.exact import ExactForceModel

    train, new = _table([CALIBRATED], 1), _table([NEW], 2)
    fit = fit_multi_fidelity(
        train,
        force_model_named("standin"),
        n_steps=60,
        n_walkers=16,
        max_rows=80,
        ensemble_config=EnsembleConfig(n_members=2, steps=10, monotone=False),
        progress=False,
        stop_when_converged=False,
    )
    assert for_table(fit, new, "standin") is fit.mf  # physics that holds every design: the fit's own
    mf = for_table(fit, new, "exact")
    fm = mf.model.force_model
    assert isinstance(fm, ExactForceModel) and {CALIBRATED, NEW} <= set(fm.design_keys)
    data = mf.data_for(None, None, None, table=new)
    draws = np.asarray(mf.sample_data(data, 0))
    assert np.all(np.isfinite(draws))  # every posterior draw inside the lattice at every row
    # at the posterior median, the new membrane's rows are the simulator's own forces there
    # (within the lattice's interpolation: tests/calibration/test_effect_axes.py allows 0.15 N)
    import jax

    x = np.median(np.asarray(mf.theta), axis=0)
    params = mf.model.sim_params(jnp.asarray(x), data)
    pick = np.linspace(0, len(data) - 1, 8).astype(int)
    one = jax.tree.map(lambda a: float(np.asarray(a).reshape(-1)[pick[0]]), params)  # one membrane: one row's
    h, p = np.asarray(data.rows.h_mm)[pick], np.asarray(data.rows.p_pa)[pick]
    got = np.asarray(fm(jnp.asarray(np.asarray(data.design)[pick]), jnp.asarray(h), jnp.asarray(p), one))
    ref = np.asarray(force_at(Membrane.from_key(NEW), h, p, one).force_n)
    ok = np.isfinite(ref)
    assert ok.sum() >= 6 and np.all(np.isfinite(got[ok]))
    assert np.max(np.abs(got[ok] - ref[ok])) <= 0.15, got - ref
