"""Bone meshes centred on their labels (marching cubes at any --bone-mesh-step), and VTU cells that are
the solver's cells (issue 20 side findings)."""
import numpy as np
import pytest
import trimesh
from scipy import ndimage

from phantoms import make_phantom, make_phantom_model
from tissue_sim.core import model as M
from tissue_sim.core.builder.bones import _mc_mesh
from tissue_sim.core.builder.io import load_labels, voxel_to_model
from tissue_sim.core.geometry import prism_volumes


@pytest.mark.parametrize('kind', ['column', 'two_bones'])
@pytest.mark.parametrize('step', [2, 3])
def test_bone_mesh_centred_on_its_label(kind, step):
    """Centroid within 0.15 slice and slice-axis extent within 0.3 slice of the label voxels' (the old
    step-2 mesh sat half a slice superior, or lost a whole slice of extent)."""
    lab, aff, table = make_phantom(kind)
    vol = load_labels(lab, aff)
    objs = ndimage.find_objects(vol.labels)
    dz = vol.pixel_mm[2] / 1000.0
    for b in (1, 2):
        ijk = np.argwhere(vol.labels == b).astype(float)
        centroid = voxel_to_model(vol.affine, ijk).mean(axis=0)
        zlo = voxel_to_model(vol.affine, np.array([0, 0, ijk[:, 2].min() - 0.5]))[2]
        zhi = voxel_to_model(vol.affine, np.array([0, 0, ijk[:, 2].max() + 0.5]))[2]
        v, f = _mc_mesh(vol, b, objs[b - 1], step)
        m = trimesh.Trimesh(v, f)
        assert m.is_watertight
        assert np.all(np.abs(m.center_mass - centroid) < 0.15 * dz), (m.center_mass - centroid) / dz
        assert abs(v[:, 2].min() - zlo) < 0.3 * dz and abs(v[:, 2].max() - zhi) < 0.3 * dz, \
            ((v[:, 2].min() - zlo) / dz, (v[:, 2].max() - zhi) / dz)


def test_bone_mesh_step_below_one_is_refused():
    from tissue_sim.core.builder import build_model
    from tissue_sim.errors import UserError
    lab, aff, table = make_phantom('column')
    with pytest.raises(UserError, match='bone_mesh_step'):
        build_model((lab, aff), table, slice_mm=25.0, bone_mesh_step=0)


def _polyhedron_volumes(grid):
    import pyvista as pv
    out = np.full(grid.n_cells, np.nan)
    for c in range(grid.n_cells):
        if grid.celltypes[c] == pv.CellType.POLYHEDRON:
            out[c] = grid.GetCell(c).ComputeVolume()      # VTK's own polyhedron volume (divergence theorem)
    return out


@pytest.mark.parametrize('kind', ['split'])
def test_vtu_cells_are_the_solver_cells(kind, tmp_path):
    """Every exported cell encloses exactly the model's prism_volumes volume (1e-6 relative): muscle
    polyhedra by VTK's polyhedron volume, fat hexahedra by VTK's cell-size filter. Side quads are not
    planar here, so the old quad-faced polyhedra were off (by up to several per cent)."""
    import pyvista as pv
    from tissue_sim.core.builder.export import to_vtu
    tm = make_phantom_model(kind)
    ref = prism_volumes(tm.rest_positions, tm.cell_offsets, tm.cell_vertices, tm.cell_tissue == M.TISSUE_FAT)
    to_vtu(tm, tmp_path / 'm.vtu')
    g = pv.read(tmp_path / 'm.vtu')
    assert g.n_cells == tm.n_cells
    poly = g.celltypes == pv.CellType.POLYHEDRON
    assert np.all(poly[tm.cell_tissue == M.TISSUE_MUSCLE])
    vol = np.where(poly, _polyhedron_volumes(g), g.compute_cell_sizes()['Volume'])
    assert np.allclose(vol, ref, rtol=1e-6, atol=0), np.abs(vol / ref - 1).max()
    assert np.allclose(g.cell_data['volume'], ref, rtol=1e-12)
    # the model's vertices are the first points, unchanged
    assert np.array_equal(g.points[:tm.n_vertices], tm.rest_positions)


def test_vtu_cells_of_the_bundled_limb(default_tm, tmp_path):
    """The bundled model's muscle cells: exported volume total was +13.5 % (+11.6 % in this version)."""
    import pyvista as pv
    from tissue_sim.core.builder.export import to_unstructured_grid
    tm = default_tm
    g = to_unstructured_grid(tm)
    ref = prism_volumes(tm.rest_positions, tm.cell_offsets, tm.cell_vertices, tm.cell_tissue == M.TISSUE_FAT)
    poly = g.celltypes == pv.CellType.POLYHEDRON
    vol = np.where(poly, _polyhedron_volumes(g), g.compute_cell_sizes()['Volume'])
    assert np.allclose(vol, ref, rtol=1e-6, atol=0), np.abs(vol / ref - 1).max()


def test_vtu_write_failure_is_one_error_and_no_vtk_output(tmp_path, capfd):
    """VTK's own error printing (~25 lines on stderr) is silenced; the failure is one UserError."""
    from tissue_sim.core.builder.export import to_vtu
    from tissue_sim.errors import UserError
    tm = make_phantom_model('column')
    (tmp_path / 'afile').write_text('x')
    capfd.readouterr()
    with pytest.raises(UserError, match='afile/x.vtu: cannot write'):
        to_vtu(tm, tmp_path / 'afile' / 'x.vtu')
    out, err = capfd.readouterr()
    assert err == '' and out == '', err
    assert not (tmp_path / 'afile' / 'x.vtu').exists()


def test_winding_number_is_one_inside_a_closed_mesh_and_a_solid_angle_outside_one():
    """bones.winding_number (the builder's and the contact checks' inside test): 1 inside a closed mesh, 0 outside,
    and for one triangle the solid angle over 4 pi: a cube's face seen from its centre is 1/6 of the sphere."""
    from tissue_sim.core.builder.bones import winding_number
    box = trimesh.creation.box(extents=(0.02, 0.03, 0.04))
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    rng = np.random.default_rng(0)
    for mesh, inside in ((box, rng.uniform(-0.009, 0.009, (50, 3)) * [1, 1.5, 2]),
                         (sphere, rng.normal(size=(50, 3)) * 0.01)):
        V, T = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        assert np.allclose(winding_number(V, T, inside), 1.0, atol=1e-9)
        assert np.allclose(winding_number(V, T, inside + [0.2, 0.0, 0.0]), 0.0, atol=1e-9)
    cube = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    top = np.asarray(cube.faces)[np.all(np.asarray(cube.vertices)[cube.faces][:, :, 2] > 0.5, axis=1)]   # the +z face
    assert len(top) == 2
    assert winding_number(np.asarray(cube.vertices), top, np.zeros((1, 3)))[0] == pytest.approx(1 / 6, abs=1e-12)
