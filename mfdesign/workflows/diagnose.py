"""``mfdesign diagnose``: compare a model with measurements, find the missing effect, add it
(:func:`diagnose`; the analysis itself is :func:`mfdesign.diagnosis.pipeline.diagnose`).

``data``: Measurements sources (:func:`mfdesign.workflows.data.load_data`). Without a
``model`` folder the model is the plain simulator (authors' constants), evaluated by
``physics``: ``exact`` (simulator planes of the measured membranes at simulator accuracy,
solved once and cached), ``emulator`` (the bundled neural emulator, about 1 N RMS off the
simulator) or ``standin`` (a cheap stand-in, for trials); ``effects`` adds effects to it
(calibrated unless ``theta`` fixes every parameter), giving a before/after report. A config
file (TOML or JSON, :func:`load_config`) may hold any of ``effects``, ``theta``,
``effects_module``, ``model``, ``physics``, ``candidates``; explicit arguments win.
``effects_module`` imports the Python files it names, so a config file runs code: treat
one from elsewhere as a script (docs/diagnose.md).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from mfdesign.errors import InputError
from mfdesign.user_effects import load_effects_module  # the one loader (calibrate and campaigns use it too)

__all__ = ["DiagnoseResult", "PHYSICS", "check_theta", "diagnose", "load_config", "load_effects_module"]

PHYSICS = ("exact", "emulator", "standin")


def load_config(path: Path) -> dict:
    """Options from a TOML (``.toml``) or JSON file; unknown keys are an error.

    Arguments:
        path: the config file; it may hold ``effects``, ``theta``, ``effects_module``,
            ``model``, ``physics``, ``candidates``.

    Raises :class:`~mfdesign.errors.InputError` saying what is wrong."""
    allowed = {"effects", "theta", "effects_module", "model", "physics", "candidates"}
    if not path.is_file():
        raise InputError(f"config file {path} does not exist")
    text = path.read_text()
    if path.suffix == ".toml":
        import tomllib

        try:
            cfg = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise InputError(f"config file {path} is not valid TOML: {err}") from None
    else:
        try:
            cfg = json.loads(text)
        except json.JSONDecodeError as err:
            raise InputError(f"config file {path} is not valid JSON ({err}); use .toml for TOML") from None
    if not isinstance(cfg, dict):
        raise InputError(f"config file {path} must hold a table/object, got {type(cfg).__name__}")
    bad = sorted(set(cfg) - allowed)
    if bad:
        raise InputError(f"config file {path}: unknown key(s) {bad}; allowed: {sorted(allowed)}")
    for key in ("effects", "effects_module", "candidates"):
        value = cfg.get(key, [])
        if not (isinstance(value, str) or (isinstance(value, list) and all(isinstance(v, str) for v in value))):
            raise InputError(f"config file {path}: {key} is {value!r}; allowed: a string or a list of strings")
    for key in ("model", "physics"):
        if key in cfg and not isinstance(cfg[key], str):
            raise InputError(f"config file {path}: {key} is {cfg[key]!r}; allowed: a string")
    if "theta" in cfg:
        check_theta(cfg["theta"], f"config file {path}: theta")
    return cfg


def check_theta(theta: Any, where: str = "--theta") -> dict:
    """Effect parameters: an object of "effect.parameter" -> a finite number (in the
    parameter's own unit: Pa, mm, N, ...).

    Why finite: a NaN parameter made every predicted force NaN, and diagnose wrote an
    "after" of n = 0 rows with RMSE NaN instead of refusing.

    Arguments:
        theta: the parsed parameters.
        where: what they came from (starts the message).

    Raises :class:`~mfdesign.errors.InputError` saying what is wrong; returns ``theta``."""
    if not isinstance(theta, dict):
        raise InputError(f'{where} must be an object {{"effect.parameter": value}}, got {type(theta).__name__}')
    for name, value in theta.items():
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if not ok:
            raise InputError(f"{where}: {name!r} is {value!r}; allowed: a finite number")
    return theta


def _items(values: Any) -> list[str]:
    """A list from the command line (a repeated option) or a config file (a list, or one
    string for one item); no comma splitting: every list is written one way."""
    if isinstance(values, str):
        return [values]
    return [str(v) for v in values or []]


@dataclass(frozen=True)
class DiagnoseResult:
    """What :func:`diagnose` found and wrote: the
    :class:`~mfdesign.diagnosis.pipeline.Diagnosis` and the report's files by kind
    (``html``, ``json``, ...)."""

    diagnosis: Any
    paths: dict

    def summary(self) -> str:
        """RMSE [N] and noise floor before; the worst regions in words; where lift plates
        stall; each round's screen and verdict; what was not screened; RMSE after."""
        from mfdesign.data.lifts import STALL_PA
        from mfdesign.diagnosis.residuals import stall_words, worst_regions

        diag = self.diagnosis
        b = diag.before
        lines = [f"before: RMSE {b.rmse_n:.3f} N, noise floor {b.noise_floor_n:.3f} N"]
        # the same words as the report (diagnosis.json), without rebuilding its whole JSON
        lines += [f"  {w['words']}" for w in worst_regions(b)]
        if diag.stalls is not None:
            kpa = STALL_PA / 1e3
            lines.append(
                f"where the lift plates stall (data only: the pressure climbed > {kpa:.1f} kPa over 1 mm of rise):"
            )
            lines += [f"  {w}" for w in stall_words(diag.stalls)]
        for i, s in enumerate(diag.steps):
            screen = ", ".join(f"{r.effect} {r.explained_fraction:.2f}" for r in s["screen"][:5])
            lines.append(f"round {i + 1}: screen {screen}")
            if s.get("pair_screen"):
                lines.append(
                    "  pairs: " + ", ".join(f"{r.effect} {r.explained_fraction:.2f}" for r in s["pair_screen"][:3])
                )
            lines.append(f"  {s['verdict']['words']}")
        lines += [f"not screened: {name} ({why})" for name, why in diag.not_screened.items()]
        if diag.after is not None:
            lines.append(f"after ({', '.join(diag.effects)}): RMSE {diag.after.rmse_n:.3f} N")
        lines.append(f"wrote {self.paths['html']} and {self.paths['json']}")
        return "\n".join(lines)


@dataclass(frozen=True)
class _Options:
    """The options of one diagnosis, the config file's merged under the explicit ones."""

    effects: list[str]
    candidates: list[str]
    theta: dict
    physics: str
    model: Path | None


def _options(
    config: Path | None,
    effects: Sequence[str] | None,
    theta: str | None,
    effects_module: Sequence[Path] | None,
    candidates: Sequence[str] | None,
    physics: str,
    model: Path | None,
) -> _Options:
    """Read the config file, import the effects modules, check effect names and ``theta``."""
    from mfdesign.physics import effects as fx

    cfg = load_config(config) if config is not None else {}
    for f in _items(effects_module) or _items(cfg.get("effects_module", [])):
        load_effects_module(Path(f))
    names = _items(effects) or _items(cfg.get("effects", []))
    searched = _items(candidates or cfg.get("candidates", []))
    for n in names + searched:
        if n not in fx.EFFECTS:
            raise InputError(f"unknown effect {n!r}; registered: {sorted(fx.EFFECTS)}")
    th = cfg.get("theta", {})
    if theta:
        try:
            th = json.loads(theta)
        except json.JSONDecodeError as err:
            raise InputError(f"--theta is not valid JSON: {err}") from None
    check_theta(th, "--theta" if theta else "theta")
    try:
        fx.split_theta(names, th) if names else (th and fx.split_theta([], th))
    except (ValueError, KeyError) as err:
        raise InputError(str(err).strip('"')) from None
    sim_name = cfg.get("physics", physics) if physics == "exact" else physics
    if sim_name not in PHYSICS:
        raise InputError(f"--physics must be one of {list(PHYSICS)}, got {sim_name!r}")
    model_dir = model if model is not None else (Path(cfg["model"]) if cfg.get("model") else None)
    return _Options(names, searched, th, sim_name, model_dir)


def _ensemble_model(model_dir: Path | None) -> tuple[Callable | None, str]:
    """``(predict, name)``: a saved ensemble's mean force [N] per row, or the simulator's name."""
    if model_dir is None:
        return None, "simulator"
    import numpy as np

    from mfdesign.models.ensemble import Ensemble

    from mfdesign.models.predictor import EnsemblePredictor
    from mfdesign.models.sanity import check_predictor

    try:
        ens = Ensemble.load(model_dir)
    except (FileNotFoundError, ValueError) as err:
        raise InputError(f"--model {model_dir}: {err}") from None
    # a folder that loads can still predict NaN or absurd forces (issue 44, class 4)
    check_predictor(EnsemblePredictor(ens), str(model_dir))

    def predict(m: Any) -> Any:
        a = m.arrays()
        return np.asarray(ens.mean_std(a["design"], a["height_mm"], a["pressure_pa"])[0], float)

    return predict, f"ensemble {model_dir}"


def diagnose(
    data: Any,
    out: Path,
    model: Path | None = None,
    effects: Sequence[str] | None = None,
    theta: str | None = None,
    config: Path | None = None,
    effects_module: Sequence[Path] | None = None,
    candidates: Sequence[str] | None = None,
    physics: str = "exact",
    search: bool = True,
    check_top: int = 3,
    check_pairs: int = 3,
    max_steps: int = 2,
    folds: int = 3,
    shapes: bool = True,
    cache_dir: Path | None = None,
    allow_outside_design_space: bool = False,
) -> DiagnoseResult:
    """Residuals by height, pressure, design, trial and phase; worst regions in words; which
    effect is missing (screen + full check); before/after with ``effects``. Writes
    ``index.html``, ``diagnosis.json`` and the PNGs into ``out``.

    Arguments:
        data: the Measurements sources (:func:`mfdesign.workflows.data.load_data`).
        out: output folder.
        model: a saved ensemble folder (None: the plain simulator, authors' constants).
        effects: effects to add (calibrated unless ``theta`` fixes every parameter).
        theta: effect parameters as JSON, e.g. ``'{"pressure_sensor.offset_pa": 150}'`` (Pa).
        config: TOML / JSON options file (:func:`load_config`; its ``effects_module`` runs code).
        effects_module: Python files registering new effects (imported: their code runs).
        candidates: effects the search may try (None: all).
        physics: ``exact`` | ``emulator`` | ``standin`` (module doc).
        search: search for the missing effect.
        check_top: candidates given the full check.
        check_pairs: pairs of the joint screen given the full check as well (0: none).
        max_steps: rounds of forward selection.
        folds: folds of held-out membranes in each candidate's check.
        shapes: plot the simulated shape at the worst points (exact physics only).
        cache_dir: the plane cache (None: ``~/.cache/mfdesign/planes``).
        allow_outside_design_space: accept membranes outside the product's design space.

    Raises :class:`~mfdesign.errors.InputError` (one line) for bad options, config, effects
    or data."""
    from mfdesign.diagnosis.forward import forward_model, likelihood_effects
    from mfdesign.diagnosis.pipeline import diagnose as run
    from mfdesign.report.diagnosis import write_report
    from mfdesign.workflows.data import load_data

    opts = _options(config, effects, theta, effects_module, candidates, physics, model)
    try:
        meas = load_data(data, "diagnose", allow_outside_design_space)
    except (ValueError, KeyError) as err:
        raise InputError(str(err).strip('"')) from None
    predict, model_name = _ensemble_model(opts.model)
    try:
        likelihood_effects(opts.effects + opts.candidates)
        sim = forward_model(opts.physics, meas, cache=cache_dir, progress=True)
    except (ValueError, FileNotFoundError) as err:
        raise InputError(str(err)) from None
    diag = run(
        meas,
        sim,
        model=predict,
        model_name=model_name,
        effects=opts.effects,
        theta=opts.theta,
        candidates=opts.candidates or None,
        search=search,
        check_top=check_top,
        check_pairs=check_pairs,
        max_steps=max_steps,
        n_folds=folds,
        progress=True,
    )
    from mfdesign.provenance import call_line, input_hashes

    named = [*(data if isinstance(data, (list, tuple)) else [data]), *(p for p in (model, config) if p is not None)]
    paths = write_report(
        diag,
        out,
        shapes=shapes and opts.physics == "exact",
        call=call_line("mfdesign.workflows.diagnose.diagnose()"),
        inputs=input_hashes(named),
    )
    return DiagnoseResult(diag, paths)
