"""The 28 muscles of the bundled limb: Rajagopal 2016 parts merged to the paper's level.

Each entry: standard name, the Rajagopal muscles merged into it, functional group, and the vertical
extent of the fleshy belly in limb units (0 hip centre, 1 knee centre, 2 ankle centre).  The
Rajagopal path points give each muscle's line of action but not where its fleshy fibres are (the
vasti, for instance, start their paths at mid-femur), so belly extents are modelled from
descriptive anatomy (Gray's Anatomy, 41st ed., 2016, ch. 80 and 83: where the fleshy fibres begin
and end relative to the bony landmarks); they are estimates, not measurements.  Along the belly the
cross-section follows a spindle, area ~ sin(pi v)**SPINDLE_P (v = 0..1 along the belly).

Not included, because their bellies lie above the stack (on the ilium / in the pelvis, above the
lowest point of the pelvis bone where the stack starts): gluteus medius, gluteus minimus,
piriformis, iliopsoas (iliacus + psoas; its path ends at the lesser trochanter, 52 mm below the
hip centre, above the first slice at 57.5 mm).  Adductor magnus keeps its three standard parts
(Terminologia Anatomica): adductor minimus (its upper part; Rajagopal addmagProx), the adductor
part (addmagMid + addmagDist) and the ischiocondylar 'hamstring' part (addmagIsch): 28 muscles.
"""
SPECIFIC_TENSION = 60.0e4  # N/m^2 (60 N/cm^2, Rajagopal et al. 2016)
SPINDLE_P = 0.6

MUSCLES = [
    # name, Rajagopal parts, group, belly (u_top, u_bottom) in limb units:
    # u = 0 hip centre, 1 knee centre, 2 ankle centre (linear in height within thigh and shank);
    # negative u is above the hip centre.
    ('gluteus_maximus', ('glmax1', 'glmax2', 'glmax3'), 'hip_extensors', (-0.40, 0.30)),
    ('tensor_fasciae_latae', ('tfl',), 'hip_abductors', (-0.15, 0.30)),
    ('sartorius', ('sart',), 'hip_flexors', (-0.12, 0.95)),
    ('rectus_femoris', ('recfem',), 'quadriceps', (0.05, 0.85)),
    ('vastus_lateralis', ('vaslat',), 'quadriceps', (0.08, 0.90)),
    ('vastus_medialis', ('vasmed',), 'quadriceps', (0.30, 0.95)),
    ('vastus_intermedius', ('vasint',), 'quadriceps', (0.12, 0.85)),
    ('adductor_longus', ('addlong',), 'adductors', (0.05, 0.55)),
    ('adductor_brevis', ('addbrev',), 'adductors', (0.05, 0.38)),
    ('adductor_minimus', ('addmagProx',), 'adductors', (0.08, 0.28)),
    ('adductor_magnus', ('addmagMid', 'addmagDist'), 'adductors', (0.10, 0.72)),
    ('adductor_magnus_ischiocondylar', ('addmagIsch',), 'adductors', (0.15, 0.85)),
    ('gracilis', ('grac',), 'adductors', (0.10, 0.80)),
    ('biceps_femoris_long_head', ('bflh',), 'hamstrings', (0.18, 0.88)),
    ('biceps_femoris_short_head', ('bfsh',), 'hamstrings', (0.47, 0.93)),
    # semimembranosus: the belly ends ~50 mm above the knee centre; below, its distal tendon runs on its OpenSim path
    # through the posteromedial corner of the knee (Beltran et al. 2003; De Maeseneer et al. 2014). With the belly down
    # to 0.95 the partition filled the popliteal fossa's centre with it (1,107 mm^2 at S -382.5 mm, centroid 8 mm
    # behind the knee axis) and its active knee moment arm at 0 deg was 13.8 mm against the source model's 31.2 (docs/anatomy.md)
    ('semimembranosus', ('semimem',), 'hamstrings', (0.35, 0.88)),
    ('semitendinosus', ('semiten',), 'hamstrings', (0.15, 0.72)),
    # gastrocnemii: the bellies start at 0.93 limb units, 27 mm above the knee centre, about where the source model's
    # origins on the posterior condyles are (27 and 29 mm above it), seeded on the wrapped path (WRAPPED_SEEDS)
    ('gastrocnemius_medialis', ('gasmed',), 'triceps_surae', (0.93, 1.55)),
    ('gastrocnemius_lateralis', ('gaslat',), 'triceps_surae', (0.93, 1.47)),
    ('soleus', ('soleus',), 'triceps_surae', (1.15, 1.85)),
    ('tibialis_anterior', ('tibant',), 'ankle_dorsiflexors', (1.08, 1.70)),
    ('extensor_digitorum_longus', ('edl',), 'ankle_dorsiflexors', (1.08, 1.80)),
    ('extensor_hallucis_longus', ('ehl',), 'ankle_dorsiflexors', (1.35, 1.85)),
    ('peroneus_longus', ('perlong',), 'peronei', (1.05, 1.55)),
    ('peroneus_brevis', ('perbrev',), 'peronei', (1.40, 1.88)),
    ('tibialis_posterior', ('tibpost',), 'deep_plantarflexors', (1.10, 1.75)),
    ('flexor_digitorum_longus', ('fdl',), 'deep_plantarflexors', (1.20, 1.85)),
    ('flexor_hallucis_longus', ('fhl',), 'deep_plantarflexors', (1.35, 1.92)),
]

