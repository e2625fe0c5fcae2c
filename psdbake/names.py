"""The names psdbake's registries are keyed by, in a module that imports nothing.

The CLI offers these as choices while it parses options, and ``psdbake --help`` must not
load numpy, SciPy or USD to print them (issue 16: every farm chunk and batch job pays
start-up). The registries that give the names meaning key themselves by these tuples,
``dict(zip(NAMES, entries, strict=True))``, so a name cannot be offered without an entry nor
an entry exist without a name: a new pose space, kernel or output format is one name here
and one entry there (``posespace.POSE_SPACES``, ``rbf_model.KERNELS``, ``usd.write.FORMATS``).
"""

from __future__ import annotations

#: ``psd:poseSpace`` tokens, in the order ``posespace.POSE_SPACES`` lists their meanings.
POSE_SPACE_NAMES = ("rotationVector", "swingTwist", "quaternion")

#: ``psd:kernel`` tokens (scipy.interpolate.RBFInterpolator's names), in the order
#: ``rbf_model.KERNELS`` lists their phi(r).
KERNEL_NAMES = (
    "gaussian", "linear", "thin_plate_spline", "cubic", "quintic", "multiquadric", "inverse_multiquadric",
    "inverse_quadratic",
)

#: Extensions of the layers psdbake writes, in the order ``usd.write.FORMATS`` lists USD's
#: export arguments for them.
LAYER_FORMATS = (".usda", ".usdc", ".usd")

#: The group a psd: v1 layer's flat data belongs to, and fit's group when none is named.
DEFAULT_GROUP = "main"
