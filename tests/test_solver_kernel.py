"""The cell kernel (cells.cell_forces: SIMD across cells, in blocks of cells of one size) against the
readable definition in src, reference.cell_forces (plain numpy, exact polar rotation by SVD): the same
forces, energies, rotations and pressures to rounding (the kernel's warm-started Newton rotation run to
convergence), on the bundled anatomy (both parameter sets) and on synthetic cells of mixed sizes (odd sizes,
partial blocks, muscle and fat, damped and undamped, with and without volume term or active tension in one
block); bit-identical results across processes; the divergence check naming the lowest bad cell. The whole
step against reference_step: tests/test_solver_reference.py."""
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from numba import njit

from tissue_sim.core import solver
from tissue_sim.core.solver import cells as K
from tissue_sim.core.solver import reference
from tissue_sim.core.solver.measures import cell_axial_lengths
from tissue_sim.core.solver.reference import padded, rotation_quaternions


# ------------------------------------------------------------------------------------ helpers
ITERS = 50                  # rotation iterations of the kernel: converged to the exact polar factor the reference uses


def _run_both(x, v, quat, lam, act, pressure, vol_gain, volume_actual, csr, cells, volume_cap=None):
    """(new, reference) results of one call each on copies of the mutable inputs: (bad, f, rotation
    quaternion (w >= 0), pressure, cell_energy, cell_length); the reference's bad is always -1 (it has no check)."""
    off, cv, X0, Qinv, fibre, cell_muscle, k, k_active, damp_b, k_volume, q_tr, q_ff, rest_length = csr
    f, q, p, e, ln = np.zeros_like(x), quat.copy(), pressure.copy(), np.zeros(off.size - 1), np.full(off.size - 1, np.nan)
    bad = K.cell_forces(x, v, f, q, cells, lam, act, volume_actual, ITERS, e, p, vol_gain, K.cell_work(cells), ln)
    q = q * np.where(q[:, 3:] < 0, -1.0, 1.0)
    new = (bad, f, q, p, e, ln)
    ns = SimpleNamespace(off=off, cv=cv, X0=X0, Qinv=Qinv, fibre=fibre, cell_muscle=cell_muscle, k=k, k_active=k_active,
                         damp_b=damp_b, k_volume=k_volume, rest_length=rest_length, k_enclosed=np.zeros(off.size - 1),
                         end_rings=K.end_rings(np.full(off.size - 1, -1), np.zeros(off.size - 1), off, cv, None),
                         volume_cap=np.zeros(off.size - 1) if volume_cap is None else volume_cap)
    rp = pressure.copy()
    rf, re, rln, R = reference.cell_forces(ns, padded(ns), x, v, lam, act, rp, vol_gain, volume_actual)
    return new, (-1, rf, rotation_quaternions(R), rp, re, rln)


def _assert_agree(new, ref, even_only=True):
    bad, f, q, p, e, ln = new
    rbad, rf, rq, rp, re, rln = ref
    assert bad == rbad == -1
    scale = np.abs(rf).max()
    assert scale > 0
    assert np.abs(f - rf).max() <= 1e-9 * scale
    assert np.abs(q - rq).max() <= 3e-8                 # (the Newton iteration stops after a correction below 1e-5 rad;
                                                        # 1.2e-8 measured on the bundled model, paper set)
    assert np.abs(p - rp).max() <= 1e-9 * max(np.abs(rp).max(), 1e-300)
    assert np.abs(e - re).max() <= 1e-9 * np.abs(re).max()
    assert np.allclose(ln, rln, rtol=1e-12, atol=1e-15)            # the axial length (ring-centroid distance)


def _csr(sim):
    # (a cell whose volume energy is on its enclosed volume, volume_measure 'enclosed', has no affine volume term in the
    # cell pass: volume.enclosed_lanes adds it after, tests/test_solver_volume.py; the reference gets no partly bound end
    # rings: cells.end_ring_shift acts after the pass too, tests/test_end_rings.py)
    return (sim.off, sim.cv, sim.X0, sim.Qinv, sim.fibre, sim.cell_muscle, sim.k, sim.k_active, sim.damp_b,
            np.where(sim.k_enclosed > 0, 0.0, sim.k_volume), sim.q_tr, sim.q_ff, sim.rest_length)


