"""Checks of the bundled right lower limb (src/tissue_sim/tissue_sim/data/lower_limb).

Volumes are checked against physiology recomputed here (Fmax x optimal fibre length / 60 N/cm^2,
with the belly extents of tools/anatomy/muscles.py), not against numbers the generator wrote.
"""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import yaml
from scipy import ndimage
from skimage import measure

from tissue_sim.core import anatomy

ROOT = Path(__file__).resolve().parents[1]
TOOLS = ROOT / 'tools' / 'anatomy'
sys.path.insert(0, str(TOOLS))
import muscles as MU  # noqa: E402
import raster  # noqa: E402

HAMSTRINGS = {'biceps_femoris_long_head', 'biceps_femoris_short_head', 'semimembranosus', 'semitendinosus'}


@pytest.fixture(scope='module')
def data():
    img = nib.load(anatomy.labels_path())
    lab = np.asarray(img.dataobj)
    tissues = yaml.safe_load(anatomy.tissues_path().read_text())
    joints = yaml.safe_load(anatomy.joints_path().read_text())
    S = img.affine[2, 3] + img.affine[2, 2] * np.arange(lab.shape[2])
    return {'img': img, 'lab': lab, 'labels': tissues['labels'], 'tissues': tissues, 'joints': joints, 'S': S}


def _muscles(d):
    return {k: v for k, v in d['labels'].items() if v['tissue'] == 'muscle'}


def _joint(d, name):
    return next(j for j in d['joints']['joints'] if j['name'] == name)


def _slice_at(d, s):
    return int(np.argmin(np.abs(d['S'] - s)))


def test_format(data):
    img, lab = data['img'], data['lab']
    A = img.affine
    assert lab.dtype == np.uint8 and lab.ndim == 3
    assert np.allclose(np.abs(np.diag(A)[:2]), 1.0), 'in-plane pixels must be 1 mm'
    assert 1.0 <= abs(A[2, 2]) <= 5.0, 'slices 1-5 mm'
    assert np.allclose(A[:3, :2][2], 0) and np.allclose(A[:2, 2], 0), 'third voxel axis must be S-I'
    assert img.header.get_xyzt_units()[0] == 'mm'
    # stack: from just below the hip to the foot, about 0.8 m
    assert -100 < data['S'].max() < 0 and data['S'].min() < -850
    assert anatomy.labels_path().stat().st_size + sum(
        p.stat().st_size for p in anatomy.DEFAULT_DIR.rglob('*') if p.is_file()) < 5e6


def test_label_sets(data):
    lab, labels = data['lab'], data['labels']
    present = set(np.unique(lab).tolist()) - {0}
    assert present == set(labels), f'volume/table mismatch: {present ^ set(labels)}'
    kinds = [v['tissue'] for v in labels.values()]
    assert kinds.count('bone') == 6 and kinds.count('muscle') == 28 and kinds.count('fat') == 1
    names = [v['name'] for v in labels.values()]
    assert len(set(names)) == len(names)
    assert HAMSTRINGS <= set(names)
    segs = {s['name'] for s in data['joints']['segments']}
    for v in labels.values():
        if v['tissue'] == 'bone':
            assert v['segment'] in segs
            assert (anatomy.DEFAULT_DIR / v['mesh']).is_file()


