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

__all__ = ["Posterior"]


@dataclasses.dataclass(frozen=True)
class Posterior:
    """Posterior of a :class:`~mfdesign.models.hierarchical.HierarchicalModel`.

    ``names``/``units`` of the parameters; ``samples`` [S, dim] physical values after
    burn-in and thinning; ``log_prob`` [S]; ``x_map`` [dim] physical MAP; ``log_lik_map``
    (weighted log-likelihood at the MAP); ``n_rows``; ``bic``; ``log_evidence_laplace``;
    ``convergence`` (dict, see :func:`mfdesign.calibrate.convergence_report`);
    ``design_keys`` (membrane order of the latents); ``effects``.
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
    # The force model the chain was sampled with (the exact model's lattice grows during
    # calibration); not saved: a reloaded posterior rebuilds its model from the data.
    force_model: Any = dataclasses.field(default=None, compare=False, repr=False)

    @property
    def dim(self) -> int:
        return len(self.names)

    def median(self) -> np.ndarray:
        return np.median(self.samples, axis=0)

    def derived(self) -> tuple[list[str], list[str], np.ndarray]:
        """Per-membrane relative thickness ``t_m = thickness_sd z_m`` [S, M] (if latent)."""
        if "thickness_sd" not in self.names:
            return [], [], np.zeros((len(self.samples), 0))
        sd = self.samples[:, self.names.index("thickness_sd")]
        k = self.names.index("z_thickness[0]")
        z = self.samples[:, k:k + len(self.design_keys)]
        names = [f"thickness_rel {key}" for key in self.design_keys]
        return names, ["1"] * len(names), sd[:, None] * z

    def summary(self) -> pd.DataFrame:
        """One row per parameter (and derived per-membrane thickness): unit, median, 5 / 95 %
        and 2.5 / 97.5 % quantiles, MAP."""
        d_names, d_units, d_samples = self.derived()
        keep = [i for i, n in enumerate(self.names) if not n.startswith("z_thickness")]
        names = [self.names[i] for i in keep] + d_names
        units = [self.units[i] for i in keep] + d_units
        samples = np.concatenate([self.samples[:, keep], d_samples], axis=1)
        x_map = list(self.x_map[keep])
        if d_names:
            sd = self.x_map[self.names.index("thickness_sd")]
            k = self.names.index("z_thickness[0]")
            x_map += list(sd * self.x_map[k:k + len(d_names)])
        q = np.quantile(samples, [0.5, 0.05, 0.95, 0.025, 0.975], axis=0)
        return pd.DataFrame({"parameter": names, "unit": units, "median": q[0], "q05": q[1], "q95": q[2],
                             "q025": q[3], "q975": q[4], "map": x_map})

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
            lines.append(f"{r.parameter:<44} {r.unit:>5} {r.median:>11.4g} {r.q05:>11.4g} {r.q95:>11.4g} {r.map:>11.4g}")
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        return {"parameters": self.summary().to_dict(orient="records"), "names": list(self.names),
                "units": list(self.units), "x_map": self.x_map.tolist(), "log_lik_map": self.log_lik_map,
                "n_rows": self.n_rows, "bic": self.bic, "log_evidence_laplace": self.log_evidence_laplace,
                "convergence": self.convergence, "design_keys": list(self.design_keys),
                "effects": list(self.effects), "n_samples": int(len(self.samples))}

    def save(self, path) -> Path:
        """``path.json`` (summary, diagnostics) and ``path.npz`` (samples), each written atomically."""
        from mfdesign import outputs

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with outputs.atomic_path(path.with_suffix(".npz")) as tmp:
            np.savez(tmp, samples=self.samples, log_prob=self.log_prob, x_map=self.x_map)
        outputs.write_json(path.with_suffix(".json"), self.to_json(), default=float)
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
                raise InputError(f"posterior file {f} is missing; allowed: posterior.json + posterior.npz "
                                 "as `mfdesign calibrate` writes them")
        try:
            meta = json.loads(js.read_text())
            if not isinstance(meta, dict):
                raise InputError(f"{js}: expected a JSON object, got {type(meta).__name__}")
            arrays = _read_npz_bounded(npz, ("samples", "log_prob", "x_map"))
            samples, log_prob, x_map = (np.asarray(arrays[k], dtype=np.float64) for k in ("samples", "log_prob", "x_map"))
            post = cls(tuple(map(str, meta["names"])), tuple(map(str, meta["units"])), samples, log_prob, x_map,
                       float(meta["log_lik_map"]), float(meta["n_rows"]), float(meta["bic"]),
                       float(meta["log_evidence_laplace"]), dict(meta["convergence"]),
                       tuple(map(str, meta["design_keys"])), tuple(map(str, meta["effects"])))
        except InputError:
            raise
        except Exception as err:  # noqa: BLE001 -- corrupt JSON / zip / npy fail in many ways
            raise InputError(f"{path}.json/.npz: not a readable posterior ({type(err).__name__}: "
                             f"{one_line(err, 200)}); allowed: the files `mfdesign calibrate` writes") from None
        dim = len(post.names)
        if (samples.ndim != 2 or samples.shape[1] != dim or len(samples) < 1 or log_prob.shape != (len(samples),)
                or x_map.shape != (dim,) or len(post.units) != dim):
            raise InputError(f"{path}: samples {samples.shape}, log_prob {log_prob.shape}, x_map {x_map.shape} and "
                             f"{dim} names / {len(post.units)} units do not fit; allowed: samples [S, dim], "
                             "log_prob [S], x_map [dim]")
        for name, a in (("samples", samples), ("x_map", x_map)):
            if not np.isfinite(a).all():
                raise InputError(f"{npz}: {int((~np.isfinite(a)).sum())} {name} values are NaN or infinite; "
                                 "allowed: finite parameters (rerun the calibration)")
        return post


def _read_npz_bounded(path: Path, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Arrays of an ``np.savez`` file, each header checked first: a corrupt header may
    declare a shape of terabytes, which ``np.load`` would allocate before reading."""
    import zipfile

    from mfdesign.errors import InputError

    limit = path.stat().st_size  # np.savez stores uncompressed: no array is larger than the file
    out = {}
    with zipfile.ZipFile(path) as z:
        for name in names:
            with z.open(f"{name}.npy") as fh:
                version = np.lib.format.read_magic(fh)
                read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, _, dtype = read_header(fh)
                if dtype.hasobject or int(np.prod(shape, dtype=object)) * dtype.itemsize > limit:
                    raise InputError(f"{path}: array {name!r} declares shape {shape} {dtype}, more than the "
                                     f"file holds ({limit} bytes); allowed: the file as np.savez wrote it")
        with np.load(path, allow_pickle=False) as z:
            for name in names:
                out[name] = z[name]
    return out
