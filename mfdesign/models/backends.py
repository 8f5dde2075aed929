"""The force model by name (``--physics exact | emulator | standin``): the one place that
knows every implementation of :class:`~mfdesign.models.force.ForceModel`."""

from __future__ import annotations

from mfdesign.models.force import FORCE_MODELS, ForceModel
from mfdesign.physics.params import SimParams

__all__ = ["force_model_for"]


def force_model_for(
    name: str,
    design_keys=(),
    *,
    h_max_mm: float = 80.0,
    p_max_pa: float = 10_000.0,
    base: SimParams = SimParams(),
    progress: bool = False,
    cache=None,
    grow: str = "tensor",
    also: SimParams | None = None,
    tensor: dict | None = None,
    additive: dict | None = None,
) -> ForceModel:
    """The force model called ``name`` (one of :data:`FORCE_MODELS`).

    Arguments:
        name: ``"exact"`` (simulator planes of ``design_keys``; the lattice grows as fits
            need it), ``"emulator"`` (the bundled neural emulator) or ``"standin"``.
        design_keys: the measured designs (exact only).
        h_max_mm, p_max_pa: the highest plate height [mm] and gauge pressure [Pa] of the rows (exact only).
        base: the reference simulator constants (exact only).
        progress: progress bars while planes are solved.
        cache: plane cache folder (exact only; default ``$MFDESIGN_CACHE_DIR/planes``).
        grow: where the exact model's lattice puts a constant it does not vary yet
            (``"tensor"``: calibration; ``"additive"``: diagnosis, one effect at a time).
        also: constants (fields of any shape) the exact model holds from the start (their
            planes are solved with the reference ones).
        tensor: axes of the exact model's full product lattice from the start (axis name ->
            coordinate range); with ``grow="additive"``, ``{"jm": (0, 0), "ring": (0, 0)}``
            keeps the material's axes crossed and puts effects on additive axes.
        additive: axes that cross only the reference node from the start (exact only), e.g.
            ``{"ring": (0, 0)}`` with ``tensor={"jm": (0, 0)}``: effects crossed with J_m only.
    """
    if name == "exact":
        from mfdesign.models.exact import build_exact

        if not len(design_keys):
            raise ValueError("the exact force model needs the measured designs")
        return build_exact(
            design_keys,
            h_max_mm=h_max_mm,
            p_max_pa=p_max_pa,
            base=base,
            outside="clamp",
            cache=cache,
            progress=progress,
            grow=grow,
            also=also,
            tensor=tensor,
            additive=additive,
        )
    if name == "emulator":
        from mfdesign.models.emulator import load_default

        try:
            return load_default()
        except FileNotFoundError as err:
            raise ValueError(f"no trained emulator artifact ({err}); train it or use --physics exact") from None
    if name == "standin":
        from mfdesign.models.standin import StandinForceModel

        return StandinForceModel()
    raise ValueError(f"--physics must be one of {list(FORCE_MODELS)}, got {name!r}")
