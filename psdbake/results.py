"""What the pipeline returns: frozen data, never printed by the library (the CLI renders it)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from . import tolerances as tol
from .model.data import DEFAULT_GROUP, BlendShapeData, DriverData
from .normals import CorrectiveNormals
from .settings import FitSettings, MirrorSettings
from .solver.inverse import InverseResult


@dataclass(frozen=True)
class Example:
    """One sculpted example of one mesh."""

    label: str  # "file.usda@t" for messages and reports
    source: str  # EXAMPLES file path
    time: float
    pose: NDArray[np.float64]  # (j, 4) every joint's rotation away from the bind pose, quaternions xyzw


@dataclass(frozen=True)
class MeshFit:
    """Everything fitted for one mesh."""

    mesh: str
    skeleton: str
    point_count: int
    examples: tuple[Example, ...]
    inverses: tuple[InverseResult, ...]
    channels: tuple[str, ...]  # blend-shape channel per example ("" when it has no corrective)
    drivers: tuple[str, ...]
    driver_data: DriverData
    existing_channels: tuple[str, ...]
    existing_targets: tuple[str, ...]
    group: str = DEFAULT_GROUP
    joints: tuple[str, ...] = ()  # skeleton order, as the example poses
    normals: tuple[CorrectiveNormals | None, ...] = ()  # per example, when the mesh authors normals
    #: the BlendShapes to write when they are not the inverses themselves: a combination's
    #: carry what its joints' own correctives do not already give at its poses
    shapes: tuple[BlendShapeData, ...] | None = None
    condition: float = float("nan")  # 2-norm condition number of the group's RBF system (nan: none solved)
    #: the default fit's kind of group: "joint" (one joint's term) or "combination" (what the
    #: joints' terms leave, gated); "" for a group of explicit drivers or one global group
    role: str = ""
    vertices: int = 0  # points the group's BlendShapes move


@dataclass(frozen=True)
class ExampleSplit:
    """How one example's corrective divides between the per-joint groups and the combinations."""

    mesh: str
    label: str
    source: str
    time: float
    norm: float  # |d_k|: the norm of its rest-space offsets over the mesh's points
    combination: float  # |r_k| / |d_k|: the part the combination groups carry (0 for a zero example)
    terms: float = 0.0  # |A_k| / |d_k|: the part the per-joint terms give (A_k + r_k = d_k)

    @property
    def shares(self) -> tuple[float, float]:
        """(additive, interaction): |A_k| and |r_k| as fractions of |A_k| + |r_k| (0, 0 for a
        zero example): how much of the sculpt the per-joint terms explain and how much is left
        to the combinations."""
        total = self.terms + self.combination
        return (self.terms / total, self.combination / total) if total > 0 else (0.0, 0.0)


@dataclass(frozen=True)
class ExampleCheck:
    """One example of one mesh after the fit, through the composition a client uses
    (``fitcheck``): how far the product is from the sculpt."""

    mesh: str
    label: str
    source: str
    time: float
    error: float  # largest distance of a product point to the sculpt, fraction of the sculpt's diagonal
    worst_vertex: int

    @property
    def reproduced(self) -> bool:
        return self.error <= tol.ROUNDTRIP_RTOL


@dataclass(frozen=True)
class FitResult:
    """What ``psdbake.fit`` made: per mesh and group the examples, their inverses (rest-space
    offsets, residuals, calls) and the RBF driver data; ``missed`` (vertices above the fit
    tolerance) and ``degraded`` (examples the product misses through UsdSkel) say whether
    it may be written (``write_correctives`` refuses a degraded one unless allowed)."""

    asset: str
    example_files: tuple[str, ...]
    settings: FitSettings
    meshes: tuple[MeshFit, ...]
    warnings: tuple[str, ...] = field(default_factory=tuple)
    seconds: float = 0.0
    skipped: tuple[str, ...] = ()  # examples the explicit drivers do not move (labels, with the mesh)
    layout: tuple[str, ...] = ()  # why a mesh's correctives are one global group instead of local ones
    #: the input files' layers (``Sdf.Layer``), kept open so that writing CORRECTIVES reads
    #: no input again: a 1M-point .usda asset took seconds to parse each time
    input_layers: tuple[object, ...] = field(default=(), repr=False, compare=False)
    #: the asset's rig as fitted on (``usd.provenance.rig_record``), stamped in CORRECTIVES
    rig: dict = field(default_factory=dict, repr=False, compare=False)
    #: every fitted example through the client's composition (``fitcheck.check_product``)
    checks: tuple[ExampleCheck, ...] = ()
    #: the default fit: per mesh and example, how much the combinations carry (``decompose``)
    splits: tuple[ExampleSplit, ...] = ()

    @property
    def solved(self) -> dict[tuple[str, str, float], tuple[Example, InverseResult]]:
        """Each example and its inverse once, by (mesh, source, time): the groups of one default
        fit of a mesh all carry every example of it."""
        return {(m.mesh, ex.source, ex.time): (ex, inv) for m in self.meshes
                for ex, inv in zip(m.examples, m.inverses, strict=True)}

    @property
    def solves(self) -> dict[tuple[str, str, float], InverseResult]:
        """Each example's inverse once, by (mesh, source, time) (``solved``)."""
        return {key: inv for key, (_, inv) in self.solved.items()}

    @property
    def missed(self) -> int:
        return int(sum(len(inv.missed) for inv in self.solves.values()))

    @property
    def degraded(self) -> tuple[ExampleCheck, ...]:
        """The examples the product does not reproduce within ``tol.ROUNDTRIP_RTOL``. With RBF
        smoothing the product approximates the examples by request, so none is degraded."""
        if self.settings.smoothing > 0:
            return ()
        return tuple(c for c in self.checks if not c.reproduced)


