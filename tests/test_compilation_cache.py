"""The persistent compilation cache (mfdesign._cache): a cache folder moved elsewhere still hits."""

import os
import shutil
import subprocess
import sys
import textwrap

# One small program compiled through enable_compilation_cache; JAX's compiler log says
# whether the persistent cache served it.
_SCRIPT = textwrap.dedent(
    """
    import logging
    from mfdesign._cache import enable_compilation_cache
    enable_compilation_cache()
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    logging.getLogger("jax._src.compiler").setLevel(logging.DEBUG)
    import jax, jax.numpy as jnp
    jax.jit(lambda x: jnp.sin(x) @ x.T + 1.0)(jnp.ones((3, 3))).block_until_ready()
    """
)


def _run(cache) -> str:
    env = os.environ | {"MFDESIGN_CACHE_DIR": str(cache), "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run([sys.executable, "-c", _SCRIPT], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stderr


def test_a_cache_moved_to_another_folder_still_serves_its_programs(tmp_path):
    first = _run(tmp_path / "a")
    assert "cache miss for 'jit__lambda'" in first.lower()
    shutil.move(tmp_path / "a", tmp_path / "b")  # e.g. a CI cache restored at another path
    again = _run(tmp_path / "b")
    assert "Persistent compilation cache hit for 'jit__lambda'" in again, again[-2000:]
