"""The chain's HDF5 file: emcee's own backend, its metadata read once instead of every step."""

from __future__ import annotations

import emcee

__all__ = ["ChainFile"]


class ChainFile(emcee.backends.HDFBackend):
    """:class:`emcee.backends.HDFBackend` (the same file and layout: every step is written
    as it is taken, the crash record a run resumes from) that remembers the ensemble's
    shape, whether it has blobs and the iteration instead of opening the file to read
    them. emcee's backend opens the file seven times a step, six of them to read these
    (``save_step``'s checks, the sampler's and our loop's iteration): 6 of the 8 s that
    1,100 steps of a warm demo spent in the file (cProfile, issue 40). One sampler writes a chain file at a time, so what it wrote is
    what it remembers; :meth:`reset` and :meth:`grow` read them again."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._known: dict = {}

    def _remembered(self, key: str, read):
        if key not in self._known:
            self._known[key] = read()
        return self._known[key]

    @property
    def shape(self):
        return self._remembered("shape", lambda: emcee.backends.HDFBackend.shape.fget(self))

    @property
    def iteration(self):
        return self._remembered("iteration", lambda: emcee.backends.HDFBackend.iteration.fget(self))

    def has_blobs(self):
        return self._remembered("has_blobs", super().has_blobs)

    def reset(self, nwalkers, ndim):
        self._known.clear()
        super().reset(nwalkers, ndim)

    def grow(self, ngrow, blobs):
        super().grow(ngrow, blobs)
        self._known.clear()  # grow may set has_blobs

    def save_step(self, state, accepted):
        done = self.iteration
        super().save_step(state, accepted)
        self._known["iteration"] = done + 1
