"""The tissue table (tissues.yaml) and the joints file (joints.yaml); see docs/FORMATS.md.

``load_tissue_table(path_or_dict)`` returns a plain dict::

    {'name': str, 'base': Path | None,
     'labels': {label: {'name', 'tissue', 'segment', 'group', 'max_isometric_force',
                        'optimal_fibre_length', 'rest_fibre_length', 'stiffness_scale', 'mesh',
                        'origin', 'insertion', 'via_points', 'wrap_surfaces'}},
     'skeleton': {...}}   # from load_joints

All coordinates of the joints file are model frame metres (REP-103), angles in degrees in the file,
radians in the result. Bad input raises UserError naming the file and the key.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from tissue_sim.errors import UserError

TISSUES = ('bone', 'muscle', 'fat')


def _read_yaml(path: Path, what: str):
    if not path.is_file():
        raise UserError(f'{path}: no such {what} file')
    try:
        data = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise UserError(f'{path}: unreadable {what} (not valid YAML: {str(e).splitlines()[0]})') from None
    if not isinstance(data, dict):
        raise UserError(f'{path}: {what} must be a YAML mapping')
    return data


def _num(v, where, positive=False):
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise UserError(f'{where}: expected a number, got {v!r}') from None
    if not math.isfinite(x) or (positive and x <= 0):
        raise UserError(f'{where}: expected a {"positive " if positive else ""}finite number, got {v!r}')
    return x


def _type_name(v) -> str:
    return {list: 'a list', dict: 'a mapping', bool: 'a boolean', int: 'a number', float: 'a number',
            type(None): 'empty'}.get(type(v), type(v).__name__)


def _text(ent: dict, key: str, where: str, required: bool = False):
    """A string-valued key of a table entry: a non-empty string, or None when absent/empty and optional."""
    v = ent.get(key)
    if v is None or (v == '' and not required):
        if required:
            raise UserError(f'{where}: missing "{key}"')
        return None
    if not isinstance(v, str) or not v.strip():
        hint = ' (one name per entry)' if isinstance(v, list) else ''
        raise UserError(f'{where}: "{key}" must be a text string{hint}, got {_type_name(v)} {v!r}')
    return v


def _vec(v, n, where):
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise UserError(f'{where}: expected a list of {n} numbers, got {v!r}')
    return np.array([_num(x, where) for x in v])


def load_tissue_table(src) -> dict:
    """Parse and check a tissue table (path or already-parsed dict; its ``joints`` a path or a dict)."""
    if isinstance(src, dict):
        data, base, where = src, None, '<tissue table>'
    else:
        path = Path(src)
        data, base, where = _read_yaml(path, 'tissue table'), path.parent, str(path)
    labels_in = data.get('labels')
    if not isinstance(labels_in, dict) or not labels_in:
        raise UserError(f'{where}: needs a non-empty "labels" mapping (label value -> tissue entry)')
    labels = {}
    names = set()
    for key, ent in labels_in.items():
        try:
            if isinstance(key, bool) or (isinstance(key, float) and key != int(key)):
                raise ValueError
            lab = int(key)
        except (TypeError, ValueError, OverflowError):
            raise UserError(f'{where}: label {key!r} is not an integer') from None
        w = f'{where}: label {lab}'
        if lab <= 0:
            raise UserError(f'{w}: label values must be positive (0 is background)')
        if not isinstance(ent, dict):
            raise UserError(f'{w}: entry must be a mapping with name and tissue')
        name = _text(ent, 'name', w, required=True)
        tissue = ent.get('tissue')
        if not isinstance(tissue, str) or tissue not in TISSUES:
            raise UserError(f'{w} ({name}): tissue must be one of {", ".join(TISSUES)}, got {tissue!r}')
        if tissue != 'fat' and name in names:
            raise UserError(f'{w}: duplicate name {name!r}')
        names.add(name)
        out = {'name': name, 'tissue': tissue, 'segment': _text(ent, 'segment', f'{w} ({name})'),
               'group': _text(ent, 'group', f'{w} ({name})') or '',
               'max_isometric_force': float('nan'), 'optimal_fibre_length': float('nan'),
               'rest_fibre_length': 1.0, 'stiffness_scale': 1.0, 'mesh': None}
        if tissue == 'bone':
            if not isinstance(out['segment'], str) or not out['segment']:
                raise UserError(f'{w} ({name}): a bone must name its "segment" (a segment of the joints file)')
            if ent.get('mesh') is not None:
                if base is None:
                    raise UserError(f'{w} ({name}): "mesh" needs a table file (paths are relative to it)')
                mp = base / _text(ent, 'mesh', f'{w} ({name})')
                if not mp.is_file():
                    raise UserError(f'{w} ({name}): mesh file {mp} not found')
                out['mesh'] = mp
        if 'max_isometric_force' in ent and ent['max_isometric_force'] is not None:
            out['max_isometric_force'] = _num(ent['max_isometric_force'], f'{w} max_isometric_force', positive=True)
        if 'optimal_fibre_length' in ent and ent['optimal_fibre_length'] is not None:
            out['optimal_fibre_length'] = _num(ent['optimal_fibre_length'], f'{w} optimal_fibre_length', positive=True)
        if 'rest_fibre_length' in ent and ent['rest_fibre_length'] is not None:   # normalised; absent: 1.0
            out['rest_fibre_length'] = _num(ent['rest_fibre_length'], f'{w} rest_fibre_length', positive=True)
            if not 0.2 <= out['rest_fibre_length'] <= 2.0:
                raise UserError(f'{w} ({name}): rest_fibre_length must be in [0.2, 2] (normalised fibre length), '
                                f'got {out["rest_fibre_length"]}')
        if 'stiffness_scale' in ent and ent['stiffness_scale'] is not None:
            out['stiffness_scale'] = _num(ent['stiffness_scale'], f'{w} stiffness_scale', positive=True)
        for end in ('origin', 'insertion'):       # muscle attachments (docs/method.md section 3): segment name
            a = ent.get(end)
            if a is None:
                out[end] = None
                continue
            if tissue != 'muscle':
                raise UserError(f'{w} ({name}): only muscles have an {end}')
            seg = a.get('segment') if isinstance(a, dict) else a
            if not isinstance(seg, str) or not seg:
                raise UserError(f'{w} ({name}): {end} must be a segment name or a mapping with "segment", got {a!r}')
            out[end] = seg
        vias = ent.get('via_points')               # the source model's intermediate path points (docs/FORMATS.md)
        out['via_points'] = []
        if vias is not None:
            if tissue != 'muscle' or not isinstance(vias, list):
                raise UserError(f'{w} ({name}): via_points must be a list of {{segment, at_m: [x, y, z]}} on a muscle')
            for k, vp in enumerate(vias):
                at = vp.get('at_m') if isinstance(vp, dict) else None
                seg = vp.get('segment') if isinstance(vp, dict) else None
                try:
                    at = [float(x) for x in at]
                except (TypeError, ValueError):
                    at = None
                if not isinstance(seg, str) or not seg or at is None or len(at) != 3 or not all(map(math.isfinite, at)):
                    raise UserError(f'{w} ({name}): via_points[{k}] needs "segment" and "at_m": 3 finite numbers [m], '
                                    f'got {vp!r}')
                out['via_points'].append((seg, np.array(at)))
        out['wrap_surfaces'] = _wrap_surfaces(ent.get('wrap_surfaces'), tissue, f'{w} ({name})')
        labels[lab] = out
    kinds = [e['tissue'] for e in labels.values()]
    if 'fat' not in kinds:
        raise UserError(f'{where}: needs a fat label (tissue: fat)')
    if 'bone' not in kinds:
        raise UserError(f'{where}: needs at least one bone label')
    j = data.get('joints')
    if j is None:
        raise UserError(f'{where}: needs "joints" (the skeleton file, relative to the table)')
    if isinstance(j, dict):
        skel = load_joints(j)
    else:
        if base is None:
            raise UserError(f'{where}: "joints" must be an inline mapping when the table is a dict')
        skel = load_joints(base / str(j))
    segs = set(skel['segment_names'])
    for lab, e in labels.items():
        if e['tissue'] == 'bone' and e['segment'] not in segs:
            raise UserError(f'{where}: label {lab} ({e["name"]}): segment {e["segment"]!r} is not in the joints file '
                            f'(has {", ".join(skel["segment_names"])})')
        for seg, _ in e.get('via_points', []):
            if seg not in segs:
                raise UserError(f'{where}: label {lab} ({e["name"]}): via point segment {seg!r} is not in the joints file '
                                f'(has {", ".join(skel["segment_names"])})')
        for ws in e.get('wrap_surfaces', []):
            if ws['segment'] not in segs:
                raise UserError(f'{where}: label {lab} ({e["name"]}): wrap surface {ws["name"]!r} segment {ws["segment"]!r} '
                                f'is not in the joints file (has {", ".join(skel["segment_names"])})')
        for end in ('origin', 'insertion'):
            if e.get(end) is not None and e[end] not in segs:
                raise UserError(f'{where}: label {lab} ({e["name"]}): {end} segment {e[end]!r} is not in the joints file '
                                f'(has {", ".join(skel["segment_names"])})')
    tname = _text(data, 'name', where) or 'model'
    mp = data.get('muscle_paths')
    if mp is not None and not isinstance(mp, dict):
        if base is None:
            raise UserError(f'{where}: "muscle_paths" must be an inline mapping when the table is a dict')
        mp = _read_yaml(base / str(mp), 'muscle paths')
    paths = load_muscle_paths(mp, skel['joint_names'], {e['name'] for e in labels.values() if e['tissue'] == 'muscle'},
                              f'{where} muscle_paths') if mp is not None else {}
    return {'name': tname, 'base': base, 'source': where, 'labels': labels, 'skeleton': skel, 'muscle_paths': paths}


def _wrap_surfaces(wraps, tissue: str, w: str) -> list:
    """A muscle entry's ``wrap_surfaces`` (the source model's wrap cylinders its path goes over; docs/FORMATS.md): a list
    of dicts name, segment, centre (3,) [m], axis (3,) unit, radius, length [m], quadrant (3,) unit or None (every
    side); [] when absent. w: the entry's place for the messages."""
    if wraps is None:
        return []
    if tissue != 'muscle' or not isinstance(wraps, list):
        raise UserError(f'{w}: wrap_surfaces must be a list of {{name, segment, centre_m, axis, radius_m, length_m, '
                        f'quadrant}} on a muscle')
    out = []
    for k, e in enumerate(wraps):
        wk = f'{w}: wrap_surfaces[{k}]'
        if not isinstance(e, dict):
            raise UserError(f'{wk} must be a mapping with name, segment, centre_m, axis, radius_m, length_m, got {e!r}')
        for key in ('name', 'segment'):
            if not isinstance(e.get(key), str) or not e[key].strip():
                raise UserError(f'{wk} needs "{key}": a non-empty text string, got {e.get(key)!r}')

        def vec(key, nonzero):
            v = e.get(key)
            try:
                v = [float(x) for x in v]
            except (TypeError, ValueError):
                v = None
            if v is None or len(v) != 3 or not all(map(math.isfinite, v)) or (nonzero and np.linalg.norm(v) < 1e-9):
                raise UserError(f'{wk} ({e["name"]}) needs "{key}": 3 finite numbers{", not all zero" if nonzero else ""}, '
                                f'got {e.get(key)!r}')
            v = np.array(v)
            return v / np.linalg.norm(v) if nonzero else v

        def length(key):
            v = e.get(key)
            x = float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else float('nan')
            if not (math.isfinite(x) and x > 0):
                raise UserError(f'{wk} ({e["name"]}) needs "{key}": a finite number > 0 [m], got {v!r}')
            return x
        out.append({'name': e['name'], 'segment': e['segment'], 'centre': vec('centre_m', False),
                    'axis': vec('axis', True), 'radius': length('radius_m'), 'length': length('length_m'),
                    'quadrant': None if e.get('quadrant') is None else vec('quadrant', True)})
    return out


