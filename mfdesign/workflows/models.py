"""Saved model folders, as the commands read them, and the simulator constants they stand for.

A model folder is the output of ``mfdesign fit`` (``ensemble.json``: the paper's RPN
ensemble), of ``mfdesign fit-mf`` (``mf.json``: the multi-fidelity fit), or a pair of
ensembles ``sim/`` + ``discrepancy/``. Every bad folder raises
:class:`~mfdesign.errors.InputError` with one line naming what was found.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from mfdesign.errors import InputError

__all__ = [
    "describe_constants",
    "load_fit",
    "load_model",
    "load_predictor",
    "simulator_constants",
    "simulator_for_check",
]


def model_folder(path: Path) -> Path:
    """``path`` itself, or, for a campaign's folder (``mfdesign demo --out D`` leaves one),
    its latest round's model folder: every ``--model`` takes a campaign. The user's effects
    files the folder keeps are imported first (a campaign's on opening it; a fit-mf
    folder's ``effects/``: :func:`mfdesign.user_effects.import_folder`), so that its model
    rebuilds with them."""
    from mfdesign.campaign import Campaign
    from mfdesign.user_effects import import_folder

    path = Path(path)
    if Campaign.holds_campaign(path):
        return Campaign.open(path).model_folder()
    import_folder(path)
    return path


def load_fit(path: Path) -> Any:
    """The multi-fidelity fit (:class:`~mfdesign.calibration.workflow.MFFit`) of a
    ``mfdesign fit-mf`` folder (``mf.json``), or None for any other folder.

    Arguments:
        path: the model folder.

    Raises ``InputError`` when the folder holds a broken fit."""
    path = model_folder(path)
    if not (path / "mf.json").is_file():
        return None
    from mfdesign.calibration.workflow import load_multi_fidelity

    return load_multi_fidelity(path)


def load_model(path: Path, fit: Any = None) -> Any:
    """The predictor (:class:`~mfdesign.models.predictor.AbstractPredictor`) of a saved model
    folder: the RPN ensemble of ``mfdesign fit`` (``ensemble.json``) or the multi-fidelity fit
    of ``mfdesign fit-mf`` (``mf.json``; 16 posterior draws).

    Arguments:
        path: the model folder.
        fit: its multi-fidelity fit, already loaded by :func:`load_fit` (None: load it here).

    Raises ``InputError`` when the folder is missing or holds no loadable model."""
    from mfdesign.models.ensemble import Ensemble
    from mfdesign.models.predictor import EnsemblePredictor
    from mfdesign.models.sanity import check_predictor

    path = model_folder(path)
    if not path.is_dir():
        raise InputError(f"model folder {path} does not exist (fit one with `mfdesign fit` or `mfdesign fit-mf`)")
    if (path / "mf.json").is_file():
        return check_predictor((load_fit(path) if fit is None else fit).mf.predictor(16), str(path))
    try:
        predictor = EnsemblePredictor(Ensemble.load(path))
    except (FileNotFoundError, ValueError, KeyError) as err:
        raise InputError(f"cannot load a model from {path}: {err}") from None
    return check_predictor(predictor, str(path))


def load_predictor(model: Path, fit: Any = None) -> Any:
    """A :class:`~mfdesign.models.predictor.AbstractPredictor` from a folder, for ``propose``.

    * ``DIR/ensemble.json`` (``mfdesign fit``): the rig-only paper case;
    * ``DIR/sim/ensemble.json`` + ``DIR/discrepancy/ensemble.json``: a
      :class:`~mfdesign.models.predictor.SplitPredictor` offering ``rig`` and ``sim``;
    * ``DIR/mf.json`` (``mfdesign fit-mf``): the multi-fidelity model, ``rig`` and ``sim``
      (:meth:`~mfdesign.models.predictive.MultiFidelity.predictor`, 16 posterior draws).

    Arguments:
        model: the model folder.
        fit: its multi-fidelity fit, already loaded by :func:`load_fit` (None: load it here).

    Raises ``InputError`` with what was found when the folder is neither.
    """
    from mfdesign.models.ensemble import Ensemble
    from mfdesign.models.predictor import EnsemblePredictor, SplitPredictor
    from mfdesign.models.sanity import check_predictor

    model = model_folder(model)
    if not model.is_dir():
        raise InputError(f"--model {model} is not a folder (give the output folder of 'mfdesign fit')")
    if (model / "mf.json").is_file():
        return check_predictor((load_fit(model) if fit is None else fit).mf.predictor(16), str(model))
    if (model / "ensemble.json").is_file():
        return check_predictor(EnsemblePredictor(Ensemble.load(model)), str(model))
    if (model / "sim" / "ensemble.json").is_file() and (model / "discrepancy" / "ensemble.json").is_file():
        split = SplitPredictor(Ensemble.load(model / "sim"), Ensemble.load(model / "discrepancy"))
        return check_predictor(split, str(model))
    found = sorted(p.name for p in model.iterdir() if p.name != ".mfdesign.lock")[:8]
    raise InputError(
        f"--model {model} holds no ensemble.json, mf.json, nor sim/ and discrepancy/ ensembles; found {found}"
    )


def simulator_for_check(model: Path) -> tuple[bool, str]:
    """Whether the exact simulator can check this model's designs, and why not. A model
    fitted with ``--physics standin`` (``mf.json``) stands for no physics at all: checking
    its designs against the simulator would compare two unrelated models (and take minutes).

    Arguments:
        model: the model folder."""
    try:
        import mfdesign.physics.solve  # noqa: F401
    except ImportError as err:  # a broken install: say so rather than fail after the search
        return False, f"the simulator cannot be imported ({err})"
    meta_path = model_folder(model) / "mf.json"
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
        except (ValueError, UnicodeDecodeError):
            meta = {}
        physics = meta.get("physics", meta.get("search_physics")) if isinstance(meta, dict) else None
        if physics == "standin":
            return False, "the model was fitted with --physics standin (no simulator behind it)"
    return True, ""


def simulator_constants(model: Path, fit: Any = None) -> tuple[Any, dict]:
    """The constants the simulator runs at for the model in folder ``model``: a fit-mf
    model's calibrated ones (posterior median,
    :func:`~mfdesign.calibration.workflow.calibrated_sim_params`), else the authors'.

    Arguments:
        model: the model folder.
        fit: its multi-fidelity fit, already loaded by :func:`load_fit` (None: load it here).

    Returns ``(SimParams, description)``; the description (JSON-ready: ``mu_pa`` in Pa,
    ``jm``, ...) says which."""
    from mfdesign.calibration.workflow import authors_sim_params, calibrated_sim_params

    fit = load_fit(model) if fit is None else fit
    if fit is None:
        return authors_sim_params()
    params, description = calibrated_sim_params(fit)
    return params, description | {"model": str(model)}


def describe_constants(description: dict) -> str:
    """``"calibrated constants (posterior median of DIR): mu 29.4 kPa, J_m 45.7"`` or the authors'.

    Arguments:
        description: the description :func:`simulator_constants` returns (``mu_pa`` in Pa)."""
    which = (
        f"calibrated constants (posterior median of {description.get('model', 'the fit')})"
        if description.get("constants") == "calibrated"
        else "the authors' constants"
    )
    others = ", ".join(
        f"{k} {v:.4g}" for k, v in description.items() if k not in ("constants", "rule", "model", "mu_pa", "jm")
    )
    if "mu_pa" not in description or "jm" not in description:
        return which
    return f"{which}: mu {description['mu_pa'] / 1e3:.4g} kPa, J_m {description['jm']:.4g}" + (
        f", {others}" if others else ""
    )
