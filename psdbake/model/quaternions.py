"""Rotations as unit quaternions on numpy: the part of SciPy's ``Rotation`` that pose space uses.

Why not ``scipy.spatial.transform.Rotation``: importing it loads ``scipy.spatial`` whole
(k-d trees, Qhull, ``scipy.sparse``, ``scipy.special``: ~0.3 s on the project's machine),
which every ``psdbake eval`` (every farm chunk) would pay before its first frame, when eval needs half a
dozen formulas.

Bit for bit. Every operation here does what ``Rotation``'s compiled backend does (SciPy 1.17,
``_rotation_cy.pyx``), so pose coordinates, and every weight and corrective computed from
them, keep their bits: the same order of additions (``a + b + c`` is ``(a + b) + c`` in C as
in numpy, and numpy never fuses a multiply and an add), the same branch points (Shepperd's
choice of pivot in ``from_matrix``, SVD orthogonalisation of matrices that are not orthogonal
to 1e-12, the small-angle series below 1e-3 rad) and the same transcendental functions:
``atan2`` and ``sin`` from the C library, through Python's ``math`` as SciPy's Cython calls
them, where numpy's SIMD versions may round the last bit differently.
tests/test_quaternions.py holds each operation to ``Rotation`` on random and edge-case input
(bit for bit with SciPy 1.17; the test allows 4 ulps, since SciPy is not pinned and pose
coordinates now come from this module, not from SciPy).

Quaternions are (n, 4) float64 arrays, scalar last (x, y, z, w), as ``Rotation.as_quat``.
A ``Rotations`` object answers the calls pose space and its callers make on a ``Rotation``
(``as_quat``, ``as_matrix``, ``as_rotvec``, ``magnitude``, ``inv``, ``*``), so either kind
can be passed where pose space takes rotations (``RotationLike``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..arrays import Quaternions


class RotationLike(Protocol):
    """What pose space reads from rotations: ``Rotations`` or SciPy's ``Rotation``."""

    def as_quat(self) -> NDArray[np.float64]: ...


class Rotations:
    """A stack of n rotations, stored as the unit quaternions SciPy's ``Rotation`` would hold."""

    __slots__ = ("_quat",)

    def __init__(self, quat: Quaternions) -> None:
        """Wrap quaternions (n, 4) as they are (``from_quat`` normalises them first)."""
        self._quat = np.asarray(quat, dtype=np.float64).reshape(-1, 4)

    @classmethod
    def from_quat(cls, quat: ArrayLike) -> Rotations:
        """Quaternions (..., 4) scaled to unit length (``Rotation.from_quat``)."""
        return cls(_normalized(np.array(quat, dtype=np.float64).reshape(-1, 4)))

    @classmethod
    def from_matrix(cls, matrix: ArrayLike) -> Rotations:
        """Rotation matrices (n, 3, 3), column convention (``Rotation.from_matrix``): a matrix
        that is not orthogonal to 1e-12 becomes the nearest orthogonal one (SVD) first."""
        return cls(_from_matrix(np.array(matrix, dtype=np.float64).reshape(-1, 3, 3)))

    def __len__(self) -> int:
        return len(self._quat)

    def as_quat(self) -> NDArray[np.float64]:
        """(n, 4) x, y, z, w, a copy."""
        return self._quat.copy()

    def inv(self) -> Rotations:
        """The inverse rotations: the vector part negated."""
        q = self._quat.copy()
        q[:, :3] *= -1.0
        return Rotations(q)

    def __mul__(self, other: RotationLike) -> Rotations:
        """Composition: self applied after other (one rotation on either side broadcasts)."""
        return Rotations(_normalized(_compose(self._quat, np.asarray(other.as_quat(), dtype=np.float64).reshape(-1, 4))))

    def as_matrix(self) -> NDArray[np.float64]:
        """(n, 3, 3) rotation matrices, column convention."""
        x, y, z, w = self._quat.T
        x2, y2, z2, w2 = x * x, y * y, z * z, w * w
        xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
        m = np.empty((len(self._quat), 3, 3))
        m[:, 0, 0], m[:, 1, 0], m[:, 2, 0] = x2 - y2 - z2 + w2, 2 * (xy + zw), 2 * (xz - yw)
        m[:, 0, 1], m[:, 1, 1], m[:, 2, 1] = 2 * (xy - zw), -x2 + y2 - z2 + w2, 2 * (yz + xw)
        m[:, 0, 2], m[:, 1, 2], m[:, 2, 2] = 2 * (xz + yw), 2 * (yz - xw), -x2 - y2 + z2 + w2
        return m

    def as_rotvec(self) -> NDArray[np.float64]:
        """(n, 3) rotation vectors (axis times angle in radians, angle in [0, pi])."""
        q = _canonical(self._quat)
        x, y, z, w = q.T
        angle = 2 * _atan2(np.sqrt(x * x + y * y + z * z), w)
        small = angle <= 1e-3  # Taylor series of angle / sin(angle / 2) there
        a2 = angle * angle
        series = 2 + a2 / 12 + 7 * a2 * a2 / 2880
        sine = np.ones_like(angle)  # sin(angle / 2) only where it is used
        big = ~small
        sine[big] = _libm(math.sin, angle[big] / 2)
        scale = np.where(small, series, angle / sine)
        return scale[:, None] * q[:, :3]

    def magnitude(self) -> NDArray[np.float64]:
        """(n,) rotation angles in radians, in [0, pi]."""
        x, y, z, w = self._quat.T
        return 2 * _atan2(np.sqrt(x * x + y * y + z * z), np.abs(w))


