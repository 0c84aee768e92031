"""core/markers: numpy-encoded MarkerArray bytes are what rclpy deserialises, with the right content."""
import numpy as np
import pytest

from tissue_sim.core.model import JOINT_HINGE, TissueModel
from tissue_sim.core import markers as mk
from tissue_sim.core import measures


def tiny_model():
    """Two segments (thigh root, shank), one triangular-prism muscle cell, one hexahedral fat cell,
    a bone triangle on each segment. Enough structure for the marker layout, not for physics."""
    rest = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1],
                     [2, 0, 0], [3, 0, 0], [2, 0, 1], [3, 0, 1]], float) * 0.01
    cells = np.array([0, 1, 2, 3, 4, 5, 1, 6, 7, 1, 4, 8, 9, 4], np.int32)
    surf = np.array([[0, 1, 2], [3, 4, 5], [1, 6, 7], [6, 7, 9], [7, 9, 8]], np.int32)
    return TissueModel(
        name='tiny', rest_positions=rest, vertex_segment=np.array([0, -1, -1, -1, -1, -1, -1, -1, 1, 1], np.int32),
        vertex_flags=np.zeros(10, np.uint8), cell_offsets=np.array([0, 6, 14]), cell_vertices=cells,
        cell_tissue=np.array([1, 2], np.uint8), cell_muscle=np.array([0, -1], np.int32),
        cell_fibre=np.array([[0, 0, 1.0], [0, 0, 1.0]]), cell_slice=np.zeros(2, np.int32),
        cell_k_scale=np.ones(2), skin_quads=np.array([[6, 7, 9, 8]], np.int32), skin_quad_cell=np.array([1], np.int32),
        surface_triangles=surf, surface_group=np.array([1, 1, 0, 0, 0], np.int32),
        surface_group_names=('skin', 'muscle/biceps_femoris'),
        muscle_names=('biceps_femoris',), muscle_groups=('hamstrings',), muscle_max_force=np.array([900.0]),
        muscle_fibre_length=np.array([0.1]), bone_names=('femur', 'tibia'), bone_segment=np.array([0, 1], np.int32),
        bone_vertex_offsets=np.array([0, 3, 6]), bone_vertices=np.eye(3).repeat(2, 0)[[0, 2, 4, 1, 3, 5]] * 0.1,
        bone_triangle_offsets=np.array([0, 1, 2]), bone_triangles=np.array([[0, 1, 2], [0, 2, 1]], np.int32),
        segment_names=('thigh', 'shank'), segment_parent=np.array([-1, 0], np.int32), segment_mass=np.array([8.0, 3.5]),
        segment_com=np.zeros((2, 3)), segment_inertia=np.tile(np.eye(3) * 0.1, (2, 1, 1)),
        joint_names=('knee',), joint_type=np.array([JOINT_HINGE], np.uint8), joint_parent=np.array([0], np.int32),
        joint_child=np.array([1], np.int32), joint_axis=np.array([[0, 1.0, 0]]), joint_centre=np.zeros((1, 3)),
        joint_range=np.array([[0, 2.4]]), joint_rest=np.zeros(1), slice_z=np.array([0, 0.01]),
    ).validate()