def load_muscle_paths(data, joint_names, muscles, where) -> dict:
    """{muscle: [part dicts]} of a muscle paths file (tools/anatomy/paths.py writes the bundled one; docs/FORMATS.md):
    per muscle a list of parts, each with max_isometric_force [N], optimal_fibre_length [m], tendon_slack_length [m],
    pennation_at_optimal_rad, joints (names of the joints file), powers (one row of exponents per monomial, one per
    joint) and coefficients_m (one per row): L_MT = sum_t c_t prod_j q_j^e_tj."""
    if not isinstance(data, dict) or not isinstance(data.get('muscles'), dict):
        raise UserError(f'{where}: needs a "muscles" mapping')
    out = {}
    for name, parts in data['muscles'].items():
        w = f'{where}: muscle {name!r}'
        if name not in muscles:
            raise UserError(f'{w} is not a muscle of the table')
        if not isinstance(parts, list) or not parts:
            raise UserError(f'{w}: needs a list of parts')
        res = []
        for i, e in enumerate(parts):
            wp = f'{w} part {i}'
            try:
                js = [joint_names.index(j) for j in e['joints']]
                pw = [[int(k) for k in row] for row in e['powers']]
                c = [float(v) for v in e['coefficients_m']]
                num = [float(e[k]) for k in ('max_isometric_force', 'optimal_fibre_length', 'tendon_slack_length',
                                             'pennation_at_optimal_rad')]
            except (KeyError, TypeError, ValueError) as err:
                raise UserError(f'{wp}: needs joints (of the joints file), powers, coefficients_m, max_isometric_force, '
                                f'optimal_fibre_length, tendon_slack_length, pennation_at_optimal_rad ({err!r})') from None
            if len(pw) != len(c) or any(len(r) != len(js) or min(r, default=0) < 0 for r in pw):
                raise UserError(f'{wp}: powers must be one row of {len(js)} exponents >= 0 per coefficient')
            if not all(math.isfinite(v) for v in c + num) or num[0] <= 0 or num[1] <= 0 or not 0 <= num[3] < math.pi / 2:
                raise UserError(f'{wp}: numbers must be finite, forces and lengths > 0, the pennation in [0, pi/2)')
            res.append({'joints': js, 'powers': pw, 'coef': c, 'fmax': num[0], 'lopt': num[1], 'lts': num[2],
                        'pennation': num[3]})
        out[name] = res
    return out


