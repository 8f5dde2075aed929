"""Small untrained models shared by tests (import as ``from tiny_models import ...``)."""

import jax
import numpy as np

from mfdesign.models.ensemble import EnsembleConfig, Normaliser, init_ensemble


def tiny_ensemble(members=3, seed=0):
    """An untrained RPN ensemble (``members`` members, 8-wide latent net) normalised on two designs."""
    design = np.array([[2.0, 25.4, np.nan, np.nan, np.nan, np.nan], [1.5, 30.0, 45.0, 6.0, 60.0, 5.0]])
    norm = Normaliser.fit(design, np.array([0.0, 40.0]), np.array([1e3, 8e3]), np.array([1.0, 30.0]))
    cfg = EnsembleConfig(n_members=members, latent_width=8, latent_depth=1, ring_embed_dim=4)
    return init_ensemble(cfg, norm, jax.random.PRNGKey(seed))