# Distal tendons of the knee- and ankle-crossing muscles that move a joint (labelled with their muscle's label, below its belly):
# name -> bone labels it inserts on (biceps: the fibular head, or where muscles cover it in this
# model, the lateral tibial condyle beside it).  Each tendon follows the muscle's
# OpenSim path (Rajagopal 2016; last path point = insertion, in the tibia/patella frames) from the
# end of the belly down to the insertion, then runs on along the bone until it has lain on the bone
# for TENDON_ATTACH_MM (tendons blend into the periosteum over some length; this also makes sure a
# builder slice, ~18 mm apart, cuts the attached part).  Insertions (Gray's Anatomy, 41st ed., ch. 80):
# biceps femoris (both heads) on the fibular head; semimembranosus on the posteromedial tibial condyle;
# semitendinosus, gracilis, sartorius (pes anserinus) on the anteromedial proximal tibia; the four
# quadriceps through the common quadriceps tendon on the base and anterior surface of the patella;
# (ch. 83) soleus through the calcaneal (Achilles) tendon on the posterior calcaneus, tibialis
# anterior on the medial cuneiform and first metatarsal base: label 6 (foot bone), the Rajagopal
# insertions on calcn_r.  Without them these bellies end 60-130 mm above the ankle with no link to
# the foot and cannot move it.  The gastrocnemii's tendons (GASTROCNEMIUS_TENDONS, below) are added by
# generate.py unless --no-gastrocnemius-tendons.  Tensor fasciae latae: its iliotibial tract, on the source model's path
# from the belly over the lateral femoral epicondyle (a via point on the femur) to the tibia (Gerdy's tubercle; the
# Rajagopal insertion on tibia_r), as a tendon of the same disc; the builder's via_points fix its ring at the
# epicondyle to the femur, so only the tract below it crosses the knee, in front of the axis (docs/anatomy.md).
TENDONS = {
    'tensor_fasciae_latae': (3,),
    'biceps_femoris_long_head': (4, 3),
    'biceps_femoris_short_head': (4, 3),
    'semimembranosus': (3,),
    'semitendinosus': (3,),
    'gracilis': (3,),
    'sartorius': (3,),
    'rectus_femoris': (2,),
    'vastus_lateralis': (2,),
    'vastus_medialis': (2,),
    'vastus_intermedius': (2,),
    'soleus': (6,),
    'tibialis_anterior': (6,),
}
# Default (generate.py; --no-gastrocnemius-tendons leaves them out, the limb before issue 19): both gastrocnemii continue as
# tendons onto the calcaneus beside the soleus's, which they join in the calcaneal tendon.  The three
# parts share one OpenSim insertion point: side by side in the slice (R, A offsets in mm; R lateral for
# this right leg), soleus in the middle, as in the Achilles tendon, whose gastrocnemius fibres lie
# medial and lateral of the soleus part at the calcaneus.  Measured (docs/anatomy.md, "The
# gastrocnemii and the calcaneus"): alone, the tendons made the medialis' knee-end cells invert at full
# activation; with BEHIND_BONES and the builder's unbound, unshared gastrocnemii (bind_passed_over,
# unshare_passed_over) each gastrocnemius plantarflexes the foot to the stop within 6 % of its volume.
GASTROCNEMIUS_TENDONS = {
    'gastrocnemius_medialis': (6,),
    'gastrocnemius_lateralis': (6,),
}
TENDON_OFFSET_MM = {
    'gastrocnemius_medialis': (-9.0, 0.0),
    'gastrocnemius_lateralis': (9.0, 0.0),
}
# Default (generate.py; --no-behind-bones turns it off): in the slices where these are the only muscles (the knee), the
# fascia space in front of the femur/tibia section's centroid is fat, not theirs.  The gastrocnemii arise from the posterior surfaces of the femoral condyles (Gray's Anatomy,
# 41st ed., ch. 83); at the knee, where they are the only muscles, the partition gives them the whole
# fascia space, round the condyles into the front of the knee (medialis' section centred 30 mm in front
# of the femur's at S -405 mm), so their origin rings lie in front of the knee axis.
BEHIND_BONES = ('gastrocnemius_medialis', 'gastrocnemius_lateralis')
# Muscles seeded on their path as the source model wraps it at rest (paths.wrapped_points: OpenSim's current path,
# wrap arcs included) instead of the straight lines between their path points: the gastrocnemii's two points (femoral
# origin, calcaneus) join through the condyles 3 mm in front of the knee centre; the source model takes them behind
# the condyles over its wrap cylinders (Gastroc_at_condyles_r, GasLat/GasMed_at_shank_r).
WRAPPED_SEEDS = ('gastrocnemius_medialis', 'gastrocnemius_lateralis')
# Tendons that run along a bone of the segment they leave (tibialis anterior on the anterior tibia)
# keep this gap to bone above their insertion: a tendon glides over the bone; bound to it, its active
# cells would be squeezed between bound vertices.  Where such a tendon's path crosses a bone that
# lies under the skin (the tibia's medial face) it moves to the nearest place where it fits.
TENDON_OFF_BONE = ('tibialis_anterior',)
TENDON_GAP_MM = 1.0
TENDON_RADIUS_MM = 5.0    # disc of ~0.8 cm^2 (larger than real hamstring tendons, ~0.2-0.5 cm^2, so the
                          # model builder's 12-ray polygon and 10 mm^2 component threshold keep it)