def test_muscle_volumes_match_physiology(data):
    """Every muscle within 15 % of Fmax * L0 / 60 N/cm^2 (the part of its belly inside the stack)."""
    lab, img = data['lab'], data['img']
    vox_mm3 = abs(np.linalg.det(img.affine[:3, :3]))
    knee_z = _joint(data, 'knee_r')['centre'][2] * 1000
    ankle_z = _joint(data, 'ankle_r')['centre'][2] * 1000
    dz = abs(img.affine[2, 2])
    top, bottom = data['S'].max() + dz / 2, data['S'].min() - dz / 2
    ext = {name: belly for name, _, _, belly in MU.MUSCLES}
    counts = np.bincount(lab.ravel(), minlength=256)
    bad = []
    for lbl, m in _muscles(data).items():
        v_phys = m['max_isometric_force'] * m['optimal_fibre_length'] / 60e4 * 1e9  # mm^3
        u0, u1 = ext[m['name']]
        z = np.array([u * knee_z if u <= 1 else knee_z + (u - 1) * (ankle_z - knee_z) for u in (u0, u1)])
        zz = np.linspace(z[0], z[1], 20001)
        prof = np.sin(np.pi * np.linspace(0, 1, zz.size)) ** MU.SPINDLE_P
        frac = prof[(zz <= top) & (zz >= bottom)].sum() / prof.sum()
        target = v_phys * frac
        # the belly only: the distal tendons (labelled below the belly, see test_tendons_insert_on_shank)
        # are not part of the physiological (fibre) volume
        got = (lab[..., data['S'] + dz / 2 > z.min()] == lbl).sum() * vox_mm3
        if abs(got / target - 1) > 0.15:
            bad.append((m['name'], round(got / 1e3, 1), round(target / 1e3, 1)))
    assert not bad, f'volume off by > 15 % (name, got cm3, target cm3): {bad}'


def _tendon_gaps(data):
    """The knee-crossing muscles continue below their bellies as tendons (own label) that lie on a shank
    bone (tibia, fibula) in a run of slices at least 20 mm long reaching 30 mm below the knee centre (the
    hamstrings, gracilis, sartorius), so a model builder attaches them to the shank, or on the patella's upper half
    (the quadriceps: they insert on its base and upper borders, muscles.PATELLA_ATTACH_FRACTION); tendons are small
    (< 15 cm^3); the bellies are partitioned around them."""
    lab, labels = data['lab'], data['labels']
    knee_z = _joint(data, 'knee_r')['centre'][2] * 1000
    dz = abs(data['img'].affine[2, 2])
    byname = {v['name']: k for k, v in labels.items()}
    bones = {v['name']: k for k, v in labels.items() if v['tissue'] == 'bone'}
    need = {n: ('tibia', 'fibula') for n in HAMSTRINGS | {'gracilis', 'semitendinosus', 'sartorius'}}
    need.update({n: ('patella',) for n in ('rectus_femoris', 'vastus_lateralis', 'vastus_medialis')})
    on_patella = [data['S'][k] for k in np.nonzero((lab == bones['patella']).any(axis=(0, 1)))[0]]
    patella_mid = (max(on_patella) + min(on_patella)) / 2
    gap_list = []
    for name, on in need.items():
        lbl = byname[name]
        t = labels[lbl]['tendon']
        touch, gaps, zs = [], 0, []
        for k in range(t['slices'][0], t['slices'][1] + 1):
            m = lab[..., k] == lbl
            gaps += not m.any()   # a slice where other muscles leave no fat on its path
            zs.append(data['S'][k])
            if (ndimage.binary_dilation(m) & np.isin(lab[..., k], [bones[b] for b in on])).any():
                touch.append(data['S'][k])
        gap_list.append((name, gaps))
        if on == ('patella',):
            assert 0.0 < t['volume_cm3'] < 15.0 and touch, (name, t, touch)
            assert min(zs) >= patella_mid - dz, (name, min(zs), patella_mid)
        else:
            assert 0.1 < t['volume_cm3'] < 15.0, (name, t)  # the fan onto the bone makes it up to ~2 cm^2
            assert len(touch) * dz >= 20, (name, touch)
            assert min(touch) < knee_z - 30, (name, min(touch))  # reaches below the joint line
    return gap_list


def test_tendons_insert_on_shank(data):
    _tendon_gaps(data)


def test_hamstring_tendons_continuous(data):
    """Every hamstring tendon is present in all but 2 of its slices (a continuous muscle-tendon unit)."""
    gaps = dict(_tendon_gaps(data))
    bad = {n: g for n, g in gaps.items() if n in HAMSTRINGS and g > 2}
    assert not bad, f'tendon slices without the tendon: {bad}'


