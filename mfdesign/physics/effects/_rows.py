"""The rows a jitted log-likelihood sees (JAX arrays, one per recorded row)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd


__all__ = ["Rows"]


class Rows(eqx.Module):
    """Observation context of N recorded rows for a jitted likelihood (all arrays ``[N]``).

    * ``h_mm``, ``p_pa``: the RECORDED plate height [mm] and gauge pressure [Pa];
    * ``is_force``: True for a force trial (the force column is a load-cell reading),
      False for a mass lift (the force column is the known weight ``m g`` [N]);
    * ``is_deflate``: the row was recorded while deflating;
    * ``is_first_trial``: the row belongs to the membrane's first trial (trial id 0);
    * ``membrane``: int index of the row's membrane (into a list of design keys).

    Mass-lift rows enter the likelihood as force samples, as the paper does: the plate is
    in equilibrium at the recorded ``(h, p)``, so the membrane's force there equals the
    weight ``W``; ``expected force = W`` is the observation. Per effect: pressure_sensor
    acts on both kinds (the same transducer); load_cell_offset and rig_compliance only on
    force rows (a lift reads no load cell, and the free plate does not load the frame);
    hysteresis on deflating rows of both kinds (see :class:`Hysteresis`).
    """

    h_mm: jax.Array
    p_pa: jax.Array
    is_force: jax.Array
    is_deflate: jax.Array
    is_first_trial: jax.Array
    membrane: jax.Array

    @classmethod
    def from_measurements(cls, table, design_keys=None) -> "Rows":
        """Rows of a :class:`~mfdesign.data.measurements.Measurements` (membrane index into
        ``design_keys``, default the table's own order)."""
        df = table if isinstance(table, pd.DataFrame) else table.df
        keys = list(design_keys) if design_keys is not None else list(dict.fromkeys(df["design_key"]))
        index = {k: i for i, k in enumerate(keys)}
        missing = sorted(set(df["design_key"]) - set(index))
        if missing:
            raise KeyError(f"Rows: membranes {missing} not among design_keys {keys}")
        return cls(
            h_mm=jnp.asarray(df["height_mm"].to_numpy(float)),
            p_pa=jnp.asarray(df["pressure_pa"].to_numpy(float)),
            is_force=jnp.asarray(df["experiment"].to_numpy() == "force"),
            is_deflate=jnp.asarray(df["phase"].to_numpy() == "deflate"),
            is_first_trial=jnp.asarray(df["trial"].to_numpy() == 0),
            membrane=jnp.asarray(df["design_key"].map(index).to_numpy(np.int32)),
        )

    def __len__(self) -> int:
        return int(self.h_mm.shape[0])

    def take(self, idx) -> "Rows":
        """The rows at integer positions ``idx``."""
        return jax.tree.map(lambda a: a[idx], self)
