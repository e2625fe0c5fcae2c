"""psdbake: inverse Pose Space Deformation correctives for UsdSkel assets.

The pipeline (``api``): read USD -> pose space -> black-box skinning -> inverse
(lockstep Powell) -> cardinal RBF -> write USD; and eval. Import and call it from a
pipeline, or use the ``psdbake`` command, a thin shell over the same functions.
"""

from __future__ import annotations

__version__ = "0.1.0"

from .api import (
    Example,
    FitResult,
    FitSettings,
    MeshFit,
    WeightsResult,
    correctives_layer,
    evaluate,
    fit,
    parse_frames,
    points_cache_layer,
    pose,
    weights_layer,
    write_correctives,
    write_points_cache,
    write_pose,
    write_weights,
)
from .errors import DeformerError, FitError, InputError, OutputError, PsdError, PsdWarning, StrictError
from .inverse import InverseResult, invert_example
from .powell import PowellResult, minimize_lockstep
from .rbf import CardinalRbf, fit_cardinal

__all__ = [
    "CardinalRbf",
    "DeformerError",
    "Example",
    "FitError",
    "FitResult",
    "FitSettings",
    "InputError",
    "InverseResult",
    "MeshFit",
    "OutputError",
    "PowellResult",
    "PsdError",
    "PsdWarning",
    "StrictError",
    "WeightsResult",
    "__version__",
    "correctives_layer",
    "evaluate",
    "fit",
    "fit_cardinal",
    "invert_example",
    "minimize_lockstep",
    "parse_frames",
    "points_cache_layer",
    "pose",
    "weights_layer",
    "write_correctives",
    "write_points_cache",
    "write_pose",
    "write_weights",
]