def _mixed_cells(rng, sizes_counts, n_vertices=400, n_muscles=3, fat_sizes=()):
    """Random cells (vertices drawn from a shared pool, so cells share vertices, but no two share a ring)
    of the given sizes: CSR arrays and per-cell constants as compile_model computes them, and a packed
    layout. Cells of a size in fat_sizes are all fat (no volume, no tension)."""
    rest = rng.normal(scale=0.02, size=(n_vertices, 3))
    sizes = np.concatenate([np.full(c, n) for n, c in sizes_counts])
    rng.shuffle(sizes)                                   # sizes interleaved in cell order
    off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    cv = np.concatenate([rng.choice(n_vertices, n, replace=False) for n in sizes]).astype(np.int32)
    return (rest,) + _cells(rng, rest, off, cv, n_muscles, np.isin(sizes, fat_sizes))


def _stacked_cells(rng, columns, ring=6, n_muscles=3):
    """Prisms stacked in columns, each cell's top ring the next one's bottom ring (shared vertices), as
    the model builder makes them: columns = [(number of cells, closed), ...]; a closed column is a loop of
    cells around an axis (its last cell's top ring is its first cell's bottom ring: a cycle of rings)."""
    rest, off, cv, nv = [], [0], [], 0
    for c, (cells, closed) in enumerate(columns):
        n_rings = cells if closed else cells + 1
        angle = np.arange(ring) * 2 * np.pi / ring
        first = nv
        for r in range(n_rings):
            if closed:                  # rings around the z axis of this column, radius 0.1
                phi = 2 * np.pi * r / n_rings
                centre = np.array([0.1 * np.cos(phi), 0.1 * np.sin(phi), 0.2 * c])
                radial, up = np.array([np.cos(phi), np.sin(phi), 0.0]), np.array([0.0, 0.0, 1.0])
            else:
                centre, radial, up = np.array([0.05 * c, 0.0, 0.01 * r]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
            rest.append(centre + 0.004 * (np.cos(angle)[:, None] * radial + np.sin(angle)[:, None] * up)
                        + rng.normal(scale=3e-4, size=(ring, 3)))
            nv += ring
        for k in range(cells):
            bottom = first + ring * k
            top = first + ring * ((k + 1) % n_rings)
            cv += list(range(bottom, bottom + ring)) + list(range(top, top + ring))
            off.append(off[-1] + 2 * ring)
    rest = np.concatenate(rest)
    off, cv = np.array(off, np.int64), np.array(cv, np.int32)
    return (rest,) + _cells(rng, rest, off, cv, n_muscles, np.zeros(off.size - 1, bool))


def _cells(rng, rest, off, cv, n_muscles, fat):
    """Per-cell constants (random, as compile_model computes them from rest) and the packed layout."""
    sizes = np.diff(off)
    C = sizes.size
    cell_of = np.repeat(np.arange(C), sizes)
    cent = np.zeros((C, 3))
    np.add.at(cent, cell_of, rest[cv])
    cent /= sizes[:, None]
    X0 = rest[cv] - cent[cell_of]
    Q = np.zeros((C, 3, 3))
    np.add.at(Q, cell_of, X0[:, :, None] * X0[:, None, :])
    fibre = rng.normal(size=(C, 3))
    fibre /= np.linalg.norm(fibre, axis=1)[:, None]
    muscle = np.where((rng.random(C) < 0.6) & ~fat, rng.integers(0, n_muscles, C), -1).astype(np.int32)
    k = rng.uniform(50.0, 200.0, C)
    k_active = np.where((muscle >= 0) & (rng.random(C) < 0.7), rng.uniform(10.0, 80.0, C), 0.0)
    damp_b = np.where(rng.random(C) < 0.7, rng.uniform(0.1, 2.0, C), 0.0)
    k_volume = np.where((muscle >= 0) & (rng.random(C) < 0.8), rng.uniform(1.0, 20.0, C), 0.0)
    rest_length = np.zeros(C)
    cell_axial_lengths(rest, off, cv, rest_length)
    csr = (off, cv, X0, np.linalg.inv(Q), fibre, muscle, k, k_active, damp_b, k_volume, np.trace(Q, axis1=1, axis2=2),
           np.einsum('ci,cij,cj->c', fibre, Q, fibre), rest_length)
    return csr, K.pack_cells(off, cv, X0, muscle, k, k_active, damp_b, k_volume, csr[10], csr[11],
                             rest_length, fibre, csr[3])


def _ring_entries(cells):
    """How many ring-vertex entries the layout computes (real slots of real lanes)."""
    rings = cells[2]
    return int((rings[:, 0] * rings[:, 3]).sum())


def _random_state(rng, rest, C, noise=0.002, speed=0.3, bend=0.0):
    """x: rest turned, stretched 5 %, moved, with noise [m] (bend [m]: first bent smoothly along z over 20 cm);
    random velocities (speed [m/s]) and warm starts."""
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))                           # a rotation, not a reflection
    bent = rest + bend * np.sin(2 * np.pi * rest[:, 2:3] / 0.2) * [1.0, 0.5, 0.0]
    x = bent @ R.T * 1.05 + rng.normal(scale=noise, size=rest.shape) + [0.1, -0.2, 0.3]
    v = rng.normal(scale=speed, size=rest.shape)
    quat = rng.normal(size=(C, 4))                       # warm starts away from the answer: several iterations
    quat /= np.linalg.norm(quat, axis=1)[:, None]
    return x, v, quat