def test_ankle_tendons_reach_the_foot(data):
    """Soleus (the calcaneal tendon) and tibialis anterior continue below their bellies as tendons
    that are present in every slice down to the foot bone (no gap: a model builder links each
    muscle-tendon unit in one chain) and lie on the foot bone (label 6,
    calcaneus / medial cuneiform) over at least 20 mm below the ankle centre, so they can move it."""
    lab, labels = data['lab'], data['labels']
    ankle_z = _joint(data, 'ankle_r')['centre'][2] * 1000
    dz = abs(data['img'].affine[2, 2])
    byname = {v['name']: k for k, v in labels.items()}
    foot = next(k for k, v in labels.items() if v['name'] == 'foot')
    for name in ('soleus', 'tibialis_anterior'):
        lbl = byname[name]
        t = labels[lbl]['tendon']
        assert t['inserts_on'] == ['foot'] and 0.1 < t['volume_cm3'] < 15.0, (name, t)
        ks = range(t['slices'][0], t['slices'][1] + 1)
        gaps = [k for k in ks if not (lab[..., k] == lbl).any()]
        assert not gaps, (name, 'tendon slices without the tendon', gaps)
        touch = [data['S'][k] for k in ks
                 if (ndimage.binary_dilation(lab[..., k] == lbl) & (lab[..., k] == foot)).any()]
        assert len(touch) * dz >= 20 and min(touch) < ankle_z - 20, (name, touch)


def test_physiology_from_opensim(data):
    """Fmax and optimal fibre length in the table are the Rajagopal values (sums / volume-weighted)."""
    if importlib.util.find_spec('Pose2Sim') is None:
        pytest.skip('pose2sim not installed (make anatomy installs it)')
    import osim
    p2s = Path(importlib.util.find_spec('Pose2Sim').submodule_search_locations[0])
    model = osim.load(p2s / 'OpenSim_Setup' / 'Model_Pose2Sim_muscles_flex.osim')
    for m in _muscles(data).values():
        parts = [model['muscles'][p] for p in m['opensim_parts']]
        F = sum(p['max_isometric_force'] for p in parts)
        V = sum(p['max_isometric_force'] * p['optimal_fiber_length'] for p in parts)
        assert m['max_isometric_force'] == pytest.approx(F, abs=0.1)
        assert m['optimal_fibre_length'] == pytest.approx(V / F, abs=1e-4)
    assert {p for m in _muscles(data).values() for p in m['opensim_parts']} >= {'bflh', 'bfsh', 'semimem', 'semiten'}


def test_no_overlap_with_bone_meshes(data):
    """Voxels inside a bone surface carry that bone's label, never muscle or fat (one label each)."""
    lab, A = data['lab'], data['img'].affine
    import trimesh
    for lbl, b in data['labels'].items():
        if b['tissue'] != 'bone' or b['name'] == 'foot':
            continue
        mesh = trimesh.load(anatomy.DEFAULT_DIR / b['mesh'], process=False)
        tri = mesh.vertices[mesh.faces] * 1000.0
        ras = np.stack([-tri[..., 1], tri[..., 0], tri[..., 2]], -1)
        inside = agree = bone = 0
        for k in range(0, lab.shape[2], 4):
            segs = raster.plane_segments(ras, [0, 0, 1], data['S'][k])
            if len(segs) == 0:
                continue
            pix = np.stack([segs[..., 0] - A[0, 3], segs[..., 1] - A[1, 3]], -1)
            m = ndimage.binary_erosion(raster.fill_segments(pix, lab.shape[:2]))  # away from the edge
            inside += m.sum()
            agree += (lab[..., k][m] == lbl).sum()
            bone += ((lab[..., k][m] >= 1) & (lab[..., k][m] <= 6)).sum()
        assert inside > 0
        # meshes of neighbouring bones touch (talus/foot): there one bone label wins
        assert agree / inside > 0.9, f'{b["name"]}: {agree}/{inside} voxels inside its mesh carry its label'
        assert bone / inside > 0.99, f'{b["name"]}: {inside - bone} voxels inside the bone are soft tissue'


