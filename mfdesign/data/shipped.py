"""Files shipped inside the package, found with :mod:`importlib.resources` (so that an
installed wheel finds them as well as a source checkout does).

* ``bundled_virtual.parquet``: the demo's dataset, six membranes measured on the virtual
  rig with one hidden effect (``experiments/make_bundled_dataset.py`` regenerates it);
  ``bundled_card.json`` says what is hidden;
* ``emulator/``: the trained simulator emulator (``experiments/train_emulator.py``);
* ``planes.npz``: the simulator planes the demo asks of the bundled membranes, read by
  :func:`mfdesign.physics.planes.solve_planes` before it solves one
  (``python -m tools.ship_planes`` regenerates it).
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

__all__ = ["BUNDLED_NAME", "bundled_card_path", "card_truths", "bundled_path", "emulator_dir", "shipped_path"]

BUNDLED_NAME = "bundled"  # the DATA keyword for the bundled dataset (mfdesign.data.sources)


def shipped_path(name: str) -> Path:
    """Path of the shipped file ``name`` (relative to ``mfdesign/data/files``)."""
    return Path(str(files("mfdesign.data").joinpath("files", *name.split("/"))))


def bundled_path() -> Path:
    return shipped_path("bundled_virtual.parquet")


def bundled_card_path() -> Path:
    return shipped_path("bundled_card.json")


def emulator_dir() -> Path:
    return shipped_path("emulator")


def card_truths(card: dict) -> dict[str, float]:
    """The parameters the bundled data were made with: the authors' rubber constants
    (``mu_pa`` in Pa, ``jm`` dimensionless) and the card's hidden effect (its ``theta``).

    Arguments:
        card: the bundled dataset's card (``bundled_card.json``, read as a dict).
    """
    from mfdesign.materials import ECOFLEX_JM, ECOFLEX_MU_PA

    return {"mu_pa": ECOFLEX_MU_PA, "jm": ECOFLEX_JM, **card["hidden_effect"]["theta"]}
