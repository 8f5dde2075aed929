"""A lab's campaign: one folder that holds the whole design loop, round after round.

A lab runs rounds: measure membranes, diagnose and calibrate, ask which membranes to build
next, build and measure them, tell the tool, refit. :class:`Campaign` owns that loop's
state in one folder, as Ax's ``Client`` owns an experiment (``ask`` ~ ``get_next_trials``,
``tell`` ~ ``complete_trial``); membranes asked for and not yet told count as measured in
the next ask (BoTorch's ``X_pending``); :meth:`Campaign.fit` is the model update of
emukit's ``OuterLoop``. Nothing of those libraries is imported.

The folder::

    campaign.json            settings, effects in force, sources, proposals (one atomic file)
    sources/sNNN.parquet     every measurement source, as told (sha256 in campaign.json)
    effects/mN_NAME.py       a copy of each user's effects file given to create (sha256 in
                             campaign.json; every open imports it again)
    diagnosis.json           the latest diagnosis (:meth:`Campaign.diagnose`)
    asks/askNNN.json         each ask's proposal as acquisition returned it
    rounds/round-NNN/        a fitted round: model/ (mf.json, posterior.json/.npz/.nc,
                             delta/), round.json (data, fit, held-out error, provenance),
                             diagnosis.json (the one that set the round's effects)

Why the layout survives a SIGKILL at any point: ``campaign.json`` is the only file that
changes state, and it is replaced atomically (:mod:`mfdesign.outputs`), after the files
it names are complete; a round is written into ``rounds/.round-NNN.<pid>.tmp`` and renamed
into place (one ``rename``) at the end, and only ``round-NNN`` folders holding a
``round.json`` count. A killed step leaves at worst an orphan source file or a temporary
folder, which nothing reads (the next fit removes the temporary folders). One writer at a
time: every step that writes holds the folder's :class:`~mfdesign.outputs.OutputLock`.

Units: heights mm, pressures Pa, forces N.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path
from typing import Any, Sequence

from mfdesign.errors import InputError
from mfdesign.provenance import now as _now
from mfdesign.provenance import provenance
from mfdesign.provenance import sha256 as _sha256

__all__ = [
    "Campaign",
    "CampaignStatus",
    "EffectsModule",
    "ProposalEntry",
    "Round",
    "Settings",
    "Source",
    "provenance",
]

FORMAT_VERSION = 1
CAMPAIGN_FILE = "campaign.json"
STATUSES = ("pending", "measured", "dropped")
PHYSICS = ("exact", "emulator", "standin")
_ROUND_PREFIX = "round-"


# ----------------------------------------------------------------------------- settings
@dataclasses.dataclass(frozen=True)
class Settings:
    """Every default of a campaign, in one place; ``mfdesign calibrate`` and ``fit-mf`` take
    their defaults from here too (steps, walkers, rows, ensemble, seed).

    Physics and calibration: ``physics`` where the model meets the data (``"exact"``
    simulator planes, ``"emulator"``, ``"standin"`` for tests; design searches run on the
    emulator when it is ``"exact"``), ``effects`` the user's effects (a diagnosis adds what
    it finds; a user's own effect needs the file that registers it, ``Campaign.create``'s
    ``effects_module``: the names are checked there and on every open, once that file is
    imported, not here), ``mcmc_steps`` (most emcee steps; sampling stops once converged),
    ``walkers`` (at least this many; 0: automatic, ``max(32, 2 dim + 2)``; a round whose model
    has more parameters, a latent per membrane, takes ``2 dim + 2``), ``max_rows`` (rows the likelihood uses), ``likelihood``,
    ``material`` (:func:`~mfdesign.calibration.workflow.material_priors`),
    ``membrane_latents``, ``membrane_effects`` (effect parameters, ``"effect.param"`` or an
    effect's name, that vary from membrane to membrane around a calibrated population:
    applied once their effect is in force); the discrepancy ensemble: ``members``,
    ``delta_steps``.
    Acquisition: ``restarts``, ``refine``, ``opt_steps``, the costs ``cost_rig`` /
    ``cost_sim``, the plane of a simulator run ``sim_heights`` x ``sim_pressures``.
    Diagnosis: ``diagnose_search`` (False: residuals only), ``check_top``, ``check_pairs``,
    ``diagnose_rounds``. ``seed``: the one seed every step derives its own from.
    """

    physics: str = "exact"
    effects: tuple[str, ...] = ()
    mcmc_steps: int = 2000
    walkers: int = 0
    max_rows: int = 1500
    likelihood: str = "student_t"
    material: str = "free"
    membrane_latents: bool = True
    membrane_effects: tuple[str, ...] = ()
    members: int = 8
    delta_steps: int = 3000
    restarts: int = 1000
    refine: int = 32
    opt_steps: int = 20
    cost_rig: float = 1.0
    cost_sim: float = 0.01
    sim_heights: int = 15
    sim_pressures: int = 17
    diagnose_search: bool = True
    check_top: int = 3
    check_pairs: int = 3
    diagnose_rounds: int = 2
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("effects", "membrane_effects"):
            if isinstance(getattr(self, name), str):  # tuple("abc") would be its letters
                raise InputError(f"settings.{name} = {getattr(self, name)!r}; allowed: a list of names")
        object.__setattr__(self, "effects", tuple(self.effects))
        object.__setattr__(self, "membrane_effects", tuple(self.membrane_effects))
        if self.physics not in PHYSICS:
            raise InputError(f"settings.physics {self.physics!r}; allowed: {', '.join(PHYSICS)}")
        if self.likelihood not in ("gaussian", "student_t"):
            raise InputError(f"settings.likelihood {self.likelihood!r}; allowed: gaussian, student_t")
        from mfdesign.calibration.workflow import MATERIALS

        if self.material not in MATERIALS:
            raise InputError(f"settings.material {self.material!r}; allowed: {', '.join(MATERIALS)}")
        least = {"mcmc_steps": 1, "walkers": 0, "max_rows": 10, "members": 1, "delta_steps": 1, "restarts": 1}
        least |= {"refine": 1, "opt_steps": 0, "sim_heights": 2, "sim_pressures": 2, "check_top": 1}
        least |= {"check_pairs": 0, "diagnose_rounds": 1, "seed": 0}
        for name, low in least.items():
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise InputError(f"settings.{name} = {value!r}; allowed: an integer >= {low}")
        for name in ("cost_rig", "cost_sim"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 < value < float("inf")):
                raise InputError(f"settings.{name} = {value!r}; allowed: a positive finite number")
        if not all(isinstance(e, str) for e in self.effects):
            raise InputError(f"settings.effects {list(self.effects)!r}; allowed: effect names (strings)")
        if not all(isinstance(e, str) for e in self.membrane_effects):
            raise InputError(
                f"settings.membrane_effects {list(self.membrane_effects)!r}; allowed: effect parameter names "
                "('effect.param') or effect names (strings)"
            )

    def check_effects(self, where: str = "settings.effects") -> None:
        """``InputError`` when an effect of the settings is not registered (run once the
        campaign's effects files are imported: :meth:`Campaign.create`, every open)."""
        _check_registered(self.effects, where)

    @classmethod
    def quick(cls, physics: str = "standin", **changes) -> "Settings":
        """Small settings for a smoke run or a test (seconds a step on the stand-in)."""
        # walkers left to the sampler (0: max(32, 2 dim + 2)): a fixed 16 was fewer than
        # emcee allows once six membranes' latents and an effect are sampled (dim 12)
        small = dict(mcmc_steps=40, walkers=0, max_rows=60, members=2, delta_steps=20, restarts=8, refine=2)
        small |= dict(opt_steps=2, sim_heights=4, sim_pressures=4, diagnose_search=False)
        return cls(physics=physics, **(small | changes))

    def to_json(self) -> dict:
        return {
            **dataclasses.asdict(self),
            "effects": list(self.effects),
            "membrane_effects": list(self.membrane_effects),
        }

    @classmethod
    def from_json(cls, raw: Any, where: str = "settings") -> "Settings":
        if not isinstance(raw, dict):
            raise InputError(f"{where}: settings must be a JSON object, got {type(raw).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(raw) - known)
        if unknown:
            raise InputError(f"{where}: unknown setting(s) {unknown}; allowed: {sorted(known)}")
        try:
            values: dict[str, Any] = {
                k: tuple(v) if k in ("effects", "membrane_effects") else v for k, v in raw.items()
            }
            return cls(**values)
        except TypeError as err:
            raise InputError(f"{where}: {err}") from None

    @property
    def search_physics(self) -> str:
        """The force model of design searches: the exact model holds planes of the
        calibrated membranes only, so a search over new designs runs on the emulator."""
        return "emulator" if self.physics == "exact" else self.physics


# ----------------------------------------------------------------------------- records
@dataclasses.dataclass(frozen=True)
class Source:
    """One measurement source of the campaign: ``file`` (relative to the folder) holds it
    as Parquet, ``sha256`` its bytes; ``origin`` what was given; ``proposal`` the proposal
    it measured (or None); ``after_round``: rounds complete when it came (-1: none)."""

    id: str
    file: str
    sha256: str
    rows: int
    membranes: tuple[str, ...]
    origin: tuple[str, ...]
    added: str
    after_round: int
    proposal: str | None = None

    def to_json(self) -> dict:
        return {**dataclasses.asdict(self), "membranes": list(self.membranes), "origin": list(self.origin)}


@dataclasses.dataclass(frozen=True)
class EffectsModule:
    """A user's effects file the campaign keeps: ``file`` (relative to the folder) is the
    copy made by :meth:`Campaign.create`, ``sha256`` its bytes, ``origin`` the path given,
    ``effects`` the names it registered. Every open checks the copy and imports it again."""

    file: str
    sha256: str
    origin: str
    effects: tuple[str, ...]

    def to_json(self) -> dict:
        return {**dataclasses.asdict(self), "effects": list(self.effects)}


@dataclasses.dataclass(frozen=True)
class ProposalEntry:
    """One asked run: ``design`` (the key, mm) at ``fidelity``, its ``status`` (pending /
    measured / dropped), the ``round`` whose model asked for it, the source that measured
    it, and the acquisition's rank, expected reduction (N RMS) and reason."""

    id: str
    round: int
    design: str
    fidelity: str
    status: str
    ask: int
    rank: int
    reduction_rms_n: float | None
    reason: str
    source: str | None = None
    note: str = ""

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class _State:
    """``campaign.json``: replaced whole (atomically) by every step that changes it."""

    settings: Settings
    effects: tuple[str, ...]
    sources: tuple[Source, ...]
    proposals: tuple[ProposalEntry, ...]
    created: dict
    effects_modules: tuple[EffectsModule, ...] = ()

    def to_json(self) -> dict:
        return {
            "format_version": FORMAT_VERSION,
            "settings": self.settings.to_json(),
            "effects": list(self.effects),
            "effects_modules": [m.to_json() for m in self.effects_modules],
            "sources": [s.to_json() for s in self.sources],
            "proposals": [p.to_json() for p in self.proposals],
            "created": self.created,
        }


@dataclasses.dataclass(frozen=True)
class Round:
    """A fitted round: its ``number``, ``folder``, the fit (:class:`~mfdesign.calibration.
    workflow.MFFit` on the search physics: what :meth:`Campaign.model` reloads) and
    ``record`` (``round.json``)."""

    number: int
    folder: Path
    fit: Any
    record: dict

    def summary(self) -> str:
        r = self.record
        fit, held = r["fit"], r.get("heldout")
        line = (
            f"round {self.number}: {r['data']['membranes']} membranes, {r['data']['rows']} rows, effects "
            f"{r['effects'] or 'none'}; training RMSE {fit['train_rmse_n']:.3f} N, 90 % coverage "
            f"{fit['train_coverage90']:.2f}, residual noise {fit['noise_n']:.3f} N"
        )
        if held:
            line += (
                f"; round {held['model_round']}'s model on the {len(held['membranes'])} membrane(s) told since: "
                f"RMSE {held['rmse_n']:.3f} N, 90 % coverage {held['coverage90']:.2f}"
            )
        return line + f" -> {self.folder}"


@dataclasses.dataclass(frozen=True)
class CampaignStatus:
    """Where a campaign stands: its rounds (``round.json`` records), sources, proposals,
    effects in force and settings; ``problems``: sources whose bytes changed."""

    folder: Path
    settings: Settings
    effects: tuple[str, ...]
    sources: tuple[Source, ...]
    proposals: tuple[ProposalEntry, ...]
    rounds: tuple[dict, ...]
    problems: tuple[str, ...]
    effects_modules: tuple[EffectsModule, ...] = ()

    def to_json(self) -> dict:
        return {
            "folder": str(self.folder),
            "settings": self.settings.to_json(),
            "effects": list(self.effects),
            "effects_modules": [m.to_json() for m in self.effects_modules],
            "sources": [s.to_json() for s in self.sources],
            "proposals": [p.to_json() for p in self.proposals],
            "rounds": list(self.rounds),
            "problems": list(self.problems),
        }

    def summary(self) -> str:
        rows = sum(s.rows for s in self.sources)
        membranes = len({m for s in self.sources for m in s.membranes})
        lines = [
            f"campaign {self.folder}: {len(self.sources)} source(s), {rows} rows, {membranes} membranes; "
            f"physics {self.settings.physics}; effects in force: {list(self.effects) or 'none'}",
            "round  membranes  rows  train RMSE [N]  cov90  held-out RMSE [N]  held-out cov90",
        ]
        for m in self.effects_modules:
            lines.insert(1, f"effects module {m.file} (from {m.origin}): {', '.join(m.effects) or 'no effect'}")
        for r in self.rounds:
            held = r.get("heldout") or {}
            lines.append(
                f"{r['round']:>5}  {r['data']['membranes']:>9}  {r['data']['rows']:>4}  "
                f"{r['fit']['train_rmse_n']:>14.3f}  {r['fit']['train_coverage90']:>5.2f}  "
                + (f"{held['rmse_n']:>17.3f}  {held['coverage90']:>14.2f}" if held else f"{'-':>17}  {'-':>14}")
            )
        if not self.rounds:
            lines.append("(no round fitted yet: fit)")
        for p in self.proposals:
            lines.append(f"proposal {p.id} (round {p.round}, {p.fidelity}): {p.design} {p.status}")
        lines += [f"problem: {m}" for m in self.problems]
        return "\n".join(lines)


# ----------------------------------------------------------------------------- provenance
def _measurements(data, what: str):
    """A Measurements table from ``data``: a table, or a source / sources for
    :func:`mfdesign.data.sources.load_sources` (Parquet, CSV, rig job folder, ...)."""
    from mfdesign.data.measurements import Measurements
    from mfdesign.data.sources import load_sources

    if isinstance(data, Measurements):
        return data, ("<Measurements in memory>",)
    if data is None:
        raise InputError(f"{what}: no data given; allowed: a Measurements table, a file or a rig job folder")
    items = [data] if isinstance(data, (str, os.PathLike)) else list(data)
    return load_sources(items), tuple(str(i) for i in items)


def _check_registered(names: Sequence[str], where: str) -> None:
    """``InputError`` naming the effects of ``names`` that are not registered."""
    from mfdesign.physics.effects import EFFECTS

    unknown = [e for e in names if e not in EFFECTS]
    if unknown:
        raise InputError(
            f"{where} {unknown}: unknown; registered: {sorted(EFFECTS)} (a user's own effect: the file that "
            "registers it, as Campaign.create's effects_module=[FILE.py] or create's --effects-module FILE.py)"
        )


def _unkept(names: Sequence[str], modules: Sequence[EffectsModule]) -> list[str]:
    """The effects of ``names`` a reopened campaign could not register again: neither
    mfdesign's own nor registered by one of the campaign's effects files (registered in
    Python, in this session only)."""
    from mfdesign.physics.effects import EFFECTS

    kept = {e for m in modules for e in m.effects}
    return [n for n in names if n not in kept and EFFECTS[n].__module__.split(".")[0] != "mfdesign"]


def _module(record: dict) -> EffectsModule:
    """An :class:`EffectsModule` from its JSON record."""
    return EffectsModule(**{**record, "effects": tuple(record["effects"])})


def _round_folders(folder: Path) -> list[Path]:
    """Complete rounds, in order: ``round-NNN`` folders holding a ``round.json``."""
    rounds = folder / "rounds"
    if not rounds.is_dir():
        return []
    found = [p for p in rounds.iterdir() if p.name.startswith(_ROUND_PREFIX) and (p / "round.json").is_file()]
    return sorted(found, key=lambda p: int(p.name[len(_ROUND_PREFIX) :]))


# ----------------------------------------------------------------------------- campaign
class Campaign:
    """A lab's design loop in one folder (module doc). Make one with :meth:`create`, come
    back to it with :meth:`open`; then :meth:`diagnose`, :meth:`fit`, :meth:`ask`,
    :meth:`tell` (and :meth:`drop`), :meth:`status`, :meth:`report`.

    **Arguments:**

    - `folder`: the campaign's folder (holding ``campaign.json``); use :meth:`open`, which
      checks it.

    Every method that writes holds the folder's lock (one writer at a time; a killed
    writer's lock is taken over) and leaves the folder consistent if killed at any point.
    Bad input raises :class:`~mfdesign.errors.InputError` with one line saying what is
    allowed.
    """

    def __init__(self, folder: str | os.PathLike):
        self.folder = Path(folder)

    # -- making and opening
    @classmethod
    def create(
        cls,
        folder: str | os.PathLike,
        data=None,
        settings: Settings | None = None,
        *,
        effects_module: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
        call: str = "",
    ) -> "Campaign":
        """A new campaign in ``folder`` (created; it may hold other files, not a campaign).

        **Arguments:**

        - `folder`: where the campaign lives.
        - `data`: the first measurements: a :class:`~mfdesign.data.measurements.Measurements`
          table, or what :func:`mfdesign.load` reads (a Parquet or CSV file, a rig job
          folder, ``"bundled"``, or a list of them).
        - `settings`: a :class:`Settings` (default ``Settings()``).
        - `effects_module`: a user's Python file(s) registering new effects (imported: their
          code runs), so that ``settings.effects``, :meth:`diagnose`'s search, :meth:`fit`
          and :meth:`ask` know them; each is copied into ``effects/`` with its sha256, and
          every :meth:`open` imports the copy again.
        - `call`: the command line or call that made it, for the provenance.

        **Returns:**

        The :class:`Campaign`. Raises ``InputError`` when ``folder`` already holds one, an
        effects file cannot be imported, an effect of the settings is unknown (or was
        registered in Python only: a reopened campaign could not know it), or the data
        cannot be read.
        """
        from mfdesign.outputs import OutputLock, prepare_out_dir

        folder = prepare_out_dir(folder, option="campaign folder")
        if (folder / CAMPAIGN_FILE).exists():
            raise InputError(f"{folder} already holds a campaign; allowed: Campaign.open it, or a new folder")
        settings = Settings() if settings is None else settings
        if not isinstance(settings, Settings):
            raise InputError(f"settings: a {type(settings).__name__}; allowed: mfdesign.campaign.Settings")
        from mfdesign.user_effects import keep, load_effects_module

        given = [effects_module] if isinstance(effects_module, (str, os.PathLike)) else effects_module or []
        if not isinstance(given, (list, tuple)) or not all(isinstance(p, (str, os.PathLike)) for p in given):
            raise InputError(f"effects_module {effects_module!r}; allowed: a path or a list of paths to .py files")
        paths = [Path(p) for p in given]
        registered = [load_effects_module(p, "effects module") for p in paths]
        settings.check_effects()
        loose = _unkept(settings.effects, [EffectsModule("", "", str(p), n) for p, n in zip(paths, registered)])
        if loose:
            raise InputError(
                f"settings.effects {loose} were registered in Python, not by a file the campaign keeps; "
                "allowed: the .py file that registers them as effects_module=[FILE.py] (a reopened campaign imports it)"
            )
        table, origin = _measurements(data, "Campaign.create")
        with OutputLock(folder, option="campaign", reentrant=True):
            source = cls(folder)._store(table, origin, after_round=-1, proposal=None, index=0)
            modules = tuple(_module(r) for r in keep(folder, paths, registered))
            created = provenance(
                call or f"Campaign.create({str(folder)!r})",
                {"seed": settings.seed},
                {m.file: m.sha256 for m in modules},
            )
            state = _State(settings, settings.effects, (source,), (), created, modules)
            cls(folder)._write(state)
        return cls(folder)

    @classmethod
    def open(cls, folder: str | os.PathLike) -> "Campaign":
        """The campaign in ``folder``; ``InputError`` when there is none or it is unreadable."""
        if not isinstance(folder, (str, os.PathLike)):
            raise InputError(f"campaign folder: a {type(folder).__name__}; allowed: a path (str or os.PathLike)")
        campaign = cls(folder)
        campaign._read()
        return campaign

    @staticmethod
    def holds_campaign(folder: str | os.PathLike) -> bool:
        """Whether ``folder`` is a campaign's folder (it holds ``campaign.json``)."""
        return (Path(folder) / CAMPAIGN_FILE).is_file()

    # -- state
    def _read(self) -> _State:
        from mfdesign.user_effects import import_kept

        path = self.folder / CAMPAIGN_FILE
        if not path.is_file():
            raise InputError(
                f"{self.folder} is not a campaign (no {CAMPAIGN_FILE}); allowed: a folder made by "
                "Campaign.create or mfdesign demo"
            )
        try:
            raw = json.loads(path.read_text())
            if raw.get("format_version") != FORMAT_VERSION:
                raise ValueError(f"format_version {raw.get('format_version')!r}, this mfdesign reads {FORMAT_VERSION}")
            modules = tuple(_module(m) for m in raw.get("effects_modules", []))
            # before the effect names are read: the kept copies, checked and imported
            import_kept(self.folder, [m.to_json() for m in modules], f"campaign {self.folder}")
            settings = Settings.from_json(raw["settings"], where=str(path))
            settings.check_effects(f"{path}: settings.effects")
            _check_registered(raw["effects"], f"{path}: effects in force")
            sources = tuple(
                Source(**{**s, "membranes": tuple(s["membranes"]), "origin": tuple(s["origin"])})
                for s in raw["sources"]
            )
            proposals = tuple(ProposalEntry(**p) for p in raw["proposals"])
            created = dict(raw.get("created", {}))
            return _State(settings, tuple(raw["effects"]), sources, proposals, created, modules)
        except InputError:
            raise
        except (ValueError, KeyError, TypeError, AttributeError, OSError) as err:
            raise InputError(f"{path} is not a readable campaign file ({type(err).__name__}: {err})") from None

    def _write(self, state: _State) -> None:
        from mfdesign import outputs

        outputs.write_json(self.folder / CAMPAIGN_FILE, state.to_json())

    def _lock(self):
        from mfdesign.outputs import OutputLock

        return OutputLock(self.folder, option="campaign", reentrant=True)

    def _store(self, table, origin, after_round: int, proposal: str | None, index: int) -> Source:
        """Write ``table`` as the source ``sNNN`` (its Parquet bytes hashed)."""
        from mfdesign.data.store import write_parquet

        sid = f"s{index:03d}"
        path = self.folder / "sources" / f"{sid}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_parquet(table, path)
        return Source(
            id=sid,
            file=str(path.relative_to(self.folder)),
            sha256=_sha256(path),
            rows=len(table),
            membranes=tuple(table.design_keys),
            origin=tuple(origin),
            added=_now(),
            after_round=after_round,
            proposal=proposal,
        )

    @property
    def settings(self) -> Settings:
        return self._read().settings

    @property
    def effects(self) -> tuple[str, ...]:
        """The effects in force: the settings' and what a diagnosis found."""
        return self._read().effects

    def rounds(self) -> list[int]:
        """The numbers of the complete rounds, in order."""
        return [int(p.name[len(_ROUND_PREFIX) :]) for p in _round_folders(self.folder)]

    def data(self, sources: Sequence[str] | None = None):
        """The campaign's measurements (every source, or those of ``sources`` ids), one
        Measurements table; ``InputError`` when a source's bytes no longer match its sha256."""
        from mfdesign.data.sources import load_sources

        chosen = [s for s in self._read().sources if sources is None or s.id in sources]
        for s in chosen:
            path = self.folder / s.file
            if not path.is_file() or _sha256(path) != s.sha256:
                raise InputError(f"{path}: source {s.id} is missing or changed since it was told (sha256 differs)")
        return load_sources([str(self.folder / s.file) for s in chosen])

    def model_folder(self, round: int | None = None) -> Path:
        """The folder of ``round``'s fitted model (default: the latest): what ``--model``
        reads when it is given the campaign's folder (``mfdesign propose --model D``)."""
        folders = _round_folders(self.folder)
        if not folders:
            raise InputError(
                f"campaign {self.folder} has no fitted round yet; allowed: fit it first (mfdesign fit {self.folder})"
            )
        if round is None:
            return folders[-1] / "model"
        path = self.folder / "rounds" / f"{_ROUND_PREFIX}{round:03d}"
        if path not in folders:
            raise InputError(f"campaign {self.folder} has no round {round}; complete rounds: {self.rounds()}")
        return path / "model"

    def model(self, round: int | None = None):
        """The fitted model of ``round`` (default: the latest), reloaded from its folder: an
        :class:`~mfdesign.calibration.workflow.MFFit` on the search physics."""
        from mfdesign.calibration.workflow import MFFit

        folders = _round_folders(self.folder)
        if not folders:
            raise InputError(f"campaign {self.folder} has no fitted round yet; allowed: fit it first")
        if round is None:
            return MFFit.load(folders[-1] / "model")
        path = self.folder / "rounds" / f"{_ROUND_PREFIX}{round:03d}"
        if path not in folders:
            raise InputError(f"campaign {self.folder} has no round {round}; complete rounds: {self.rounds()}")
        return MFFit.load(path / "model")

    # -- the loop
    def diagnose(self, *, progress: bool = False, call: str = ""):
        """Diagnose the campaign's data (:func:`mfdesign.diagnose`) on its physics, with the
        effects in force; what it finds joins them. The search tries every registered effect
        a reopened campaign can register again (mfdesign's and its effects files'; not one
        registered in Python only). Writes ``diagnosis.json`` (copied into the next round).
        Returns the :class:`~mfdesign.diagnosis.pipeline.Diagnosis`."""
        from mfdesign import outputs
        from mfdesign.diagnosis.forward import forward_model, likelihood_effects
        from mfdesign.diagnosis.pipeline import diagnose

        s = self.settings
        with self._lock():
            state = self._read()
            table = self.data()
            pool = likelihood_effects()
            loose = set(_unkept(pool, state.effects_modules))
            result = diagnose(
                table,
                forward_model(s.physics, table, progress=progress),
                effects=state.effects,
                candidates=[c for c in pool if c not in loose] if loose else None,
                search=s.diagnose_search,
                check_top=s.check_top,
                check_pairs=s.check_pairs,
                max_steps=s.diagnose_rounds,
                progress=progress,
            )
            effects = tuple(dict.fromkeys([*state.effects, *result.found]))
            inputs = {src.id: src.sha256 for src in state.sources}
            record = {
                "for_round": len(_round_folders(self.folder)),
                "effects_before": list(state.effects),
                "effects_after": list(effects),
                "diagnosis": result.to_json(),
                "provenance": provenance(call or "Campaign.diagnose()", {"seed": s.seed}, inputs),
            }
            outputs.write_json(self.folder / "diagnosis.json", record, default=float)
            self._write(dataclasses.replace(state, effects=effects))
        return result

    def fit(self, *, progress: bool = False, call: str = "") -> Round:
        """Calibrate and fit the multi-fidelity model on every source: the next round.

        Before fitting, the previous round's model predicts the membranes told since it
        (data it never saw): that RMSE [N] and 90 % coverage are the round's held-out
        error. The round is written into a temporary folder and renamed into place at the
        end (module doc). Returns the :class:`Round` (its fit on the search physics)."""
        from mfdesign.calibration.workflow import fit_multi_fidelity, force_model_named, material_priors
        from mfdesign.models.ensemble import EnsembleConfig

        s = self.settings
        with self._lock():
            state = self._read()
            previous = _round_folders(self.folder)
            number = len(previous)
            rounds = self.folder / "rounds"
            rounds.mkdir(exist_ok=True)
            for stale in rounds.glob(".round-*.tmp"):  # a killed fit's: we hold the lock, no one writes it
                shutil.rmtree(stale, ignore_errors=True)
            table = self.data()
            heldout = self._heldout(state, previous[-1]) if previous else None
            seed = s.seed + number  # one seed per round, derived from the campaign's
            fit = fit_multi_fidelity(
                table,
                force_model_named(s.physics, table, progress=progress),
                state.effects,
                n_steps=s.mcmc_steps,
                n_walkers=s.walkers or None,
                grow_walkers=True,  # a latent per membrane: more membranes than walkers allow
                max_rows=s.max_rows,
                ensemble_config=EnsembleConfig(n_members=s.members, steps=s.delta_steps, monotone=False),
                seed=seed,
                progress=progress,
                likelihood=s.likelihood,
                membrane_latents=s.membrane_latents,
                membrane_effects=[q for q in s.membrane_effects if q.split(".")[0] in state.effects],
                **material_priors(s.material),
            )
            return self._commit_round(state, fit, table, number, seed, heldout, call or "Campaign.fit()")

    def adopt(self, fit, diagnosis=None, *, call: str = "", posterior_nc: Path | None = None) -> Round:
        """Record a fit made elsewhere (the demo's, on the campaign's data, effects and
        settings) as the campaign's next round, as :meth:`fit` would have written it; with
        ``diagnosis`` (a :class:`~mfdesign.diagnosis.pipeline.Diagnosis`) its record too.
        So ``mfdesign demo --out D`` leaves a campaign that ``ask`` / ``tell`` / ``fit``
        continue without refitting. ``posterior_nc``: the fit's ``posterior.nc``, already
        written on the campaign's data with the round's seed and ``max_rows``: copied, not
        computed again (its pointwise groups cost the demo 6-7 s a write)."""
        from mfdesign import outputs

        s = self.settings
        with self._lock():
            state = self._read()
            number = len(_round_folders(self.folder))
            (self.folder / "rounds").mkdir(exist_ok=True)
            if diagnosis is not None:
                record = {
                    "for_round": number,
                    "effects_before": [],
                    "effects_after": list(state.effects),
                    "diagnosis": diagnosis.to_json(),
                    "provenance": provenance(
                        call or "Campaign.adopt()", {"seed": s.seed}, {src.id: src.sha256 for src in state.sources}
                    ),
                }
                outputs.write_json(self.folder / "diagnosis.json", record, default=float)
            return self._commit_round(
                state, fit, self.data(), number, s.seed + number, None, call or "Campaign.adopt()", posterior_nc
            )

    def _commit_round(
        self, state: _State, fit, table, number: int, seed: int, heldout, call: str, posterior_nc: Path | None = None
    ) -> Round:
        """Write round ``number`` of ``fit`` into a temporary folder, rename it into place."""
        from mfdesign import outputs

        s = state.settings
        rounds = self.folder / "rounds"
        tmp = rounds / f".{_ROUND_PREFIX}{number:03d}.{os.getpid()}.tmp"
        tmp.mkdir()
        sources = {src.id: src.sha256 for src in state.sources}
        meta = self._write_model(fit, table, tmp / "model", seed, s, call, sources, posterior_nc)
        searched = fit
        if s.search_physics != s.physics:  # what a reload gives: the same posterior on the search physics
            from mfdesign.calibration.workflow import for_search

            mf = for_search(fit, s.search_physics)
            searched = dataclasses.replace(fit, model=mf.model, mf=mf)
        if (self.folder / "diagnosis.json").is_file():
            shutil.copy2(self.folder / "diagnosis.json", tmp / "diagnosis.json")
        record = {
            "round": number,
            "data": {"sources": sources, "membranes": len(table.design_keys), "rows": len(table)},
            "effects": list(state.effects),
            "fit": {k: meta[k] for k in ("noise_n", "train_rmse_n", "train_coverage90")},
            "heldout": heldout,
            "settings": s.to_json(),
            "provenance": provenance(call, {"seed": seed}, sources),
        }
        outputs.write_json(tmp / "round.json", record, default=float)
        final = rounds / f"{_ROUND_PREFIX}{number:03d}"
        os.rename(tmp, final)  # the round exists from here on, whole
        return Round(number, final, searched, record)

    @staticmethod
    def _write_model(
        fit, table, folder: Path, seed: int, s: Settings, call: str, sources: dict, posterior_nc: Path | None = None
    ) -> dict:
        """The round's model: ``posterior.nc`` (ArviZ) first (its R-hat and ESS go into the
        posterior's convergence; a copy of ``posterior_nc``, whose writer put them there),
        then :meth:`MFFit.save` (its provenance: ``call`` and the sources' hashes, as the round's)."""
        from mfdesign.calibration.posterior import save_inference_data

        folder.mkdir(parents=True)
        if posterior_nc is not None and Path(posterior_nc).is_file() and "draws_in_file" in fit.posterior.convergence:
            shutil.copy2(posterior_nc, folder / "posterior.nc")
        else:
            save_inference_data(
                fit.posterior, folder / "posterior.nc", fit.model, table, seed=seed, max_rows=s.max_rows
            )
        return fit.save(folder, physics=s.physics, material=s.material, table=table, call=call, inputs=sources)

    def _heldout(self, state: _State, last: Path) -> dict | None:
        """The last round's model on the sources told after it (membranes it never saw)."""
        from mfdesign.calibration.workflow import MFFit, for_table
        from mfdesign.models.predictive import coverage

        seen = json.loads((last / "round.json").read_text())["data"]["sources"]
        new = [src.id for src in state.sources if src.id not in seen]
        if not new:
            return None
        table = self.data(new)
        prev = MFFit.load(last / "model")
        # where the model meets data: on the campaign's physics (exact: the told membranes'
        # own planes, which the fit that follows reads from the cache), not on the search
        # physics the round was saved with (the emulator's error is not the model's)
        mf = for_table(prev, table, self.settings.physics)
        cov = coverage(mf, table, level=0.9, key=prev.seed)
        return {
            "model_round": int(last.name[len(_ROUND_PREFIX) :]),
            "sources": new,
            "membranes": list(table.design_keys),
            "rows": len(table),
            "rmse_n": cov["rmse_n"],
            "coverage90": cov["coverage"],
            "physics": self.settings.physics,
        }

    def ask(
        self,
        q: int = 2,
        sim_runs: int = 0,
        *,
        n_rings: Sequence[int] = (0, 1, 2),
        each_ring_count: bool = False,
        progress: bool = False,
        simulate=None,
        call: str = "",
    ):
        """The next membranes to build (``q``, rig) and simulator runs to make (``sim_runs``).

        Membranes asked for earlier and still pending count as measured
        (:func:`mfdesign.propose`'s ``pending``, BoTorch's ``X_pending``), so an ask
        before the last one's membranes are told does not repeat them. The simulator runs
        are made at once, at the round's calibrated constants (``simulate``: the planes'
        solver, :func:`mfdesign.sim_runs.make`; default the simulator, the stand-in's
        planes when the campaign's physics is ``"standin"``), and join the data as a
        source; each is then ``measured`` (or ``dropped`` when it gave no usable point).

        **Arguments:**

        - `q`: membranes to fabricate (>= 0; `q + sim_runs` >= 1).
        - `sim_runs`: simulator planes to make (>= 0).
        - `n_rings`: the ring counts to search (default all: 0, 1, 2).
        - `each_ring_count`: `q` membranes of each ring count in `n_rings`, one ask per ring
          count (each counting the ones before as pending), then the simulator runs over
          every ring count. In the stiff-rings world of docs/campaign.md this made the
          held-out error fall every round where a free batch did not: a calibration fitted
          mostly on ringed membranes carries their misfit to ringless ones until ringless
          membranes are built.
        - `progress`: progress output.
        - `simulate`: the simulator runs' solver (tests).
        - `call`: the command line, for the provenance.

        **Returns:**

        The new :class:`ProposalEntry` records, ranked. Writes ``asks/askNNN.json``.
        """
        from mfdesign import outputs
        from mfdesign.acquire import propose
        from mfdesign.design import Membrane

        for name, k in (("q", q), ("sim_runs", sim_runs)):
            if not isinstance(k, int) or isinstance(k, bool) or k < 0:
                raise InputError(f"{name} = {k!r}; allowed: an integer >= 0")
        if q + sim_runs < 1:
            raise InputError("q + sim_runs = 0: the ask holds no run; allowed: q >= 1 or sim_runs >= 1")
        if each_ring_count:  # one ask per ring count: each one's membranes pending for the next
            kw = dict(progress=progress, simulate=simulate, call=call)
            entries = []
            for n in dict.fromkeys(n_rings) if q else ():
                entries += self.ask(q, n_rings=(n,), **kw)
            if sim_runs:
                entries += self.ask(0, sim_runs, n_rings=n_rings, **kw)
            return entries
        s = self.settings
        with self._lock():
            state = self._read()
            fit = self.model()
            number = len(_round_folders(self.folder)) - 1
            n_ask = 1 + max((p.ask for p in state.proposals), default=0)
            pending = [Membrane.from_key(p.design) for p in state.proposals if p.status == "pending"]
            predictor = fit.mf.predictor(16)  # type: ignore[attr-defined]
            proposal = propose(
                predictor,
                costs={"rig": s.cost_rig, "sim": s.cost_sim},
                n_restarts=s.restarts,
                n_refine=s.refine,
                n_steps=s.opt_steps,
                key=s.seed + 1000 * n_ask,
                progress=progress,
                budget={"rig": q, "sim": sim_runs},
                pending=pending,
                n_rings=tuple(n_rings),
            )
            start = len(state.proposals)
            entries = [
                ProposalEntry(
                    id=f"p{start + j + 1}",
                    round=number,
                    design=run.design.key(),
                    fidelity=run.fidelity,
                    status="pending",
                    ask=n_ask,
                    rank=run.rank,
                    reduction_rms_n=run.reduction_rms_n,
                    reason=run.reason,
                )
                for j, run in enumerate(proposal.runs)
            ]
            made, new_source = self._make_sim_runs(proposal, predictor, fit, simulate, state, entries)
            entries = [made.get(e.id, e) for e in entries]
            report = proposal.to_json() | {
                "ids": {e.id: e.design for e in entries},
                "provenance": provenance(
                    call or f"Campaign.ask(q={q}, sim_runs={sim_runs}, n_rings={tuple(n_rings)})",
                    {"key": s.seed + 1000 * n_ask},
                ),
            }
            (self.folder / "asks").mkdir(exist_ok=True)
            outputs.write_json(self.folder / "asks" / f"ask{n_ask:03d}.json", report, default=float)
            sources = state.sources + ((new_source,) if new_source is not None else ())
            self._write(dataclasses.replace(state, proposals=state.proposals + tuple(entries), sources=sources))
        return entries

    def _make_sim_runs(self, proposal, predictor, fit, simulate, state: _State, entries):
        """Make the ask's simulator runs (their usable points become one source) and, in the
        same batch, re-compute its membranes to build with the simulator before they are
        shown (issue 43: each entry's note says how far the model is off there, beside its
        predicted spread; not under stand-in physics, whose planes stand for no simulator).
        Returns the entries that changed (by id) and that source (or None)."""
        from mfdesign import sim_runs
        from mfdesign.calibration.workflow import calibrated_sim_params

        s = self.settings
        runs = list(proposal.simulate)
        # a stand-in campaign's planes are its own model's: checking against them says nothing
        checks = list(proposal.fabricate) if simulate is not None or s.physics != "standin" else []
        if not runs and not checks:
            return {}, None
        if simulate is None and s.physics == "standin":
            simulate = _standin_planes
        params, _ = calibrated_sim_params(fit)
        spec = sim_runs.PlaneSpec(n_heights=s.sim_heights, n_pressures=s.sim_pressures)
        done = sim_runs.make(runs + checks, predictor, params, spec, simulate=simulate)
        made, checked = done[: len(runs)], done[len(runs) :]
        changed, source = {}, None
        table = sim_runs.as_measurements(made)
        if table is not None:
            n = len(state.sources)
            source = self._store(table, ("simulated by ask",), len(_round_folders(self.folder)) - 1, None, n)
        by_design = {(e.fidelity, e.design): e for e in entries}
        for m in made:
            e = by_design["sim", m.design.key()]
            usable = table is not None and m.design.key() in table.design_keys
            changed[e.id] = dataclasses.replace(
                e,
                status="measured" if usable else "dropped",
                source=source.id if usable and source is not None else None,
                note=f"simulated: {m.state}; {m.taught()}",
            )
        for m in checked:
            e = by_design["rig", m.design.key()]
            changed[e.id] = dataclasses.replace(e, note=f"simulator check ({m.state}): {m.taught()}")
        return changed, source

    def tell(self, proposal_id: str, measurements, *, check_design: bool = True, call: str = "") -> ProposalEntry:
        """The measurements of a pending proposal: they join the data (a new source) and
        the proposal becomes ``measured``; the next :meth:`fit` uses them.

        **Arguments:**

        - `proposal_id`: the id :meth:`ask` gave (``"p3"``).
        - `measurements`: a Measurements table, or what :func:`mfdesign.load` reads (a rig
          job folder, a Parquet or CSV file, or a list of them).
        - `check_design`: refuse data that hold no membrane of the proposal's design key
          (a wrong folder); False takes them as they are (a membrane built off its key).
        - `call`: the command line, for the provenance.

        **Returns:**

        The updated :class:`ProposalEntry`. ``InputError`` for an unknown id, a proposal
        not pending, or data that do not hold its membrane.
        """
        with self._lock():
            state = self._read()
            entry = self._entry(state, proposal_id)
            if entry.status != "pending":
                raise InputError(f"proposal {proposal_id} is {entry.status}; allowed: a pending proposal")
            table, origin = _measurements(measurements, f"tell {proposal_id}")
            if check_design and entry.design not in table.design_keys:
                raise InputError(
                    f"the data for {proposal_id} hold membranes {table.design_keys[:4]}, not its design "
                    f"{entry.design}; allowed: its measurements (or check_design=False / --any-design)"
                )
            source = self._store(table, origin, len(_round_folders(self.folder)) - 1, proposal_id, len(state.sources))
            told = dataclasses.replace(entry, status="measured", source=source.id, note=call or "Campaign.tell")
            proposals = tuple(told if p.id == proposal_id else p for p in state.proposals)
            self._write(dataclasses.replace(state, sources=state.sources + (source,), proposals=proposals))
        return told

    def drop(self, proposal_id: str, reason: str = "") -> ProposalEntry:
        """Mark a pending proposal ``dropped`` (it will not be built): no longer pending."""
        with self._lock():
            state = self._read()
            entry = self._entry(state, proposal_id)
            if entry.status != "pending":
                raise InputError(f"proposal {proposal_id} is {entry.status}; allowed: a pending proposal")
            dropped = dataclasses.replace(entry, status="dropped", note=reason)
            self._write(
                dataclasses.replace(
                    state, proposals=tuple(dropped if p.id == proposal_id else p for p in state.proposals)
                )
            )
        return dropped

    def _entry(self, state: _State, proposal_id: str) -> ProposalEntry:
        found = [p for p in state.proposals if p.id == proposal_id]
        if not found:
            pending = [p.id for p in state.proposals if p.status == "pending"]
            raise InputError(
                f"proposal {proposal_id!r} is not in campaign {self.folder}; allowed: a pending proposal's id "
                f"({', '.join(pending) or 'none pending: ask first'})"
            )
        return found[0]

    def status(self) -> CampaignStatus:
        """Where the campaign stands (:class:`CampaignStatus`; ``summary()`` for a table)."""
        state = self._read()
        problems = []
        for s in state.sources:
            path = self.folder / s.file
            if not path.is_file() or _sha256(path) != s.sha256:
                problems.append(f"source {s.id} ({path}) is missing or changed (sha256 differs)")
        rounds = tuple(json.loads((p / "round.json").read_text()) for p in _round_folders(self.folder))
        return CampaignStatus(
            self.folder,
            state.settings,
            state.effects,
            state.sources,
            state.proposals,
            rounds,
            tuple(problems),
            state.effects_modules,
        )

    def report(self) -> Path:
        """Write ``report.json`` (the status, every round's record) and ``report.txt`` (its
        summary) into the folder; returns the JSON's path. (No HTML page yet.)"""
        from mfdesign import outputs

        status = self.status()
        with self._lock():
            outputs.write_text(self.folder / "report.txt", status.summary() + "\n")
            return outputs.write_json(self.folder / "report.json", status.to_json(), default=float)


def _standin_planes(designs, spec, params) -> list:
    """The stand-in's planes in :func:`mfdesign.sim_runs.simulate_planes`' layout."""
    import numpy as np

    from mfdesign.models.standin import standin_plane

    out = []
    for d in designs:
        r = standin_plane(d, spec.h_mm, spec.p_pa, params)
        out.append((np.asarray(r.force_n, float), np.asarray(r.status), np.asarray(r.max_locking, float)))
    return out
