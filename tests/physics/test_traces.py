"""mfdesign.physics._traces: the solver's kernels stored as jax.export modules, so that a
new process compiles them without tracing them again (issue 40)."""

from __future__ import annotations

import pickle
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mfdesign.materials import first_invariant
from mfdesign.physics import _traces


def _flat(kernel):
    def flat(*xs):
        return kernel(*xs)

    flat.__name__ = kernel.__name__
    return flat


def _compile(x, y):
    leaves = [jnp.asarray(x), jnp.asarray(y)]
    _, tree = jax.tree.flatten(tuple(leaves))
    sig = tuple((v.shape, v.dtype, v.weak_type) for v in leaves)
    return _traces.compiled(first_invariant, _flat(first_invariant), leaves, (), tree, sig), leaves


@pytest.fixture
def store(tmp_path, monkeypatch):
    monkeypatch.setattr(_traces, "folder", lambda: tmp_path / "kernels")
    return tmp_path / "kernels"


@pytest.fixture
def exports(monkeypatch):
    """One entry per jax.export.export call: an export traces the function."""
    calls: list = []
    export = jax.export.export

    def spy(*a, **k):
        calls.append(1)
        return export(*a, **k)

    monkeypatch.setattr(jax.export, "export", spy)
    return calls


def test_a_stored_kernel_is_compiled_without_tracing_it_again(store, exports):
    l1, l2 = np.array([1.2, 1.5]), np.array([1.1, 0.9])
    program, leaves = _compile(l1, l2)
    assert len(exports) == 1 and len(list(store.glob("first_invariant-*" + _traces.SUFFIX))) == 1
    np.testing.assert_allclose(program(*leaves), np.asarray(first_invariant(l1, l2)), rtol=1e-15)
    again, leaves = _compile(l1 + 0.1, l2)  # as a new process would: read, not traced
    assert len(exports) == 1
    np.testing.assert_allclose(again(*leaves), np.asarray(first_invariant(l1 + 0.1, l2)), rtol=1e-15)
    _compile(np.ones(3), np.ones(3))  # another signature: its own module
    assert len(exports) == 2 and len(list(store.glob("*" + _traces.SUFFIX))) == 2


def test_a_damaged_file_is_traced_again_and_replaced(store):
    l1, l2 = np.array([1.2, 1.5]), np.array([1.1, 0.9])
    _compile(l1, l2)
    (path,) = store.glob("*" + _traces.SUFFIX)
    path.write_bytes(b"not a module")
    program, leaves = _compile(l1, l2)
    np.testing.assert_allclose(program(*leaves), np.asarray(first_invariant(l1, l2)), rtol=1e-15)
    assert path.read_bytes() != b"not a module"


def test_nothing_is_stored_where_the_store_is_off_or_the_kernel_is_a_closure(tmp_path, monkeypatch):
    monkeypatch.setattr(_traces, "folder", lambda: None)
    _compile(np.ones(2), np.ones(2))

    def local(x, y):  # a closure's captured values are not in the key: never stored
        return x + y

    monkeypatch.setattr(_traces, "folder", lambda: tmp_path / "kernels")
    leaves = [jnp.ones(2), jnp.ones(2)]
    _, tree = jax.tree.flatten(tuple(leaves))
    program = _traces.compiled(local, _flat(local), leaves, (), tree, ())
    np.testing.assert_allclose(program(*leaves), 2.0)
    assert not (tmp_path / "kernels").exists()