def test_muscles_present_where_bellies_cross(data):
    lab = data['lab']
    knee_z = _joint(data, 'knee_r')['centre'][2] * 1000
    ankle_z = _joint(data, 'ankle_r')['centre'][2] * 1000
    ext = {name: belly for name, _, _, belly in MU.MUSCLES}
    dz = abs(data['img'].affine[2, 2])
    missing = []
    for lbl, m in _muscles(data).items():
        z0, z1 = [u * knee_z if u <= 1 else knee_z + (u - 1) * (ankle_z - knee_z) for u in ext[m['name']]]
        ks = [k for k, s in enumerate(data['S']) if z1 + dz < s < z0 - dz]
        assert ks, m['name']
        absent = [k for k in ks if not (lab[..., k] == lbl).any()]
        if absent:
            missing.append((m['name'], len(absent), len(ks)))
        # one piece per slice, mostly
        pieces = [ndimage.label(lab[..., k] == lbl)[1] for k in ks[::4]]
        assert np.mean(np.array(pieces) <= 2) > 0.8, (m['name'], pieces)
    assert not missing, f'muscle absent from slices its belly crosses: {missing}'


def test_squeezed_muscle_shares_its_place():
    """The partition's rule for a muscle squeezed out of a slice (its seed shared with a neighbour's): it takes the
    pixels nearest its seed but leaves the neighbour at least half of its own. Taken wholly (the rule before), the
    neighbour kept only what the squeezed one did not take, or nothing: on the bundled limb 4 slices changed with the
    rule (403 voxels), e.g. the gastrocnemii at the joint line, lateralis 298 and medialis 694 mm^2 at S -402.5 mm,
    now 496 each; with the gastrocnemii changed, the tibialis anterior vanished from a slice."""
    import generate
    n = np.arange(10.0)
    D = np.stack([n ** 2, n ** 2, (9 - n) ** 2])         # muscles 0 and 1: the same seed at pixel 0; muscle 2 at 9
    best = np.array([0] * 5 + [2] * 5)
    generate.give_squeezed(best, D, np.array([5.0, 5.0, 5.0]))
    have = np.bincount(best, minlength=3)
    assert have.tolist() == [3, 4, 3], have
    assert best[:2].tolist() == [1, 1]                     # the nearest of its neighbour's pixels


def test_gastrocnemius_heads_behind_the_condyles(data):
    """The gastrocnemii arise from the posterior femoral condyles and pass behind the knee (Gray's Anatomy, ch. 83;
    the source model wraps them over cylinders there): from 13 mm above to 20 mm below the knee centre each head has
    a full section (>= 800 mm^2) whose centroid lies at least 15 mm behind the knee centre (muscles.WRAPPED_SEEDS,
    the bellies from 0.93 limb units, generate.py's fat thickness behind the condyles). Seeded on the straight line
    through the condyles they started 5-12 mm above the knee centre and went round the condyles' sides (the medialis
    78-92 mm^2 at 4-12 mm below it, centred 4 mm in front)."""
    lab, A = data['lab'], data['img'].affine
    knee = _joint(data, 'knee_r')['centre']
    kA, kS = knee[0] * 1000, knee[2] * 1000
    ids = {v['name']: int(k) for k, v in _muscles(data).items()}
    bad = []
    for name in MU.WRAPPED_SEEDS:
        for k in np.flatnonzero((data['S'] > kS - 20) & (data['S'] < kS + 13)):
            ij = np.argwhere(lab[..., k] == ids[name])
            behind = kA - (ij[:, 1].mean() + A[1, 3]) if len(ij) else 0.0
            if len(ij) < 800 or behind < 15:
                bad.append((name, round(float(data['S'][k] - kS), 1), len(ij), round(float(behind), 1)))
    assert not bad, f'(muscle, S - knee [mm], area [mm^2], centroid behind the knee centre [mm]): {bad}'


