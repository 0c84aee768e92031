"""Known answers of the deformation measures (paper section 4) on analytic deformations."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tissue_sim.core import measures, runio, tissue_cdr
from tissue_sim.core.analysis import measure
from tissue_sim.core.geometry import prism_volumes

import synthetic


def _cube(size=0.02):
    """One fat hexahedron: inner a, inner b, outer b, outer a, bottom then top (model.py convention)."""
    b = np.array([[0, 0, 0], [size, 0, 0], [size, size, 0], [0, size, 0]], float)
    return np.concatenate([b, b + [0, 0, size]])


def test_uniform_scale_gives_area_s2_and_d_proportional():
    rng = np.random.default_rng(1)
    rest = _cube() + rng.normal(scale=1e-3, size=(8, 3))
    s = 1.3
    c = rest.mean(0)
    cur = c + s * (rest - c) + [0.1, -0.2, 0.05]
    quad = np.array([[1, 2, 6, 5]])
    assert measures.quad_areas(cur, quad)[0] / measures.quad_areas(rest, quad)[0] == pytest.approx(s * s, rel=1e-12)
    Ro = rest - c
    expected = (s - 1) * np.linalg.norm(Ro, axis=1).mean()
    assert measures.d_paper(cur[None], rest[None])[0] == pytest.approx(expected, rel=1e-12)
    # a scale is not a rotation: the matched rest shape is the rest shape itself
    assert measures.d_rotation_free(cur[None], rest[None])[0] == pytest.approx(expected, rel=1e-9)


def test_rigid_motion_rotation_free_d_is_zero_paper_d_is_not():
    rng = np.random.default_rng(2)
    rest = np.stack([_cube() + rng.normal(scale=2e-3, size=(8, 3)) for _ in range(50)])
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    a = np.deg2rad(40)
    R = Rotation.from_rotvec(a * axis).as_matrix()
    cur = rest @ R.T + [0.3, 0.1, -0.2]
    np.testing.assert_allclose(measures.d_rotation_free(cur, rest), 0, atol=1e-12)
    # paper d of a rigid rotation: |Ro - R Ro| = 2 sin(a/2) |component of Ro perpendicular to the axis|
    Ro = rest - rest.mean(1, keepdims=True)
    perp = Ro - (Ro @ axis)[..., None] * axis
    expected = 2 * np.sin(a / 2) * np.linalg.norm(perp, axis=2).mean(1)
    np.testing.assert_allclose(measures.d_paper(cur, rest), expected, rtol=1e-10)
    assert np.all(expected > 1e-3)
    Rb = measures.best_rotations(cur, rest)
    np.testing.assert_allclose(Rb, np.broadcast_to(R, Rb.shape), atol=1e-10)
    np.testing.assert_allclose(measures.quad_areas(cur.reshape(-1, 3), np.array([[1, 2, 6, 5]])),
                               measures.quad_areas(rest.reshape(-1, 3), np.array([[1, 2, 6, 5]])))


def test_paper_d_for_a_known_vertex_displacement():
    """Move one vertex of an N = 8 cell by delta: the centroid moves delta/N, so
    d = (1/N) [ |delta| (N-1)/N + (N-1) |delta|/N ] = 2 (N-1) |delta| / N^2."""
    rest = _cube()
    delta = np.array([0.003, -0.004, 0.0])           # |delta| = 5 mm
    cur = rest.copy()
    cur[5] += delta
    assert measures.d_paper(cur[None], rest[None])[0] == pytest.approx(2 * 7 * 0.005 / 64, rel=1e-12)
    # a reflection is not a rotation: best_rotations keeps det = +1
    mirrored = rest * [-1, 1, 1]
    assert np.linalg.det(measures.best_rotations(mirrored[None], rest[None])[0]) == pytest.approx(1.0)


def test_prism_volumes_and_boundary():
    tm = synthetic.tube_model(n_around=12, n_slices=5)
    mus = np.flatnonzero(tm.cell_muscle == 0)
    vols = measures.cell_volumes(tm.rest_positions, tm)[mus]
    # regular hexagon of circumradius r: area 3 sqrt(3)/2 r^2; slice spacing 0.6 / 4
    np.testing.assert_allclose(vols, 1.5 * np.sqrt(3) * 0.018 ** 2 * 0.15, rtol=1e-9)
    bf = measures.boundary_faces(tm.cell_offsets, tm.cell_vertices, mus)
    total = measures.enclosed_volumes(tm.rest_positions, bf, np.zeros(len(bf), np.int64), 1)[0]
    assert total == pytest.approx(vols.sum(), rel=1e-9)      # closed, outward, no interior faces
    fat = np.flatnonzero(tm.cell_tissue == 2)
    # fat hexahedra: the contract ring order (inner a, inner b, outer b, outer a) is clockwise from +z,
    # so their signed volumes are all negative, of the size of the annulus sector; cell_volumes flips them
    v = prism_volumes(tm.rest_positions, tm.cell_offsets, tm.cell_vertices)[fat]
    sector = 0.5 * np.sin(2 * np.pi / 12) * (0.07 ** 2 - 0.055 ** 2) * 0.15
    np.testing.assert_allclose(v, -sector, rtol=1e-9)
    np.testing.assert_allclose(measures.cell_volumes(tm.rest_positions, tm)[fat], sector, rtol=1e-9)


def test_analysis_volumes_are_the_geometry_prism_volumes(tmp_path):
    """One prism-volume definition: the analysis' muscle volumes of a warped frame (non-planar faces,
    where face triangulations differ) are exactly the sums of geometry.prism_volumes over each muscle."""
    tm = synthetic.tube_model(n_around=8, n_slices=4)
    rng = np.random.default_rng(3)
    X = synthetic.bend(tm.rest_positions, 0.6) + rng.normal(0, 2e-3, tm.rest_positions.shape)
    X32 = X.astype(np.float32)
    m = measure.measure_run(_write(tm, tmp_path / 'w.mcap', [tm.rest_positions, X32]))
    v = prism_volumes(X32.astype(np.float64), tm.cell_offsets, tm.cell_vertices)
    for k, name in enumerate(m.muscle_names):
        cells = tm.cell_muscle == tm.muscle_names.index(name)
        assert m.muscle_volumes_mesh[1, k] == pytest.approx(v[cells].sum(), rel=1e-13)


def _write(tm, path, frames_X, poses=None):
    states = []
    for i, X in enumerate(frames_X):
        states.append(tissue_cdr.StateFrame(
            stamp_ns=i * 10 ** 8, frame_id='world', step=i, sim_time=0.1 * i, joint_names=['knee_r'],
            joint_positions=np.zeros(1), joint_velocities=np.zeros(1), muscle_names=list(tm.muscle_names),
            activations=np.zeros(2, np.float32), muscle_lengths=np.ones(2, np.float32),
            muscle_volumes=np.ones(2, np.float32),
            segment_poses=np.array([[0, 0, 0, 0, 0, 0, 1]] * 2, float) if poses is None else poses[i],
            vertex_positions=np.asarray(X, np.float32), kinetic_energy=0, elastic_energy=0))
    return runio.write_run(path, tm, states)


def test_measure_run_end_to_end_known_answers(tmp_path):
    """Through the MCAP file: a uniform scale s gives skin-area ratio s^2 for every fat cell;
    a rigid rotation gives ratio 1 and rotation-free d = 0; mesh volumes scale by s^3."""
    tm = synthetic.tube_model(n_around=8, n_slices=4)
    X0 = tm.rest_positions
    s = 1.2
    R = Rotation.from_euler('xyz', [20, -35, 50], degrees=True).as_matrix()
    p = _write(tm, tmp_path / 'r.mcap', [X0, s * X0, X0 @ R.T + [0.05, 0, 0]])
    m = measure.measure_run(p)
    assert m.n_frames == 3 and m.fat_cells.size == 8 * 3
    ar = m.area_ratio()
    np.testing.assert_allclose(ar[1], s * s, rtol=2e-6)
    np.testing.assert_allclose(ar[2], 1.0, rtol=2e-6)
    np.testing.assert_allclose(m.d_rotation_free[2], 0, atol=2e-7)        # float32 positions
    assert np.all(m.d_paper[2] > 1e-3)
    np.testing.assert_allclose(m.muscle_volumes_mesh[1] / m.muscle_volumes_mesh[0], s ** 3, rtol=1e-5)
    # relative d of the scale: (s - 1) mean|Ro| / RMS|Ro|, dimensionless and size-independent
    rest = X0[measures.cells_of(tm.cell_offsets, tm.cell_vertices, tm.cell_tissue, 2)[1]]
    Ro = rest - rest.mean(1, keepdims=True)
    rel = (s - 1) * np.linalg.norm(Ro, axis=2).mean(1) / measures.cell_size(rest)
    np.testing.assert_allclose(m.d_paper[1] / m.fat_size, rel, rtol=1e-5)


def test_truncated_run_reads_complete_frames(tmp_path):
    tm = synthetic.tube_model(n_around=8, n_slices=4)
    p = synthetic.bending_run(tm, tmp_path / 'r.mcap', n_frames=30, chunk_size=4096)
    full = runio.load_run(p)
    data = p.read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(data[:int(len(data) * 0.7)])
    part = runio.load_run(cut)
    assert 0 < part.n_frames < full.n_frames
    np.testing.assert_array_equal(part.frames, full.frames[:part.n_frames])
    with pytest.raises(runio.RunError, match='no such file'):
        runio.load_run(tmp_path / 'missing.mcap')
    bad = tmp_path / 'bad.mcap'
    bad.write_bytes(b'not an mcap at all')
    with pytest.raises(runio.RunError, match='not an MCAP'):
        runio.read_topology(bad)