@pytest.mark.parametrize('colouring', ['none', 'skin_area'])
def test_marker_bytes_deserialise_to_the_deformed_model(colouring):
    from rclpy.serialization import deserialize_message, serialize_message
    from visualization_msgs.msg import Marker, MarkerArray
    tm = tiny_model()
    enc = mk.MarkerArrayEncoder(tm, frame_id='world', colouring=colouring)
    rng = np.random.default_rng(1)
    pos = np.asarray(tm.rest_positions) + rng.normal(0, 1e-3, tm.rest_positions.shape)
    poses = np.array([[0, 0, 0, 0, 0, 0, 1.0], [0.1, 0.2, 0.3, 0, np.sin(0.3), 0, np.cos(0.3)]])
    rgba = None
    if colouring != 'none':
        ratio, _ = measures.skin_area_ratio_per_vertex(tm, pos)
        rgba = mk.diverging_rgba(ratio[enc.skin_corners])
    data = enc.encode(12_000_000_345, pos, poses, rgba)
    msg = deserialize_message(data, MarkerArray)
    assert len(msg.markers) == 4                 # skin, muscle, 2 bone segments
    by_ns = {m.ns: m for m in msg.markers}
    skin, mus = by_ns['tissue/skin'], by_ns['tissue/muscle/biceps_femoris']
    for m in msg.markers:
        assert m.type == Marker.TRIANGLE_LIST and m.header.frame_id == 'world'
        assert m.header.stamp.sec == 12 and m.header.stamp.nanosec == 345
        assert (m.scale.x, m.scale.y, m.scale.z) == (1.0, 1.0, 1.0)
    pts = np.array([[p.x, p.y, p.z] for p in skin.points])
    np.testing.assert_array_equal(pts, pos[np.asarray(tm.surface_triangles)[2:].ravel()])
    pts = np.array([[p.x, p.y, p.z] for p in mus.points])
    np.testing.assert_array_equal(pts, pos[np.asarray(tm.surface_triangles)[:2].ravel()])
    assert mus.color.a == 1.0 and by_ns['tissue/bone/shank'].color.a == 1.0
    # the alpha a viewer shows: RViz multiplies marker and per-corner alpha, Foxglove takes the
    # per-corner value when there is one; both must show the documented skin alpha
    rviz = skin.color.a * (skin.colors[0].a if len(skin.colors) else 1.0)
    foxglove = skin.colors[0].a if len(skin.colors) else skin.color.a
    assert rviz == pytest.approx(mk.SKIN_RGBA[3]) and foxglove == pytest.approx(mk.SKIN_RGBA[3])
    shank = by_ns['tissue/bone/shank']
    assert shank.pose.position.y == pytest.approx(0.2) and shank.pose.orientation.w == pytest.approx(np.cos(0.3))
    assert len(shank.points) == 3
    assert len({m.id for m in msg.markers}) == 4
    if colouring == 'none':
        assert len(skin.colors) == 0
    else:
        assert len(skin.colors) == len(skin.points)
        np.testing.assert_allclose([skin.colors[0].r, skin.colors[0].a], [rgba[0, 0], rgba[0, 3]], rtol=1e-6)
    # same size as rclpy's own encoding (which may add up to 8 stale padding bytes at the end and
    # leaves stale bytes in alignment gaps, so the bytes themselves are not compared)
    again = serialize_message(msg)
    assert 0 <= len(again) - len(data) <= 8
    # a second frame reuses the buffer: new content, same length
    data2 = enc.encode(13_000_000_000, pos + 0.01, poses)
    assert len(data2) == len(data) and data2 != data
    msg2 = deserialize_message(data2, MarkerArray)
    assert msg2.markers[0].points[0].x == pytest.approx(pos[tm.surface_triangles[2, 0], 0] + 0.01)  # marker 0: skin


def test_fat_deformation_is_zero_for_rigid_motion_and_grows_with_strain():
    tm = tiny_model()
    rest = np.asarray(tm.rest_positions)
    th = 0.7
    R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    d = measures.FatDeformation(tm)(rest @ R.T + 0.05)
    assert np.max(d) < 1e-12
    strained = rest.copy()
    strained[9] += [0.0, 0.0, 0.004]
    d = measures.FatDeformation(tm)(strained)
    assert d[9] > 1e-4 and d[0] == 0.0       # vertex 0 is not in the fat cell


def test_skin_area_ratio():
    tm = tiny_model()
    p = np.asarray(tm.rest_positions).copy()
    ratio, rest_area = measures.skin_area_ratio_per_vertex(tm, p)
    assert np.allclose(ratio, 1.0)
    p[[8, 9], 2] = 0.02                        # skin quad twice as tall
    ratio, _ = measures.skin_area_ratio_per_vertex(tm, p, rest_area)
    assert ratio[6] == pytest.approx(2.0) and ratio[0] == 1.0
    c = mk.diverging_rgba(np.array([1.0, 1.5, 0.5]))
    assert np.allclose(c[0, :3], 1) and c[1, 2] == 1 and c[1, 0] == 0 and c[2, 0] == 1 and c[2, 2] == 0


def test_bad_colouring_is_named():
    with pytest.raises(ValueError, match='marker colouring'):
        mk.MarkerArrayEncoder(tiny_model(), colouring='rainbow')


