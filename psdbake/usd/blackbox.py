"""SKINNING_t: rest points -> posed points in mesh local space, through UsdSkel itself.

For one mesh at one time code the black box is, in order:

1. the mesh's existing blend shapes at the animation's weights for that time
   (``UsdSkel.BlendShapeQuery.ComputeDeformedPoints``);
2. ``UsdSkel.SkinningQuery.ComputeSkinnedPoints`` with the skeleton's skinning
   transforms at that time (LBS or DQS, whatever the asset says);
3. skeleton space -> mesh local space (skel local-to-world . mesh world-to-local),
   the space in which ``UsdSkel.BakeSkinning`` writes points;
4. the user's ``--deformer`` chain, in order.

UsdSkel computes in float32, so the black box is float32-accurate: the solver
tolerances (``tolerances``) account for that. Callers never see inside: this module
is the only one that knows what the function does.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from typing import NoReturn

import numpy as np
from numpy.typing import NDArray
from pxr import Tf, Usd, UsdGeom, UsdSkel, Vt

from ..arrays import Points, is_singular
from ..deformers import DeformerFactory, PointFn
from ..errors import DeformerError, InputError, where
from .diagnostics import first_line
from .posedpoints import PosedPoints, RestPoints, writable
from .read import Scene

FLOAT32_MAX = float(np.finfo(np.float32).max)
#: The box's latest calls whose skinning it keeps, with their points, once a ``ChainSkinning``
#: asks it to (and only where deformers follow the skinning; eval, pose and the points cache
#: pay nothing): the per-vertex solver's first calls (rest, then every sculpted
#: vertex moved along x, then y, then z, its linearised start and a probe), so that the solver's
#: skinning blocks at the same points (``ChainSkinning``) are read from the calls the chain
#: made, not made again. At 100k points, 29 MB.
REMEMBERED_CALLS = 6


class _BlendShapes:
    """The mesh's existing blend shapes at the weights of one time code."""

    def __init__(self, scene: Scene, mesh: str, time: Usd.TimeCode) -> None:
        query, skel_query = scene.query(mesh)
        self.active = False
        if not query.HasBlendShapes():
            return
        anim = skel_query.GetAnimQuery()
        # The shapes themselves do not change with time: build them once per scene and mesh.
        cache = scene.__dict__.setdefault("_blend_shape_cache", {})
        if mesh not in cache:
            bs_query = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(scene.prim(mesh)))
            cache[mesh] = (bs_query, bs_query.ComputeBlendShapePointIndices(), bs_query.ComputeSubShapePointOffsets())
        bs_query, point_indices, sub_offsets = cache[mesh]
        if not anim or bs_query.GetNumBlendShapes() == 0:
            return
        weights = anim.ComputeBlendShapeWeights(time)
        mapper = query.GetBlendShapeMapper()
        if mapper is None or weights is None:
            return
        weights = mapper.Remap(weights)
        sub_weights, bs_indices, sub_indices = bs_query.ComputeSubShapeWeights(weights)
        if not any(float(w) != 0.0 for w in sub_weights):
            return
        self.args = (sub_weights, bs_indices, sub_indices, point_indices, sub_offsets)
        self.query = bs_query
        self.active = True

    def apply(self, points: Vt.Vec3fArray) -> None:
        if self.active:
            self.query.ComputeDeformedPoints(*self.args, points)


def _matrix(m) -> NDArray[np.float64]:
    return np.array(m, dtype=np.float64).reshape(4, 4)