def _circumference_cm(mask):
    c = max(measure.find_contours(mask.astype(float), 0.5), key=len)
    return float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum()) / 10.0


def test_published_ranges(data):
    """Mid-thigh muscle area and thigh/calf circumferences of an adult man.

    * Mid-thigh total muscle cross-section of young adult men, CT/MRI: about 120-180 cm^2
      (e.g. Overend TJ et al. 1992, J Gerontol 47(6):M204-M210; Maughan RJ et al. 1983, J Physiol
      338:37-49); accepted here: 100-220 cm^2.
    * Mid-thigh circumference of US men 20+ y: mean about 53 cm, 5th-95th percentile about 45-62 cm;
      maximal calf circumference: mean about 39 cm, 5th-95th about 34-45 cm (Fryar CD, Gu Q, Ogden CL.
      Anthropometric reference data for children and adults: United States, 2007-2010. Vital Health
      Stat 11(252), 2012); accepted here: thigh 44-64 cm, calf 32-46 cm.
    """
    lab = data['lab']
    knee_z = _joint(data, 'knee_r')['centre'][2] * 1000
    ankle_z = _joint(data, 'ankle_r')['centre'][2] * 1000
    k = _slice_at(data, knee_z / 2)
    mus = list(_muscles(data))
    csa = np.isin(lab[..., k], mus).sum() / 100.0  # cm^2 (1 mm pixels)
    assert 100 <= csa <= 220, csa
    thigh = _circumference_cm(lab[..., k] > 0)
    assert 44 <= thigh <= 64, thigh
    shank = [k for k, s in enumerate(data['S']) if ankle_z + 100 < s < knee_z - 50]
    calf = max(_circumference_cm(lab[..., k] > 0) for k in shank)
    assert 32 <= calf <= 46, calf
    # the thigh is mostly muscle, with a subcutaneous fat layer of realistic area
    fat = (lab[..., k] == 40).sum() / 100.0
    assert 15 <= fat <= 120, fat


def test_bone_covered_and_fat_outside(data):
    lab = data['lab']
    fat = [k for k, v in data['labels'].items() if v['tissue'] == 'fat'][0]
    for k in range(lab.shape[2]):
        sl = lab[..., k]
        body = sl > 0
        assert ndimage.label(body)[1] == 1, f'slice {k}: limb in more than one piece'
        rim = body & ~ndimage.binary_erosion(body)
        bone = (sl >= 1) & (sl <= 6)
        assert not (rim & bone).any(), f'slice {k}: bone on the skin'
        # the skin rim is fat wherever the slice has fat (subcutaneous layer)
        assert (sl[rim] == fat).mean() > 0.95, f'slice {k}: skin rim not fat'


def test_joints(data):
    j = data['joints']
    knee = _joint(data, 'knee_r')
    ax = np.array(knee['axis'])
    assert np.linalg.norm(ax) == pytest.approx(1.0, abs=1e-4)
    assert ax[1] > 0.99  # medio-lateral, pointing left: positive rotation = flexion
    assert knee['range_deg'] == [0.0, 120.0]
    assert -0.45 < knee['centre'][2] < -0.35
    segs = {s['name']: s for s in j['segments']}
    # de Leva (1996) male mass fractions
    total = j['body_mass']
    for name, frac in (('thigh', 0.1416), ('shank', 0.0433), ('foot', 0.0137)):
        assert segs[name]['mass'] == pytest.approx(frac * total, rel=1e-3)
        I = np.array(segs[name]['inertia'])
        assert np.allclose(I, I.T) and np.all(np.linalg.eigvalsh(I) > 0)
    assert knee['centre'][2] < segs['thigh']['com'][2] < 0
    assert _joint(data, 'ankle_r')['centre'][2] < segs['shank']['com'][2] < knee['centre'][2]


