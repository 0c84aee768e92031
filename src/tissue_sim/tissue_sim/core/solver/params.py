"""Physical and numerical parameters of the solver (one flat dataclass, YAML round trip).

Two presets (docs/method.md section 6):

* ``Params.paper()``: Table 2 of Inaba et al. 2005 as given: every vertex mass 1, muscle k 1e6,
  fat k 5e5, dT 1e-3, contraction rate c = 0.998 per dT. Dimensionless in the paper; we read it
  as kg, N/m and s on the model's metre coordinates.
* ``Params.physical()``: SI masses from tissue density and cell volume, passive stiffness from
  published moduli, active stiffness scaled so that an isometric, fully active muscle pulls
  with its cross-section x specific tension (60 N/cm^2, Rajagopal 2016).

Every field is documented with its unit. ``docs/solver.md`` explains the choices.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import yaml

DAMPING_MODES = ('deformation', 'velocity', 'none')
MASS_MODES = ('uniform', 'density')
STIFFNESS_MODES = ('given', 'modulus')
VOLUME_MODES = ('actual', 'rest')
VOLUME_MEASURES = ('affine', 'enclosed')
END_RING_PULLS = ('ring', 'bound')
INTEGRATORS = ('mass_scaled', 'explicit', 'implicit')
IMPLICIT_SCHEMES = ('bdf2', 'euler')
ACTIVE_LENGTHS = ('chord', 'path')
LENGTH_MEASURES = ('chord', 'centre_line')


def parse_assignments(assignments, what: str) -> dict:
    """NAME=VALUE strings (a bench's repeatable --set or --build) as a dict, each VALUE read as YAML (0.5, 3e7, true,
    knee, [0, 0, -9.81]; '' or nothing after '=' is the empty string). ValueError naming `what` and the bad one."""
    d = {}
    for a in assignments:
        name, eq, text = str(a).partition('=')
        if not eq or not name.strip():
            raise ValueError(f'{what}: {a!r}: expected NAME=VALUE')
        try:
            v = yaml.safe_load(text) if text.strip() not in ('', "''", '""') else ''
        except yaml.YAMLError:
            raise ValueError(f'{what}: {a!r}: VALUE is not a YAML scalar or list') from None
        d[name.strip()] = '' if v is None else v
    return d


@dataclasses.dataclass
class Params:
    preset: str = 'paper'                 # name of the preset this set started from (informative)
    # --- time ------------------------------------------------------------------------------
    dt: float = 1e-3                      # [s] step length dT of step() when dt is None
    integrator: str = 'mass_scaled'       # 'mass_scaled': symplectic Euler, one pass per step, a vertex's mass raised to
                                          # h^2 kappa / stability_limit^2 where its cells' summed stiffness kappa needs it;
                                          # 'explicit': true masses, automatic sub-steps (docs/solver.md);
                                          # 'implicit': implicit Euler of the free vertices (prefactored; true masses, 1 sub-step)
    implicit_scheme: str = 'euler'        # the implicit integrator's formula: 'euler' = backward Euler; 'bdf2' = the
                                          # second-order backward differentiation formula (the physical set's: the solve at
                                          # 2h/3 from the last two sub-steps, less numerical damping; its margin for stiffness
                                          # beyond the system matrix is smaller: the paper set's unit-mass cells diverged
                                          # with it; docs/solver.md "Implicit integrator", "The formula")
    implicit_iterations: int = 1          # local/global iterations per sub-step of the implicit integrator (1: one solve)
    implicit_volume_cap: float = 1.0      # implicit integrator only: a cell's volume-term stiffness at most this fraction of
                                          # its weight keff in the system matrix (the force scaled down beyond; 0 = unbounded;
                                          # docs/solver.md "Implicit integrator")
    explicit_volume_cap: float = 0.0      # mass_scaled/explicit integrators: the same bound (x keff, the stiffness the
                                          # mass scaling budgets), on the affine and the enclosed volume terms; 0 =
                                          # unbounded (the paper's; docs/solver.md "The volume term's bound")
    implicit_via_correction: bool = True  # implicit integrator only: the point via rings' centroids held inside the solve
                                          # (the least-A-norm correction that puts them on their places, the tissue round
                                          # them following; False: the ring alone moved back after the solve, as the other
                                          # integrators do; docs/solver.md "Point vias")
    substeps: int = 0                     # sub-steps per step; 0 = automatic (explicit: stability estimate; mass_scaled: 1)
    stability_limit: float = 1.8          # automatic sub-steps keep omega_max * h below this (< 2, symplectic Euler)
    # --- soft tissue -----------------------------------------------------------------------
    mass_mode: str = 'uniform'            # 'uniform': every vertex weighs vertex_mass; 'density': from cell volumes
    vertex_mass: float = 1.0              # [kg] mass of each vertex in 'uniform' mode (paper: 1)
    density_muscle: float = 1060.0        # [kg/m^3] 'density' mode (Ward & Lieber 2005)
    density_fat: float = 900.0            # [kg/m^3] 'density' mode (Farvid et al. 2005)
    stiffness_mode: str = 'given'         # 'given': k_muscle/k_fat per cell; 'modulus': k = E * cell size / N
    k_muscle: float = 1e6                 # [N/m] spring constant of a muscle cell on each of its vertices
    k_fat: float = 5e5                    # [N/m] the same for fat cells
    youngs_muscle: float = 2.0e4          # [Pa] passive muscle modulus, 'modulus' mode
    youngs_fat: float = 3.0e3             # [Pa] fat modulus, 'modulus' mode
    specific_tension: float = 0.0         # [Pa] active stress at full activation (physical: 6e5 = 60 N/cm^2); 0 = off.
                                          # > 0: an axial active tension per muscle cell, calibrated so each muscle pulls
                                          # with its max isometric force x specific_tension / 6e5 (model.active_stiffness)
    damping: str = 'deformation'          # 'deformation' (relative to each cell's rigid motion), 'velocity', 'none'
    damping_ratio: float = 0.05           # fraction of critical damping of one cell's mode (deformation damping)
    damping_ratio_fat: float = -1.0       # the same for fat cells; < 0: damping_ratio (physical: 2.0, keeps the fat in front
                                          # of the ankle from turning inside out when the knee hits its stop; docs/contact.md)
    velocity_damping: float = 0.0         # [1/s] plain velocity damping of free vertices (any mode)
    # --- contraction -----------------------------------------------------------------------
    contraction_rate: float = 0.998       # factor on a fully active muscle's fibre stretch per rate_dt (paper c)
    relax_rate: float = 0.998             # factor (<1) by which the stretch recovers towards its target per rate_dt
    rate_dt: float = 1e-3                 # [s] time unit of contraction_rate/relax_rate (paper: per dT)
    min_stretch: float = 0.7              # fibre stretch reached at full activation; > 0, the shortening limit
    active_length: str = 'chord'          # the active tension's rest length L of a muscle cell: 'chord' = the distance between
                                          # its ring centroids; 'path' = that chord projected on the muscle's centre line
                                          # smoothed over active_path_sigma (the rings' lateral offsets are not fibre length:
                                          # a chain under tension pulls them straight and loses force; docs/solver.md)
    active_path_sigma: float = 0.015      # [m] the muscle centre line's Gaussian smoothing length ('path', 'centre_line')
    length_measure: str = 'chord'         # a muscle's reported length (observe's muscle_lengths, validate's moment arms):
                                          # 'chord' = the sum over its slice gaps of the ring-centroid distances; 'centre_line'
                                          # = the length of its centre line, end ring to end ring through the smoothed gap
                                          # centres (the rings' sideways wander and a slack chain's kinks are not musculotendon
                                          # length; docs/solver.md "Muscle length")
    volume_stiffness: float = 1.0         # muscle volume energy 1/2 kappa (det D - 1)^2, stiffness relative to k (0 = off; keeps
                                          # each muscle cell's volume; the earlier default, with the pressure term, was 0.5)
    volume_relax_time: float = 0.0        # [s] integral (pressure) term restoring each muscle cell's volume; 0 = off (default:
                                          # it is not conservative and kept the paper set swinging; 0.005 = the earlier term)
    volume_measure: str = 'affine'        # what the volume energies (volume_stiffness, volume_stiffness_fat) hold: 'affine' = the
                                          # determinant of each cell's best-fit affine map (the earlier term), 'enclosed' = the
                                          # volume its closed surface encloses (core/solver/volume.py, docs/solver.md "Volume"; the
                                          # physical set's; under integrator 'implicit' every cell holds the affine measure)
    end_ring_pull: str = 'ring'           # the active tension on a muscle's end ring that is partly bound to a bone across a joint
                                          # from its other end: 'ring' = on every vertex of the ring (the paper: its free part
                                          # is pulled along the muscle), 'bound' = the free vertices' share on the bound ones
                                          # (cells.end_ring_shift; the physical set's; docs/solver.md "Partly bound end rings")
    volume_mode: str = 'actual'           # muscle cross-section: 'actual' = 1/sqrt(current fibre stretch), 'rest' = 1/sqrt(lambda)
    max_contraction_velocity: float = 0.0 # [1/s] Hill force-velocity of the active tension: v_max in rest lengths per second
                                          # (physical: 10, Zajac 1989); 0 = off (the paper: no force-velocity property)
    fv_max_lengthening: float = 1.4       # eccentric plateau of the force-velocity factor (x isometric; Thelen 2003)
    fv_filter_time: float = 0.005         # [s] low-pass time constant of the muscle velocity the factor uses
    activation_time: float = 0.0          # [s] activation time constant of the first-order excitation -> activation dynamics
                                          # (Thelen 2003: 0.015; physical: 0.015); 0 = off: the command is the activation (paper)
    deactivation_time: float = 0.05       # [s] its deactivation time constant (Thelen 2003: 0.050; used when activation_time > 0)
    force_length: bool = False            # active force-length of the fibres, exp(-(l - 1)^2 / fl_width), multiplying the active
                                          # tension (Thelen 2003; physical: on; needs specific_tension > 0)
    passive_force_length: bool = False    # passive fibre force Fmax (exp(k (l - 1) / eps0) - 1) / (exp(k) - 1) for l > 1 along each
                                          # muscle's source-model path, as joint torques (Thelen 2003; needs specific_tension > 0;
                                          # physical: on with fl_passive_strain 2.0, a calibration; docs/solver.md)
    fl_width: float = 0.45                # gamma, width of the active force-length curve (Thelen 2003 / OpenSim KshapeActive)
    fl_passive_shape: float = 5.0         # k_PE, shape of the passive curve (Thelen 2003 / OpenSim KshapePassive)
    fl_passive_strain: float = 0.6        # eps0, fibre strain at which the passive force reaches Fmax (Thelen 2003, young adults)
    fl_passive_curve: str = 'thelen'      # passive curve: 'thelen' (Thelen 2003 eq. 3, 0 below l = 1) or 'degroote' (De Groote et
                                          # al. 2016, the source model's DeGrooteFregly2016Muscle; k_PE 4, eps0 0.6/0.7 there)
    rest_fibre_length: float = 0.0        # > 0: override, the normalised fibre length l of every muscle in the model's rest pose;
                                          # 0 = each muscle's own (the tissue table's rest_fibre_length, from the source model;
                                          # 1.0 without one). A muscle with a source-model path: its path's fibre length shifted
                                          # to the override (rigid tendon, docs/solver.md "Force-length")
    volume_stiffness_fat: float = 0.0     # fat volume energy 1/2 kappa (det D - 1)^2, stiffness relative to k, like volume_stiffness
                                          # for muscle (physical: 20, effective Poisson ratio 0.465: fat is nearly incompressible; keeps fat cells from
                                          # inverting; 0 = off: the paper's fat has no volume term; docs/contact.md)
    # --- skeleton --------------------------------------------------------------------------
    gravity: tuple = (0.0, 0.0, 0.0)      # [m/s^2] model frame, e.g. (0, 0, -9.81) standing; off in both presets (the paper's figures;
                                          # the isometric validation and the dynamometry it compares with exclude the limb's weight)
    fixed_root: bool = True               # the root segment (thigh) is fixed to the world
    joint_paths: bool = False             # a hinge with a path in the joints file (the knee: the source model's walker knee)
                                          # follows it: its child also turns about two secondary axes and translates with
                                          # the angle; False: every hinge is a plain hinge about its axis and centre (the
                                          # paper's knee; docs/solver.md "Skeleton")
    attached_mass_to_segment: bool = True # bone-attached vertices' masses join their segment's inertia
    joint_damping: float = 20.0           # [N m s/rad] passive viscous damping of every hinge (implicit)
    limit_omega_dt: float = 1.0           # end-stop natural frequency x h (stiffness relative to the joint's inertia; implicit)
    limit_damping_ratio: float = 1.0      # end-stop damping, fraction of critical
    # --- bone contact (docs/contact.md) -----------------------------------------------------
    bone_contact: bool = False            # keep free soft-tissue vertices outside the bones (signed-distance grid per segment,
                                          # projection after the integration); the paper has none: off in Params.paper()
    contact_margin: float = 5e-4          # [m] distance from a bone's surface a free vertex is projected back to
    contact_friction: float = 0.0         # Coulomb coefficient of the tissue-bone contact (0: frictionless sliding)
    contact_grid: float = 1.5e-3          # [m] spacing of the bones' signed-distance grids
    fold_contact: str = ''                # hinges (comma-separated names or name starts) whose flexion-side soft tissue keeps to its side
                                          # of the plane bisecting the two segments (thigh/calf tissue in the popliteal fold; '' off, the paper)
    fold_reach: float = 0.15              # [m] free vertices within this distance of the hinge along the segments' axis take part
    fold_plane: bool = True               # the fold's bisector plane (False: only the flexion side, no tissue crosses to the front)
    sheath_group: str = ''                # muscle group(s)/names held in a sheath above each folding hinge (a retinaculum, e.g. 'hamstrings'; '' none)
    sheath_radius: float = 3e-3           # [m] how far a sheathed vertex may leave its rest line along the segment, across it
    sheath_below: str = ''                # muscle group(s)/names held in the sheath below each folding hinge too, in the child
                                          # segment's frame ('' none)
    sheath_shared: bool = True            # the sheath holds the vertices the named muscles share with other muscles' cells too
                                          # (False: only their own and those shared with fat, docs/contact.md "The sheath")
    wrap_surfaces: str = ''               # the model's wrap surfaces (the source model's wrap cylinders, TissueModel.wrap_names;
                                          # comma-separated, 'all' every one, '' none: the paper) that keep the free vertices
                                          # of the muscles wrapping over them outside (docs/contact.md "Wrap surfaces")
    # --- numerics / safety -----------------------------------------------------------------
    rotation_iterations: int = 1          # max iterations of the warm-started rotation extraction per cell and step (Newton: 1 tracks the rotation to ~(change per step)^2)
    max_speed: float = 200.0              # [m/s] a vertex faster than this is reported as divergence (energy blow-up)
    threads: int = 1                      # threads of the step (1: serial; 0: numba's default, all cores; n: n, at most
                                          # NUMBA_NUM_THREADS; the parallel parts are two: the cell pass, and with the
                                          # implicit integrator BDF2's start and the triangular passes, so more than 2 change
                                          # nothing); the results do not depend on it (bit-identical). 1 by default: 2 pay on
                                          # finer models (the 34k-vertex limb 1.33x, implicit), not on the bundled one
                                          # (0.92-0.97x), and lose on cores that other busy processes share (docs/solver.md "Threads")

    # ------------------------------------------------------------------------------ presets
    @classmethod
    def paper(cls, **kw) -> 'Params':
        """Inaba et al. 2005, Table 2 (mass 1, k 1e6 / 5e5, dT 1e-3, c 0.998)."""
        return cls(**kw).validate()

    @classmethod
    def physical(cls, **kw) -> 'Params':
        """SI tissue: density masses, moduli, active force = cross-section x 60 N/cm^2."""
        base = dict(preset='physical', mass_mode='density', stiffness_mode='modulus', specific_tension=6.0e5,
                    damping_ratio=0.3, gravity=(0.0, 0.0, 0.0), joint_damping=5.0, max_speed=50.0,
                    integrator='mass_scaled', substeps=4, implicit_scheme='bdf2', explicit_volume_cap=1.0,
                    max_contraction_velocity=10.0,
                    bone_contact=True, stability_limit=1.4, activation_time=0.015, deactivation_time=0.05,
                    force_length=True, rest_fibre_length=0.0, volume_stiffness_fat=20.0, damping_ratio_fat=2.0,
                    passive_force_length=True, fl_passive_strain=2.0,
                    fold_contact='knee', fold_plane=False, sheath_group='hamstrings,sartorius,gracilis',
                    sheath_below='', sheath_radius=1e-3, wrap_surfaces='KnExt_at_fem_r,ST_at_condyles_r',
                    active_length='path', length_measure='centre_line', volume_measure='enclosed',
                    end_ring_pull='bound', joint_paths=True)
        # gram masses, stiff active tension: h = 0.25 ms with selective mass scaling (the light tendon/edge
        # vertices get heavier; docs/solver.md gives the added mass). stability_limit 1.4, not 1.8: the mass
        # scaling budgets each muscle cell's volume term at its rest stiffness; in cells a contraction deforms
        # strongly (V/V0 2.4, semitendinosus near the knee) it was measured ~1.5x that (omega h 1.98 at 1.8: a
        # hamstring contraction without force-velocity diverged at step 140). joint_damping 5 N m s/rad, not 1:
        # when the knee reaches its stop the light free foot whipped on (ankle -4 -> -22 deg in 20 ms, the soleus
        # and ankle fat cells at V/V0 0.56..5, omega h 2.04 at 1.4: divergence at step ~440 with or without
        # force-velocity); at 5 the ankle stays within -6..+2 deg (-32..-3 with the passive fibre force, which
        # plantarflexes the relaxed foot). (tests/test_solver_default_model.py::
        # test_physical_without_force_velocity_is_stable)
        # fold_contact knee without the plane, a 1-mm hamstring sheath above the knee (docs/contact.md): held passively
        # the hamstrings shorten with flexion (semitendinosus -49 mm at 90 deg, was -0.1; OpenSim -70), `tissue-sim
        # validate`: 57 of 338 signs wrong (70 without), 9 of 24 hamstring moment arms within 25 % (8), every hamstring
        # >= 60 % of Fmax (semimembranosus 53 -> 70 %); the plane (fold_plane) and the hamstrings' sheath below the knee were
        # measured and left off: the active knee then stops short of 120 deg; sartorius and gracilis (the pes anserinus)
        # in the sheath above the knee, as the fascia holds them behind the medial condyle: active alone, sartorius no
        # longer pulls straight in front of it and lengthens from 0 to 10 deg (today's limb: +2.7 mm without the sheath
        # on it, an extensor; -2.2 mm with it, a +12.7 mm moment arm, OpenSim +12 to +18; tests/test_solver_fold.py)
        # no sheath below the knee (sheath_below ''): held in the shank's frame there, sartorius and gracilis passed a
        # flexing torque to the shank that grew with refinement, and the demo motion's knee (bench/convergence.py --motion
        # demo, 1 ms) did not converge over the 1x/3x/6x limbs (max difference 13.3 deg, then 84.3: the 6x knee at its
        # stop by 2.5 s); without it the differences shrink (7.9 / 4.2 deg, then 4.9 / 3.1, max / RMS), `tissue-sim
        # validate` gives 9 wrong signs instead of 10 (sartorius and gracilis keep the source model's sign everywhere,
        # the other targets the same), and semitendinosus' isometric knee torque at 0 deg (implicit x4, 0.3 s) is 16.6
        # N m on the 1x and the 3x limb (19.8 on the 3x with its tendon sheathed below; docs/convergence.md "The demo
        # motion")
        # rest_fibre_length 0: each muscle's source-model operating point (tissues.yaml), not 1.0 (every fibre at its
        # optimum at rest): with 1.0 the vasti and rectus femoris sit on the descending limb, their extensor torque
        # falls as the knee flexes, and full co-contraction at 30 deg gives 18.4 N m/rad against the passive knee's 8.8
        # (`tissue-sim stiffness --levels 0,1 --settle 0.15 --free 0.3`); with their own values 76.4 against 3.2. The price:
        # the fully active hamstrings' isometric torque is further below OpenSim's (`tissue-sim validate`: RMS 37.1 N m
        # at 0/30/60/90/120 deg, peak 62.7 N m at 20 deg; docs/solver.md "Force-length")
        # passive_force_length on with eps0 2.0, a calibration (Thelen's 0.6 is the uncalibrated value): on the source
        # model's wrapped paths the shank muscles sit at l = 1.42-1.85 with the ankle at 0, and with eps0 0.6 the
        # passive fibres put -1,251 N m on the ankle there and 66 N m on the knee at 15 deg (OpenSim's own De Groote-Fregly
        # curve: -501 and 56); Riener & Edrich 1999's passive knee moment (hip 0, ankle 0) is matched with eps0 1.5-2.0
        # (whole model, `tissue-sim validate --passive`: RMS 4.6 N m against 5.7 with the fibres off and 47.8 with
        # eps0 0.6), and their ankle fit best with 2.0 (docs/solver.md "Force-length")
        base.update(kw)
        return cls(**base).validate()

    # ------------------------------------------------------------------------------ checks
    def validate(self) -> 'Params':
        def need(cond, msg):
            if not cond:
                raise ValueError(f'solver parameters: {msg}')
        need(self.dt > 0 and self.dt < 1, 'dt must be in (0, 1) s')
        need(isinstance(self.substeps, int) and self.substeps >= 0, 'substeps must be an integer >= 0')
        need(0 < self.stability_limit < 2, 'stability_limit must be in (0, 2)')
        need(self.mass_mode in MASS_MODES, f'mass_mode must be one of {MASS_MODES}')
        need(self.stiffness_mode in STIFFNESS_MODES, f'stiffness_mode must be one of {STIFFNESS_MODES}')
        need(self.integrator in INTEGRATORS, f'integrator must be one of {INTEGRATORS}')
        need(self.damping in DAMPING_MODES, f'damping must be one of {DAMPING_MODES}')
        need(self.volume_mode in VOLUME_MODES, f'volume_mode must be one of {VOLUME_MODES}')
        need(self.volume_measure in VOLUME_MEASURES, f'volume_measure must be one of {VOLUME_MEASURES}')
        need(self.end_ring_pull in END_RING_PULLS, f'end_ring_pull must be one of {END_RING_PULLS}')
        for name in ('vertex_mass', 'density_muscle', 'density_fat', 'k_muscle', 'k_fat', 'youngs_muscle',
                     'youngs_fat', 'rate_dt', 'max_speed'):
            need(getattr(self, name) > 0, f'{name} must be > 0')
        need(self.fv_max_lengthening >= 1, 'fv_max_lengthening must be >= 1')
        need(0 <= self.activation_time <= 1, 'activation_time must be in [0, 1] s')
        need(0 < self.deactivation_time <= 1, 'deactivation_time must be in (0, 1] s')
        need(0 < self.fl_width <= 10, 'fl_width must be in (0, 10]')
        need(0 < self.fl_passive_shape <= 50, 'fl_passive_shape must be in (0, 50]')
        need(0 < self.fl_passive_strain <= 5, 'fl_passive_strain must be in (0, 5]')
        need(self.fl_passive_curve in ('thelen', 'degroote'), "fl_passive_curve must be 'thelen' or 'degroote'")
        need(self.rest_fibre_length == 0 or 0.2 <= self.rest_fibre_length <= 2,
             'rest_fibre_length must be 0 (each muscle\'s own) or in [0.2, 2]')
        need(self.volume_stiffness_fat >= 0, 'volume_stiffness_fat must be >= 0')
        need(math.isfinite(self.damping_ratio_fat), 'damping_ratio_fat must be finite (< 0: damping_ratio)')
        for name in ('max_contraction_velocity', 'fv_filter_time', 'volume_relax_time', 'volume_stiffness', 'specific_tension', 'damping_ratio', 'velocity_damping', 'joint_damping', 'limit_damping_ratio'):
            need(getattr(self, name) >= 0, f'{name} must be >= 0')
        need(0 < self.contraction_rate <= 1, 'contraction_rate must be in (0, 1]')
        need(0 < self.relax_rate <= 1, 'relax_rate must be in (0, 1]')
        need(0.2 <= self.min_stretch <= 1, 'min_stretch must be in [0.2, 1] (a muscle cannot shorten without bound)')
        need(self.active_length in ACTIVE_LENGTHS, f'active_length must be one of {ACTIVE_LENGTHS}')
        need(self.length_measure in LENGTH_MEASURES, f'length_measure must be one of {LENGTH_MEASURES}')
        need(math.isfinite(self.active_path_sigma) and 0 < self.active_path_sigma <= 0.2,
             'active_path_sigma must be in (0, 0.2] m')
        need(len(tuple(self.gravity)) == 3, 'gravity must be 3 numbers')
        self.gravity = tuple(float(g) for g in self.gravity)
        need(0 <= self.contact_margin <= 0.01, 'contact_margin must be in [0, 0.01] m')
        need(self.contact_friction >= 0, 'contact_friction must be >= 0')
        need(2e-4 <= self.contact_grid <= 0.01, 'contact_grid must be in [2e-4, 0.01] m')
        need(0 < self.fold_reach <= 1, 'fold_reach must be in (0, 1] m')
        need(0 < self.sheath_radius <= 0.05, 'sheath_radius must be in (0, 0.05] m')
        need(0 < self.limit_omega_dt <= 10, 'limit_omega_dt must be in (0, 10]')
        need(math.isfinite(self.implicit_volume_cap) and self.implicit_volume_cap >= 0,
             'implicit_volume_cap must be a finite number >= 0 (0: off)')
        need(math.isfinite(self.explicit_volume_cap) and self.explicit_volume_cap >= 0,
             'explicit_volume_cap must be a finite number >= 0 (0: off)')
        need(self.implicit_scheme in IMPLICIT_SCHEMES, f'implicit_scheme must be one of {IMPLICIT_SCHEMES}')
        need(isinstance(self.implicit_iterations, int) and 1 <= self.implicit_iterations <= 20,
             'implicit_iterations must be an integer in [1, 20]')
        need(1 <= self.rotation_iterations <= 50, 'rotation_iterations must be in [1, 50]')
        need(isinstance(self.threads, int) and not isinstance(self.threads, bool) and self.threads >= 0,
             'threads must be an integer >= 0 (0: all cores)')
        need(self.fixed_root, 'fixed_root False (floating base) is not supported yet')
        return self

    # ------------------------------------------------------------------------------ YAML
    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d['gravity'] = list(self.gravity)
        return d

    def to_yaml(self, path=None) -> str:
        text = yaml.safe_dump(self.to_dict(), sort_keys=False)
        if path is not None:
            Path(path).write_text(text)
        return text

    @classmethod
    def from_dict(cls, d: dict) -> 'Params':
        if not isinstance(d, dict):
            raise ValueError('solver parameters: expected a mapping of field: value')
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f'solver parameters: unknown field(s) {", ".join(unknown)}')
        preset = d.get('preset', 'paper')
        base = cls.physical() if preset == 'physical' else cls.paper()
        kw = base.to_dict()
        kw.update(d)
        types = {f.name: type(getattr(base, f.name)) for f in dataclasses.fields(cls)}
        for k, v in kw.items():
            t = types[k]
            if t is float:
                try:
                    if isinstance(v, bool):
                        raise ValueError
                    kw[k] = float(v)           # also '3e7', which YAML 1.1 reads as a string
                except (TypeError, ValueError):
                    raise ValueError(f'solver parameters: {k} must be a number, got {v!r}') from None
            elif t is tuple:
                if not isinstance(v, (list, tuple)):
                    raise ValueError(f'solver parameters: {k} must be a list of 3 numbers, got {v!r}')
            elif t in (bool, int, str) and (not isinstance(v, t) or (t is int and isinstance(v, bool))):
                raise ValueError(f'solver parameters: {k} must be a {t.__name__}, got {v!r}')
        return cls(**kw).validate()

    @classmethod
    def from_assignments(cls, preset: str, assignments, **fields) -> 'Params':
        """The preset ('paper' or 'physical') with ``fields`` and then NAME=VALUE overrides (a bench's repeatable --set;
        each VALUE read as YAML: 0.5, 3e7, true, knee, [0, 0, -9.81]; '' or nothing after '=' is the empty string).
        ValueError naming the bad assignment or field."""
        return cls.from_dict({'preset': preset, **fields, **parse_assignments(assignments, 'solver parameters')})

    @classmethod
    def from_yaml(cls, path) -> 'Params':
        from tissue_sim.core.load import read_yaml
        path = Path(path)
        d = read_yaml(path, 'parameter')
        try:
            return cls.from_dict(d or {})
        except ValueError as e:
            raise ValueError(f'{path}: {e}') from None
