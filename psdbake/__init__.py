"""psdbake: inverse Pose Space Deformation correctives for UsdSkel assets.

The pipeline (``api``): read USD -> pose space -> black-box skinning -> inverse
(lockstep Powell) -> cardinal RBF -> write USD; and eval. Import and call it from a
pipeline, or use the ``psdbake`` command, a thin shell over the same functions.

Names load on first use (PEP 562), so ``import psdbake`` is cheap and the command can
install its signal handling before USD and SciPy load.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_EXPORTS = {
    "api": (
        "Example", "FitResult", "FitSettings", "MeshFit", "WeightsResult", "correctives_layer", "evaluate", "fit",
        "parse_frames", "points_cache_layer", "pose", "weights_layer", "write_correctives", "write_points_cache",
        "write_pose", "write_weights",
    ),
    "batch": ("Batch", "BatchResult", "JobResult", "load_jobs", "run_batch"),
    "chunks": ("ChunkedWeights", "ChunkPlan", "evaluate_chunks", "plan_chunks", "write_chunks"),
    "errors": ("DeformerError", "FitError", "InputError", "OutputError", "PsdError", "PsdWarning", "StrictError"),
    "inverse": ("InverseResult", "invert_example"),
    "powell": ("PowellResult", "minimize_lockstep"),
    "rbf": ("CardinalRbf", "fit_cardinal"),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted([*_WHERE, "__version__"])


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'psdbake' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__


if TYPE_CHECKING:  # for type checkers and IDEs: the same names, eagerly
    from .api import (  # noqa: F401
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
    from .batch import Batch, BatchResult, JobResult, load_jobs, run_batch  # noqa: F401
    from .chunks import ChunkedWeights, ChunkPlan, evaluate_chunks, plan_chunks, write_chunks  # noqa: F401
    from .errors import DeformerError, FitError, InputError, OutputError, PsdError, PsdWarning, StrictError  # noqa: F401
    from .inverse import InverseResult, invert_example  # noqa: F401
    from .powell import PowellResult, minimize_lockstep  # noqa: F401
    from .rbf import CardinalRbf, fit_cardinal  # noqa: F401
