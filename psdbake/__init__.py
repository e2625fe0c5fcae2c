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

from . import reproducible

reproducible.pin()  # before numpy loads: the same BLAS kernel, so the same bytes, on every x86-64 machine

__version__ = "0.1.0"

#: The public surface, by defining module: the one list (``__all__`` and the type checker's
#: view below are derived from it; tests/test_layering.py checks they agree).
_EXPORTS = {
    "api": (
        "correctives_layer", "describe", "edit_groups", "evaluate", "export_blender", "export_gltf", "files_read", "fit",
        "list_groups", "mirror", "mirror_reads", "points_cache_layer", "pose", "sculpts", "weights_layer",
        "write_correctives", "write_mirror", "write_points_cache", "write_pose", "write_sculpts", "write_stack",
        "write_weights",
    ),
    "settings": ("FitSettings", "MirrorSettings"),
    "results": ("AnimWeights", "Example", "FitResult", "GltfResult", "MeshFit", "MirroredGroup", "MirrorResult",
                "PoseResult", "WeightsResult"),
    "arrays": ("Progress",),
    "shot.frames": ("parse_frames",),
    "farm": ("Batch", "BatchResult", "JobResult", "load_jobs", "run_batch"),
    "farm.chunked": ("ChunkedWeights", "evaluate_chunks", "write_chunks"),
    "farm.plan": ("ChunkPlan", "plan_chunks"),
    "errors": (
        "DeformerError", "FitError", "InputError", "OutputError", "PsdError", "PsdWarning", "SettingError",
        "StrictError", "UsdDataError",
    ),
    "solver.inverse": ("InverseResult", "invert_example"),
    "solver.powell": ("PowellResult", "minimize_lockstep"),
    "model.rbf": ("KERNELS", "CardinalRbf"),
    "fitting.rbf_fit": ("fit_cardinal",),
    "model.posespace": ("POSE_SPACES",),
    "model.data": ("DriverData", "PSD_VERSION"),
    "export.blender.export": ("BlenderRigResult",),
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
        correctives_layer,
        describe,
        edit_groups,
        evaluate,
        export_blender,
        export_gltf,
        files_read,
        fit,
        list_groups,
        mirror,
        mirror_reads,
        points_cache_layer,
        pose,
        sculpts,
        weights_layer,
        write_correctives,
        write_mirror,
        write_points_cache,
        write_pose,
        write_sculpts,
        write_stack,
        write_weights,
    )
    from .arrays import Progress  # noqa: F401
    from .errors import (  # noqa: F401
        DeformerError,
        FitError,
        InputError,
        OutputError,
        PsdError,
        PsdWarning,
        SettingError,
        StrictError,
        UsdDataError,
    )
    from .export.blender.export import BlenderRigResult  # noqa: F401
    from .farm import Batch, BatchResult, JobResult, load_jobs, run_batch  # noqa: F401
    from .farm.chunked import ChunkedWeights, evaluate_chunks, write_chunks  # noqa: F401
    from .farm.plan import ChunkPlan, plan_chunks  # noqa: F401
    from .fitting.rbf_fit import fit_cardinal  # noqa: F401
    from .model.data import PSD_VERSION, DriverData  # noqa: F401
    from .model.posespace import POSE_SPACES  # noqa: F401
    from .model.rbf import KERNELS, CardinalRbf  # noqa: F401
    from .results import (  # noqa: F401
        AnimWeights,
        Example,
        FitResult,
        GltfResult,
        MeshFit,
        MirroredGroup,
        MirrorResult,
        PoseResult,
        WeightsResult,
    )
    from .settings import FitSettings, MirrorSettings  # noqa: F401
    from .shot.frames import parse_frames  # noqa: F401
    from .solver.inverse import InverseResult, invert_example  # noqa: F401
    from .solver.powell import PowellResult, minimize_lockstep  # noqa: F401
