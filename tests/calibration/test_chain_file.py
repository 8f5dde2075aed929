"""The chain file (ChainFile): emcee's HDF5 layout and per-step crash record, one opening a step."""

from __future__ import annotations

import emcee
import numpy as np

from mfdesign.calibration.chain_file import ChainFile


def log_prob(x):
    return -0.5 * np.sum(x**2, axis=-1)


def sample(backend, steps: int, start=None):
    sampler = emcee.EnsembleSampler(8, 3, log_prob, vectorize=True, backend=backend)
    if start is None:
        sampler.random_state = np.random.RandomState(1).get_state()
        start = np.random.default_rng(0).standard_normal((8, 3))
    for it in sampler.sample(start, iterations=steps):
        assert sampler.iteration == backend.iteration  # the iteration it remembers is the file's
    return sampler


def test_the_chain_file_is_emcees_written_every_step_with_one_opening(tmp_path, monkeypatch):
    opened = []
    real_open = emcee.backends.HDFBackend.open

    def counting_open(self, mode="r"):
        opened.append(mode)
        return real_open(self, mode)

    monkeypatch.setattr(emcee.backends.HDFBackend, "open", counting_open)
    counts = {}
    for steps in (10, 40):
        chain = ChainFile(str(tmp_path / f"chain{steps}.h5"), name="mcmc")
        chain.reset(8, 3)
        opened.clear()
        sample(chain, steps)
        counts[steps] = (len(opened), opened.count("a"))
    # every step written as it is taken (the crash record), in one opening a step; emcee's
    # own backend opens the file five times a step, four to read what it already knows
    assert counts[40][0] - counts[10][0] == 30 and counts[40][1] - counts[10][1] == 30, counts

    monkeypatch.undo()
    memory = emcee.backends.Backend()
    memory.reset(8, 3)
    sample(memory, 40)
    plain = emcee.backends.HDFBackend(str(tmp_path / "chain40.h5"), name="mcmc", read_only=True)
    assert plain.iteration == 40
    np.testing.assert_array_equal(plain.get_chain(), memory.get_chain())
    np.testing.assert_array_equal(plain.get_log_prob(), memory.get_log_prob())
    np.testing.assert_array_equal(plain.accepted, memory.accepted)

    # a new process resumes from the file: the chain goes on as one run would have
    again = ChainFile(str(tmp_path / "chain40.h5"), name="mcmc")
    assert again.iteration == 40 and again.shape == (8, 3)
    go_on = sample(again, 10, start=again.get_last_sample())
    assert again.iteration == 50 and go_on.get_chain().shape == (50, 8, 3)
    np.testing.assert_array_equal(go_on.get_chain()[:40], memory.get_chain())
