"""numba's on-disk cache, safe for processes that compile into it at the same time.

numba (0.68, ``numba.core.caching.IndexDataCacheFile``) keeps one index per function, signature -> data file, and saves
a new signature by reading the index, taking the first data-file name the index does not use, writing the index, then
the data file. Two processes that compile two signatures of one function at once can both read the same index and
both take ``.1.nbc``: the index then keeps one of the two signatures, and the data file may hold the other's machine
code, which a later process loads for it. ``install()`` makes every save hold an exclusive lock (``flock``) on a file
beside the function's index (``<index>.lock``) and every load a shared one: a save reads the index the last save wrote,
and a load never finds an index entry whose data file is not written yet. Installed by the packages whose kernels
are cached (``tissue_sim.core.solver``, ``tissue_sim.core.builder``, ``tissue_sim.core.markers``) when they are
imported; where the lock file cannot be opened (a read-only cache) numba's own unlocked method runs.
"""
from __future__ import annotations

import functools

try:
    import fcntl
except ImportError:      # not POSIX: numba's methods stay as they are
    fcntl = None

from numba.core import caching


def _locked(method, mode):
    @functools.wraps(method)
    def wrapper(self, *args, **kwargs):
        try:
            lock = open(self._index_path + '.lock', 'a')
        except OSError:
            return method(self, *args, **kwargs)
        with lock:
            fcntl.flock(lock, mode)
            return method(self, *args, **kwargs)     # the lock goes with the file's closing
    wrapper.tissue_sim_lock = True
    return wrapper


def install() -> bool:
    """Wrap numba's index-and-data cache file's save and load in the lock (once per process). Returns whether they
    are wrapped."""
    cls = caching.IndexDataCacheFile
    if fcntl is None:
        return False
    if not getattr(cls.save, 'tissue_sim_lock', False):
        cls.save = _locked(cls.save, fcntl.LOCK_EX)
        cls.load = _locked(cls.load, fcntl.LOCK_SH)
    return True
