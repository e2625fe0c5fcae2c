"""Posed points as USD stores them (float32 points + extent), made at UsdSkel's own speed.

The points cache (``eval --points-cache``) and ``pose``'s examples author, per mesh and time
code, the black box's output as float32 ``points`` and the ``extent`` [min, max] of them.
Converting the float64 (n, 3) array of ``SkinningBlackBox.__call__`` would cost several times
UsdSkel's whole ``BakeSkinning`` at 100k points (docs/decisions/speed.md): the skel -> local
transform as an (n, 1) x (3,) broadcast (3-element inner loops), ``min(axis=0)`` over (n, 3)
(also 3-element loops) and ``Vt.Vec3fArray.FromNumpy`` (a conversion per element). Here the
same numbers are computed axis by axis over contiguous rows and written straight
into the VtArray USD keeps, so the output is byte for byte what the float64 path gives:

- the transform does the same float64 products and sums in the same order, each rounded
  once (numpy ufuncs never fuse a multiply and an add, unlike BLAS), then rounds to float32
  as ``astype(np.float32)`` does;
- per-axis minima and maxima of a set of numbers do not depend on the order they are taken
  in, except which of +0 and -0 is kept: a zero bound is taken over the (n, 3) array as the
  float64 path takes it;
- the float32 rounding is monotonic, so the float32 of the float64 bound is the bound of the
  float32 points.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pxr import Vt

from ..arrays import Points

Axes = NDArray[np.float64]  # (3, n) one row per axis: x, y, z of every point


def writable(array: Vt.Vec3fArray) -> NDArray[np.float32]:
    """A writable (n, 3) view of a VtArray this module has just made and shares with nobody.

    Vt exports its buffer read-only because VtArrays are copy-on-write: writing into storage
    another array shares would change both. A fresh array's storage is its own, so writing
    through this view does what C++'s ``array.data()`` does, without ``FromNumpy``'s
    conversion per element (0.7 ms per 100k points). The caller keeps ``array`` alive while
    it writes, and takes the view again after anything else (UsdSkel) has written into it.
    """
    view = np.asarray(array)
    if not view.size:
        return np.empty((0, 3), dtype=np.float32)
    buffer = (ctypes.c_float * view.size).from_address(view.__array_interface__["data"][0])
    return np.frombuffer(memoryview(buffer), dtype=np.float32).reshape(view.shape)


def _extent(lo: NDArray[np.float64], hi: NDArray[np.float64], points: NDArray[np.float64]) -> Vt.Vec3fArray:
    """[min, max] per axis, as ``np.stack([points.min(axis=0), points.max(axis=0)])`` rounded
    to float32. lo and hi are the per-axis bounds taken axis by axis; a zero among them is
    taken again over the (n, 3) array, since whether +0 or -0 is kept depends on the order."""
    if not (lo.all() and hi.all()):
        whole = np.ascontiguousarray(points)
        lo, hi = whole.min(axis=0), whole.max(axis=0)
    return Vt.Vec3fArray.FromNumpy(np.array([lo, hi], dtype=np.float32))


@dataclass(frozen=True)
class PosedPoints:
    """One mesh's final points at one time code as USD stores them: ``points`` (n,) float32
    Vec3f, the value authored, and ``extent`` (2,) [min, max] per axis."""

    points: Vt.Vec3fArray
    extent: Vt.Vec3fArray

    @classmethod
    def of(cls, points: Points) -> PosedPoints:
        """From (n, 3) float64 points (the user deformers' output): rounded to float32."""
        out = Vt.Vec3fArray(len(points))
        writable(out)[...] = points
        columns = [points[:, k] for k in range(3)]
        lo, hi = np.array([c.min() for c in columns]), np.array([c.max() for c in columns])
        return cls(out, _extent(lo, hi, points))


class RestPoints:
    """One mesh's rest points as UsdSkel takes them (float32) and the work space of the
    skel -> local transform: made once per mesh, reused at every time code."""

    def __init__(self, points: Points) -> None:
        self.float32 = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
        self._buffers = work_rows(len(self.float32))

    def vt(self) -> Vt.Vec3fArray:
        """A new VtArray of the rest points, for UsdSkel to deform in place."""
        out = Vt.Vec3fArray(len(self.float32))
        writable(out)[...] = self.float32
        return out

    def to_local(self, skinned: Vt.Vec3fArray, linear: NDArray[np.float64], translate: NDArray[np.float64]) -> Axes:
        """Skeleton space -> mesh local space (``to_local_rows``) into this mesh's work buffers:
        the result is overwritten at the next call."""
        return to_local_rows(skinned, linear, translate, self._buffers)

    @staticmethod
    def stored(skinned: Vt.Vec3fArray, local: Axes, lo: NDArray[np.float64], hi: NDArray[np.float64]) -> PosedPoints:
        """local (rounded to float32) written over skinned, a VtArray of ``vt()`` that UsdSkel
        deformed (so no one else holds it), with the extent of the bounds lo and hi."""
        out = writable(skinned)
        for k in range(3):  # axis by axis: one long strided loop each, 3x faster than out.T[...] = local
            out[:, k] = local[k]
        return PosedPoints(skinned, _extent(lo, hi, local.T))


Buffers = tuple[Axes, Axes, Axes]  # (skel, local, term), each (3, n): to_local_rows' work space


def work_rows(n: int) -> Buffers:
    """Work space of ``to_local_rows`` for n points, made once and reused: fresh (3, n)
    buffers fault their pages in at every call (1 ms of 1.6 at 100k points)."""
    return np.empty((3, n)), np.empty((3, n)), np.empty((3, n))


def to_local_rows(skinned: Vt.Vec3fArray, linear: NDArray[np.float64], translate: NDArray[np.float64],
                  buffers: Buffers) -> Axes:
    """Skeleton space -> mesh local space, p . linear + translate (row vectors), axis by axis:
    local[k] = ((x linear[0, k] + y linear[1, k]) + z linear[2, k]) + translate[k] in float64,
    the one formula of the black box (``SkinningBlackBox.skin`` computes it straight into its
    (n, 3) result; tests/test_exact_kernels.py holds the two equal) and the points cache. The
    result is buffers' ``local``, overwritten at the next call with them."""
    skel, local, term = buffers
    np.copyto(skel, np.asarray(skinned).T)  # float32 -> float64, exact
    np.multiply(linear[0][:, None], skel[0], out=local)
    np.multiply(linear[1][:, None], skel[1], out=term)
    local += term
    np.multiply(linear[2][:, None], skel[2], out=term)
    local += term
    local += translate[:, None]
    return local
