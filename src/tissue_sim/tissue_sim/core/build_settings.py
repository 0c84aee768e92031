"""The builder's settings: their defaults and their checks (``tissue_sim.core.builder`` re-exports both).

Kept apart from the builder's geometry (assemble.py) so that reading or checking settings, the command line's
defaults for one, imports no numerics.
"""
from __future__ import annotations

import math

from tissue_sim.errors import UserError

# Default settings: a model of the paper's size (Table 1 of Inaba et al. 2005: Visible Human slices
# 1700-2878, every 25th, 540 fat cells = 45 slice gaps x 12 rays); sections='rays' is the paper's
# cross-section method. See docs/builder.md.
SLICE_KEYS = ('slices', 'slice_mm', 'slice_step')
NONE_IS_A_VALUE = ('attach_mm', 'bone_clearance_mm')   # settings whose None means 'off' (not 'the default')
DEFAULTS = {
    'slices': 46,              # this many slices evenly over the labelled extent (the paper's 46 slices)
    'slice_mm': None,          # or a slice spacing [mm] (the paper's was 25 mm over a 1178-mm stack)
    'slice_step': None,        # or every Nth slice of the volume
    'muscle_rays': 11,         # polygon vertex count of every muscle cross-section
    'fat_rays': 12,            # rays of the fat tube per slice (paper: 540 cells = 45 gaps x 12)
    'share_mm': 3.0,           # vertex sharing threshold [mm] (paper section 2.4 gives none; see docs/builder.md)
    'attach_mm': None,         # bone attachment distance [mm]; None = one pixel
    'anchor_muscles': True,    # fix muscle end rings to their origin/insertion segments (table); False = only
                               # vertices touching bone are fixed (the paper's section 2.4 rule alone)
    'bind_passed_over': False,  # False: a muscle's vertices are not bound to a segment it passes over (the shank
                               # for the gastrocnemii; below); True = to any segment between its origin and insertion
    'via_points': True,        # also fix the ring nearest each of a muscle's via points (the source model's
                               # intermediate path points, tissues.yaml) to the via point's segment, as its end rings,
    'via_mm': 3.0,             # ... where the ring's section holds the via point (inside, or this close to its outline)
    'point_vias': ['semitendinosus'],  # ... and where that ring, fixed whole, would turn a cell inside out: for these
                               # muscles (a list of names; True: every muscle) its centroid is held at the bone instead
                               # (a point via: the ring turns freely); False: such a via point is skipped. The bundled
                               # limb's list: measured (docs/builder.md "Via points")
    'unshare_passed_over': True,  # with bind_passed_over off: where such a muscle shares a vertex with the end
                               # ring of a muscle arising from the bone it passes over, it gets its own free copy
    'bone_clearance_mm': 0.5,  # a free vertex inside a bone mesh at rest is moved out to this distance from its
                               # surface (the contact's margin, Params.contact_margin); None = left where it is
    'min_area_mm2': 10.0,      # smaller components of a label on a slice are dropped (reported)
    'min_fat_mm': 2.0,         # minimum fat thickness along a fat ray [mm]
    'min_cell_volume_mm3': 1.0,  # cells below this volume are degenerate (dropped, reported)
    'sections': 'contour',     # cross-sections: 'contour' (traced label outline, area kept) or 'rays' (the paper's)
    'fat_follow': False,       # contour sections: each fat ring's vertices follow their predecessors on the slice below
                               # (contours.follow_ring, pair_inner) instead of an even ring from the least-twist start
                               # (fewer sheared fat cells on finer models; docs/builder.md "Fat tube")
    'allow_broken': False,     # a muscle whose chain breaks between slices: warning instead of error
    'tendon_frac': 0.3,        # a muscle section of at most this x the muscle's largest is thin (a tendon) ...
    'merge_tol': 0.25,         # ... and is one longer cell with its neighbours where it lies within this x the
                               # muscle's largest equivalent radius of the straight prism between them
    'merge_gaps': 3,           # a merged tendon cell spans at most this many slice gaps (1 = the paper's: one per gap)
    'shear_limit': 2.0,        # quality report: a cell sheared more than this x its height is reported (warning)
    'ray_hit': 'first',        # 'first' (polygon inside the region) or 'last' boundary crossing
    'ray_origin': 'best',      # 'best' (largest polygon among centroid and interior maxima) or 'centroid'
    'bone_mesh_step': 2,       # marching-cubes step [voxels] for bone surfaces without a mesh file
    'allow_missing': False,    # table labels absent from the volume: warning instead of error
    'max_fragment': 0.01,      # a piece of a muscle cut off from its main part by slices without its label and holding at
                               # most this share of the muscle's volume is left out (reported); 0 = every such piece is a break
    'path_smooth_mm': 17.5,    # each inner muscle ring moved across its slice onto the chain's centroid path fitted over
                               # +-this [mm] along the axis, by at most half its radius (smooth_path): the outlines'
                               # slice-to-slice jitter out of the finer models' chains (at the default slicing,
                               # 17.5-20-mm gaps, nothing moves); 0 = off (docs/builder.md "Muscle paths")
    'refine': 1.0,             # N x finer: slice gaps, muscle_rays and fat_rays x refine (rounded), min_cell_volume_mm3
                               # / refine^3; lengths (share_mm, attach_mm, min_area_mm2, min_fat_mm, path_smooth_mm) stay
                               # (docs/builder.md)
}