@dataclass(frozen=True)
class AnimWeights:
    """Blend-shape channels and weights to author on one SkelAnimation."""

    animation: str
    channels: tuple[str, ...]  # existing channels first, then psdbake's
    times: NDArray[np.float64]  # (f,)
    weights: NDArray[np.float64]  # (f, c)
    psd_channels: int  # how many of the channels are psdbake's


@dataclass(frozen=True)
class WeightsResult:
    """What ``psdbake.evaluate`` computed: per SkelAnimation of ANIM, every blend-shape channel's
    weight at every frame (the asset's own channels first, then the correctives'), to write with
    ``write_weights``."""

    asset: str
    correctives: str
    anim: str
    animations: tuple[AnimWeights, ...]
    fps: float | None
    seconds: float = 0.0
    rig: dict = field(default_factory=dict, repr=False, compare=False)  # the asset's, stamped in WEIGHTS


@dataclass(frozen=True)
class GltfResult:
    """What ``export_gltf`` wrote: the .glb and what is in it."""

    output: str
    weights: WeightsResult  # the morph weights baked into it (eval's)
    meshes: tuple[str, ...]
    morph_targets: int  # over every mesh
    sparse_targets: int  # of those, stored as sparse accessors
    frames: int  # keyframes (the most of any skeleton)
    size: int  # bytes


@dataclass(frozen=True)
class PoseResult:
    asset: str
    poses: str
    times: tuple[float, ...]
    meshes: tuple[str, ...]
    layer: object  # Sdf.Layer
    deformers: tuple[str, ...] = ()
    rig: dict = field(default_factory=dict, repr=False, compare=False)  # the asset's, stamped in EXAMPLES


@dataclass(frozen=True)
class SculptFile:
    """One sculpt read back from an OBJ (``psdbake sculpts``) and how far it moved."""

    file: str  # the OBJ's path
    mesh: str
    time: float
    points: NDArray[np.float32]  # (n, 3) the sculpt, mesh local space, as authored
    moved: int  # vertices farther from the posed points than fit's unmoved tolerance
    max_displacement: float
    mean_displacement: float  # over the moved vertices (0 when none moved)
    diagonal: float  # of the posed mesh's bounding box
    edited: bool  # its bytes differ from what psdbake pose wrote


@dataclass(frozen=True)
class SculptsResult:
    asset: str
    examples: str
    obj_dir: str
    files: tuple[SculptFile, ...]
    read: tuple[str, ...]  # the OBJ files and manifest read (no output may be one of them)
    scale: float | None = None
    up_axis: str | None = None
    warnings: tuple[str, ...] = ()
    seconds: float = 0.0


@dataclass(frozen=True)
class MirroredGroup:
    """One correctives group made by ``psdbake mirror`` from another on the same mesh."""

    mesh: str
    source: str  # the group mirrored
    group: str  # its mirror's name
    driver_data: DriverData  # client-safe channels planned afresh
    shapes: tuple[BlendShapeData, ...]  # one per channel, as written
    drivers: tuple[tuple[str, str], ...]  # (driver, partner), sorted
    vertices: int  # vertices the source group moves (each paired with its mirror image)
    worst_vertex: float  # largest distance of a mirror image to its partner vertex, fraction of the diagonal
    worst_joint: float  # largest distance of a mirror image to its partner joint, fraction of the skeleton's extent


@dataclass(frozen=True)
class MirrorResult:
    """What ``psdbake mirror`` made: the mirrored groups, to be written into CORRECTIVES's groups."""

    asset: str
    correctives: str
    settings: MirrorSettings
    groups: tuple[MirroredGroup, ...]
    skipped: tuple[str, ...] = ()  # whole-layer mode: groups left out, each with why
    seconds: float = 0.0
    rig: dict = field(default_factory=dict, repr=False, compare=False)  # the asset's, stamped in CORRECTIVES
