"""Read the right leg of an OpenSim 4 model (.osim XML) without the OpenSim engine.

Poses the model at full extension (every coordinate 0) by evaluating the joints' spatial
transforms (CustomJoint TransformAxis functions: Constant, LinearFunction, SimmSpline;
PinJoint; WeldJoint) and composing parent/child offset frames.  Gives each body's 4x4 transform
into the *femur_r frame* (origin = right hip joint centre; x anterior, y up, z right; metres),
the muscles' path points in that frame, and their DeGroote-Fregly parameters.

Conditional and moving path points are not evaluated (the right-leg muscles of the pose2sim model
have only plain PathPoints) and neither is wrapping (see README); the wrap cylinders are read (pose,
size and quadrant, load()['wrap_objects']), the muscles' paths do not go round them here.
"""
from __future__ import annotations

import functools
import xml.etree.ElementTree as ET

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

RIGHT_BODIES = ('pelvis', 'femur_r', 'patella_r', 'tibia_r', 'talus_r', 'calcn_r', 'toes_r')


def _vec(el, tag):
    return np.array([float(v) for v in el.find(tag).text.split()])


def _frame(translation, orientation):
    """OpenSim offset frame: body-fixed X-Y-Z Euler angles, then translation (parent coords)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler('XYZ', orientation).as_matrix()
    T[:3, 3] = translation
    return T


def _function_value(fn, q):
    tag = fn.tag
    if tag == 'Constant':
        return float(fn.find('value').text)
    if tag == 'LinearFunction':
        a, b = (float(v) for v in fn.find('coefficients').text.split())
        return a * q + b
    if tag == 'SimmSpline':
        return float(simm_spline(_vec(fn, 'x'), _vec(fn, 'y'), q))
    if tag == 'NaturalCubicSpline':
        x = _vec(fn, 'x')
        y = _vec(fn, 'y')
        return float(CubicSpline(x, y, bc_type='natural')(q))
    if tag == 'MultiplierFunction':
        inner = [c for c in fn.find('function')][0]
        return float(fn.find('scale').text) * _function_value(inner, q)
    raise ValueError(f'unsupported OpenSim function {tag}')


def simm_spline(x, y, q):
    """OpenSim's SimmSpline at q: the cubic spline of Forsythe, Malcolm & Moler (Computer Methods for
    Mathematical Computations, 1977, routine SPLINE), whose end conditions match the third derivative of
    the cubic through the first (last) four points; beyond the end knots a straight line with the end
    slope (as OpenSim's SimmSpline::calcValue)."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    n = len(x)
    if n < 2:
        return float(y[0])
    if n == 2:
        return float(y[0] + (y[1] - y[0]) / (x[1] - x[0]) * (q - x[0]))
    nm1 = n - 1
    b, c, d = np.zeros(n), np.zeros(n), np.zeros(n)
    d[0] = x[1] - x[0]
    c[1] = (y[1] - y[0]) / d[0]
    for i in range(1, nm1):
        d[i] = x[i + 1] - x[i]
        b[i] = 2.0 * (d[i - 1] + d[i])
        c[i + 1] = (y[i + 1] - y[i]) / d[i]
        c[i] = c[i + 1] - c[i]
    b[0], b[nm1] = -d[0], -d[n - 2]
    c[0] = c[nm1] = 0.0
    if n > 3:
        c[0] = c[2] / (x[3] - x[1]) - c[1] / (x[2] - x[0])
        c[nm1] = c[n - 2] / (x[nm1] - x[n - 3]) - c[n - 3] / (x[n - 2] - x[n - 4])
        c[0] = c[0] * d[0] * d[0] / (x[3] - x[0])
        c[nm1] = -c[nm1] * d[n - 2] * d[n - 2] / (x[nm1] - x[n - 4])
    for i in range(1, n):
        t = d[i - 1] / b[i - 1]
        b[i] -= t * d[i - 1]
        c[i] -= t * c[i - 1]
    c[nm1] /= b[nm1]
    for i in range(n - 2, -1, -1):
        c[i] = (c[i] - d[i] * c[i + 1]) / b[i]
    b[nm1] = (y[nm1] - y[n - 2]) / d[n - 2] + d[n - 2] * (c[n - 2] + 2.0 * c[nm1])
    for i in range(nm1):
        b[i] = (y[i + 1] - y[i]) / d[i] - d[i] * (c[i + 1] + 2.0 * c[i])
        d[i] = (c[i + 1] - c[i]) / d[i]
        c[i] = 3.0 * c[i]
    c[nm1] = 3.0 * c[nm1]
    d[nm1] = d[n - 2]
    if q < x[0]:
        return float(y[0] + (q - x[0]) * b[0])
    if q > x[nm1]:
        return float(y[nm1] + (q - x[nm1]) * b[nm1])
    k = int(np.clip(np.searchsorted(x, q, side='right') - 1, 0, nm1 - 1))
    dx = q - x[k]
    return float(y[k] + dx * (b[k] + dx * (c[k] + dx * d[k])))


def _rot(axis, angle):
    axis = np.asarray(axis, float)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()


def _joint_motion(joint, coords):
    """4x4 transform of the child offset frame in the parent offset frame for the joint type."""
    kind = joint.tag
    M = np.eye(4)
    if kind == 'WeldJoint':
        return M
    if kind == 'PinJoint':
        name = joint.find('coordinates/Coordinate').get('name')
        M[:3, :3] = _rot([0, 0, 1], coords.get(name, 0.0))
        return M
    if kind != 'CustomJoint':
        raise ValueError(f'unsupported joint {kind}')
    R = np.eye(3)
    t = np.zeros(3)
    for ta in joint.find('SpatialTransform'):
        cname = (ta.find('coordinates').text or '').strip()
        q = coords.get(cname, 0.0) if cname else 0.0
        fn = [c for c in ta if c.tag not in ('coordinates', 'axis')][0]
        v = _function_value(fn, q)
        axis = _vec(ta, 'axis')
        if ta.get('name').startswith('rotation'):
            R = R @ _rot(axis, v)           # body-fixed sequence
        else:
            t = t + v * axis / np.linalg.norm(axis)  # translations in the parent frame
    M[:3, :3] = R
    M[:3, 3] = t
    return M


def transform_axis(joint, name, coordinate):
    """Unit axis (child-offset = parent-offset frame at 0) of a CustomJoint's TransformAxis `name`,
    checked to be driven by `coordinate` through a unit LinearFunction (a plain hinge about it) and the
    joint's other TransformAxes to be constant 0 (no coupled motion). joint: an entry of load()['joints']."""
    el = joint['element']
    if el.tag != 'CustomJoint':
        raise ValueError(f'{el.get("name")}: {el.tag}, not a CustomJoint')
    axis = None
    for ta in el.find('SpatialTransform'):
        fn = [c for c in ta if c.tag not in ('coordinates', 'axis')][0]
        cname = (ta.find('coordinates').text or '').strip()
        if ta.get('name') == name:
            if cname != coordinate or fn.tag != 'LinearFunction' or \
                    [float(v) for v in fn.find('coefficients').text.split()] != [1.0, 0.0]:
                raise ValueError(f'{el.get("name")} {name}: not {coordinate} through a unit LinearFunction')
            axis = _vec(ta, 'axis')
        elif cname or fn.tag != 'Constant' or float(fn.find('value').text) != 0.0:
            raise ValueError(f'{el.get("name")} {ta.get("name")}: not constant 0 (the joint is not a plain hinge)')
    if axis is None:
        raise ValueError(f'{el.get("name")}: no TransformAxis {name}')
    return axis / np.linalg.norm(axis)


@functools.lru_cache(maxsize=4)
def _parsed(path: str):
    """The .osim file's XML tree, parsed once per process (load only reads it; the generator poses the model ~70 times)."""
    return ET.parse(path).getroot()


def load(path, coords=None):
    """Parse the .osim file. coords: coordinate values in rad/m (default: all 0, full extension).

    Returns dict with 'bodies' {name: {'T': 4x4 in femur_r frame, 'meshes': [(file, scale)],
    'mass', 'com', 'inertia'}}, 'joints' {name: element info}, 'muscles' {name: {...}},
    'wrap_objects' {name: {'body', 'T': 4x4 of the cylinder's frame in the femur_r frame (its axis: local z),
    'radius', 'length', 'quadrant': OpenSim's string, 'all', 'x', '-y', ...}} (every WrapCylinder).
    """
    coords = dict(coords or {})
    root = _parsed(str(path))
    model = root.find('Model')
    bodies = {}
    for b in model.find('BodySet/objects'):
        meshes = [(m.find('mesh_file').text.strip(), _vec(m, 'scale_factors'))
                  for m in b.iter('Mesh')]
        bodies[b.get('name')] = {
            'meshes': meshes, 'mass': float(b.find('mass').text),
            'com': _vec(b, 'mass_center'),
            'inertia': _vec(b, 'inertia'),  # Ixx Iyy Izz Ixy Ixz Iyz about COM, body frame
        }
    # joints: child body -> (parent body, transform parent->child body)
    rel = {}
    joints = {}
    for j in model.find('JointSet/objects'):
        frames = {}
        for f in j.find('frames'):
            frames[f.get('name')] = (f.find('socket_parent').text.strip().split('/')[-1],
                                     _frame(_vec(f, 'translation'), _vec(f, 'orientation')))
        pb, P = frames[j.find('socket_parent_frame').text.strip()]
        cb, C = frames[j.find('socket_child_frame').text.strip()]
        Mj = _joint_motion(j, coords) if cb in RIGHT_BODIES else np.eye(4)
        rel[cb] = (pb, P @ Mj @ np.linalg.inv(C))
        cnames = [c.get('name') for c in j.iter('Coordinate')]
        ranges = {c.get('name'): _vec(c, 'range') for c in j.iter('Coordinate')}
        joints[j.get('name')] = {'parent': pb, 'child': cb, 'type': j.tag, 'P': P, 'C': C,
                                 'coordinates': cnames, 'ranges': ranges, 'element': j}

    def ground_T(name):
        if name == 'ground':
            return np.eye(4)
        pb, X = rel[name]
        return ground_T(pb) @ X

    ref = np.linalg.inv(ground_T('femur_r'))
    for name in bodies:
        if name in rel:
            bodies[name]['T'] = ref @ ground_T(name)

    wrap_objects = {}
    for b in model.find('BodySet/objects'):
        for w in b.findall('WrapObjectSet/objects/*'):
            if w.tag != 'WrapCylinder':       # WrapEllipsoid (the torso's): no muscle of the leg wraps over one
                continue
            wrap_objects[w.get('name')] = {
                'body': b.get('name'),
                'T': bodies[b.get('name')]['T'] @ _frame(_vec(w, 'translation'), _vec(w, 'xyz_body_rotation')),
                'radius': float(w.find('radius').text), 'length': float(w.find('length').text),
                'quadrant': (w.find('quadrant').text or 'all').strip() if w.find('quadrant') is not None else 'all'}

    muscles = {}
    for m in model.find('ForceSet/objects'):
        name = m.get('name')
        gp = m.find('GeometryPath')
        if gp is None or not name.endswith('_r'):
            continue
        pts, pbodies = [], []
        for pp in gp.find('PathPointSet/objects'):
            if pp.tag != 'PathPoint':
                raise ValueError(f'{name}: unsupported path point {pp.tag}')
            body = pp.find('socket_parent_frame').text.strip().split('/')[-1]
            loc = _vec(pp, 'location')
            T = bodies[body]['T']
            pts.append(T[:3, :3] @ loc + T[:3, 3])
            pbodies.append(body)
        wraps = [w.find('wrap_object').text.strip() for w in gp.iter('PathWrap')]
        muscles[name[:-2]] = {
            'points': np.array(pts),
            'bodies': pbodies,                     # OpenSim body of each path point (first: origin, last: insertion)
            'max_isometric_force': float(m.find('max_isometric_force').text),
            'optimal_fiber_length': float(m.find('optimal_fiber_length').text),
            'tendon_slack_length': float(m.find('tendon_slack_length').text),
            'pennation_angle': float(m.find('pennation_angle_at_optimal').text),
            'wraps': wraps,
        }
    return {'bodies': bodies, 'joints': joints, 'muscles': muscles, 'wrap_objects': wrap_objects, 'path': str(path)}
