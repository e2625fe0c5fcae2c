"""Client-safe channels: written weights in [0, 1], every name at most 63 bytes.

Real clients clamp blend-shape weights to a slider range ([0, 1] in Blender, whose USD
importer never widens it) and cut shape-key names at 63 bytes, while a cardinal RBF weight
b_s(x) is any real number. So each corrective s is written as up to two channels: a
positive one carrying M+_s d'_s with weight max(0, b_s / M+_s), and a negative one carrying
M-_s d'_s (M-_s < 0) with weight max(0, b_s / M-_s); the two add to b_s d'_s exactly as the
unclamped design, for BakeSkinning and Blender alike. M+_s and M-_s (``channel_scales``) are
the guaranteed bounds of b_s over every pose (``weight_range``: interval arithmetic over the
stored formula, the pose coordinates being bounded) where those are within 2x of what the
weights reach over sampled poses (``weights.sampled_ranges``), else 2x that reach: the bound of
an ill-conditioned RBF can be 1e6 where its weights stay within a few units, and a channel
weight of 1e-6 is one UsdSkel skips. A weight past its scale is written as is and warned
about by ``eval``. A side no pose reaches gets no channel (a combination is never negative).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from .. import tolerances as tol
from .data import BlendShapeData, DriverData
from .posespace import POSE_SPACES
from .rbf import KERNELS

#: Blender's shape-key name limit (bytes); longer names are cut there and de-duplicated.
MAX_NAME_BYTES = 63
#: Channel suffixes for the positive and negative side of a corrective.
SIDES = ("pos", "neg")

Interval = tuple[NDArray[np.float64], NDArray[np.float64]]


def short_name(name: str, limit: int = MAX_NAME_BYTES) -> str:
    """name when it fits in limit bytes, else a readable prefix, ``_`` and 8 hex digits of
    its SHA-1 (stable: the same name always gives the same short name; distinct names stay
    distinct but for a hash collision)."""
    if len(name.encode()) <= limit:
        return name
    digest = hashlib.sha1(name.encode()).hexdigest()[:8]
    return name.encode()[: limit - 9].decode(errors="ignore") + "_" + digest


def _kernel_range(kernel: str, r_max: NDArray[np.float64]) -> Interval:
    """phi over r in [0, r_max] (per centre): every kernel is monotone there except the thin
    plate spline, whose minimum -1/(2e) sits at r = e^-1/2."""
    phi = KERNELS[kernel]
    ends = np.stack([phi(np.zeros_like(r_max)), phi(r_max)])
    lo, hi = ends.min(axis=0), ends.max(axis=0)
    if kernel == "thin_plate_spline":
        lo = np.where(r_max > math.exp(-0.5), np.minimum(lo, -0.5 / math.e), lo)
    return lo, hi


def _times(c: NDArray[np.float64], lo: NDArray[np.float64], hi: NDArray[np.float64]) -> Interval:
    """c * [lo, hi], elementwise, for coefficients c."""
    a, b = c * lo, c * hi
    return np.minimum(a, b), np.maximum(a, b)


def _power(lo: float, hi: float, n: int) -> tuple[float, float]:
    """[lo, hi] ** n for an integer n >= 0."""
    if n == 0:
        return 1.0, 1.0
    a, b = lo**n, hi**n
    if n % 2 == 0 and lo <= 0.0 <= hi:
        return 0.0, max(a, b)
    return min(a, b), max(a, b)


def _product(a: tuple[float, float], b: tuple[float, float]) -> tuple[float, float]:
    ends = (a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1])
    return min(ends), max(ends)


def rbf_range(data: DriverData, coefficients: NDArray[np.float64] | None = None) -> Interval:
    """(lo, hi) per output column: bounds of the group's RBF outputs over every pose.

    Every pose coordinate lies in [-B, B] (B: the pose space's bound), so |x - c_i| <= |x| + |c_i|
    with |x| <= B sqrt(m); each kernel term and each monomial is bounded by interval arithmetic."""
    coef = data.coefficients if coefficients is None else coefficients
    bound = POSE_SPACES[data.pose_space].bound
    m = len(data.dims)
    k = len(data.centers)
    r_max = (bound * math.sqrt(m) + np.linalg.norm(data.centers, axis=1)) / data.sigma
    phi_lo, phi_hi = _kernel_range(data.kernel, r_max)
    lo, hi = _times(coef[:k], phi_lo[:, None], phi_hi[:, None])
    lo, hi = lo.sum(axis=0), hi.sum(axis=0)
    xhat = [sorted(((-bound - data.shift[d]) / data.scale[d], (bound - data.shift[d]) / data.scale[d]))
            for d in range(m)]
    for row, powers in enumerate(data.powers):
        mono = (1.0, 1.0)
        for d, n in enumerate(powers):
            mono = _product(mono, _power(xhat[d][0], xhat[d][1], int(n)))
        a, b = _times(coef[k + row], np.array(mono[0]), np.array(mono[1]))
        lo, hi = lo + a, hi + b
    return lo, hi


def weight_range(data: DriverData, groups: Mapping[str, DriverData]) -> Interval:
    """(lo, hi) per output column: bounds of the group's weights b_s over every pose, gates
    (each in [0, its group's largest activation]) and clamp/normalise options included."""
    lo, hi = rbf_range(data)
    gate = 1.0  # v3 joint gates and v5 ramp gates are in [0, 1]
    for name in data.gate_groups:
        other = groups[name]
        _, top = rbf_range(other, other.coefficients.sum(axis=1, keepdims=True))
        gate *= max(0.0, float(top[0]))
    if len(data.gate_groups) or len(data.gates) or len(data.ramp_gates):
        lo, hi = np.minimum(lo, 0.0) * gate, np.maximum(hi, 0.0) * gate
    if data.normalize_weights:  # w / max(1, sum w) lies between 0 and w
        lo, hi = np.minimum(lo, 0.0), np.maximum(hi, 0.0)
    if data.clamp_weights:
        lo, hi = np.clip(lo, 0.0, 1.0), np.clip(hi, 0.0, 1.0)
    return lo, hi


def channel_scales(bound: Interval, sampled: Interval) -> Interval:
    """Each side's scale: the guaranteed bound (``weight_range``) when it is within
    ``tol.CHANNEL_HEADROOM`` of what the weights reach over sampled poses, else that headroom
    times the sampled reach (the bound of an ill-conditioned RBF can be 1e6 where its weights
    stay within [-1, 2], and a channel weight of 1e-6 is one UsdSkel skips). A positive scale
    is at least the headroom (every corrective reaches 1 at its own example); a side the bound
    allows but no sample reaches keeps a scale of at least ``tol.CHANNEL_FLOOR`` of it."""
    (b_lo, b_hi), (s_lo, s_hi) = bound, sampled
    hi = np.where(b_hi > 0.0, np.minimum(b_hi, tol.CHANNEL_HEADROOM * np.maximum(s_hi, 1.0)), 0.0)
    reach = np.maximum(-s_lo, tol.CHANNEL_FLOOR * np.maximum(hi, 1.0))
    lo = np.where(b_lo < 0.0, np.maximum(b_lo, -tol.CHANNEL_HEADROOM * reach), 0.0)
    return lo, hi


def plan_channels(names: Sequence[str], lo: NDArray[np.float64], hi: NDArray[np.float64]
                  ) -> tuple[list[str], NDArray[np.int64], NDArray[np.float64]]:
    """(channel names, the output column each carries, its signed scale): a positive channel
    where the column can be positive (scale M+ = hi), a negative one where it can be
    negative (scale M- = lo)."""
    channels, columns, scales = [], [], []
    for s, name in enumerate(names):
        for side, scale in zip(SIDES, (hi[s], lo[s]), strict=True):
            if (scale > 0.0) if side == "pos" else (scale < 0.0):
                channels.append(short_name(f"{name}_{side}"))
                columns.append(s)
                scales.append(float(scale))
    return channels, np.array(columns, dtype=np.int64), np.array(scales, dtype=np.float64)


def channel_weights(data: DriverData, b: NDArray[np.float64]) -> NDArray[np.float64]:
    """(f, c) the written weights from the columns' weights b (f, s): max(0, b / scale) per
    channel (in [0, 1] wherever b stays within the scales); a layer without channels (psd:
    v1-v3) writes b itself."""
    if not len(data.channels):
        return b
    w = b[:, data.channel_columns]  # a new array: divided and clamped in place (the same operations)
    w /= data.channel_scales
    return np.maximum(w, 0.0, out=w)


def column_weights(data: DriverData, w: NDArray[np.float64]) -> NDArray[np.float64]:
    """(f, s) the columns' weights b back from the written channel weights w (f, c): the sum
    over each column's channels of weight x scale (the inverse of ``channel_weights``)."""
    if not len(data.channels):
        return w
    b = np.zeros((len(w), len(data.shapes)))
    for c, (col, scale) in enumerate(zip(data.channel_columns, data.channel_scales, strict=True)):
        b[:, int(col)] += w[:, c] * scale
    return b


def channel_names(data: DriverData) -> list[str]:
    """The channels a group's weights are written to (psd:shapes before v4)."""
    return list(data.channels) if len(data.channels) else list(data.shapes)


def split_shapes(shapes: Sequence[BlendShapeData], data: DriverData) -> list[BlendShapeData]:
    """One BlendShape per channel: its column's offsets (and normal offsets) times its scale,
    named after the channel."""
    out = []
    for name, col, scale in zip(data.channels, data.channel_columns, data.channel_scales, strict=True):
        shape = shapes[int(col)]
        out.append(BlendShapeData(
            name=name, channel=name, indices=shape.indices, offsets=shape.offsets * scale,
            normal_offsets=None if shape.normal_offsets is None else shape.normal_offsets * scale,
        ))
    return out
