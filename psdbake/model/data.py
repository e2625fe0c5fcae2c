"""The psd: data: what a CORRECTIVES layer holds per correctives group, as plain data.

``usd/schema.py`` reads and writes these (validating every value, naming the attribute);
``weights`` evaluates them. Nothing here imports USD: the formula can be evaluated by a
program without usd-core. The one table of psd: attributes (``PSD_ATTRIBUTES``) gives each
attribute's USD value type and the ``DriverData`` field it holds: the writer is driven by it,
and the reader's type check uses it (``usd/valuetypes.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..names import DEFAULT_GROUP

__all__ = ["DEFAULT_GROUP", "PSD_ATTRIBUTES", "PSD_VERSION", "READABLE_PSD_VERSIONS", "RESERVED_GROUP_NAMES",
           "BlendShapeData", "DriverData"]

#: Version of the psd: attribute schema written by this psdbake.
PSD_VERSION = 5
#: psd: schema versions this psdbake reads (1: one flat group, read as group "main"; 2: groups;
#: 3: groups with optional joint gates; 4: combinations gated by the groups they sit on, and
#: client-safe channels; 5: ramp gates, min(1, |x_j| / r_j) per gate joint).
READABLE_PSD_VERSIONS = (1, 2, 3, 4, 5)
#: Group names become attribute namespaces: identifiers, and not the schema's own names.
RESERVED_GROUP_NAMES = ("version", "groups")

#: Every psd: attribute (``psd:version``, ``psd:groups``, then per group under ``psd:<group>:``):
#: name -> (its USD value type, the ``DriverData`` field it holds, "" for the two per-mesh ones,
#: and whether it is written only when that field is set). The order is the writer's.
PSD_ATTRIBUTES: dict[str, tuple[str, str, bool]] = {
    "version": ("Int", "", False),
    "groups": ("TokenArray", "", False),
    "poseSpace": ("Token", "pose_space", False),
    "twistAxis": ("Double3", "twist_axis", True),
    "clampWeights": ("Bool", "clamp_weights", False),
    "normalizeWeights": ("Bool", "normalize_weights", False),
    "drivers": ("TokenArray", "drivers", False),
    "driverBindRotations": ("QuatdArray", "bind_rotations", False),
    "kernel": ("Token", "kernel", False),
    "sigma": ("Double", "sigma", False),
    "degree": ("Int", "degree", False),
    "smoothing": ("Double", "smoothing", False),
    "centers": ("DoubleArray", "centers", False),
    "centerLabels": ("StringArray", "center_labels", False),
    "shapes": ("TokenArray", "shapes", False),
    "coefficients": ("DoubleArray", "coefficients", False),
    "polyPowers": ("IntArray", "powers", False),
    "dimensions": ("IntArray", "dims", False),
    "polyShift": ("DoubleArray", "shift", False),
    "polyScale": ("DoubleArray", "scale", False),
    "exampleTimes": ("DoubleArray", "example_times", False),
    "exampleSources": ("StringArray", "example_sources", False),
    "gates": ("TokenArray", "gates", True),
    "gatePoses": ("DoubleArray", "gate_poses", True),
    "gateGroups": ("TokenArray", "gate_groups", True),
    "gateDirections": ("DoubleArray", "gate_directions", True),
    "rampGates": ("TokenArray", "ramp_gates", True),
    "rampRadii": ("DoubleArray", "ramp_radii", True),
    "channels": ("TokenArray", "channels", True),
    "channelColumns": ("IntArray", "channel_columns", True),
    "channelScales": ("DoubleArray", "channel_scales", True),
}

#: Optional attributes written together: each is written when the first of its set is set.
PSD_OPTIONAL_SETS = (("twistAxis",), ("gates", "gatePoses"), ("gateGroups", "gateDirections"),
                     ("rampGates", "rampRadii"), ("channels", "channelColumns", "channelScales"))


@dataclass(frozen=True)
class BlendShapeData:
    """One corrective BlendShape: sparse rest-space offsets in the mesh's point space."""

    name: str  # prim name under the mesh
    channel: str  # skel:blendShapes token (SkelAnimation channel)
    indices: NDArray[np.int64]
    offsets: NDArray[np.float64]  # (k, 3)
    normal_offsets: NDArray[np.float64] | None = None  # (k, 3) when the shading normals change too


@dataclass(frozen=True)
class DriverData:
    """The RBF driver data of one correctives group on one mesh, as stored in the psd:
    namespace (docs/reference/psd-schema.md)."""

    drivers: Sequence[str]  # joint paths, skeleton joint tokens
    bind_rotations: NDArray[np.float64]  # (d, 4) xyzw, each driver's bind local rotation
    pose_space: str
    twist_axis: tuple[float, ...] | None
    clamp_weights: bool
    normalize_weights: bool
    kernel: str
    sigma: float
    degree: int
    smoothing: float
    centers: NDArray[np.float64]  # (k, m) over dims
    center_labels: Sequence[str]
    shapes: Sequence[str]  # channels, one per coefficient column
    coefficients: NDArray[np.float64]  # (k + p, s)
    powers: NDArray[np.int64]  # (p, m)
    shift: NDArray[np.float64]  # (m,)
    scale: NDArray[np.float64]  # (m,)
    dims: NDArray[np.int64]  # (m,) pose coordinates used, indices into the 3 d vector
    example_times: Sequence[float]
    example_sources: Sequence[str]
    gates: Sequence[str] = ()  # combination groups: driver joints whose activation multiplies the weights
    gate_poses: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 0)))  # (g, width) coordinates
    gate_groups: Sequence[str] = ()  # combinations (v4): groups whose activation multiplies the weights
    #: v4: (shapes, coordinates): per shape, its unit direction in each gate group's pose coordinates
    gate_directions: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 0)))
    #: v5: driver joints whose ramp min(1, |x_j| / r_j) multiplies the weights (|x_j| the norm of
    #: that driver's pose coordinates), and each one's radius r_j > 0
    ramp_gates: Sequence[str] = ()
    ramp_radii: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    #: v4: the written channels (client-safe, see channels.py): each carries one output column
    #: times a signed scale, its weight max(0, b_column / scale). Empty: the shapes themselves.
    channels: Sequence[str] = ()
    channel_columns: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    channel_scales: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