def path_arrays(paths: dict, muscle_names, n_joints: int):
    """(path_muscle (P,), path_data (P, 4), path_powers (T, J), path_coef (P, T)) of the TissueModel from
    load_muscle_paths' dict (the muscles of the model only; T: every monomial of any part)."""
    rows, parts = {}, []
    for m, name in enumerate(muscle_names):
        ps = paths.get(name, [])
        total = sum(p['fmax'] for p in ps)
        for p in ps:
            terms = {}
            for e, c in zip(p['powers'], p['coef']):
                full = [0] * n_joints
                for j, k in zip(p['joints'], e):
                    full[j] = k
                t = rows.setdefault(tuple(full), len(rows))
                terms[t] = terms.get(t, 0.0) + c
            parts.append((m, [p['fmax'] / total, p['lopt'], p['lts'], p['lopt'] * math.sin(p['pennation'])], terms))
    coef = np.zeros((len(parts), len(rows)))
    for i, (_, _, terms) in enumerate(parts):
        for t, c in terms.items():
            coef[i, t] = c
    return (np.array([p[0] for p in parts], np.int32), np.array([p[1] for p in parts], np.float64).reshape(-1, 4),
            np.array(list(rows), np.int32).reshape(-1, n_joints), coef)


def _coupling(j: dict, w: str):
    """(axis, angle range [rad], table rows (K, 5) in SI: driver [rad], angle [rad], dx, dy, dz [m]) of a
    coupled joint entry (docs/FORMATS.md): ``driver``, ``axis``, ``table_columns`` [driver_deg, angle_deg,
    dx, dy, dz] and ``table`` (rows in increasing driver angle)."""
    if not isinstance(j.get('driver'), str):
        raise UserError(f'{w}: a coupled joint needs "driver" (the name of the hinge that drives it)')
    ax = _vec(j.get('axis'), 3, f'{w} axis')
    if np.linalg.norm(ax) < 1e-9:
        raise UserError(f'{w}: axis must be non-zero')
    rows = _table_rows(j, COUPLING_COLUMNS, w, 'a coupled joint', 'table')
    rows[:, :2] = np.radians(rows[:, :2])
    return ax / np.linalg.norm(ax), np.array([rows[:, 1].min(), rows[:, 1].max()]), rows