class SkinningBlackBox:
    """Callable SKINNING_t for one mesh: (n, 3) float64 rest -> (n, 3) float64 posed.

    ``evaluations`` counts calls. A mesh inside an instance is refused: everything built on
    its black box (pose's examples, fit's correctives, the points cache) is authored at the
    mesh's path, and USD composition ignores opinions over an instance proxy.
    """

    def __init__(
        self,
        scene: Scene,
        mesh: str,
        time: float,
        deformers: Sequence[tuple[str, DeformerFactory]] = (),
    ) -> None:
        scene.require_not_instanced(mesh)
        if not np.isfinite(time):  # USD accepts a time sample at inf; no pose or frame lives there
            raise InputError(f"{where(scene.label, mesh)}: time code {time!r} is not finite (a time sample key of "
                             "inf in the layer): time codes must be finite numbers")
        self._scene = scene  # UsdSkel queries die with their stage: keep it alive
        self.mesh = mesh
        self.time = float(time)
        self.label = scene.label
        tc = Usd.TimeCode(time)
        self._query, skel_query = scene.query(mesh)
        self._tc = tc
        self._xforms = skel_query.ComputeSkinningTransforms(tc)
        if self._xforms is None or len(self._xforms) != len(skel_query.GetJointOrder()):
            raise InputError(f"{where(scene.label, mesh)}: UsdSkel cannot compute skinning transforms at time {time:g}")
        if not np.all(np.isfinite(np.array(self._xforms, dtype=np.float64))):
            skel = str(skel_query.GetSkeleton().GetPrim().GetPath())
            raise InputError(f"{where(scene.label, skel)}: joint transforms at time {time:g} are not finite "
                             "(NaN or inf in the animation)")
        self._blend = _BlendShapes(scene, mesh, tc)
        self._linear, self._translate = _skel_to_local(scene, mesh, skel_query.GetPrim(), self.time)
        self._deformers: list[tuple[str, PointFn]] = [
            (spec, _instantiate(spec, factory, scene, mesh, self.time)) for spec, factory in deformers
        ]
        self.evaluations = 0
        # the latest calls' points and skinning (``REMEMBERED_CALLS``), kept from ``remember_skinning`` on
        self._skinned: deque[tuple[Points, Points]] = deque(maxlen=REMEMBERED_CALLS)
        self._remembering = False
        # skin's work space, kept for the box's next calls: the points UsdSkel deforms (a VtArray
        # shared with nobody), their float64 rows x, y, z (3, n) and two (n,) rows to sum in
        self._vt: Vt.Vec3fArray | None = None
        self._work: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None = None

    def _skin_vt(self, vt: Vt.Vec3fArray) -> None:
        """Blend shapes + UsdSkel skinning of vt, in place (skeleton space)."""
        self._blend.apply(vt)
        if not self._query.ComputeSkinnedPoints(self._xforms, vt, self._tc):
            raise InputError(f"{where(self.label, self.mesh)}: UsdSkel failed to skin the points at time {self.time:g}")

    def _bounds(self, rows: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Per-axis minima and maxima of the posed points (3, n); refuses NaN (it fails both
        comparisons), inf and float32 overflow."""
        lo, hi = rows.min(axis=1, initial=np.inf), rows.max(axis=1, initial=-np.inf)
        if not (np.all(hi <= FLOAT32_MAX) and np.all(lo >= -FLOAT32_MAX)):
            self._refuse_range()
        return lo, hi

    def _refuse_range(self) -> NoReturn:
        raise InputError(f"{where(self.label, self.mesh)}: posed points at time {self.time:g} are NaN, "
                         "infinite or overflow float32 (extreme transforms or points)")

    def skin(self, points: Points) -> Points:
        """Blend shapes + UsdSkel skinning + skel->local, without the user deformers."""
        n = len(points)
        # One VtArray and one work space for every call, written over: new ones fault their pages
        # in afresh at every call (1.2 MB and 4 MB at 100k points, ~1.5 us a page). No view of the
        # VtArray outlives a call, so UsdSkel deforms it in place.
        if self._vt is None or self._work is None or len(self._vt) != n:
            self._vt, self._work = Vt.Vec3fArray(n), (np.empty((3, n)), np.empty(n), np.empty(n))
        vt = self._vt
        writable(vt)[...] = points  # rounded to float32 as astype rounds, in one pass (no FromNumpy copy)
        self._skin_vt(vt)
        # to_local_rows' formula, ((x l0k + y l1k) + z l2k) + t_k in float64, the same products and
        # sums in the same order, so the same bits; element-wise rather than posed @ linear: a small
        # (n,3)x(3,3) product goes to multithreaded BLAS, which fights UsdSkel's worker threads
        # (measured 15x slower). Over contiguous rows x, y, z (an (n, 1) x (3,) broadcast runs
        # 3-element inner loops), one output axis at a time, each summed in one row and added to
        # t_k straight into the (n, 3) result (no (3, n) copy of it to transpose).
        skel, total, term = self._work
        np.copyto(skel, np.asarray(vt).T)  # float32 -> float64, exact
        local = np.empty((n, 3))
        lin = self._linear
        for k in range(3):
            np.multiply(skel[0], lin[0, k], out=total)
            np.multiply(skel[1], lin[1, k], out=term)
            total += term
            np.multiply(skel[2], lin[2, k], out=term)
            total += term
            np.add(total, self._translate[k], out=local[:, k])
        # NaN fails both comparisons; inf and float32 overflow fail one (over the whole array at
        # once: the same verdict as _bounds' per-axis one)
        if not (local.max(initial=-np.inf) <= FLOAT32_MAX and local.min(initial=np.inf) >= -FLOAT32_MAX):
            self._refuse_range()
        return local

    def __call__(self, points: Points) -> Points:
        self.evaluations += 1
        posed = self.skin(points)
        if self._remembering:
            self._skinned.append((np.array(points, dtype=np.float64), posed.copy()))
        for spec, fn in self._deformers:
            posed = _checked(spec, fn, posed, self)
        return posed

    def remember_skinning(self) -> None:
        """Keep the skinning of the calls from now on (``skinned_by_call``); a box without
        deformers is its skinning, and keeps nothing."""
        self._remembering = bool(self._deformers)

    def skinned_by_call(self, points: Points) -> Points | None:
        """The skinning alone at ``points`` where one of the box's latest calls was made at
        exactly them (a copy; ``REMEMBERED_CALLS``), else None."""
        for at, skinned in reversed(self._skinned):
            if np.array_equal(at, points):
                return skinned.copy()
        return None

    def posed(self, rest: RestPoints) -> PosedPoints:
        """``self(rest)`` as USD stores it, float32 points and their extent, byte for byte, at
        UsdSkel's own speed (``posedpoints``): the points cache's and ``pose``'s path."""
        self.evaluations += 1
        vt = rest.vt()
        self._skin_vt(vt)
        local = rest.to_local(vt, self._linear, self._translate)
        lo, hi = self._bounds(local)
        if not self._deformers:
            return rest.stored(vt, local, lo, hi)
        posed = np.ascontiguousarray(local.T)  # (n, 3), the array skin returns
        for spec, fn in self._deformers:
            posed = _checked(spec, fn, posed, self)
        return PosedPoints.of(posed)


class ChainSkinning:
    """The box's skinning alone, as the solver asks for it (``coupled.invert(skinning=)``):
    the chain skins on the way to its deformers, so where a call of the chain was made at the
    same points the skinning it did then is returned and no call is spent. ``fresh`` counts the
    skinnings run for it alone, which the solver adds to the example's calls. Same bits either
    way (the same ``skin``). Made before the solver's first call of the chain, as ``fit`` makes
    it, so that the box keeps those calls' skinning."""

    def __init__(self, box: SkinningBlackBox) -> None:
        self._box = box
        self.fresh = 0
        box.remember_skinning()

    def __call__(self, points: Points) -> Points:
        seen = self._box.skinned_by_call(points)
        if seen is not None:
            return seen
        self.fresh += 1
        return self._box.skin(points)


def _skel_to_local(scene: Scene, mesh: str, skel: Usd.Prim, time: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(linear (3, 3), translate (3,)) of skeleton space -> mesh local space at time, row
    vectors: skel local-to-world . mesh world-to-local, checked finite, invertible and in
    float32's range. Remembered per scene and mesh when neither prim nor any ancestor has a
    time-varying transform (the usual rig): the points cache then computes it once per mesh,
    not once per frame (2 world transforms, 2 determinants and an inverse: 30 us a frame)."""
    cache = scene.__dict__.setdefault("_skel_to_local_cache", {})
    if mesh in cache:
        return cache[mesh]
    tc = Usd.TimeCode(time)
    mesh_prim = scene.prim(mesh)
    skel_to_world = _matrix(UsdGeom.Xformable(skel).ComputeLocalToWorldTransform(tc))
    mesh_to_world = _matrix(UsdGeom.Xformable(mesh_prim).ComputeLocalToWorldTransform(tc))
    for prim_path, m in ((str(skel.GetPath()), skel_to_world), (mesh, mesh_to_world)):
        if is_singular(m[:3, :3]):
            raise InputError(f"{where(scene.label, prim_path)}: its world transform at time {time:g} is singular "
                             "or not finite (a zero, NaN or infinite xformOp)")
    try:
        with np.errstate(all="ignore"):
            to_local = skel_to_world @ np.linalg.inv(mesh_to_world)
    except np.linalg.LinAlgError:  # LU of a matrix whose entries overflow on the way
        to_local = np.full((4, 4), np.inf)
    if not np.all(np.abs(to_local) <= FLOAT32_MAX):  # finite and in float32's range
        raise InputError(f"{where(scene.label, mesh)}: its transform relative to the skeleton at time {time:g} "
                         "is beyond float32's range (a huge xformOp)")
    value = to_local[:3, :3], to_local[3, :3]
    if not (_transform_might_vary(skel) or _transform_might_vary(mesh_prim)):
        cache[mesh] = value
    return value


def _transform_might_vary(prim: Usd.Prim) -> bool:
    """Whether prim's local-to-world transform may differ between time codes: any xformOp of
    it or an ancestor with more than one time sample (USD's own conservative test)."""
    while prim and not prim.IsPseudoRoot():
        xformable = UsdGeom.Xformable(prim)
        if xformable and xformable.TransformMightBeTimeVarying():
            return True
        prim = prim.GetParent()
    return False


def _instantiate(spec: str, factory: DeformerFactory, scene: Scene, mesh: str, time: float) -> PointFn:
    try:
        fn = factory(scene.stage, mesh, time)
    except (Exception, SystemExit) as exc:  # a deformer cannot end the run: it fails (exit 5)
        raise DeformerError(
            f"deformer {spec} failed to set up for {where(scene.label, mesh)} at time {time:g}: {_why(exc)}"
        ) from None
    if not callable(fn):
        raise DeformerError(f"deformer {spec} returned {type(fn).__name__}, not a function of the points")
    return fn


def _why(exc: BaseException) -> str:
    """One line for an exception a deformer raised (SystemExit: it tried to end the process)."""
    if isinstance(exc, SystemExit):
        return f"it called sys.exit({exc.code!r}) (SystemExit): a deformer must return points or raise an error"
    if isinstance(exc, Tf.ErrorException) or "pxrInternal" in str(exc):  # USD's error: its words, not its C++ location
        return f"USD error: {first_line(exc)}"
    text = (str(exc).strip().splitlines() or [""])[0]
    return f"{type(exc).__name__}: {text}"


def _checked(spec: str, fn: PointFn, points: Points, box: SkinningBlackBox) -> Points:
    """The deformer's output, or DeformerError: it must be an (n, 3) array of real numbers,
    finite and within float32's range (USD stores points as float32: beyond it they become inf)."""
    at = f"{where(box.label, box.mesh)} at time {box.time:g}"
    try:
        out = fn(points.copy())
    except (Exception, SystemExit) as exc:  # a deformer cannot end the run: it fails (exit 5)
        raise DeformerError(f"deformer {spec} failed on {at}: {_why(exc)}") from None
    try:
        array = None if out is None else np.asarray(out)
    except (Exception, SystemExit) as exc:  # a ragged list, or an object whose __array__ fails
        raise DeformerError(f"deformer {spec} returned a {type(out).__name__} that is not an array of numbers "
                            f"for {at} ({_why(exc)})") from None
    if array is None or array.dtype.kind not in "iuf":
        kinds = {"U": "strings", "S": "bytes", "b": "booleans", "c": "complex numbers", "M": "dates", "m": "timedeltas"}
        what = "None" if out is None else f"{type(out).__name__} of {kinds.get(array.dtype.kind, array.dtype.name)}" \
            if array.dtype.kind != "O" else type(out).__name__
        raise DeformerError(f"deformer {spec} returned {what} for {at}, expected an {points.shape} array of numbers")
    out = array.astype(np.float64)
    if out.shape != points.shape:
        raise DeformerError(f"deformer {spec} returned shape {out.shape} for {at}, expected {points.shape}")
    if not np.all(np.isfinite(out)):
        raise DeformerError(f"deformer {spec} returned NaN or inf for {at}")
    if not np.abs(out).max(initial=0.0) <= FLOAT32_MAX:
        raise DeformerError(
            f"deformer {spec} returned values up to {np.abs(out).max():.3g} for {at}: beyond float32's range "
            f"(+-{FLOAT32_MAX:.3g}), USD would store them as inf"
        )
    return out