# ------------------------------------------------------------------------------------ tests
@pytest.mark.parametrize('preset', ['paper', 'physical'])
def test_matches_the_reference_on_the_default_model(default_tm, preset):
    sim = solver.compile_model(default_tm, getattr(solver.Params, preset)())
    # a state like a contraction's, made without the step (which tests/test_solver_reference.py checks against its
    # reference, and which this file's other-lane-width run would otherwise compile again): bent 5 mm over 20 cm,
    # 0.3-mm noise, every muscle's contraction state in [0.7, 1), random pressures
    rng = np.random.default_rng(3)
    x, v, quat = _random_state(rng, sim.rest, sim.n_cells, noise=3e-4, speed=0.05, bend=0.005)
    quat[:] = [0.0, 0.0, 0.0, 1.0]      # warm starts at identity: from random ones the iterations miss the
                                        # reference rotation on some of the limb's cells
    lam, pressure = rng.uniform(0.7, 1.0, max(sim.n_muscles, 1)), rng.normal(scale=0.01, size=sim.n_cells)
    act = np.zeros(max(sim.n_muscles, 1))
    act[solver.muscle_indices(sim, 'hamstrings')] = 1.0
    p = sim.params
    new, ref = _run_both(x, v, quat, lam, act, pressure, 0.01, p.volume_mode == 'actual', _csr(sim), sim.cell_blocks,
                         sim.volume_cap)       # (the physical set bounds the volume term: explicit_volume_cap)
    _assert_agree(new, ref)
    assert np.abs(new[2] - quat).max() > 0.1                 # the rotations did move


@pytest.mark.parametrize('volume_actual', [True, False])
def test_matches_the_reference_on_mixed_cell_sizes(volume_actual):
    rng = np.random.default_rng(7)
    # sizes: odd (rings of two sizes, a padding slot), small, several blocks, a single cell, an all-fat size
    # (the kernel's version compiled without muscle, volume and tension)
    rest, csr, cells = _mixed_cells(rng, [(5, 7), (8, 2 * K.BLK + 3), (12, K.BLK - 1), (24, 9), (9, 1), (6, 20)],
                                    fat_sizes=(6,))
    C = csr[0].size - 1
    groups, ids = cells[0], cells[1]
    assert np.array_equal(np.sort(ids[ids >= 0]), np.arange(C))          # every cell in exactly one lane
    assert sorted(groups[:, 0]) == [5, 6, 8, 9, 12, 24]                  # one group of lanes per size
    assert groups[groups[:, 0] == 6, 4].tolist() == [1] and groups[groups[:, 0] != 6, 4].sum() == 0   # plain
    assert _ring_entries(cells) == csr[0][-1]                            # nothing shared: every ring once per cell
    x, v, quat = _random_state(rng, rest, C)
    lam, act = np.array([0.7, 1.0, 0.85]), np.array([1.0, 0.0, 0.4])
    pressure = rng.normal(scale=0.5, size=C)
    new, ref = _run_both(x, v, quat, lam, act, pressure, 0.05, volume_actual, csr, cells)
    _assert_agree(new, ref)
    assert np.abs(new[2] - quat).max() > 0.1                             # the rotations did move