PATH_COLUMNS = ['angle_deg', 'angle2_deg', 'angle3_deg', 'dx', 'dy', 'dz']
COUPLING_COLUMNS = ['driver_deg', 'angle_deg', 'dx', 'dy', 'dz']


def _table_rows(d: dict, columns: list, w: str, what: str, key: str) -> np.ndarray:
    """(K, len(columns)) the rows of a joint's spline table (d's ``table_columns``, which must be columns, and
    ``table``: at least 4 rows, the first column strictly increasing), as given (degrees, metres)."""
    cols = d.get('table_columns', columns)
    if list(cols) != columns:
        raise UserError(f'{w}: {key} table_columns must be {columns}, got {cols!r}')
    tab = d.get('table')
    if not isinstance(tab, list) or len(tab) < 4:
        raise UserError(f'{w}: {what} needs a "table" of at least 4 rows {columns}')
    rows = np.array([_vec(r, len(columns), f'{w} {key} row {i}') for i, r in enumerate(tab)])
    if np.any(np.diff(rows[:, 0]) <= 0):
        raise UserError(f'{w}: {key} rows must be in strictly increasing {columns[0]}')
    return rows


def _hinge_path(path, w: str):
    """(axes (2, 3), rows (K, 6) in SI: q [rad], angle 2, angle 3 [rad], dx, dy, dz [m]) of a hinge's ``path``
    (docs/FORMATS.md): ``axes`` (the two secondary rotation axes), ``table_columns`` [angle_deg, angle2_deg,
    angle3_deg, dx, dy, dz] and ``table`` (rows in increasing angle)."""
    if not isinstance(path, dict):
        raise UserError(f'{w}: "path" must be a mapping with axes, table_columns and table')
    axes = path.get('axes')
    if not isinstance(axes, list) or len(axes) != 2:
        raise UserError(f'{w}: path axes must be a list of 2 axes (3 numbers each)')
    ax = np.array([_vec(a, 3, f'{w} path axis {i}') for i, a in enumerate(axes)])
    if np.any(np.linalg.norm(ax, axis=1) < 1e-9):
        raise UserError(f'{w}: path axes must be non-zero')
    ax = ax / np.linalg.norm(ax, axis=1)[:, None]
    rows = _table_rows(path, PATH_COLUMNS, w, 'a path', 'path table')
    rows[:, :3] = np.radians(rows[:, :3])
    return ax, rows