def test_cluster_decimate_keeps_shape_and_drops_degenerate_triangles():
    import trimesh
    m = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    v, t = mk.cluster_decimate(np.asarray(m.vertices), np.asarray(m.faces, np.int64), 0.01)
    assert 20 < len(t) < len(m.faces) / 3
    assert np.all((t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2]))
    r = np.linalg.norm(v, axis=1)
    assert np.all(np.abs(r - 0.05) < 0.01)               # still a sphere of radius 5 cm (within a cell)
    v0, t0 = mk.cluster_decimate(np.asarray(m.vertices), np.asarray(m.faces, np.int64), 1e-6)
    assert len(t0) == len(m.faces)                        # a fine grid changes nothing


def test_display_surface_of_a_finer_limb_is_its_own_vertices_on_a_coarser_mesh():
    """marker_resolution: the 3x limb's soft-tissue surface decimated on a 1-cm grid for display. Every corner is a
    vertex its group's full surface uses (the skin drawn with skin vertices; the gather takes current positions);
    no triangle collapses or repeats; the closed skin keeps its volume and area within 3 % and its outward
    orientation; the MarkerArray shrinks 2.5-fold or more (6.7 -> 2.3 MB); 0 changes nothing."""
    from tissue_sim.core.builder import default_model
    tm = default_model(refine=3)
    x = np.asarray(tm.rest_positions)
    tris, groups = np.asarray(tm.surface_triangles, np.int64), np.asarray(tm.surface_group)
    t, g = mk.display_surface(x, tris, groups, 0.01)
    assert set(np.unique(g)) == set(np.unique(groups))
    for k in np.unique(groups):
        assert np.isin(t[g == k], tris[groups == k]).all()
    assert np.all((t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2]))
    for k in np.unique(g):
        assert len(np.unique(np.sort(t[g == k], axis=1), axis=0)) == np.sum(g == k)
    skin = list(tm.surface_group_names).index('skin')

    def volume_area(tt):
        a, b, c = x[tt[:, 0]], x[tt[:, 1]], x[tt[:, 2]]
        return (np.einsum('ij,ij->i', a, np.cross(b, c)).sum() / 6,
                0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())
    (v0, a0), (v1, a1) = volume_area(tris[groups == skin]), volume_area(t[g == skin])
    assert v0 > 0 and abs(v1 / v0 - 1) < 0.03 and abs(a1 / a0 - 1) < 0.03
    full, coarse = mk.MarkerArrayEncoder(tm, bones=False), mk.MarkerArrayEncoder(tm, bones=False, soft_resolution=0.01)
    assert coarse.nbytes < full.nbytes / 2.5
    pos = x + np.random.default_rng(0).normal(0, 1e-3, x.shape)
    assert full.encode(5, pos) == mk.MarkerArrayEncoder(tm, bones=False, soft_resolution=0.0).encode(5, pos)


def test_builder_model_markers_have_every_group_and_posed_bones():
    """A model from the real builder (tests/phantoms.py 'two_bones'): one marker per surface group
    and per bone-carrying segment; bone points are the bones' rest triangles."""
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import MarkerArray
    from phantoms import make_phantom_model
    tm = make_phantom_model('two_bones')
    enc = mk.MarkerArrayEncoder(tm)
    x = np.asarray(tm.rest_positions)
    msg = deserialize_message(enc.encode(1, x), MarkerArray)
    ns = [m.ns for m in msg.markers]
    used = sorted(set(np.asarray(tm.surface_group).tolist()))
    assert ns[:len(used)] == [f'tissue/{tm.surface_group_names[g]}' for g in used]
    bone_segs = sorted(set(np.asarray(tm.bone_segment).tolist()))
    assert ns[len(used):] == [f'tissue/bone/{tm.segment_names[s]}' for s in bone_segs]
    n_bone_pts = sum(len(m.points) for m in msg.markers if '/bone/' in m.ns)
    assert n_bone_pts == 3 * len(tm.bone_triangles)
    assert sum(len(m.points) for m in msg.markers if '/bone/' not in m.ns) == 3 * len(tm.surface_triangles)