def _libm(fn: Callable[..., float], *args: NDArray[np.float64]) -> NDArray[np.float64]:
    """fn (a ``math`` function, i.e. the C library's) elementwise over equal-shaped arrays."""
    values = map(fn, *(np.asarray(a, dtype=np.float64).ravel().tolist() for a in args))
    return np.fromiter(values, dtype=np.float64, count=np.size(args[0])).reshape(np.shape(args[0]))


def _atan2(s: NDArray[np.float64], w: NDArray[np.float64]) -> NDArray[np.float64]:
    """``atan2(s, w)`` of the C library for sin-half-angles s >= +0: 0 without a call where the
    rotation is the identity (s == +0, w > 0: exactly +0 by C99 Annex F, which glibc and the
    other C libraries follow), as a good share of sampled poses are (a joint at bind)."""
    out = np.zeros_like(s)
    turned = ~((s == 0) & ~np.signbit(s) & (w > 0))
    out[turned] = _libm(math.atan2, s[turned], w[turned])
    return out


def _normalized(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each row divided by its norm; a zero (or NaN) norm is refused, as by ``Rotation``."""
    x, y, z, w = q.T
    norm = np.sqrt(x * x + y * y + z * z + w * w)
    if np.any((norm == 0) | np.isnan(norm)):
        raise ValueError("Found zero norm quaternions in `quat`.")
    return q / norm[:, None]


def _compose(p: NDArray[np.float64], q: NDArray[np.float64]) -> NDArray[np.float64]:
    """Hamilton products p q, row by row (one row on either side broadcasts), not normalised."""
    p0, p1, p2, p3 = (p[:, i] for i in range(4))
    q0, q1, q2, q3 = (q[:, i] for i in range(4))
    c0, c1, c2 = p1 * q2 - p2 * q1, p2 * q0 - p0 * q2, p0 * q1 - p1 * q0  # p_xyz x q_xyz
    return np.stack([p3 * q0 + q3 * p0 + c0, p3 * q1 + q3 * p1 + c1, p3 * q2 + q3 * p2 + c2,
                     p3 * q3 - p0 * q0 - p1 * q1 - p2 * q2], axis=1)


def _canonical(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """q or -q, whichever has w > 0 (ties broken by x, then y, then z): angles in [0, pi]."""
    x, y, z, w = q.T
    flip = (w < 0) | ((w == 0) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0))))))
    out = q.copy()  # np.where(flip[:, None], q * -1.0, q), without where's (n, 1)-broadcast loops (4x slower)
    out[flip] = q[flip] * -1.0
    return out


def _from_matrix(matrix: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternions (n, 4) of rotation matrices (n, 3, 3) (a fresh array, changed in place)."""
    dets = np.linalg.det(matrix)
    if np.any(dets <= 0):
        ind = int(np.where(dets <= 0)[0][0])
        raise ValueError(f"Non-positive determinant (left-handed or null coordinate frame) in rotation matrix "
                         f"{ind}: {matrix[ind]}.")
    gramians = matrix @ np.transpose(matrix, (0, 2, 1))
    orthogonal = np.all(np.isclose(gramians, np.eye(3), atol=1e-12), axis=(1, 2))
    fix = np.where(~orthogonal)[0]
    if len(fix):  # the orthogonal Procrustes solution, U V^T
        u, _, vt = np.linalg.svd(matrix[fix, :, :])
        matrix[fix, :, :] = u @ vt
    m = matrix
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    decision = np.stack([m[:, 0, 0], m[:, 1, 1], m[:, 2, 2], trace], axis=1)
    choice, best = np.zeros(len(m), dtype=np.int64), decision[:, 0]
    for i in (1, 2, 3):  # the first largest wins, and NaN never does, as in a compiled loop
        better = decision[:, i] > best
        choice, best = np.where(better, i, choice), np.where(better, decision[:, i], best)
    quat = np.empty((len(m), 4))
    for i in (0, 1, 2):  # Shepperd: the largest diagonal entry as pivot
        j, k, rows = (i + 1) % 3, (i + 2) % 3, choice == i
        quat[rows, i] = 1 - trace[rows] + 2 * m[rows, i, i]
        quat[rows, j] = m[rows, j, i] + m[rows, i, j]
        quat[rows, k] = m[rows, k, i] + m[rows, i, k]
        quat[rows, 3] = m[rows, k, j] - m[rows, j, k]
    rows = choice == 3  # ... or the trace
    quat[rows, 0] = m[rows, 2, 1] - m[rows, 1, 2]
    quat[rows, 1] = m[rows, 0, 2] - m[rows, 2, 0]
    quat[rows, 2] = m[rows, 1, 0] - m[rows, 0, 1]
    quat[rows, 3] = 1 + trace[rows]
    x, y, z, w = quat.T
    norm = np.sqrt(x * x + y * y + z * z + w * w)
    return np.where(norm[:, None] == 0, quat, quat / np.where(norm == 0, 1.0, norm)[:, None])
