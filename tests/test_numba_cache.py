"""tissue_sim.core.numba_cache: processes compiling two signatures of one function into one numba cache at the same
time keep both (real processes, a real numba cache; numba's index write slowed so that the two saves overlap)."""
import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / 'src' / 'tissue_sim'

KERNEL = textwrap.dedent('''
    from numba import njit

    @njit(cache=True)
    def twice(x):
        return x + x
''')

# One process: (optionally) the lock, numba's index write slowed by 2 s (its read comes before, in the same save),
# start at a given time, compile twice() for one argument type, save it.
COMPILE = textwrap.dedent('''
    import sys, time
    sys.path[:0] = [sys.argv[1], sys.argv[2]]
    from numba.core import caching
    if sys.argv[3] == 'lock':
        from tissue_sim.core import numba_cache
        assert numba_cache.install()
    save_index = caching.IndexDataCacheFile._save_index
    def slow(self, overloads):
        time.sleep(2.0)
        save_index(self, overloads)
    caching.IndexDataCacheFile._save_index = slow
    import kernel
    start = float(sys.argv[5])
    while time.time() < start:
        time.sleep(0.001)
    print(kernel.twice(3 if sys.argv[4] == 'int' else 3.0))
''')

# A later process: both signatures from the cache, not compiled again.
CHECK = textwrap.dedent('''
    import json, sys
    sys.path[:0] = [sys.argv[1], sys.argv[2]]
    from tissue_sim.core import numba_cache
    numba_cache.install()
    import kernel
    out = [kernel.twice(3), kernel.twice(3.0)]
    print(json.dumps({'values': [repr(v) for v in out], 'hits': sum(kernel.twice.stats.cache_hits.values()),
                      'misses': sum(kernel.twice.stats.cache_misses.values())}))
''')


def _race(tmp_path, lock: bool):
    folder = tmp_path / ('lock' if lock else 'nolock')
    (folder / 'cache').mkdir(parents=True)
    (folder / 'kernel.py').write_text(KERNEL)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(folder / 'cache'))
    start = str(time.time() + 3.0)     # after both have imported numba (~1 s)
    procs = [subprocess.Popen([sys.executable, '-c', COMPILE, str(folder), str(SRC), 'lock' if lock else 'none', kind,
                               start], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for kind in ('int', 'float')]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    assert [o[0].strip() for o in outs] == ['6', '6.0']
    files = sorted(p.name for p in (folder / 'cache').rglob('kernel.twice-*.nbc'))     # before the check saves any
    r = subprocess.run([sys.executable, '-c', CHECK, str(folder), str(SRC)], env=env, capture_output=True, text=True,
                       timeout=120)
    return r, files


def test_two_processes_saving_two_signatures_at_once_keep_both(tmp_path):
    r, files = _race(tmp_path, lock=True)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    assert got == {'values': ['6', '6.0'], 'hits': 2, 'misses': 0}
    assert len(files) == 2


def test_without_the_lock_the_same_race_loses_a_signature(tmp_path):
    """The race the lock prevents is real: numba's own save, run the same way, keeps one data file for the two
    signatures, so a later process misses one of them (or gets the other's code, or crashes)."""
    r, files = _race(tmp_path, lock=False)
    if r.returncode == 0:
        got = json.loads(r.stdout)
        assert got['misses'] >= 1 or got['values'] != ['6', '6.0']
    assert len(files) == 1


@pytest.mark.parametrize('module', ['tissue_sim.core.solver', 'tissue_sim.core.builder', 'tissue_sim.core.markers'])
def test_the_packages_with_cached_kernels_install_the_lock(module):
    code = (f'import sys; sys.path.insert(0, {str(SRC)!r}); import {module}; '
            'from numba.core import caching; print(getattr(caching.IndexDataCacheFile.save, "tissue_sim_lock", False))')
    r = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == 'True'
