"""``mfdesign diagnose``: compare a model with measurements, find the missing effect, add it.

    mfdesign diagnose DATA [--model DIR] [--effects NAME ...] [--theta JSON] [--config FILE]
                      [--effects-module FILE.py ...] [--physics exact|emulator|standin] --out DIR

``DATA``: a Measurements Parquet file or ``mass-lift``. Without ``--model`` the model is
the plain simulator (authors' constants), evaluated by ``--physics``: ``exact`` (default:
simulator planes of the measured membranes at simulator accuracy, solved once and cached;
autodiff screen and nonlinear refit of every candidate), ``emulator`` (the bundled neural
emulator, about 1 N RMS off the simulator: fast, but its error is as large as the gaps
diagnosis looks for) or ``standin`` (a cheap stand-in, for trials); ``--effects`` adds effects to it (calibrated
unless ``--theta`` fixes every parameter), giving a before/after report. A config file
(TOML or JSON) may hold any of ``effects``, ``theta``, ``effects_module``, ``model``,
``physics``, ``candidates``; command-line values win. ``effects_module`` (like
``--effects-module``) imports the Python files it names, so a config file runs code: treat
one from elsewhere as a script (docs/diagnose.md).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import List, Optional

import typer

from mfdesign.cli._contract import effect_name, item_parser

PHYSICS = ("exact", "emulator", "standin")


def load_config(path: Path) -> dict:
    """Options from a TOML (``.toml``) or JSON file; unknown keys are an error."""
    allowed = {"effects", "theta", "effects_module", "model", "physics", "candidates"}
    if not path.is_file():
        raise ValueError(f"config file {path} does not exist")
    text = path.read_text()
    if path.suffix == ".toml":
        import tomllib

        try:
            cfg = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise ValueError(f"config file {path} is not valid TOML: {err}") from None
    else:
        try:
            cfg = json.loads(text)
        except json.JSONDecodeError as err:
            raise ValueError(f"config file {path} is not valid JSON ({err}); use .toml for TOML") from None
    if not isinstance(cfg, dict):
        raise ValueError(f"config file {path} must hold a table/object, got {type(cfg).__name__}")
    bad = sorted(set(cfg) - allowed)
    if bad:
        raise ValueError(f"config file {path}: unknown key(s) {bad}; allowed: {sorted(allowed)}")
    for key in ("effects", "effects_module", "candidates"):
        value = cfg.get(key, [])
        if not (isinstance(value, str) or (isinstance(value, list) and all(isinstance(v, str) for v in value))):
            raise ValueError(f"config file {path}: {key} is {value!r}; allowed: a string or a list of strings")
    for key in ("model", "physics"):
        if key in cfg and not isinstance(cfg[key], str):
            raise ValueError(f"config file {path}: {key} is {cfg[key]!r}; allowed: a string")
    if "theta" in cfg:
        check_theta(cfg["theta"], f"config file {path}: theta")
    return cfg


def check_theta(theta, where: str = "--theta") -> dict:
    """Effect parameters: an object of "effect.parameter" -> a finite number.

    Why finite: a NaN parameter made every predicted force NaN, and diagnose wrote an
    "after" of n = 0 rows with RMSE NaN instead of refusing."""
    if not isinstance(theta, dict):
        raise ValueError(f'{where} must be an object {{"effect.parameter": value}}, got {type(theta).__name__}')
    for name, value in theta.items():
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if not ok:
            raise ValueError(f"{where}: {name!r} is {value!r}; allowed: a finite number")
    return theta


def load_effects_module(path: Path) -> None:
    """Import a user's effects file (its ``@register_effect`` classes join the library)."""
    import importlib.util

    path = Path(path)
    if not path.is_file() or path.suffix != ".py":
        raise ValueError(f"--effects-module {path}: not a Python file")
    spec = importlib.util.spec_from_file_location(f"mfdesign_user_effects_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as err:  # noqa: BLE001 -- report any failure of the user's file in one line
        raise ValueError(f"--effects-module {path} failed to import: {type(err).__name__}: {err}") from None


def _items(values) -> list[str]:
    """A list from the command line (a repeated option) or a config file (a list, or one
    string for one item); no comma splitting: every list is written one way."""
    if isinstance(values, str):
        return [values]
    return [str(v) for v in values or []]


def register(app: typer.Typer) -> None:
    @app.command()
    def diagnose(
        data: List[Path] = typer.Argument(
            ...,
            help="Measurements .parquet/.csv file(s), SPA_Design .pkl, rig job folder(s), or 'mass-lift' (several: concatenated; docs/data.md).",
        ),
        out: Path = typer.Option(..., help="Folder for report.html, diagnosis.json and the PNGs."),
        model: Optional[Path] = typer.Option(None, help="Saved ensemble folder (default: the plain simulator)."),
        effects: Optional[List[str]] = typer.Option(
            None,
            "--effects",
            parser=item_parser(effect_name, "an effect name"),
            help="Effects to add (repeat for several).",
        ),
        theta: Optional[str] = typer.Option(
            None, help="Effect parameters as JSON, e.g. '{\"pressure_sensor.offset_pa\": 150}'."
        ),
        config: Optional[Path] = typer.Option(
            None,
            help="TOML/JSON file with effects, theta, effects_module, ... (its effects_module runs the Python files it names: treat a config as code).",
        ),
        effects_module: Optional[List[Path]] = typer.Option(
            None, "--effects-module", help="Python file(s) registering new effects (imported: their code runs)."
        ),
        candidates: Optional[List[str]] = typer.Option(
            None,
            "--candidates",
            parser=item_parser(effect_name, "an effect name"),
            help="Effects the search may try (repeat; default: all).",
        ),
        physics: str = typer.Option(
            "exact",
            help="exact (simulator planes of the measured membranes, cached) | emulator (neural emulator, ~1 N RMS error) | standin (no physics; trials).",
        ),
        search: bool = typer.Option(True, help="Search for the missing effect."),
        check_top: int = typer.Option(3, min=1, help="Candidates given the full check."),
        check_pairs: int = typer.Option(
            3, min=0, help="Pairs of the joint screen given the full check as well (0: single effects only)."
        ),
        max_steps: int = typer.Option(2, min=1, help="Rounds of forward selection."),
        folds: int = typer.Option(
            3,
            min=2,
            help="Folds of held-out membranes in each candidate's check (more than the membranes: one membrane a fold).",
        ),
        shapes: bool = typer.Option(True, help="Plot the simulated shape at the worst points (exact physics only)."),
        cache_dir: Optional[Path] = typer.Option(None, help="Plane cache (default ~/.cache/mfdesign/planes)."),
        allow_outside_design_space: bool = typer.Option(
            False,
            "--allow-outside-design-space",
            help="Research: accept membranes outside the product's design space (wider physical range).",
        ),
    ) -> None:
        """Residuals by height, pressure, design, trial and phase; worst regions in words; which
        effect is missing (screen + full check); before/after with --effects. Writes HTML + JSON."""
        from mfdesign.cli._app import fail

        try:
            cfg = load_config(config) if config is not None else {}
            for f in _items(effects_module) or _items(cfg.get("effects_module", [])):
                load_effects_module(Path(f))
            from mfdesign.physics import effects as fx

            names = _items(effects) or _items(cfg.get("effects", []))
            for n in names + _items(candidates or cfg.get("candidates", [])):
                if n not in fx.EFFECTS:
                    raise ValueError(f"unknown effect {n!r}; registered: {sorted(fx.EFFECTS)}")
            th = cfg.get("theta", {})
            if theta:
                try:
                    th = json.loads(theta)
                except json.JSONDecodeError as err:
                    raise ValueError(f"--theta is not valid JSON: {err}") from None
            check_theta(th, "--theta" if theta else "theta")
            fx.split_theta(names, th) if names else (th and fx.split_theta([], th))
            sim_name = cfg.get("physics", physics) if physics == "exact" else physics
            if sim_name not in PHYSICS:
                raise ValueError(f"--physics must be one of {list(PHYSICS)}, got {sim_name!r}")
            model_dir = model if model is not None else (Path(cfg["model"]) if cfg.get("model") else None)
            from mfdesign.cli.data import load_data

            meas = load_data(data, "diagnose", allow_outside_design_space)
        except (ValueError, KeyError) as err:
            fail(str(err).strip('"'))
        import numpy as np

        from mfdesign.data.lifts import STALL_PA
        from mfdesign.diagnose.pipeline import diagnose as run
        from mfdesign.diagnose.residuals import stall_words, worst_regions
        from mfdesign.report.diagnosis import write_report

        predict, model_name = None, "simulator"
        if model_dir is not None:
            from mfdesign.models.ensemble import Ensemble

            try:
                ens = Ensemble.load(model_dir)
            except (FileNotFoundError, ValueError) as err:
                fail(f"--model {model_dir}: {err}")

            def predict(m):
                a = m.arrays()
                return np.asarray(ens.mean_std(a["design"], a["height_mm"], a["pressure_pa"])[0], float)

            model_name = f"ensemble {model_dir}"
        from mfdesign.diagnose.emulated import forward_model, likelihood_effects

        try:
            likelihood_effects(names + _items(candidates or cfg.get("candidates", [])))
            sim = forward_model(sim_name, meas, cache=cache_dir, progress=True)
        except (ValueError, FileNotFoundError) as err:
            fail(str(err))
        diag = run(
            meas,
            sim,
            model=predict,
            model_name=model_name,
            effects=names,
            theta=th,
            candidates=_items(candidates) or _items(cfg.get("candidates", [])) or None,
            search=search,
            check_top=check_top,
            check_pairs=check_pairs,
            max_steps=max_steps,
            n_folds=folds,
            progress=True,
        )
        paths = write_report(diag, out, shapes=shapes and sim_name == "exact")
        b = diag.before
        typer.echo(f"before: RMSE {b.rmse_n:.3f} N, noise floor {b.noise_floor_n:.3f} N")
        # the same words as the report (diagnosis.json), without rebuilding its whole JSON
        for w in worst_regions(b):
            typer.echo(f"  {w['words']}")
        if diag.stalls is not None:
            kpa = STALL_PA / 1e3
            typer.echo(
                f"where the lift plates stall (data only: the pressure climbed > {kpa:.1f} kPa over 1 mm of rise):"
            )
            for w in stall_words(diag.stalls):
                typer.echo(f"  {w}")
        for i, s in enumerate(diag.steps):
            typer.echo(
                f"round {i + 1}: screen " + ", ".join(f"{r.effect} {r.explained_fraction:.2f}" for r in s["screen"][:5])
            )
            if s.get("pair_screen"):
                typer.echo(
                    "  pairs: " + ", ".join(f"{r.effect} {r.explained_fraction:.2f}" for r in s["pair_screen"][:3])
                )
            typer.echo(f"  {s['verdict']['words']}")
        for name, why in diag.not_screened.items():
            typer.echo(f"not screened: {name} ({why})")
        if diag.after is not None:
            typer.echo(f"after ({', '.join(diag.effects)}): RMSE {diag.after.rmse_n:.3f} N")
        typer.echo(f"wrote {paths['html']} and {paths['json']}")