def test_the_store_is_on_only_with_the_compilation_cache_and_nan_checks(tmp_path, monkeypatch):
    monkeypatch.setenv("MFDESIGN_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("EQX_ON_ERROR", "nan")
    monkeypatch.setattr(_traces, "_compilation_cache_dir", lambda: None)
    assert _traces.folder() is None
    monkeypatch.setattr(_traces, "_compilation_cache_dir", lambda: str(tmp_path))
    assert _traces.folder() == tmp_path / "kernels"
    monkeypatch.setenv("EQX_ON_ERROR", "raise")  # host callbacks: no export
    assert _traces.folder() is None


def test_a_new_process_finds_the_stored_shapes_of_a_kernels_family(store):
    """A padded call (solve._kept_call) may run on a kernel an earlier process stored:
    KeptPrograms.holders lists it beside the programs kept in memory."""
    from mfdesign.physics.solve import KeptPrograms

    _compile(np.ones(4), np.ones(4))
    small = (jnp.ones(2), jnp.ones(2))
    _, tree = jax.tree.flatten(small)
    sig = tuple((v.shape, v.dtype, v.weak_type) for v in small)
    assert _traces.stored_shapes(first_invariant, (), tree, sig) == [((4,), (4,))]
    assert KeptPrograms().holders(first_invariant, small, padded=(0, 1)) == [{0: (4,), 1: (4,)}]
    assert KeptPrograms().holders(first_invariant, small, padded=(0,)) == []  # the second may not grow
    for path in store.glob("*" + _traces.SUFFIX):
        path.unlink()  # listed but gone: not offered
    assert _traces.stored_shapes(first_invariant, (), tree, sig) == []


def test_a_kernels_key_reads_the_sources_it_imports_and_not_the_others():
    """Imports flow downstream, so the solver's key holds the physics and what it imports,
    not the CLI or a workflow: an edit there keeps every stored (and shipped) kernel."""
    names = {str(p.relative_to(_traces._PACKAGE)) for p in _traces._closure({"mfdesign.physics.solve"})}
    assert {"physics/solve.py", "physics/shooting.py", "design.py", "materials.py"} <= names
    assert not any(n.startswith(("cli/", "workflows/", "report/", "models/")) or n == "acquire.py" for n in names)
    acquire = {str(p.relative_to(_traces._PACKAGE)) for p in _traces._closure({"mfdesign.acquire"})}
    assert {"acquire.py", "physics/solve.py"} <= acquire | names and "acquire.py" not in names
    # the classes in a kernel's arguments bring their modules' sources into the key
    _, modules = _traces._key_bytes((_Scale(jnp.ones(1), 1.0), first_invariant))
    assert {__name__, "mfdesign.materials"} <= modules


def test_a_comment_or_a_docstring_is_not_part_of_a_kernels_key(tmp_path):
    a, b, c = (tmp_path / f"{n}.py" for n in "abc")
    a.write_text('"""Doc."""\n\n\ndef f(x):\n    """Twice."""\n    return 2 * x  # why\n')
    b.write_text('"""Other doc."""\n\n\ndef f(x):\n    # a new comment\n    return 2 * x\n')
    c.write_text('"""Doc."""\n\n\ndef f(x):\n    """Twice."""\n    return 3 * x  # why\n')
    assert _traces._digest(a) == _traces._digest(b) != _traces._digest(c)


def test_kernels_are_keyed_from_many_threads_at_once():
    """The plane solves' threads key the solver's kernels together: CPython 3.11's ast.parse
    is not thread-safe (bench_round22 crashed with "AST constructor recursion depth
    mismatch" in session 40); the key's parses run under a lock."""
    from concurrent.futures import ThreadPoolExecutor

    roots = ["mfdesign.physics.solve", "mfdesign.acquire", "mfdesign.calibration.mcmc", "mfdesign.optimization"]
    for _ in range(3):
        for cached in (_traces._imports, _traces._digest, _traces._code):
            cached.cache_clear()
        with ThreadPoolExecutor(8) as pool:
            codes = list(pool.map(lambda r: _traces._code(frozenset({r})), roots * 4))
        assert codes == [_traces._code(frozenset({r})) for r in roots * 4]


def test_a_labs_own_effect_file_keys_the_kernels_it_runs_in(tmp_path, monkeypatch):
    """mfdesign.user_effects registers the module it loads; its code is in the key of any
    kernel whose arguments hold one of its classes, as mfdesign's own sources are."""
    import types

    name = _traces.USER_MODULES + "mine"
    keys = []
    for i, text in enumerate(["GAIN = 1.0\n", "GAIN = 1.0  # a comment\n", "GAIN = 2.0\n"]):
        (tmp_path / f"v{i}.py").write_text(text)
        module = types.ModuleType(name)
        module.__file__ = str(tmp_path / f"v{i}.py")
        monkeypatch.setitem(__import__("sys").modules, name, module)
        _traces._code.cache_clear()
        keys.append(_traces._code(frozenset({name, "mfdesign.materials"})))
    _traces._code.cache_clear()
    assert keys[0] == keys[1] != keys[2]


def test_a_shipped_kernel_is_read_where_the_store_lacks_it(tmp_path, monkeypatch, exports):
    """tools.ship_kernels packs a store; a store without the file reads the pack's copy
    (compiled without tracing, its family's shapes listed); MFDESIGN_SHIPPED_KERNELS=0 traces."""
    from mfdesign.data import shipped
    from tools.ship_kernels import pack

    monkeypatch.setattr(_traces, "folder", lambda: tmp_path / "made" / "kernels")
    l1, l2 = np.array([1.2, 1.5]), np.array([1.1, 0.9])
    _compile(l1, l2)
    assert pack([tmp_path / "made"], tmp_path / "kernels.npz") == 1 and len(exports) == 1
    monkeypatch.setattr(shipped, "shipped_path", lambda name: tmp_path / name)
    monkeypatch.setattr(_traces, "folder", lambda: tmp_path / "fresh" / "kernels")
    _traces._shipped_pack.cache_clear()
    try:
        program, leaves = _compile(l1 + 0.1, l2)
        assert len(exports) == 1  # read from the pack, not traced
        np.testing.assert_allclose(program(*leaves), np.asarray(first_invariant(l1 + 0.1, l2)), rtol=1e-15)
        small = (jnp.ones(2), jnp.ones(2))
        _, tree = jax.tree.flatten(small)
        sig = tuple((v.shape, v.dtype, v.weak_type) for v in small)
        assert _traces.stored_shapes(first_invariant, (), tree, sig) == [((2,), (2,))]
        assert _traces.stale_shipped() == []
        code = _traces._code
        monkeypatch.setattr(_traces, "_code", lambda roots: "edited since")  # a source changed
        assert _traces.stale_shipped() == [p.name for p in (tmp_path / "made" / "kernels").glob("*.jaxexport")]
        monkeypatch.setattr(_traces, "_code", code)
        monkeypatch.setenv(_traces.SHIPPED_ENV, "0")
        assert _traces.stored_shapes(first_invariant, (), tree, sig) == []
        monkeypatch.setattr(_traces, "folder", lambda: tmp_path / "off" / "kernels")
        _compile(l1, l2)
        assert len(exports) == 2  # off: traced as before the pack
    finally:
        _traces._shipped_pack.cache_clear()


def test_the_shipped_kernels_are_those_of_todays_sources():
    """Every kernel in mfdesign/data/files/kernels.npz was packed from the sources it runs
    today: a stale one is traced again by every lab's first demo (their tracing: ~38 s of
    a cold demo on 2 cores, issue 40). After a change to the physics, the models, the acquisition or
    the optimiser: ``python -m tools.ship_kernels`` (~10 minutes on 2 cores)."""
    import json

    from tools.ship_kernels import VERSIONS, environment

    _traces._shipped_pack.cache_clear()
    made = json.loads(_traces._shipped_pack().get(VERSIONS) or b"{}")
    if made != environment():  # every key holds the versions: the pack is not read here at all
        pytest.skip(f"kernels.npz was made with {made}; this environment has {environment()}")
    stale = _traces.stale_shipped()
    assert not stale, f"{len(stale)} shipped kernel(s) stale, e.g. {stale[:3]}: run python -m tools.ship_kernels"


class _Scale(eqx.Module):
    w: jax.Array
    factor: float = eqx.field(static=True)


def _affine(m: _Scale, x, n: int):
    return m.factor * m.w * x + n


_stored_affine = _traces.stored_jit(_affine)


def _affine_minus(m: _Scale, x, n: int):
    return m.factor * m.w * x - n


_stored_affine_fast = _traces.stored_jit(fast_compile=True)(_affine_minus)  # OPTIONS['jit-fast']'s programs


@pytest.fixture
def stored_jit_store(store, monkeypatch):
    """The store on for this module's functions (stored_jit stores mfdesign's alone), and
    this process's programs forgotten before and after (a new process)."""
    monkeypatch.setattr(_traces, "_storable", lambda fn: True)
    _traces._PROGRAMS.clear()
    yield store
    _traces._PROGRAMS.clear()


def test_stored_jit_calls_the_stored_module_in_a_new_process(stored_jit_store, exports):
    m, x = _Scale(jnp.array([1.0, 2.0]), 2.0), np.array([3.0, 4.0])
    out = _stored_affine(m, x, 1)
    np.testing.assert_array_equal(out, eqx.filter_jit(_affine)(m, x, 1))
    assert len(exports) == 1 and len(list(stored_jit_store.glob("_affine-*" + _traces.SUFFIX))) == 1
    _traces._PROGRAMS.clear()  # a new process: read from the store, not traced
    m2 = _Scale(jnp.array([5.0, 6.0]), 2.0)
    np.testing.assert_array_equal(_stored_affine(m2, x + 1, 1), eqx.filter_jit(_affine)(m2, x + 1, 1))
    assert len(exports) == 1
    # a static value is in the key: another factor, another n, another shape: each its own module
    np.testing.assert_array_equal(_stored_affine(_Scale(m.w, 3.0), x, 1), 3.0 * m.w * x + 1)
    np.testing.assert_array_equal(_stored_affine(m, x, 2), 2.0 * m.w * x + 2)
    _stored_affine(_Scale(jnp.ones(3), 2.0), np.ones(3), 1)
    assert len(exports) == 4 and len(list(stored_jit_store.glob("*" + _traces.SUFFIX))) == 4


def test_stored_jit_traces_as_usual_what_it_cannot_key(stored_jit_store):
    """A closure's captured values would not be in the key (it does not pickle), and a
    call under a trace has no values to export: both are plain filter_jit calls."""
    k = 3.0

    class _Closure(eqx.Module):
        fn: object = eqx.field(static=True)

    def under(x):
        return _stored_affine(_Scale(jnp.ones(2), 2.0), x, 1)

    np.testing.assert_array_equal(jax.jit(under)(jnp.array([1.0, 2.0])), [3.0, 5.0])
    m = _Closure(lambda v: v * k)
    out = _traces.stored_jit(_apply)(m, jnp.array([1.0, 2.0]))
    np.testing.assert_array_equal(out, [3.0, 6.0])
    assert not list(stored_jit_store.glob("*" + _traces.SUFFIX))


def _apply(m, x):
    return m.fn(x)


def test_stored_jit_keys_a_jitted_function_by_name_and_refuses_a_closure():
    """jnp.tanh (a jitted function, which pickle refuses) in an ensemble's static fields
    still keys; a closure never does (its captured values are not in the bytes)."""
    assert _traces._key_bytes((jnp.tanh, jax.nn.gelu))[0] == _traces._key_bytes((jnp.tanh, jax.nn.gelu))[0]
    assert _traces._key_bytes(jnp.tanh)[0] != _traces._key_bytes(jnp.sinh)[0]
    k = 2.0

    def local(x):
        return k * x

    with pytest.raises(pickle.PicklingError):
        _traces._key_bytes(local)
    with pytest.raises(pickle.PicklingError):
        _traces._key_bytes(jax.jit(local))


_IDENTITY = lambda x: x  # noqa: E731 -- as equinox's MLP keeps its default final activation
_DOUBLE = lambda x: 2 * x  # noqa: E731


def test_stored_jit_keys_a_module_level_lambda_by_its_code():
    assert _traces._key_bytes(_IDENTITY)[0] == _traces._key_bytes(_IDENTITY)[0]
    assert _traces._key_bytes(_IDENTITY)[0] != _traces._key_bytes(_DOUBLE)[0]
    # an MLP as the ensemble builds them: its default final activation is equinox's lambda
    mlp = eqx.nn.MLP(2, 2, 4, 1, activation=jnp.tanh, key=jax.random.key(0))
    assert _traces._key_bytes(eqx.filter(mlp, eqx.is_array, inverse=True))


@pytest.fixture
def ahead_clean():
    _traces.USED.clear()
    _traces.cancel_ahead()
    yield
    _traces.cancel_ahead()
    _traces.USED.clear()


@pytest.fixture
def compilation_cache(tmp_path, monkeypatch):
    """JAX's persistent compilation cache on in a fresh folder (every program written), and
    the names of the programs read back from it; the process's own settings restored after."""
    from jax._src import compilation_cache as cc
    from jax._src import compiler

    hits: list[str] = []
    log_hit = compiler.log_persistent_cache_hit
    monkeypatch.setattr(compiler, "log_persistent_cache_hit", lambda name, key: (hits.append(name), log_hit(name, key)))
    names = (
        "jax_compilation_cache_dir",
        "jax_persistent_cache_min_compile_time_secs",
        "jax_persistent_cache_min_entry_size_bytes",
    )
    old = {n: getattr(jax.config, n) for n in names}
    for n, v in zip(names, (str(tmp_path / "xla"), 0.0, 0)):
        jax.config.update(n, v)
    cc.reset_cache()
    yield hits
    for n, v in old.items():
        jax.config.update(n, v)
    cc.reset_cache()


def test_a_plan_compiles_its_kernels_ahead_into_the_compilation_cache(
    stored_jit_store, exports, ahead_clean, compilation_cache
):
    """A run's kernels in the order it called them (its plan) compile on a background
    thread in the next process; the calls then load those programs from the compilation
    cache (no compilation, no trace), with the same results."""
    m, x = _Scale(jnp.array([1.0, 2.0]), 2.0), np.array([3.0, 4.0])
    _stored_affine(m, x, 1)
    l1, l2 = np.array([1.2, 1.5]), np.array([1.1, 0.9])
    _compile(l1, l2)
    _stored_affine_fast(m, x, 1)
    assert [kind for _, kind in _traces.USED] == ["jit", "kernel", "jit-fast"]
    _traces.write_plan("run")
    assert (stored_jit_store / "run.plan.json").is_file()
    # a new process: its own programs and a compilation cache with none of the kernels
    _traces._PROGRAMS.clear()
    jax.clear_caches()
    for entry in (stored_jit_store.parent / "xla").iterdir():
        entry.unlink()
    assert _traces.compile_ahead("run") == 3
    for job in list(_traces._AHEAD.values()):
        assert job.result(timeout=120)
    compilation_cache.clear()
    np.testing.assert_array_equal(_stored_affine(m, x + 1, 1), 2.0 * m.w * (x + 1) + 1)
    program, leaves = _compile(l1 + 0.1, l2)
    np.testing.assert_allclose(program(*leaves), np.asarray(first_invariant(l1 + 0.1, l2)), rtol=1e-15)
    np.testing.assert_array_equal(_stored_affine_fast(m, x + 1, 1), 2.0 * m.w * (x + 1) - 1)
    # each compiled ahead with its caller's compiler options (part of the cache's key): hits
    assert {"jit_call", "jit_first_invariant"} <= set(compilation_cache), compilation_cache
    assert compilation_cache.count("jit_call") == 2, compilation_cache
    assert not _traces._AHEAD and len(exports) == 3
    assert _traces.compile_ahead("no-such-plan") == 0


def test_a_kernel_still_queued_is_compiled_by_its_caller(stored_jit_store, ahead_clean):
    """Waiting for a queued kernel would wait for the queue before it: the caller cancels it."""
    import concurrent.futures

    m, x = _Scale(jnp.array([1.0, 2.0]), 2.0), np.array([3.0, 4.0])
    _stored_affine(m, x, 1)
    ((name, _),) = _traces.USED
    _traces._PROGRAMS.clear()
    queued: concurrent.futures.Future = concurrent.futures.Future()  # never started
    _traces._AHEAD[name] = queued
    np.testing.assert_array_equal(_stored_affine(m, x, 1), 2.0 * m.w * x + 1)
    assert queued.cancelled() and not _traces._AHEAD


def test_a_demo_has_a_plan_only_at_its_default_settings():
    from mfdesign.workflows.demo import BUNDLED, DemoSettings, _plan_name

    assert _plan_name(DemoSettings(), BUNDLED) == "demo-full"
    assert _plan_name(DemoSettings.quick(), BUNDLED) == "demo-quick"
    assert _plan_name(DemoSettings(seed=1), BUNDLED) is None
    assert _plan_name(DemoSettings(), "elsewhere.parquet") is None


def test_a_demo_compiles_ahead_only_where_no_earlier_run_stored_its_plan(store, ahead_clean):
    assert not store.exists()  # a cold run that read every kernel from the pack stores none
    assert not _traces.plan_stored("demo-quick")  # a cold store: compiled ahead
    _traces.USED.append(("k.jaxexport", "jit"))
    _traces.write_plan("demo-quick")  # makes the store's folder
    assert _traces.plan_stored("demo-quick")  # warm: its programs are in the compilation cache


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a thread's own nice value is Linux's")
def test_the_ahead_thread_runs_at_the_lowest_priority():
    """The ahead thread runs at the lowest priority, the rest of the process as it was."""
    import os
    import threading

    main = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    seen: list[int] = []

    def worker():
        _traces._lowest_priority()
        seen.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert seen == [19] and os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == main
