"""Named numeric defaults, each with the reason for its value.

Lengths are relative to the mesh's bounding-box diagonal unless stated, so the
same defaults work for a 2 cm eyebrow and a 20 m dragon.
"""

from __future__ import annotations

import numpy as np

#: float32 machine epsilon: USD stores points, offsets and skinning results as float32.
EPS32 = float(np.finfo(np.float32).eps)

#: Default inverse tolerance (fraction of the diagonal). float32 round-off of a
#: skinned point is ~1e-7 of its magnitude, so 1e-6 is reachable yet ten times
#: tighter than the 1e-5 round-trip guarantee.
INVERSE_RTOL = 1e-6

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

#: A Jacobian with |det J| below this fraction of |J|_F^3 is treated as singular (e.g. a
#: zero-scale joint): Powell then starts from the identity directions instead of the
#: linearised guess. (For a rotation the ratio is 3^-1.5 ~ 0.19.)
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

#: A sculpted vertex farther than this many diagonals from where skinning puts it is
#: not a sculpt but broken data (1e30 coordinates, a unit mix-up): refused, never fitted.
ABSURD_SCULPT_DIAGONALS = 10.0

#: Automatic sigma falls back to this (radians) with only one example pose.
DEFAULT_SIGMA = 1.0

#: The RBF must give each example a weight of at least this at its own pose.
SELF_WEIGHT_MIN = 0.99

#: Most whole frames one ``--frames START:END`` may name (eval, compare, batch chunk plans).
#: 1,000,000 frames is 11.5 hours at 24 fps, 4.6 at 60: longer than any shot or film, so a
#: larger range is a typo (``1:1000000000``). ``eval`` holds every frame's joint transforms
#: (frames x joints x 128 bytes), so a range near the limit is for ``--chunk-size`` farms.
MAX_FRAMES = 1_000_000

#: Largest magnitude of a ``--frames`` bound: beyond 2**53 consecutive whole frames are no
#: longer distinct float64 time codes.
MAX_FRAME_MAGNITUDE = 2.0**53


def float32_floor(points: np.ndarray) -> float:
    """Smallest residual the float32 black box can resolve for these points."""
    scale = float(np.max(np.abs(points))) if points.size else 0.0
    return FLOAT32_FLOOR_ULPS * EPS32 * max(scale, 1e-30)


def bbox_diagonal(points: np.ndarray) -> float:
    """Length of the axis-aligned bounding-box diagonal (0 for empty input)."""
    if len(points) == 0:
        return 0.0
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