def load_joints(src) -> dict:
    """Parse the joints file (path or dict) into skeleton arrays (model frame, SI, radians)."""
    if isinstance(src, dict):
        data, where = src, '<joints>'
    else:
        data, where = _read_yaml(Path(src), 'joints'), str(src)
    segs = data.get('segments')
    if not isinstance(segs, list) or not segs:
        raise UserError(f'{where}: needs a non-empty "segments" list')
    names = []
    for i, s in enumerate(segs):
        if not isinstance(s, dict) or not isinstance(s.get('name'), str):
            raise UserError(f'{where}: segment #{i} needs a "name"')
        if s['name'] in names:
            raise UserError(f'{where}: duplicate segment {s["name"]!r}')
        names.append(s['name'])
    parent = np.full(len(segs), -1, np.int32)
    mass = np.zeros(len(segs))
    com = np.zeros((len(segs), 3))
    inertia = np.zeros((len(segs), 3, 3))
    for i, s in enumerate(segs):
        w = f'{where}: segment {s["name"]!r}'
        p = s.get('parent')
        if p is not None:
            if p not in names:
                raise UserError(f'{w}: unknown parent {p!r}')
            parent[i] = names.index(p)
        mass[i] = _num(s.get('mass'), f'{w} mass [kg]', positive=True)
        com[i] = _vec(s.get('com'), 3, f'{w} com [m]')
        I = s.get('inertia')
        if isinstance(I, (list, tuple)) and len(I) == 3 and all(isinstance(r, (list, tuple)) for r in I):
            inertia[i] = np.array([_vec(r, 3, f'{w} inertia') for r in I])
        elif isinstance(I, (list, tuple)) and len(I) == 3:
            inertia[i] = np.diag(_vec(I, 3, f'{w} inertia'))
        else:
            raise UserError(f'{w}: inertia must be a 3x3 matrix or 3 principal moments [kg m^2]')
        if not np.allclose(inertia[i], inertia[i].T, atol=1e-9) or np.linalg.eigvalsh(inertia[i]).min() <= 0:
            raise UserError(f'{w}: inertia must be symmetric positive definite')
    if np.sum(parent == -1) != 1:
        raise UserError(f'{where}: the skeleton needs exactly one root segment (parent: null), found {int(np.sum(parent == -1))}')
    # cycle check
    for i in range(len(segs)):
        seen, k = set(), i
        while k != -1:
            if k in seen:
                raise UserError(f'{where}: segment parents form a cycle at {names[i]!r}')
            seen.add(k)
            k = parent[k]
    joints = data.get('joints') or []
    if not isinstance(joints, list):
        raise UserError(f'{where}: "joints" must be a list')
    jn, jt, jp, jc, ja, jctr, jr, jrest = [], [], [], [], [], [], [], []
    couplings = {}                                   # joint index -> (driver name, table rows)
    paths = {}                                       # hinge index -> (secondary axes, table rows)
    root_joint = None
    for i, j in enumerate(joints):
        if not isinstance(j, dict) or not isinstance(j.get('name'), str):
            raise UserError(f'{where}: joint #{i} needs a "name"')
        w = f'{where}: joint {j["name"]!r}'
        typ = j.get('type', 'hinge')
        if typ not in ('hinge', 'fixed', 'coupled'):
            raise UserError(f'{w}: type must be hinge, fixed or coupled, got {typ!r}')
        if j.get('parent') is None and j.get('child') in names and parent[names.index(j['child'])] == -1:
            # the root segment's attachment to the world (e.g. a fixed hip): not a model joint
            if typ != 'fixed':
                raise UserError(f'{w}: a joint of the root segment to the world must be fixed (the root is fixed to the world)')
            root_joint = {'name': j['name'], 'centre': [float(x) for x in _vec(j.get('centre', [0, 0, 0]), 3, f'{w} centre')]}
            continue
        for key in ('parent', 'child'):
            if j.get(key) not in names:
                raise UserError(f'{w}: {key} {j.get(key)!r} is not a segment')
        p, c = names.index(j['parent']), names.index(j['child'])
        if parent[c] != p:
            raise UserError(f'{w}: child {j["child"]!r} has parent {names[parent[c]] if parent[c] >= 0 else None!r} in segments, not {j["parent"]!r}')
        ctr = _vec(j.get('centre', j.get('center')), 3, f'{w} centre [m]')
        if typ == 'hinge':
            ax = _vec(j.get('axis'), 3, f'{w} axis')
            if np.linalg.norm(ax) < 1e-9:
                raise UserError(f'{w}: axis must be non-zero')
            ax = ax / np.linalg.norm(ax)
            rng = _vec(j.get('range_deg', [-180, 180]), 2, f'{w} range_deg')
            if rng[0] > rng[1]:
                raise UserError(f'{w}: range_deg lower > upper')
            if j.get('path') is not None:
                paths[len(jn)] = _hinge_path(j['path'], w)
        elif typ == 'coupled':
            ax, rng, rows = _coupling(j, w)
            couplings[len(jn)] = (j.get('driver'), rows)
        else:
            ax, rng = np.array([0.0, 0.0, 1.0]), np.zeros(2)
        rest = _num(j.get('rest_deg', 0.0), f'{w} rest_deg')
        jn.append(j['name']); jt.append({'fixed': 0, 'hinge': 1, 'coupled': 2}[typ]); jp.append(p); jc.append(c)
        ja.append(ax); jctr.append(ctr); jr.append(np.radians(rng)); jrest.append(math.radians(rest))
    children = sorted(jc)
    nonroot = sorted(int(i) for i in np.nonzero(parent >= 0)[0])
    if children != nonroot:
        missing = [names[i] for i in nonroot if i not in jc]
        raise UserError(f'{where}: every non-root segment needs exactly one joint (missing or duplicate: {missing or "duplicate"})')
    J = len(jn)
    driver = np.full(J, -1, np.int32)
    coff, ctab = [0], []
    for k in range(J):
        if k in couplings:
            dname, rows = couplings[k]
            if dname not in jn or jt[jn.index(dname)] != 1:
                raise UserError(f'{where}: joint {jn[k]!r}: driver {dname!r} is not a hinge joint of the file')
            if any(parent[s] == jc[k] for s in range(len(names))):
                raise UserError(f'{where}: joint {jn[k]!r}: the child of a coupled joint must be a leaf segment')
            driver[k] = jn.index(dname)
            ctab.append(rows)
        coff.append(coff[-1] + (len(couplings[k][1]) if k in couplings else 0))
    poff, ptab, pax = [0], [], np.zeros((J, 2, 3))
    for k in range(J):
        if k in paths:
            pax[k], rows = paths[k]
            ptab.append(rows)
        poff.append(poff[-1] + (len(paths[k][1]) if k in paths else 0))
    return {
        'joint_path_offsets': np.array(poff, np.int64), 'joint_path_axes': pax,
        'joint_path_table': np.concatenate(ptab) if ptab else np.zeros((0, 6)),
        'joint_driver': driver, 'coupling_offsets': np.array(coff, np.int64),
        'coupling_table': np.concatenate(ctab) if ctab else np.zeros((0, 5)),
        'source': str(data.get('source', '')), 'root_joint': root_joint,
        'segment_names': tuple(names), 'segment_parent': parent, 'segment_mass': mass,
        'segment_com': com, 'segment_inertia': inertia,
        'joint_names': tuple(jn), 'joint_type': np.array(jt, np.uint8), 'joint_parent': np.array(jp, np.int32),
        'joint_child': np.array(jc, np.int32), 'joint_axis': np.array(ja).reshape(J, 3),
        'joint_centre': np.array(jctr).reshape(J, 3), 'joint_range': np.array(jr).reshape(J, 2),
        'joint_rest': np.array(jrest, np.float64),
    }
