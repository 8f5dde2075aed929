"""Simulator planes on a Dask cluster (optional: ``pip install "mfdesign[dask]"``).

:func:`~mfdesign.physics.solve.force_planes` (and so :func:`~mfdesign.physics.planes.solve_planes`,
the exact model's lattice growth and the simulator runs of ``propose`` / ``ask``) sends its
plane jobs to a Dask distributed scheduler when one is named: its ``scheduler`` argument,
else the innermost :func:`use_scheduler` (the CLI's ``--scheduler ADDRESS``), else the
environment variable ``MFDESIGN_SCHEDULER`` (an address such as ``tcp://host:8786``).
Without one, every plane is solved on this machine's cores, as before. Dask is imported
only when a scheduler is named; a missing Dask is then one line of bad input
(:class:`~mfdesign.errors.InputError`).

On the cluster each task solves :data:`PLANES_PER_TASK` planes with the same function the
local path runs (``solve._planes_here``: the plane, its repair and its atomic cache write),
one core per task; results come back in order. Planes differ in cost (a repair by the FE
reference can take several planes' time), so small tasks balance best, and a task's
overhead (milliseconds) is nothing against a plane's seconds.

Workers: ``dask worker ADDRESS --nthreads 1 --preload mfdesign.physics.cluster`` (one
thread each: a plane's vmapped continuation runs on one core; ``--preload`` runs
:func:`dask_setup` before any task: float64, JAX's persistent compilation cache in
``$MFDESIGN_CACHE_DIR`` and equinox's NaN-on-error mode, as the CLI sets them). Planes
are written by the workers into the cache folder the caller names, so
``MFDESIGN_CACHE_DIR`` must be a folder every worker sees at the same path (a shared
file system); the caller writes any plane it then does not find there itself.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
from typing import Any, Callable, Iterator, Sequence

from mfdesign.errors import InputError

__all__ = ["PLANES_PER_TASK", "SCHEDULER_ENV", "dask_setup", "map_chunks", "scheduler_from", "use_scheduler"]

log = logging.getLogger(__name__)

SCHEDULER_ENV = "MFDESIGN_SCHEDULER"
PLANES_PER_TASK = 1
CONNECT_TIMEOUT_S = 20  # a scheduler that does not answer by then is bad input, not a hang

_ACTIVE: list[Any] = []  # use_scheduler's stack (innermost last)


def _distributed(address: Any):
    """``dask.distributed``, or the one-line InputError saying how to get it."""
    try:
        import distributed
    except ImportError:
        raise InputError(
            f"a Dask scheduler was named ({address!r}: --scheduler or {SCHEDULER_ENV}) but Dask distributed "
            f'is not installed; allowed: pip install "mfdesign[dask]", or no scheduler (this machine\'s cores)'
        ) from None
    return distributed


def scheduler_from(scheduler: Any = None) -> Any:
    """The scheduler plane jobs go to, or None for this machine: ``scheduler`` itself (an
    address, a ``distributed.Client`` or a cluster object; ``False`` or ``""``: this machine,
    whatever the environment says), else the innermost :func:`use_scheduler`, else
    ``$MFDESIGN_SCHEDULER`` (unset or empty: this machine)."""
    if scheduler is None:
        scheduler = _ACTIVE[-1] if _ACTIVE else os.environ.get(SCHEDULER_ENV, "").strip()
    if scheduler is False or (isinstance(scheduler, str) and not scheduler.strip()):
        return None
    return scheduler.strip() if isinstance(scheduler, str) else scheduler


@contextlib.contextmanager
def use_scheduler(scheduler: Any = None) -> Iterator[None]:
    """Within the block, plane jobs go to ``scheduler`` (the CLI's ``--scheduler``); None
    changes nothing (``$MFDESIGN_SCHEDULER`` still counts). Checks at once that Dask is
    installed (before any computation)."""
    if scheduler is None:
        yield
        return
    if scheduler_from(scheduler) is not None:
        _distributed(scheduler)
    _ACTIVE.append(scheduler)
    try:
        yield
    finally:
        _ACTIVE.pop()


@contextlib.contextmanager
def _client(scheduler: Any) -> Iterator[Any]:
    """A ``distributed.Client`` on ``scheduler`` (one given as a Client is used as it is and
    left open); an address no scheduler answers at is InputError."""
    distributed = _distributed(scheduler)
    if isinstance(scheduler, distributed.Client):
        yield scheduler
        return
    try:
        client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, ValueError, TypeError) as err:  # refused, timed out, not an address
        raise InputError(
            f"Dask scheduler {scheduler!r} (--scheduler or {SCHEDULER_ENV}): no scheduler answered "
            f"({type(err).__name__}: {err}); allowed: the address `dask scheduler` prints, e.g. tcp://host:8786"
        ) from None
    with client:
        yield client


def map_chunks(
    scheduler: Any,
    fn: Callable[[list], list],
    items: Sequence,
    *,
    per_task: int,
    progress: bool = False,
    desc: str = "",
) -> list:
    """``fn`` on consecutive chunks of ``per_task`` items as tasks of ``scheduler``; the
    results (each chunk's list) concatenated in the items' order. ``fn`` must pickle (a
    module-level function or a ``functools.partial`` of one). A failed task raises here
    and the tasks not yet run are cancelled."""
    items = list(items)
    chunks = [items[i : i + per_task] for i in range(0, len(items), max(1, per_task))]
    with _client(scheduler) as client:
        futures = client.map(fn, chunks, pure=False)
        try:
            if progress:
                from distributed import as_completed
                from tqdm.auto import tqdm

                size = {f.key: len(c) for f, c in zip(futures, chunks)}
                with tqdm(total=len(items), desc=f"{desc} (Dask)", unit="plane") as bar:
                    for done in as_completed(futures, loop=client.loop):
                        bar.update(size[done.key])
            parts = client.gather(futures)
        finally:
            client.cancel([f for f in futures if not f.done()])
    return [r for part in parts for r in part]


def prepare_worker() -> None:
    """What an mfdesign entry point sets, in a worker process: float64, JAX's persistent
    compilation cache in ``$MFDESIGN_CACHE_DIR`` and ``EQX_ON_ERROR=nan``
    (:func:`mfdesign._cache.enable_compilation_cache`; that one works only before equinox
    is imported, i.e. from ``--preload``), and the worker's own ``JAX_PLATFORMS``.
    Idempotent.

    Why ``JAX_PLATFORMS`` again: JAX reads it when it is imported, and a worker that a
    script importing JAX at its top spawns (``LocalCluster(env={"JAX_PLATFORMS": "cpu"})``)
    re-imports that script (multiprocessing's spawn) before Dask sets the worker's
    environment. On a GPU machine every such worker then took the GPU the script already
    held and failed for want of its memory (H200, session 35). Set while no backend is up,
    it counts; afterwards it changes nothing."""
    import jax

    from mfdesign._cache import enable_compilation_cache
    from mfdesign._x64 import enable_x64

    platforms = os.environ.get("JAX_PLATFORMS", "")
    if platforms and jax.config.jax_platforms != platforms:  # type: ignore[attr-defined]
        jax.config.update("jax_platforms", platforms)
    enable_compilation_cache()
    enable_x64()


def dask_setup(worker: Any = None) -> None:
    """Dask's preload hook: ``dask worker ADDRESS --nthreads 1 --preload mfdesign.physics.cluster``."""
    prepare_worker()


def on_worker(fn: Callable, **kwargs: Any) -> Callable[[list], list]:
    """``fn(chunk, **kwargs)`` as a picklable task body that prepares its worker first."""
    return functools.partial(_run_prepared, fn, kwargs)


def _run_prepared(fn: Callable, kwargs: dict, chunk: list) -> list:
    prepare_worker()
    return fn(chunk, **kwargs)
