"""The names psdbake's registries are keyed by, in a module that imports nothing.

The CLI offers these as choices while it parses options, and ``psdbake --help`` must not
load numpy, SciPy or USD to print them (every farm chunk and batch job pays start-up). The
registries that give the names meaning are dictionaries keyed by the same literal names
(``model.posespace.POSE_SPACES``, ``model.rbf.KERNELS``, ``usd.write.FORMATS``), and
tests/test_layering.py checks that each registry's keys are exactly these names, in order:
a new pose space, kernel or output format is one name here and one entry there.
"""

from __future__ import annotations

#: ``psd:poseSpace`` tokens (``model.posespace.POSE_SPACES`` keys).
POSE_SPACE_NAMES = ("rotationVector", "swingTwist", "quaternion")

#: ``psd:kernel`` tokens, scipy.interpolate.RBFInterpolator's names (``model.rbf.KERNELS`` keys).
KERNEL_NAMES = (
    "gaussian", "linear", "thin_plate_spline", "cubic", "quintic", "multiquadric", "inverse_multiquadric",
    "inverse_quadratic",
)

#: Extensions of the layers psdbake writes (``usd.write.FORMATS`` keys).
LAYER_FORMATS = (".usda", ".usdc", ".usd")

#: The group a psd: v1 layer's flat data belongs to, and fit's group when none is named.
DEFAULT_GROUP = "main"