def test_knee_hinge_follows_opensim(data):
    """The hinge (axis, centre) puts the ankle where OpenSim's walker knee does: within 1 cm to 60 deg
    and 1.5 cm at 90 deg (the hinge leaves out the walker knee's coupled secondary motion)."""
    if importlib.util.find_spec('Pose2Sim') is None:
        pytest.skip('pose2sim not installed (make anatomy installs it)')
    import osim
    from scipy.spatial.transform import Rotation
    p2s = Path(importlib.util.find_spec('Pose2Sim').submodule_search_locations[0])
    path = p2s / 'OpenSim_Setup' / 'Model_Pose2Sim_muscles_flex.osim'
    knee = _joint(data, 'knee_r')
    c, a = np.array(knee['centre']), np.array(knee['axis'])
    ankle = np.array(_joint(data, 'ankle_r')['centre'])
    for deg in (30, 60, 90):
        t = osim.load(path, coords={'knee_angle_r': np.radians(deg)})['bodies']['talus_r']['T'][:3, 3]
        ref = np.array([t[0], -t[2], t[1]])  # OpenSim femur frame -> model frame
        hinge = Rotation.from_rotvec(a * np.radians(deg)).apply(ankle - c) + c
        assert np.linalg.norm(hinge - ref) < (0.01 if deg <= 60 else 0.015), (deg, hinge, ref)
        assert hinge[0] < ankle[0] - 0.1  # flexion moves the ankle backwards


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_regenerates(tmp_path, data):
    """The generator reproduces the committed files from the registry packages (with the muscle paths' OpenSim
    sampling, tools/anatomy/paths.py, more than the default 300 s on a loaded machine)."""
    for pkg in ('Pose2Sim', 'anny', 'opensim'):
        if importlib.util.find_spec(pkg) is None:
            pytest.skip(f'{pkg} not installed: run `make anatomy` (tools/anatomy/run.sh) to install '
                        'requirements/anatomy.txt and requirements/validation.txt')
    env = dict(os.environ, PYTHONPATH=str(ROOT / 'src' / 'tissue_sim'))
    r = subprocess.run([sys.executable, '-m', 'tissue_sim.cli', 'make-anatomy', '--out', str(tmp_path), '--quiet'],
                       capture_output=True, text=True, timeout=1100, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    img = nib.load(tmp_path / 'labels.nii.gz')
    new = np.asarray(img.dataobj)
    assert np.allclose(img.affine, data['img'].affine)
    assert new.shape == data['lab'].shape
    diff = (new != data['lab']).mean()
    assert diff <= 0.005, f'{diff:.4%} of voxels differ (documented tolerance 0.5 %)'
    assert yaml.safe_load((tmp_path / 'joints.yaml').read_text()) == data['joints']
    paths = {n: yaml.safe_load(p.read_text())['muscles'] for n, p in (('new', tmp_path / 'muscle_paths.yaml'),
                                                                      ('old', ROOT / 'src' / 'tissue_sim' / 'tissue_sim' /
                                                                       'data' / 'lower_limb' / 'muscle_paths.yaml'))}
    assert paths['new'].keys() == paths['old'].keys()
    for name, parts in paths['old'].items():
        for a, b in zip(parts, paths['new'][name]):
            assert a['powers'] == b['powers'] and np.allclose(a['coefficients_m'], b['coefficients_m'], rtol=1e-6, atol=1e-9)
    t_new = yaml.safe_load((tmp_path / 'tissues.yaml').read_text())['labels']
    assert {k: v['name'] for k, v in t_new.items()} == {k: v['name'] for k, v in data['labels'].items()}
    # segments of the bones and of the muscles' ends (the patella's own segment: tools/anatomy/patella.py)
    ends = lambda labels: {k: (v.get('segment'), *(v[e]['segment'] for e in ('origin', 'insertion') if e in v))  # noqa: E731
                           for k, v in labels.items()}
    assert ends(t_new) == ends(data['labels'])
    assert {k: v.get('via_points') for k, v in t_new.items()} == {k: v.get('via_points') for k, v in data['labels'].items()}
    assert {k: v.get('wrap_surfaces') for k, v in t_new.items()} == {k: v.get('wrap_surfaces') for k, v in data['labels'].items()}