TENDON_ATTACH_MM = 25.0   # length over which the tendon lies on its bone at the insertion
# A tendon inserting on the patella (label 2; the quadriceps) lies on it no lower than this fraction of the patella's
# height from its top: the quadriceps tendon inserts on the base of the patella and the upper part of its borders and
# anterior surface (Gray's Anatomy, 41st ed., ch. 80; the vastus medialis' lowest fibres on the upper half of the
# medial border; the source model's insertion points vasmed_r-P3 and vaslat_r-P3 8 and 10 mm below its top).  Without it the vastus
# medialis' tendon, the lowest, ran on for TENDON_ATTACH_MM down to 4 mm below the knee centre (the patella's lower
# third), a model's insertion ring there swung behind the knee with the patella's tilt in deep flexion and its length
# stopped growing from 90 deg (7 moment-arm signs wrong; docs/anatomy.md "The moving patella").
PATELLA_ATTACH_FRACTION = 0.5
TENDON_SNAP_MM = 15.0     # from this far above the insertion point the tendon is moved onto the bone

# Muscles whose fleshy origin runs up along a bone above the first point of their OpenSim path (a path
# has one origin point; the fibres arise from a line).  name -> bone label.  Above the path's origin
# point the partition seed keeps the origin point's offset from that bone's section centroid, so the
# belly follows the bone, instead of the path's first segment extended upwards.  The biceps femoris
# short head arises from the lateral lip of the linea aspera, on the back of the femur, up almost to
# the gluteal tuberosity (Gray's Anatomy, 41st ed., ch. 80); its first path segment runs forwards as it
# rises (origin 5 mm in front of its tibial end), and extended 50 mm above the origin it put the
# belly's top slices in front of the femur (centroids 38-41 mm anterior of the femur's).  Its belly
# starts at the middle of the femur (0.47: the linea aspera's middle third; from 0.40 the partition
# still put the three highest, smallest sections, 12-190 mm^2, in front of the femur).
ORIGIN_ALONG_BONE = {'biceps_femoris_short_head': 1}