def test_fat_deformation_colours_skin_and_fat_markers_alike():
    """fat_deformation colours every fat marker as well as the skin; skin_area only the skin; the
    alpha shown is 0.3 in RViz (product) and in Foxglove (per-corner value) for each of them."""
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import MarkerArray
    from phantoms import make_phantom_model
    tm = make_phantom_model('two_bones')
    names = list(tm.surface_group_names) or ['fat']
    for colouring, expect in (('skin_area', {'skin'}), ('fat_deformation', {'skin', 'fat'})):
        enc = mk.MarkerArrayEncoder(tm, colouring=colouring)
        x = np.asarray(tm.rest_positions) * 1.01
        d = measures.FatDeformation(tm)(x)
        rgba = mk.sequential_rgba(d[enc.skin_corners], 1e-3)
        msg = deserialize_message(enc.encode(1, x, None, rgba), MarkerArray)
        coloured = {m.ns.split('/')[1] for m in msg.markers if len(m.colors)}
        present = {n.split('/')[0] for n in names if n.split('/')[0] in ('skin', 'fat')}
        assert coloured == expect & present, (colouring, coloured, names)
        i = 0
        for m in msg.markers:
            if len(m.colors):
                assert len(m.colors) == len(m.points)
                assert m.color.a == 1.0 and m.colors[0].a == pytest.approx(mk.SKIN_RGBA[3])
                np.testing.assert_allclose([m.colors[0].g], [rgba[i, 1]], rtol=1e-6)
                i += len(m.points)
            elif '/bone/' not in m.ns and not m.ns.startswith('tissue/muscle'):
                assert m.color.a == pytest.approx(mk.SKIN_RGBA[3])
        assert i == len(rgba)


def test_bone_markers_in_link_frames_match_the_posed_bones():
    """The once-sent bone MarkerArray (frame = segment, frame_locked) placed by the TF of a state
    lands where the per-frame world-frame bone markers are; the per-frame array without bones is
    smaller by exactly those markers."""
    from rclpy.serialization import deserialize_message
    from visualization_msgs.msg import MarkerArray
    from scipy.spatial.transform import Rotation
    from tissue_sim.core import urdf
    from tissue_sim.core.tissue_cdr import quat_to_matrix
    tm = tiny_model()
    once = deserialize_message(mk.bone_marker_array(tm), MarkerArray)
    assert [m.header.frame_id for m in once.markers] == ['thigh', 'shank']
    assert all(m.frame_locked and m.color.a == 1.0 and m.pose.orientation.w == 1.0 for m in once.markers)
    # a knee-flexed state: segment poses (rest point p -> R p + t)
    q = Rotation.from_rotvec([0, 0.7, 0]).as_quat()
    poses = np.array([[0, 0, 0, 0, 0, 0, 1.0], [0.01, 0.02, -0.03, *q]])
    R, t = quat_to_matrix(poses[:, 3:]), poses[:, :3]
    # world pose of each link frame from the TF tree, composed from the root
    tf = {child: (parent, tr, quat_to_matrix(qq)) for parent, child, tr, qq in urdf.tf_transforms(tm, R, t)}

    def world(frame):
        if frame == urdf.ROOT_LINK:
            return np.eye(3), np.zeros(3)
        parent, tr, Rr = tf[frame]
        Rp, tp = world(parent)
        return Rp @ Rr, Rp @ tr + tp
    full = deserialize_message(mk.MarkerArrayEncoder(tm).encode(5, tm.rest_positions, poses), MarkerArray)
    for m in once.markers:
        Rw, tw = world(m.header.frame_id)
        got = np.array([[p.x, p.y, p.z] for p in m.points]) @ Rw.T + tw
        ref = next(f for f in full.markers if f.ns == m.ns)
        Rm = quat_to_matrix(np.array([ref.pose.orientation.x, ref.pose.orientation.y, ref.pose.orientation.z,
                                      ref.pose.orientation.w]))
        tm_ = np.array([ref.pose.position.x, ref.pose.position.y, ref.pose.position.z])
        want = np.array([[p.x, p.y, p.z] for p in ref.points]) @ Rm.T + tm_
        np.testing.assert_allclose(got, want, atol=1e-12)
    soft = mk.MarkerArrayEncoder(tm, bones=False)
    msg = deserialize_message(soft.encode(5, tm.rest_positions), MarkerArray)
    assert [m.ns for m in msg.markers] == [m.ns for m in full.markers if '/bone/' not in m.ns]
    assert soft.nbytes < mk.MarkerArrayEncoder(tm).nbytes