def settings_with_defaults(settings: dict) -> dict:
    unknown = set(settings) - set(DEFAULTS)
    if unknown:
        raise UserError(f'unknown builder setting(s): {", ".join(sorted(unknown))} (known: {", ".join(DEFAULTS)})')
    given = [k for k in SLICE_KEYS if settings.get(k) is not None]
    if len(given) > 1:
        raise UserError(f'give only one of {", ".join(SLICE_KEYS)} (got {", ".join(given)})')
    s = dict(DEFAULTS)
    if given:
        s.update({k: None for k in SLICE_KEYS})
    s.update({k: v for k, v in settings.items() if v is not None or k in NONE_IS_A_VALUE})
    for k in ('muscle_rays', 'fat_rays'):
        if int(s[k]) != s[k] or s[k] < 3:
            raise UserError(f'{k} must be an integer >= 3, got {s[k]!r}')
        s[k] = int(s[k])
    if s['slice_step'] is not None and (int(s['slice_step']) != s['slice_step'] or s['slice_step'] < 1):
        raise UserError(f'slice_step must be a positive integer, got {s["slice_step"]!r}')
    if s['slices'] is not None and (int(s['slices']) != s['slices'] or s['slices'] < 2):
        raise UserError(f'slices must be an integer >= 2, got {s["slices"]!r}')
    for k in ('slice_mm', 'min_cell_volume_mm3'):
        if s[k] is None and k == 'slice_mm':
            continue
        if not (isinstance(s[k], (int, float)) and math.isfinite(s[k]) and s[k] > 0):
            raise UserError(f'{k} must be a positive number, got {s[k]!r}')
    for k in ('share_mm', 'min_area_mm2', 'min_fat_mm', 'via_mm', 'path_smooth_mm'):
        if not (isinstance(s[k], (int, float)) and math.isfinite(s[k]) and s[k] >= 0):
            raise UserError(f'{k} must be a number >= 0, got {s[k]!r}')
    if isinstance(s['point_vias'], (list, tuple)):
        if not all(isinstance(n, str) and n for n in s['point_vias']):
            raise UserError(f'point_vias must be true, false or a list of muscle names, got {s["point_vias"]!r}')
        s['point_vias'] = sorted(set(s['point_vias']))
    elif not isinstance(s['point_vias'], bool):
        raise UserError(f'point_vias must be true, false or a list of muscle names, got {s["point_vias"]!r}')
    for k in ('anchor_muscles', 'via_points', 'fat_follow'):
        if not isinstance(s[k], bool):
            raise UserError(f'{k} must be true or false, got {s[k]!r}')
    if s['attach_mm'] is not None and not (math.isfinite(s['attach_mm']) and s['attach_mm'] >= 0):
        raise UserError(f'attach_mm must be >= 0, got {s["attach_mm"]!r}')
    if s['ray_origin'] not in ('best', 'centroid'):
        raise UserError(f"ray_origin must be 'best' or 'centroid', got {s['ray_origin']!r}")
    if s['sections'] not in ('contour', 'rays'):
        raise UserError(f"sections must be 'contour' or 'rays', got {s['sections']!r}")
    if not isinstance(s['allow_broken'], bool):
        raise UserError(f'allow_broken must be true or false, got {s["allow_broken"]!r}')
    if not isinstance(s['merge_gaps'], (int, float)) or isinstance(s['merge_gaps'], bool) or \
            int(s['merge_gaps']) != s['merge_gaps'] or s['merge_gaps'] < 1:
        raise UserError(f'merge_gaps must be an integer >= 1 (1 = one cell per slice gap), got {s["merge_gaps"]!r}')
    s['merge_gaps'] = int(s['merge_gaps'])
    if isinstance(s['tendon_frac'], bool) or not (isinstance(s['tendon_frac'], (int, float)) and 0 <= s['tendon_frac'] <= 1):
        raise UserError(f'tendon_frac must be a number in [0, 1], got {s["tendon_frac"]!r}')
    if isinstance(s['merge_tol'], bool) or not (isinstance(s['merge_tol'], (int, float)) and math.isfinite(s['merge_tol']) and s['merge_tol'] >= 0):
        raise UserError(f'merge_tol must be a number >= 0, got {s["merge_tol"]!r}')
    if not (isinstance(s['shear_limit'], (int, float)) and math.isfinite(s['shear_limit']) and s['shear_limit'] > 0):
        raise UserError(f'shear_limit must be a positive number, got {s["shear_limit"]!r}')
    bc = s['bone_clearance_mm']
    if bc is not None and (isinstance(bc, bool) or not (isinstance(bc, (int, float)) and 0 <= bc <= 5)):
        raise UserError(f'bone_clearance_mm must be a number in [0, 5] or None (off), got {bc!r}')
    if s['ray_hit'] not in ('first', 'last'):
        raise UserError(f"ray_hit must be 'first' or 'last', got {s['ray_hit']!r}")
    if isinstance(s['max_fragment'], bool) or not (isinstance(s['max_fragment'], (int, float)) and 0 <= s['max_fragment'] < 0.5):
        raise UserError(f'max_fragment must be a number in [0, 0.5) (share of a muscle\'s volume), got {s["max_fragment"]!r}')
    return refined(s)


