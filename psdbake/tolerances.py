"""Named numeric defaults, each with the reason for its value.

Lengths are relative to the mesh's bounding-box diagonal unless stated, so the
same defaults work for a 2 cm eyebrow and a 20 m dragon.

Plain numbers, no numpy at import: the CLI reads its defaults from here while it parses
options, and ``psdbake --help`` loads no numerics.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

#: float32 machine epsilon (``np.finfo(np.float32).eps``, 2^-23): USD stores points, offsets
#: and skinning results as float32.
EPS32 = 2.0**-23

#: Default inverse tolerance (fraction of the diagonal). float32 round-off of a
#: skinned point is ~1e-7 of its magnitude, so 1e-6 is reachable yet ten times
#: tighter than the 1e-5 round-trip guarantee.
INVERSE_RTOL = 1e-6

#: The product's guarantee (fraction of the diagonal): UsdSkel evaluating ASSET + CORRECTIVES +
#: ANIM + WEIGHTS at an example's pose reproduces its sculpt within this. Ten times the inverse
#: tolerance, for the float32 round-off the offsets, blend shapes and skinning add in a client.
#: A fit whose product misses an example by more is degraded (``fitcheck``): exit 7 by default.
ROUNDTRIP_RTOL = 1e-5

#: The inverse can never beat float32 round-off of the black box's output: the
#: absolute floor is this many float32 ulps of the largest coordinate.
FLOAT32_FLOOR_ULPS = 16.0

#: A vertex whose sculpt is within this fraction of the diagonal of the skinned
#: rest (and above the float32 floor) was not moved by the artist: no corrective.
UNMOVED_RTOL = 1e-6

#: Finite-difference step for the initial Jacobian (fraction of the diagonal).
#: Large enough that float32 noise in the black box (~1e-7 of the diagonal)
#: perturbs the Jacobian by ~1e-5 only; Powell corrects what the secant misses.
JACOBIAN_STEP_RTOL = 1e-2

#: Powell's relative decrease test (as scipy's ``ftol``): a cycle that improves
#: a vertex's objective by less than this fraction means it has stalled.
POWELL_FTOL = 1e-10

#: Upper bound on Powell cycles per vertex (each cycle: 3 line minimisations).
POWELL_MAX_CYCLES = 30

#: Parabolic steps may extrapolate at most this many trial steps (scipy's Brent
#: bracket uses a grow limit of 110; 8 keeps a bad model from flinging a vertex).
LINE_SEARCH_GROW_LIMIT = 8.0

#: A matrix M (n x n) is singular when |det M| <= rcond |M|_F^n (``arrays.is_singular``: scale-
#: free, so a rig in millimetres and one in metres agree; for a rotation the ratio is n^(-n/2),
#: 0.19 for n = 3). Inputs (bind and geomBind transforms, world transforms, joint frames) are
#: refused below this: 1e-12 is a zero-scale axis or a frame collapsed to a plane, far below any
#: real rig (a 1000:1 non-uniform scale is 1e-3 at n = 3).
SINGULAR_RCOND = 1e-12

#: The solver's own threshold, by the same measure: a per-vertex Jacobian with |det J| below
#: this fraction of |J|_F^3 is treated as singular (e.g. a zero-scale joint): Powell then starts
#: from the identity directions instead of the linearised guess.
JACOBIAN_RCOND = 1e-6

#: Two example poses closer than this (radians, Euclidean in pose coordinates)
#: are the same pose: the RBF system would be singular.
DUPLICATE_POSE_ATOL = 1e-4

#: Poses closer than this (radians) are near-duplicates: legal but worth a warning.
NEAR_DUPLICATE_POSE_ATOL = 1e-2

#: A joint is "rotated" in an example (and becomes a default driver) when its
#: rotation away from the bind pose exceeds this angle (radians). Exported
#: float32 quaternions carry ~1e-7 rad of noise.
DRIVER_ANGLE_ATOL = 1e-5

#: A joint "moves" in an example (for local correctives: which joints drive which sculpt)
#: when it turns more than this from the bind pose (radians, 0.57 degrees): sculpt poses are
#: set deliberately, degrees at least, while float32 export noise is ~1e-7 rad and a rig's
#: tiny secondary motion (a spine settling by a tenth of a degree) is not what was sculpted.
ACTIVE_JOINT_ANGLE = 1e-2

#: A joint influences a point (for which joints can explain its corrective, ``fitting.locality``)
#: when its skinning weight there exceeds this: rigs pad influences with weights of a few 1e-3
#: that barely move the point, and each joint added to a point's set costs the additive fit
#: identifiability. Measured on the humanoid's shot sculpts (docs/decisions/additive-correctives.md):
#: 1e-2 keeps less of plain skinning's error on motions nobody sculpted than 1e-3 or 5e-2.
INFLUENCE_WEIGHT_MIN = 1e-2

#: sigma (radians) of a group driven by one joint (``fitting.additive``, ``drivers.plan_group``;
#: ``--sigma`` overrides): a corrective grows over a joint's range of motion, not over the spacing
#: of its sculpts, so a joint sculpted at one angle needs the same width as one sculpted at five,
#: and the group gets it whether fitted alone or with others. 1.843 is the width the humanoid's
#: joint groups had when a default fit derived one shared width from all its examples (the mean
#: pairwise distance of its poses), so that its table stands; widths from 1.5 to 3 rad move its
#: errors by less than 1.8x (docs/decisions/additive-correctives.md).
JOINT_SIGMA = 1.843

#: The additive fit's ridge (``fitting.additive``): the weight of the RKHS norm of the per-joint
#: terms against the squared misfit at an example that moves several of a point's joints, in the
#: units of the kernel (1 at a centre). What the ridge leaves goes into the combination terms, so
#: the examples stay exact; smaller fits the shot sculpts' frames closer, larger keeps the terms
#: smoother. Measured on the humanoid's shot sculpts (docs/decisions/additive-correctives.md):
#: 1e-4 beats 1e-3, 1e-2 and 1e-1 with the additive truth and matches them with the dual-quaternion
#: one; 1e-5 does slightly better with the additive truth and worse with the dual-quaternion one.
ADDITIVE_RIDGE = 1e-4

#: The largest value a joint's term may take at its probe poses (``PROBE_ANGLES``), over the
#: largest sculpted offset of its points, before ``fitting.additive`` raises the ridge tenfold
#: at a time, up to ``ADDITIVE_RIDGE_MAX``. Shot frames where several joints move, some sculpted
#: and some left as they were, tell the joints apart only by cancellation: on CesiumMan (two of
#: eight frames sculpted) terms fitted through close centres swelled to many times the sculpt
#: off the shot (docs/decisions/additive-correctives.md).
ADDITIVE_AMPLIFICATION = 2.0
ADDITIVE_RIDGE_MAX = 1e4
#: Angles (radians) of the probe poses: a joint turned 15 to 90 degrees from bind.
PROBE_ANGLES = (0.25, 0.5, 0.75, 1.0, 1.25, 1.5)

#: sigma of a combination group with several centres (``fitting.decompose``; ``--sigma``
#: overrides), as a fraction of the mean pairwise distance of its poses: a combination carries
#: what the per-joint terms leave at its examples, which on the humanoid's shot sculpts is
#: detail of those frames, not a trend between them; 0.25 of the spacing keeps it near its
#: frames (docs/decisions/additive-correctives.md: the dual-quaternion truth's mean error falls
#: from 6.6% to 4.9% of plain skinning's on the sculpted shot and from 32% to 31% one joint at
#: a time; narrower still measures lower, but a corrective that fades within a few degrees of
#: its frame pops as a shot passes it).
COMBINATION_SIGMA_FRACTION = 0.25

#: The ridge at an example that moves a single joint of a point's set: nothing else can explain
#: its sculpt there, so the fit is exact up to round-off (a regularisation only for duplicated rows).
ADDITIVE_RIDGE_EXACT = 1e-12

#: A residual of the additive part below this fraction of the diagonal is left as it is instead
#: of becoming combination terms: a thousandth of the round-trip tolerance (ROUNDTRIP_RTOL).
RESIDUAL_NEGLIGIBLE_RTOL = 1e-8

#: A combination is gated by the activations of the groups it sits on and divided by their
#: product at its own pose (so its weight is 1 there). Below this product the joints'
#: correctives are essentially off at the combination's pose: the division would amplify
#: the combination a thousandfold, so the fit refuses instead.
GATE_ACTIVATION_MIN = 1e-3

#: Client-safe channels (channels.py): a channel's scale is the guaranteed bound of its
#: corrective's weight when that bound is within this factor of what the weight reaches over
#: sampled poses, else this factor times the sampled reach. 2: a corrective at its own
#: example (weight 1) then sits at a channel weight of at least 0.5 for well-conditioned
#: groups, far above UsdSkel's skipping of weights below 1e-6, and a pose beyond every sample
#: has twice the sampled reach before a client clamps it.
CHANNEL_HEADROOM = 2.0
#: Poses drawn per driver joint to measure that reach (weights.sampled_ranges: between and
#: past the sculpts, every mix of joints, a quarter uniform over SO(3); fixed seed): 20,000
#: cost ~0.1 s per group of 100 examples.
CHANNEL_RANGE_SAMPLES = 20_000
#: A side no sample reaches but the bound allows keeps a scale of this fraction of the
#: other side's (or of 1), so its channel stays usable.
CHANNEL_FLOOR = 0.05
#: eval warns when a channel's weight exceeds 1 by more than float64 round-off (b beyond its
#: scale: a pose outside the sampled reach, or an edited psd:channelScales); it writes the
#: weight as is, so UsdSkel stays exact, while clients that clamp to [0, 1] under-correct.
CHANNEL_BOUND_SLACK = 1e-9

#: A sculpted vertex farther than this many diagonals from where skinning puts it is
#: not a sculpt but broken data (1e30 coordinates, a unit mix-up): refused, never fitted.
ABSURD_SCULPT_DIAGONALS = 10.0

#: Automatic sigma falls back to this (radians) with only one example pose.
DEFAULT_SIGMA = 1.0

#: Automatic sigma keeps the RBF system's 2-norm condition number at or below this. The
#: weights are stored as float32 (UsdSkel ``blendShapeWeights``, ulp 1.2e-7 at 1); round-off
#: of a float64 solve and evaluation grows like eps64 x cond = 2.2e-8 here, below half a
#: float32 ulp, so conditioning costs nothing a user can see. (Measured on the bench rig's
#: example poses: the mean-pairwise-distance sigma gives 6.8e8 at 32 examples, 2.4e18 at 128.)
RBF_COND_TARGET = 1e8

#: The condition number a per-joint term's system keeps to: it admits centres only while its
#: system stays within it (``fitting.additive.choose_centres``). Its weights are also evaluated
#: live in float32 by Blender's drivers (export-blender), where round-off grows with the
#: coefficients: at the float64 RBF_COND_TARGET a knee term of the humanoid's shot sculpts
#: (7 centres, condition 7.8e7) was off by 2.9e-2 through Blender. Measured on those sculpts
#: (float32 replay of the drivers; the sculpted shot's mean error with the dual-quaternion truth,
#: against one global group's 5.32% of plain): 1e6 3.8e-4, no worse; 1e5 2.9e-5, no worse; 1e4
#: 1.2e-5 (the combinations' share from there), 5.38%; 1e3 6.3%; 50 8.3%.
#: Poses a term does not take as centres are still fitted through its basis, and what it
#: leaves goes to the combination terms, so the examples stay exact.
JOINT_TERM_COND_TARGET = 1e5

#: Candidate automatic sigmas: the mean pairwise distance times RBF_SIGMA_STEP**j, j = 0, 1, ...
#: (quarter octaves). A quarter octave changes the Gaussian condition number by about 10x at
#: 32-500 bench examples, fine enough to stay within a decade of RBF_COND_TARGET.
RBF_SIGMA_STEP = 2.0**-0.25

#: The automatic-sigma search stops at this fraction of the closest two poses' distance:
#: there the Gaussian between them is exp(-64) ~ 1e-28, the kernel matrix is the identity to
#: float64 precision and a smaller sigma cannot improve the condition number.
RBF_SIGMA_FLOOR_SPACINGS = 0.125

#: An RBF system whose condition number reaches 1/eps64 (4.5e15) is numerically singular: no
#: digit of its solution is reliable, so it is refused before anything is solved.
RBF_COND_MAX = 1.0 / sys.float_info.epsilon

#: The stored formula's weights at the example poses must be the cardinal delta
#: (b_s(c_i) = [i == s]) within this, and their round-off (eps64 x sum |phi| |C|, the
#: noise of any evaluation, at the examples or between them) must stay below it too.
#: 1e-6 is 8 float32 ulps of a weight of 1 (UsdSkel stores weights as float32); a weight
#: error e moves a posed point by e times its corrective, so for correctives up to a tenth of
#: the diagonal the error stays 100x inside the 1e-5-of-the-diagonal round-trip guarantee.
CARDINAL_ATOL = 1e-6

#: The stored formula and scipy's evaluation sum the same terms in a different order and
#: compute the kernel from eps|x - c| versus |eps x - eps c|: they may differ by about
#: (terms + this) x eps64 x sum |phi| |C| (a dot product's rounding bound, which grows with
#: the coefficients, i.e. with the condition number), plus the kernel's own sensitivity
#: |r phi'(r)| times this many eps64. Beyond that bound the two are different formulas.
FORMULA_ULPS = 16.0

#: The RBF must give each example a weight of at least this at its own pose.
SELF_WEIGHT_MIN = 0.99

#: ``psdbake mirror``: a driver joint and its partner (and each of their ancestors that the
#: joint map renames) must sit at mirror images of each other in skeleton bind space within
#: this fraction of the skeleton's extent (the bounding-box diagonal of its joints' bind
#: positions). Rigs are built and exported in float32 (~6e-8 of a coordinate), so an exactly
#: symmetric rig lands 1000x inside it, while 1e-4 of a 2 m character is 0.2 mm: far below any
#: asymmetry a rigger makes on purpose, and a joint that far off moves skinned points by at
#: most about as much (2 x the offset at a half turn), so the mirrored pose is the mirror image.
MIRROR_JOINT_RTOL = 1e-4

#: ``psdbake mirror``: each vertex a group moves must have a mesh vertex within this fraction
#: of the mesh's diagonal of its mirror image (skeleton bind space). float32 points carry
#: ~6e-8 of a coordinate (at most ~1e-7 of the diagonal), so an exactly symmetric mesh from any
#: tool passes 100x inside it; it is the round-trip guarantee itself (a partner that far off
#: changes no offset, only where it applies, by less than the sculpts are reproduced to), and
#: thousands of times below any mesh's edge length, so the nearest vertex is never a neighbour.
MIRROR_VERTEX_RTOL = 1e-5

#: ``export-blender``: a driver's stored bind rotation and the joint's bind rotation in the
#: asset (where Blender's bones rest) are the same rotation when the vector part of
#: q_stored^-1 q_rest is below this (an angle of 2e-12 rad): psdbake writes both from the same
#: bindTransforms, equal to float64 round-off; the driver then reads the bone's rotation as is.
#: Anything larger is composed into the driver (a layer fitted against other bind transforms).
BLENDER_REST_MATCH = 1e-12

#: Most whole frames one ``--frames START:END`` may name (eval, compare, batch chunk plans).
#: 1,000,000 frames is 11.5 hours at 24 fps, 4.6 at 60: longer than any shot or film, so a
#: larger range is a typo (``1:1000000000``). ``eval`` holds every frame's joint transforms
#: (frames x joints x 128 bytes), so a range near the limit is for ``--chunk-size`` farms.
MAX_FRAMES = 1_000_000

#: Deepest nesting of brackets, braces and parentheses a text layer (``.usda``) may hold, counted
#: before USD parses it (``usd.nesting``): USD's text parser recurses per level and crashed
#: (SIGSEGV) at 100,000 nested dictionaries or prims, and took 10 s for one value of 10,000
#: nested parentheses (over 120 s at 100,000). Real layers nest a few dozen levels (prim
#: hierarchy plus a matrix array's three).
MAX_TEXT_NESTING = 1_000

#: Largest magnitude of a ``--frames`` bound: beyond 2**53 consecutive whole frames are no
#: longer distinct float64 time codes.
MAX_FRAME_MAGNITUDE = 2.0**53


def float32_floor(points: np.ndarray) -> float:
    """Smallest residual the float32 black box can resolve for these points."""
    import numpy as np

    # max |p| as max(max p, -min p): the same number (NaN too) without an |p| copy of the points
    scale = max(float(np.max(points)), -float(np.min(points))) if points.size else 0.0
    return FLOAT32_FLOOR_ULPS * EPS32 * max(scale, 1e-30)


def bbox_diagonal(points: np.ndarray) -> float:
    """Length of the axis-aligned bounding-box diagonal (0 for empty input)."""
    import numpy as np

    if len(points) == 0:
        return 0.0
    # Column by column: max(axis=0) of an (n, 3) array runs 3-element inner loops, 20x slower
    # at 1M points. Minima and maxima are exact, so the diagonal is the same to the bit.
    columns = [points[:, k] for k in range(points.shape[1])]
    return float(np.linalg.norm(np.array([c.max() for c in columns]) - np.array([c.min() for c in columns])))