def test_shared_rings_are_computed_once_and_agree():
    """Columns of prisms (the builder's shape): each shared ring is summed and forced once for its two
    cells. Columns longer than a lane (cut: the ring at a cut twice), shorter ones (lanes pass from one
    column to the next through a dummy position) and a closed loop of cells (a cycle of rings)."""
    rng = np.random.default_rng(5)
    columns = [(120, False), (3, False), (1, False), (60, True), (47, False), (29, False)]
    rest, csr, cells = _stacked_cells(rng, columns)
    C = csr[0].size - 1
    ids = cells[1]
    assert np.array_equal(np.sort(ids[ids >= 0]), np.arange(C))
    distinct_rings = sum(n if closed else n + 1 for n, closed in columns)
    entries = _ring_entries(cells)
    assert entries < 0.6 * csr[0][-1]                                     # vs 12 entries per cell
    assert distinct_rings * 6 <= entries <= (distinct_rings + K.BLK + 1) * 6     # at most one extra ring per cut
    x, v, quat = _random_state(rng, rest, C)
    lam, act = np.array([0.75, 1.0, 0.9]), np.array([1.0, 0.3, 0.0])
    pressure = rng.normal(scale=0.5, size=C)
    for volume_actual in (True, False):
        new, ref = _run_both(x, v, quat, lam, act, pressure, 0.05, volume_actual, csr, cells)
        _assert_agree(new, ref)