def refined(s: dict) -> dict:
    """Settings ``s`` made ``s['refine']`` times finer: slice gaps (``slices``: (n - 1) x R + 1, so the coarse
    slices are among the fine ones for an integer R; ``slice_mm`` / R; ``slice_step`` / R, which must stay an
    integer), ``muscle_rays`` and ``fat_rays`` x R (rounded), ``min_cell_volume_mm3`` / R^3 (cells are R^3
    smaller). Physical lengths stay: ``share_mm``, ``attach_mm``, ``min_area_mm2``, ``min_fat_mm`` (which
    tissues touch and what is bone-attached does not change with the mesh). Returns a new dict."""
    R = s['refine']
    if isinstance(R, bool) or not (isinstance(R, (int, float)) and math.isfinite(R) and 1 <= R <= 50):
        raise UserError(f'refine must be a number in [1, 50] (N x finer than the other settings), got {R!r}')
    s = dict(s, refine=float(R))
    if R == 1:
        return s
    if s['slice_step'] is not None:
        step = s['slice_step'] / R
        if abs(step - round(step)) > 1e-9 or round(step) < 1:
            raise UserError(f'refine {R:g} with slice_step {s["slice_step"]}: the step / refine must be a whole number of slices')
        s['slice_step'] = int(round(step))
    elif s['slice_mm'] is not None:
        s['slice_mm'] = s['slice_mm'] / R
    else:
        s['slices'] = int(round((s['slices'] - 1) * R)) + 1
    for k in ('muscle_rays', 'fat_rays'):
        s[k] = int(round(s[k] * R))
    s['min_cell_volume_mm3'] = s['min_cell_volume_mm3'] / R ** 3
    return s