def test_the_implicit_volume_bound_matches_the_reference():
    """The implicit integrator's bound on the volume term (SimModel.volume_cap, Params.implicit_volume_cap): cells
    sheared 3:1 (det D near 1, |grad det D|^2 ~10x its rest value) with the bound on every other cell at 2x the rest
    value: the kernel's scaled volume force agrees with the reference's, and the bound did act (the forces differ
    from the unbounded ones)."""
    rng = np.random.default_rng(13)
    rest, csr, _ = _mixed_cells(rng, [(8, 2 * K.BLK + 3), (12, 9), (24, 5)])
    off, cv, X0, Qinv, fibre, muscle, k, k_active, damp_b, k_volume, q_tr, q_ff, rest_length = csr
    C = off.size - 1
    g2 = np.trace(Qinv, axis1=1, axis2=2)                    # |grad det D|^2 at rest: sum_i |Qinv X0_i|^2
    cap = np.where((np.arange(C) % 2 == 0) & (k_volume > 0), 2.0 * g2, 0.0)
    cells = K.pack_cells(off, cv, X0, muscle, k, k_active, damp_b, k_volume, q_tr, q_ff, rest_length, fibre, Qinv,
                         volume_cap=cap)
    shear = np.array([[1.0, 3.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    x = rest @ shear.T + rng.normal(scale=0.001, size=rest.shape)
    v = rng.normal(scale=0.1, size=rest.shape)
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (C, 1))
    lam, act = np.array([0.8, 1.0, 0.9]), np.array([1.0, 0.0, 0.5])
    pressure = np.zeros(C)
    new, ref = _run_both(x, v, quat, lam, act, pressure, 0.0, True, csr, cells, volume_cap=cap)
    _assert_agree(new, ref)
    free, _ = _run_both(x, v, quat, lam, act, pressure, 0.0, True, csr, _mixed_cells(np.random.default_rng(13), [
        (8, 2 * K.BLK + 3), (12, 9), (24, 5)])[2])
    assert np.abs(free[1] - new[1]).max() > 0.1 * np.abs(free[1]).max()


def test_divergence_names_the_lowest_bad_cell():
    rng = np.random.default_rng(11)
    rest, csr, cells = _mixed_cells(rng, [(8, 40), (6, 20)])
    off, cv = csr[0], csr[1]
    x = rest.copy()
    i = cv[off[30]]                                      # a vertex of cell 30 (and maybe of lower cells)
    x[i] = np.nan
    first = int(np.flatnonzero([i in cv[off[c]:off[c + 1]] for c in range(off.size - 1)])[0])
    C = off.size - 1
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (C, 1))
    lam, act = np.ones(3), np.ones(3)
    f, e = np.zeros_like(x), np.zeros(C)
    bad = K.cell_forces(x, np.zeros_like(x), f, quat, cells, lam, act, True, 1, e, np.zeros(C), 0.0, K.cell_work(cells),
                        np.empty(C))
    assert bad == first


_RUN = """
import hashlib, sys
sys.path.insert(0, {src!r})
from tissue_sim.core import solver
from tissue_sim.core.solver import phantom
sim = solver.compile_model(phantom.knee(n_gaps=6, fat_sectors=4), solver.Params.{preset}())
for t, st in solver.simulate(sim, 0.05, {{'hamstrings': [(0, 0.0), (0.02, 1.0)]}}, every=10):
    pass
digest = hashlib.sha256(st.x.tobytes() + st.v.tobytes() + st.q.tobytes() + st.quat.tobytes()).hexdigest()
"""


@pytest.mark.parametrize('preset', ['paper', 'physical'])
def test_bit_identical_across_processes(preset):
    """The same run in this process (after whatever ran before it) and in a fresh one."""
    code = _RUN.format(src=str(Path(__file__).resolve().parents[1] / 'src' / 'tissue_sim'), preset=preset)
    here = {}
    exec(code, here)
    there = subprocess.run([sys.executable, '-c', code + 'print(digest)'], capture_output=True, text=True, check=True)
    assert here['digest'] == there.stdout.strip()


def test_a_stale_advance_cache_is_dropped_in_numba_cache_dir_too(tmp_path, monkeypatch):
    """advance()'s cached code embeds the kernels of cells.py and the others, which numba does not check: step.py
    deletes it when one of them is newer, beside the sources and in NUMBA_CACHE_DIR."""
    import importlib
    import os
    import time
    step = importlib.import_module('tissue_sim.core.solver.step')      # (the package exports the function step)
    folder = tmp_path / 'solver_0123abcd'
    folder.mkdir()
    stale, fresh = folder / 'step.advance-300.py311.nbi', folder / 'step.advance-120.py311.1.nbc'
    other = folder / 'step.set_threads-431.py311.nbi'          # not advance's: kept whatever its age
    for f, t in ((stale, 1.0), (fresh, time.time() + 3600.0), (other, 1.0)):     # older / newer than any source
        f.write_bytes(b'x')
        os.utime(f, (t, t))
    monkeypatch.setenv('NUMBA_CACHE_DIR', str(tmp_path))
    step._drop_stale_advance_cache()
    assert not stale.exists() and fresh.exists() and other.exists()


def test_the_fused_gather_is_compiled_noalias():
    """The pinned numba takes the noalias option (else the fused gather silently stays scalar: right
    results, ~10 % slower), and _ring_moments is compiled with it: every array argument noalias in its IR."""
    assert K.NOALIAS == {'_noalias': True}
    from numba.core import compiler
    assert 'noalias' in compiler.Flags.options              # the flag the option maps to still exists
    fn = K._ring_moments.py_func
    ir = njit(fastmath={'contract'}, error_model='numpy', **K.NOALIAS)(fn)
    rs, gv = np.zeros(K.N_R * K.BLK), np.zeros(6 * 2 * K.BLK)
    x = np.arange(30.0)
    ir(rs, gv, np.zeros(2 * 3 * K.BLK), 2, 2, x, x, np.zeros((2, K.BLK), np.uint32) + 9)    # vertex 3: offset 3 * 3
    text = next(iter(ir.inspect_llvm().values()))
    define = next(line for line in text.splitlines() if line.startswith('define') and '_ring_moments' in line)
    assert define.count('noalias') >= 8                     # retptr, excinfo + the data pointers of the arrays
    assert rs[K.R_O * K.BLK] == 9.0 and gv[0] == 9.0         # gathered x[3 * 3] through the slot offset


def test_lanes_per_block_follow_the_cpu():
    """32 lanes where LLVM emits 512-bit vectors by default (AMD Zen 4 and later), else 16; the module's
    BLK is the choice for the CPU numba compiles for, and a whole number of 8-double vectors."""
    assert K.lanes_for_cpu('znver4') == K.lanes_for_cpu('znver5') == 32
    for name in ('znver3', 'znver2', 'skylake-avx512', 'haswell', 'generic', 'neoverse-n1'):
        assert K.lanes_for_cpu(name) == 16, name
    assert K.BLK == K.lanes_for_cpu() and K.BLK % 8 == 0


@pytest.mark.slow
def test_the_other_lane_width_matches_the_reference_too():
    """On a CPU that runs 32 lanes, the 16-lane layout (what every other CPU runs) passes this file's
    tests too, all but the run in two processes (it would compile the whole step again, ~100 s): a fresh process
    compiling for NUMBA_CPU_NAME=generic (a CPU name of its own in numba's cache index, so the two layouts never share
    cached code)."""
    if K.BLK == 16:
        pytest.skip('this CPU runs the 16-lane layout already (the tests above cover it)')
    import os
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, NUMBA_CPU_NAME='generic')
    probe = subprocess.run([sys.executable, '-c', 'import sys; sys.path.insert(0, sys.argv[1]); '
                            'from tissue_sim.core.solver import cells as K; print(K.BLK)', str(root / 'src' / 'tissue_sim')],
                           capture_output=True, text=True, env=env, check=True)
    assert probe.stdout.strip() == '16'
    run = subprocess.run([sys.executable, '-m', 'pytest', '-q', '-m', 'not slow', '-p', 'no:cacheprovider', '-k',
                          'not across_processes', str(Path(__file__).resolve())], capture_output=True, text=True,
                         env=env, cwd=root)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert ' passed' in run.stdout and 'failed' not in run.stdout
