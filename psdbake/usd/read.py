"""Stage -> skinned meshes, rest points, poses and sculpted examples (validated, sorted).

Composition: every command opens an in-memory root layer whose sublayers are the
given files, strongest first (e.g. ``[EXAMPLES, ASSET]``), so ``POSES``/``EXAMPLES``/
``ANIM`` layers need not reference ASSET. Inputs are opened read-only and never
saved.

Gf convention: matrices are row-vector (p' = p . M); they are converted to numpy
(4, 4) arrays unchanged and interpreted in ``posespace``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pxr import Sdf, Tf, Usd, UsdGeom, UsdSkel

from ..errors import InputError, where
from ..posespace import undefined_rotations
from .dependencies import layer_files, require_regular
from .diagnostics import first_line as _first_line
from .integrity import require_readable_crates


@dataclass(frozen=True)
class SkinnedMesh:
    """A skinned point-based prim and the skeleton that deforms it."""

    path: str
    skeleton: str
    skel_root: str
    joints: tuple[str, ...]  # skeleton joint order (full joint paths)
    point_count: int


def open_layer(path: str) -> Sdf.Layer:
    """Open one input file read-only, or raise InputError naming it."""
    if not os.path.exists(path):
        raise InputError(f"{path}: file not found")
    if os.path.isdir(path):
        raise InputError(f"{path}: is a folder, not a USD file")
    if not os.access(path, os.R_OK):
        raise InputError(f"{path}: file is not readable (permission denied)")
    require_regular(path)
    require_readable_crates([path])
    try:
        layer = Sdf.Layer.FindOrOpen(path)
    except Tf.ErrorException as exc:
        raise InputError(f"{path}: not a readable USD file ({_first_line(exc)})") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a readable USD file (it holds text that is not UTF-8)") from None
    if layer is None:
        raise InputError(f"{path}: not a readable USD file")
    # USD's time-sample queries loop forever on an infinite time-code rate: refuse it here.
    for key in ("timeCodesPerSecond", "framesPerSecond", "startTimeCode", "endTimeCode"):
        if layer.pseudoRoot.HasInfo(key):
            raw = layer.pseudoRoot.GetInfo(key)
            try:
                value = float(raw)
            except (TypeError, ValueError):
                raise InputError(f"{path}: layer metadata {key} is {type(raw).__name__} {raw!r}, not a number") from None
            positive = key.endswith("PerSecond")
            if not np.isfinite(value) or (positive and value <= 0):
                raise InputError(f"{path}: layer metadata {key} = {value!r} is not a {'positive ' if positive else ''}number")
    return layer


def compose(files: Sequence[str | Sdf.Layer]) -> Usd.Stage:
    """A stage over the given files (or in-memory layers), strongest first; inputs stay untouched."""
    root = Sdf.Layer.CreateAnonymous("psdbake.usda")
    keep: list[Sdf.Layer] = []
    for item in reversed(files):  # weakest first, so a file given twice keeps its weakest place
        layer = item if isinstance(item, Sdf.Layer) else open_layer(item)
        if any(layer.identifier == k.identifier for k in keep):
            continue  # e.g. --anim ASSET: the asset's own animation must stay weaker than CORRECTIVES
        keep.insert(0, layer)
    layer_files(keep)  # every layer the stage will open is a regular file: no FIFO blocks composition
    for layer in keep:
        root.subLayerPaths.append(layer.identifier)
    try:
        stage = Usd.Stage.Open(root, Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise InputError(f"{files[0]}: cannot compose ({_first_line(exc)})") from None
    errors = stage.GetCompositionErrors() if hasattr(stage, "GetCompositionErrors") else []
    if errors:
        raise InputError(f"{files[0]}: composition error: {_first_line(str(errors[0]))}")
    stage.psdbake_layers = keep  # keep in-memory sublayers alive as long as the stage
    return stage


def _matrices(values) -> NDArray[np.float64]:
    """Vt.Matrix4dArray (or a list of Gf.Matrix4d) -> (n, 4, 4) float64, row-vector convention."""
    return np.array(values, dtype=np.float64).reshape(-1, 4, 4)


def _types(**names: str) -> dict[str, Sdf.ValueTypeName]:
    return {name.replace("__", ":"): getattr(Sdf.ValueTypeNames, t) for name, t in names.items()}


#: The value type of every attribute psdbake reads, per schema (roles ignored: a float3[]
#: where point3f[] belongs is the same data). An attribute authored with another type (a
#: DCC that retyped it, a damaged file) is refused naming it, before any of it is used.
_SCHEMA_TYPES = {
    "PointBased": _types(points="Point3fArray", normals="Normal3fArray", primvars__normals="Normal3fArray",
                         faceVertexIndices="IntArray", faceVertexCounts="IntArray",
                         primvars__skel__jointIndices="IntArray", primvars__skel__jointWeights="FloatArray",
                         primvars__skel__geomBindTransform="Matrix4d", primvars__skel__skinningMethod="Token",
                         skel__joints="TokenArray", skel__blendShapes="TokenArray"),
    "Skeleton": _types(joints="TokenArray", bindTransforms="Matrix4dArray", restTransforms="Matrix4dArray"),
    "SkelAnimation": _types(joints="TokenArray", translations="Float3Array", rotations="QuatfArray",
                            scales="Half3Array", blendShapes="TokenArray", blendShapeWeights="FloatArray"),
    "BlendShape": _types(offsets="Vector3fArray", normalOffsets="Vector3fArray", pointIndices="IntArray"),
}
#: psd: attributes (``psd:version``, ``psd:groups``, then ``psd:[GROUP:]NAME``): the schema's types.
_PSD_TYPES = _types(
    version="Int", groups="TokenArray", poseSpace="Token", twistAxis="Double3", clampWeights="Bool",
    normalizeWeights="Bool", drivers="TokenArray", driverBindRotations="QuatdArray", kernel="Token", sigma="Double",
    degree="Int", smoothing="Double", centers="DoubleArray", centerLabels="StringArray", shapes="TokenArray",
    coefficients="DoubleArray", polyPowers="IntArray", dimensions="IntArray", polyShift="DoubleArray",
    polyScale="DoubleArray", exampleTimes="DoubleArray", exampleSources="StringArray",
)


def check_value_types(stage: Usd.Stage, label: str) -> None:
    """Refuse an attribute psdbake reads that is authored with the wrong value type."""
    schemas = [(UsdGeom.PointBased, _SCHEMA_TYPES["PointBased"]), (UsdSkel.Skeleton, _SCHEMA_TYPES["Skeleton"]),
               (UsdSkel.Animation, _SCHEMA_TYPES["SkelAnimation"]), (UsdSkel.BlendShape, _SCHEMA_TYPES["BlendShape"])]
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        expected: dict[str, Sdf.ValueTypeName] = {}
        for schema, types in schemas:
            if prim.IsA(schema):
                expected.update(types)
        if prim.IsA(UsdGeom.PointBased):
            for name in prim.GetPropertyNames():
                if name.startswith("psd:"):
                    leaf = name.rsplit(":", 1)[-1]
                    if leaf in _PSD_TYPES:
                        expected[name] = _PSD_TYPES[leaf]
        for name, want in expected.items():
            attr = prim.GetAttribute(name)
            # the authored opinions' types: for a schema attribute the composed type name is the schema's
            for spec in attr.GetPropertyStack() if attr else []:
                if isinstance(spec, Sdf.AttributeSpec) and spec.typeName.type != want.type:
                    raise InputError(f"{where(spec.layer.identifier, str(prim.GetPath()), name)}: authored as "
                                     f"{spec.typeName}, where UsdSkel and psdbake read {want}")


class Scene:
    """A composed stage with its UsdSkel cache: the skinned meshes and their skeletons."""

    def __init__(self, files: Sequence[str | Sdf.Layer], label: str | None = None) -> None:
        self.files = list(files)
        self.label = label or str(self.files[0])
        self.stage = compose(self.files)
        check_value_types(self.stage, self.label)
        self.cache = UsdSkel.Cache()
        # mesh -> (skinning query, skeleton query, owning SkelRoot, bound Skeleton's path)
        self._targets: dict[str, tuple[UsdSkel.SkinningQuery, UsdSkel.SkeletonQuery, str, str]] = {}
        predicate = Usd.TraverseInstanceProxies()
        roots = [p for p in self.stage.Traverse(predicate) if p.IsA(UsdSkel.Root)]
        # Nested SkelRoots: sorted paths put a SkelRoot before the ones inside it, and the
        # cache keeps the first binding it populates for a prim. So, as in UsdSkel's own
        # BakeSkinning of a stage and UsdSkelImaging, the outermost SkelRoot owns everything
        # its traversal reaches, with the bindings inherited from above any inner SkelRoot;
        # an inner root only adds prims the outer traversal cannot reach.
        for prim in sorted(roots, key=lambda p: str(p.GetPath())):
            root = UsdSkel.Root(prim)
            self.cache.Populate(root, predicate)
            for binding in self.cache.ComputeSkelBindings(root, predicate):
                skel_query = self.cache.GetSkelQuery(binding.GetSkeleton())
                # the binding's own path: inside an instance, skel_query's is the prototype's
                skel_path = str(binding.GetSkeleton().GetPrim().GetPath())
                for query in binding.GetSkinningTargets():
                    target = query.GetPrim()
                    if not target.IsA(UsdGeom.PointBased):
                        continue
                    self._targets.setdefault(str(target.GetPath()), (query, skel_query, str(prim.GetPath()), skel_path))
        above: set[str] = set()
        for path in self._targets:
            parent = self.stage.GetPrimAtPath(path).GetParent()
            while parent and not parent.IsPseudoRoot():
                if parent.IsA(UsdSkel.Root):
                    above.add(str(parent.GetPath()))
                parent = parent.GetParent()
        #: Every SkelRoot above a skinned prim, nested ones included: the prims a points
        #: cache must retype to Xform so that no UsdSkel skins its points a second time.
        self.skel_roots: list[str] = sorted(above)

    # -- what is here ---------------------------------------------------------------
    def skinned_meshes(self) -> list[SkinnedMesh]:
        """Every skinned point-based prim, sorted by path.

        Refuses what UsdSkel would get silently wrong or psdbake could not write back: a
        mesh ``skel:joints`` entry that is not a joint of the skeleton (UsdSkel leaves the
        points bound to it unskinned), and an animation inside an instance (weights
        authored over an instance proxy are ignored by composition)."""
        out = []
        for path in sorted(self._targets):
            query, skel_query, root, skeleton = self._targets[path]
            if not skel_query:
                raise InputError(f"{where(self.label, path)}: bound skeleton is invalid")
            joints = tuple(str(j) for j in skel_query.GetJointOrder())
            unknown = [str(j) for j in (query.GetJointOrder() or []) if str(j) not in set(joints)]
            if unknown:
                raise InputError(
                    f"{where(self.label, path, 'skel:joints')}: joint {unknown[0]!r} is not in skeleton <{skeleton}> "
                    "(UsdSkel would leave the points bound to it unskinned)"
                )
            anim = skel_query.GetAnimQuery()
            if anim and (anim.GetPrim().IsInPrototype() or anim.GetPrim().IsInstanceProxy()):
                source = UsdSkel.BindingAPI(self.prim(skeleton)).GetInheritedAnimationSource()
                anim_path = source.GetPath() if source else anim.GetPrim().GetPath()
                instance, asset = self.instance_of(str(anim_path)) or (str(anim_path), "its asset")
                raise InputError(
                    f"{where(self.label, path)}: its SkelAnimation <{anim_path}> is inside instance <{instance}> of "
                    f"{asset}: USD ignores blend-shape weights authored over an instance; bind a SkelAnimation outside "
                    f"the instance (skel:animationSource on <{instance}>) or run psdbake on the asset itself"
                )
            out.append(
                SkinnedMesh(
                    path=path,
                    skeleton=skeleton,
                    skel_root=root,
                    joints=joints,
                    point_count=len(self.rest_points(path)),
                )
            )
        return out

    def instance_of(self, path: str) -> tuple[str, str] | None:
        """(instance root, '@asset@</prim>' it instances) when path is inside an instance,
        else None: where psdbake's output for path would have to go instead."""
        prim = self.stage.GetPrimAtPath(path)
        if not prim or not prim.IsInstanceProxy():
            return None
        while prim and not prim.IsInstance():
            prim = prim.GetParent()
        arcs = list(prim.GetPrimIndex().rootNode.children)
        if not arcs:
            return str(prim.GetPath()), "its prototype"
        return str(prim.GetPath()), f"@{arcs[0].layerStack.identifier.rootLayer.identifier}@<{arcs[0].path}>"

    def require_not_instanced(self, mesh: str) -> None:
        """Refuse a mesh inside an instance: USD ignores opinions authored over instance
        proxies, so psdbake's output for it would be silently lost."""
        inside = self.instance_of(mesh)
        if inside:
            raise InputError(
                f"{where(self.label, mesh)}: is inside instance <{inside[0]}> of {inside[1]}: USD ignores opinions "
                "authored over an instance, so psdbake's output for this mesh would be lost; run psdbake on that "
                f"asset itself, or set instanceable = false on <{inside[0]}>"
            )

    def require_skinned(self) -> None:
        """Raise InputError when the stage has no SkelRoot or no skinned mesh."""
        roots = [p for p in self.stage.Traverse(Usd.TraverseInstanceProxies()) if p.IsA(UsdSkel.Root)]
        if not roots:
            raise InputError(f"{self.label}: no SkelRoot prim found (UsdSkel needs one above the skinned meshes)")
        if not self._targets:
            names = ", ".join(f"<{p.GetPath()}>" for p in roots)
            raise InputError(
                f"{self.label}: no skinned mesh under {names} "
                "(a Mesh needs UsdSkelBindingAPI with skel:skeleton, jointIndices and jointWeights)"
            )

    def query(self, mesh: str) -> tuple[UsdSkel.SkinningQuery, UsdSkel.SkeletonQuery]:
        if mesh not in self._targets:
            raise InputError(f"{where(self.label, mesh)}: not a skinned mesh in this stage")
        query, skel_query, _, _ = self._targets[mesh]
        return query, skel_query

    def prim(self, path: str) -> Usd.Prim:
        return self.stage.GetPrimAtPath(path)

    # -- values ---------------------------------------------------------------------
    def rest_points(self, mesh: str) -> NDArray[np.float64]:
        """The mesh's authored (default-time) points, float64 (n, 3)."""
        attr = UsdGeom.PointBased(self.prim(mesh)).GetPointsAttr()
        value = attr.Get(Usd.TimeCode.Default())
        if value is None:
            raise InputError(f"{where(self.label, mesh, 'points')}: no rest points authored")
        try:
            pts = np.array(value, dtype=np.float64).reshape(-1, 3)
        except (TypeError, ValueError):
            raise InputError(f"{where(self.label, mesh, 'points')}: is not a point array ({type(value).__name__})") from None
        if not np.all(np.isfinite(pts)):
            raise InputError(f"{where(self.label, mesh, 'points')}: rest points contain NaN or inf")
        return pts

    def animation_times(self, mesh: str) -> list[float]:
        """Authored time samples of the skeleton's animation (joints and blend shapes)."""
        _, skel_query = self.query(mesh)
        anim = skel_query.GetAnimQuery()
        if not anim:
            return []
        times = set(anim.GetJointTransformTimeSamples()) | set(anim.GetBlendShapeWeightTimeSamples())
        return sorted(float(t) for t in times)

    def animation_prim(self, mesh: str) -> str | None:
        _, skel_query = self.query(mesh)
        anim = skel_query.GetAnimQuery()
        return str(anim.GetPrim().GetPath()) if anim else None

    def joint_local_transforms(self, mesh: str, time: float) -> NDArray[np.float64]:
        """Skeleton-order local joint transforms at time (UsdSkel's own computation)."""
        _, skel_query = self.query(mesh)
        local = _matrices(skel_query.ComputeJointLocalTransforms(Usd.TimeCode(time)) or [])
        if len(local) != len(skel_query.GetJointOrder()):
            skel = str(skel_query.GetSkeleton().GetPrim().GetPath())
            raise InputError(
                f"{where(self.label, skel)}: UsdSkel cannot pose the skeleton at time {time:g} "
                "(restTransforms missing or the wrong size for joints the animation does not cover)"
            )
        return local

    def bind_local_transforms(self, mesh: str) -> NDArray[np.float64]:
        """Local transforms of the bind pose (where skinning is the identity).

        UsdSkel's bindTransforms are skeleton-space; local_j = bind_j . bind_parent^-1.
        """
        _, skel_query = self.query(mesh)
        skel = skel_query.GetSkeleton()
        world = _matrices(skel.GetBindTransformsAttr().Get() or [])
        parents = np.array(skel_query.GetTopology().GetParentIndices(), dtype=np.int64)
        if len(world) != len(parents):
            raise InputError(
                f"{where(self.label, str(skel.GetPrim().GetPath()), 'bindTransforms')}: "
                f"{len(world)} matrices for {len(parents)} joints"
            )
        attr = where(self.label, str(skel.GetPrim().GetPath()), "bindTransforms")
        if undefined_rotations(world).any():
            joint = skel_query.GetJointOrder()[int(np.argmax(undefined_rotations(world)))]
            raise InputError(f"{attr}: joint {str(joint)!r} has a NaN, infinite, huge, zero-scale or degenerate matrix")
        local = world.copy()
        has_parent = parents >= 0
        with np.errstate(all="ignore"):
            local[has_parent] = world[has_parent] @ np.linalg.inv(world[parents[has_parent]])
        bad = undefined_rotations(local)
        if bad.any():
            joint = skel_query.GetJointOrder()[int(np.argmax(bad))]
            raise InputError(f"{attr}: joint {str(joint)!r} has no usable local bind transform (its parent's matrix "
                             "cannot be inverted at float precision)")
        return local

    def authored_point_samples(self, layer: Sdf.Layer, mesh: str) -> list[float]:
        """Time codes at which ``layer`` itself authors points samples for mesh."""
        spec_path = Sdf.Path(mesh).AppendProperty("points")
        return sorted(float(t) for t in layer.ListTimeSamplesForPath(spec_path))

    def point_sample(self, layer: Sdf.Layer, mesh: str, time: float) -> NDArray[np.float64]:
        spec_path = Sdf.Path(mesh).AppendProperty("points")
        value = layer.QueryTimeSample(spec_path, time)
        if value is None:
            raise InputError(f"{where(layer.identifier, mesh, 'points')}: time sample {time:g} is not a point array")
        try:
            return np.array(value, dtype=np.float64).reshape(-1, 3)
        except (TypeError, ValueError):
            raise InputError(
                f"{where(layer.identifier, mesh, 'points')}: time sample {time:g} is not a point array"
            ) from None


#: psd: schema versions this psdbake reads (1: one flat group, read as group "main").
READABLE_PSD_VERSIONS = (1, 2)
#: The group a v1 layer's flat psd: data belongs to, and fit's group when none is named.
DEFAULT_GROUP = "main"


def read_driver_groups(scene: Scene, mesh: str) -> list[tuple[str, object]]:
    """Every correctives group's psd: driver data on mesh, validated, sorted by group
    name: [(group, DriverData)]; empty if the mesh has none."""
    prim = scene.prim(mesh)
    version_attr = prim.GetAttribute("psd:version")
    if not version_attr or not version_attr.HasAuthoredValue():
        return []
    version = version_attr.Get()
    if version not in READABLE_PSD_VERSIONS:
        raise InputError(
            f"{where(scene.label, mesh, 'psd:version')}: version {version} is not supported by this psdbake "
            f"(reads {', '.join(map(str, READABLE_PSD_VERSIONS))}); upgrade psdbake or re-fit"
        )
    if version == 1:
        return [(DEFAULT_GROUP, _read_group(scene, mesh, "psd:"))]
    groups_attr = prim.GetAttribute("psd:groups")
    names = [str(g) for g in (groups_attr.Get() if groups_attr else None) or []]
    if not names:
        raise InputError(f"{where(scene.label, mesh, 'psd:groups')}: missing or empty (the CORRECTIVES layer is incomplete)")
    if len(set(names)) != len(names):
        raise InputError(f"{where(scene.label, mesh, 'psd:groups')}: a group is listed twice")
    return [(name, _read_group(scene, mesh, f"psd:{name}:")) for name in sorted(names)]


def _read_group(scene: Scene, mesh: str, prefix: str):
    """One group's psd: driver data, every number validated on read (finite, shapes,
    positivity), each refusal naming its attribute: eval then never computes NaN weights."""
    from ..posespace import WIDTH
    from ..rbf import KERNELS
    from .write import DriverData

    prim = scene.prim(mesh)
    label = scene.label

    def at(name: str) -> str:
        return where(label, mesh, prefix + name)

    def get(name: str, required: bool = True):
        attr = prim.GetAttribute(prefix + name)
        value = attr.Get() if attr else None
        if value is None and required:
            raise InputError(f"{at(name)}: missing (the CORRECTIVES layer is incomplete)")
        return value

    def numbers(name: str, value=None) -> NDArray[np.float64]:
        """An attribute's values as float64 (a scalar becomes one value), or refuse its type."""
        value = get(name) if value is None else value
        try:
            return np.array(value, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise InputError(f"{at(name)}: {type(value).__name__} value is not numbers") from None

    def finite(name: str, values: NDArray[np.float64], why: str = "NaN or inf would make the weights NaN"
               ) -> NDArray[np.float64]:
        bad = np.nonzero(~np.isfinite(values))[0]
        if len(bad):
            raise InputError(f"{at(name)}: value {int(bad[0])} is {float(values[bad[0]])!r}: every value must be "
                             f"finite ({why})")
        return values

    def integers(name: str) -> NDArray[np.int64]:
        values = numbers(name)
        bad = np.nonzero(~np.isfinite(values) | (values != np.round(values)))[0]
        if len(bad):
            raise InputError(f"{at(name)}: value {int(bad[0])} is {float(values[bad[0]])!r}, not an integer")
        return values.astype(np.int64)

    def scalar(name: str) -> float:
        values = numbers(name)
        if len(values) != 1:
            raise InputError(f"{at(name)}: {len(values)} values, expected one number")
        return float(values[0])

    drivers = [str(d) for d in get("drivers")]
    dims = integers("dimensions")
    dim = len(dims)
    shapes = [str(s) for s in get("shapes")]
    centers = numbers("centers")
    powers = integers("polyPowers")
    coefficients = numbers("coefficients")
    quats = get("driverBindRotations")
    try:
        bind = np.array([[*q.GetImaginary(), q.GetReal()] for q in quats], dtype=np.float64).reshape(-1, 4)
    except (AttributeError, TypeError, ValueError):
        raise InputError(f"{at('driverBindRotations')}: not an array of quaternions") from None
    space = str(get("poseSpace"))
    if space not in WIDTH:
        raise InputError(f"{at('poseSpace')}: unknown pose space {space!r}")
    bad_dims = dim == 0 or dims.min() < 0 or dims.max() >= WIDTH[space] * len(drivers)
    if bad_dims or centers.size % dim or powers.size % dim or len(bind) != len(drivers):
        raise InputError(f"{where(label, mesh)}: {prefix} driver data sizes do not match {len(drivers)} drivers")
    _, skel_query = scene.query(mesh)
    joints = {str(j) for j in skel_query.GetJointOrder()}
    missing = [d for d in drivers if d not in joints]
    if missing:
        skel = skel_query.GetSkeleton().GetPrim().GetPath()
        raise InputError(f"{at('drivers')}: joint {missing[0]!r} is not in skeleton <{skel}>")
    if str(get("kernel")) not in KERNELS:
        raise InputError(f"{at('kernel')}: unknown kernel {get('kernel')!r}")
    centers = centers.reshape(-1, dim)
    powers = powers.reshape(-1, dim)
    rows = len(centers) + len(powers)
    if not shapes or coefficients.size != rows * len(shapes):
        raise InputError(f"{at('coefficients')}: expected {rows} x {len(shapes)} values, got {coefficients.size}")
    # -- every number finite, every shape consistent (README: "The psd: schema") --
    finite("centers", centers.reshape(-1))
    finite("coefficients", coefficients)
    sigma = scalar("sigma")
    if not (np.isfinite(sigma) and sigma > 0):
        raise InputError(f"{at('sigma')}: {sigma!r} is not a finite number > 0 (the RBF width in radians)")
    smoothing = scalar("smoothing")
    if not (np.isfinite(smoothing) and smoothing >= 0):
        raise InputError(f"{at('smoothing')}: {smoothing!r} is not a finite number >= 0")
    degree = integers("degree")
    if len(degree) != 1 or degree[0] < -1:
        shown = int(degree[0]) if len(degree) == 1 else degree.tolist()
        raise InputError(f"{at('degree')}: {shown!r} is not one integer >= -1 (-1: no polynomial term)")
    degree = int(degree[0])
    _check_powers(at("polyPowers"), powers, degree, dim)
    shift = finite("polyShift", numbers("polyShift"))
    scale = finite("polyScale", numbers("polyScale"))
    for name, values in (("polyShift", shift), ("polyScale", scale)):
        if len(values) != dim:
            raise InputError(f"{at(name)}: {len(values)} values for {dim} psd:dimensions (one per dimension)")
    if np.any(scale == 0):
        raise InputError(f"{at('polyScale')}: value {int(np.argmax(scale == 0))} is zero (the polynomial term "
                         "divides by it)")
    with np.errstate(over="ignore", invalid="ignore"):
        norms = np.linalg.norm(np.nan_to_num(bind, nan=0.0, posinf=0.0, neginf=0.0), axis=1)
    # psdbake writes unit quaternions; 1e-3 leaves room for hand-authored or rounded ones
    bad = np.nonzero(~np.all(np.isfinite(bind), axis=1) | ~(np.abs(norms - 1.0) < 1e-3))[0]
    if len(bad):
        raise InputError(f"{at('driverBindRotations')}: quaternion {int(bad[0])} (driver {drivers[bad[0]]!r}) is "
                         f"{tuple(bind[bad[0]][[3, 0, 1, 2]].tolist())!r}: not a unit quaternion (a rotation)")
    twist = get("twistAxis", required=False)
    twist_axis = None
    if space == "swingTwist":
        if twist is None:
            raise InputError(f"{at('twistAxis')}: missing: the swingTwist pose space needs the twist axis")
        axis = numbers("twistAxis", twist)
        if len(axis) != 3 or not np.all(np.isfinite(axis)) or np.linalg.norm(axis) == 0:
            raise InputError(f"{at('twistAxis')}: {tuple(axis.tolist())!r} is not a finite non-zero 3-vector")
        twist_axis = tuple(float(v) for v in axis)
    elif twist is not None:
        twist_axis = tuple(float(v) for v in numbers("twistAxis", twist))
    example_times = finite("exampleTimes", numbers("exampleTimes"), "time codes are finite numbers")
    return DriverData(
        drivers=drivers,
        bind_rotations=bind,
        pose_space=space,
        twist_axis=twist_axis,
        clamp_weights=bool(get("clampWeights", required=False) or False),
        normalize_weights=bool(get("normalizeWeights", required=False) or False),
        kernel=str(get("kernel")),
        sigma=sigma,
        degree=degree,
        smoothing=smoothing,
        centers=centers,
        center_labels=[str(s) for s in get("centerLabels")],
        shapes=shapes,
        coefficients=coefficients.reshape(rows, len(shapes)),
        powers=powers,
        shift=shift,
        scale=scale,
        dims=dims,
        example_times=[float(t) for t in example_times],
        example_sources=[str(s) for s in get("exampleSources")],
    )


def _check_powers(at: str, powers: NDArray[np.int64], degree: int, dim: int) -> None:
    """psd:polyPowers must be the monomials of total degree <= psd:degree in dim variables
    (scipy's RBFInterpolator's set, in any order): empty for degree -1."""
    from math import comb

    expected = comb(dim + degree, dim) if degree >= 0 else 0
    sums = powers.sum(axis=1) if len(powers) else np.zeros(0, dtype=np.int64)
    distinct = len({tuple(row) for row in powers.tolist()}) == len(powers)
    if len(powers) != expected or np.any(powers < 0) or np.any(sums > degree) or not distinct:
        raise InputError(
            f"{at}: {len(powers)} monomials do not match psd:degree {degree} in {dim} dimensions (expected the "
            f"{expected} distinct monomials of total degree <= {degree}{', none' if degree < 0 else ''})"
        )


#: What decides how UsdSkel skins a mesh: the binding (UsdSkelBindingAPI, inherited down
#: namespace), and on Skeleton and BlendShape prims their joints, bind pose and offsets.
_BINDING = frozenset({"skel:joints", "skel:skeleton", "skel:skinningMethod", "skel:blendShapes",
                      "skel:blendShapeTargets"})
_BINDING_ON = {"Skeleton": frozenset({"joints", "bindTransforms"}),
               "BlendShape": frozenset({"offsets", "pointIndices", "normalOffsets", "inbetweens"})}


def check_examples_binding(asset: Scene, examples: Scene, path: str) -> None:
    """Refuse an EXAMPLES file (``examples``: the file composed over the asset) that changes
    the skinning: the binding primvars and relationships of any prim, a Skeleton's joints or
    bindTransforms, a BlendShape's offsets. fit would invert a skinning that eval and UsdSkel
    (reading the asset's binding) never apply, and the correctives would miss the sculpts.
    EXAMPLES may carry only the pose (the bound SkelAnimation) and the sculpted points."""
    for prim in examples.stage.Traverse(Usd.TraverseInstanceProxies()):
        original = asset.stage.GetPrimAtPath(prim.GetPath())
        kinds = [kind for kind in _BINDING_ON if prim.IsA(getattr(UsdSkel, kind))
                 or (original and original.IsA(getattr(UsdSkel, kind)))]
        extra = frozenset().union(*(_BINDING_ON[k] for k in kinds))
        for prop in prim.GetAuthoredProperties():
            name = prop.GetName()
            if not (name.startswith("primvars:skel:") or name in _BINDING or name in extra):
                continue
            before = original.GetProperty(name) if original else None
            if not _same_property(prop, before):
                raise InputError(
                    f"{where(path, str(prim.GetPath()), name)}: the EXAMPLES layer re-authors the asset's skinning "
                    "binding: EXAMPLES may only carry the pose (the bound SkelAnimation) and the sculpted points, "
                    "because eval and UsdSkel skin with the asset's binding (change it in the asset and run "
                    "psdbake pose again)"
                )


def require_finite_time_samples(scene: Scene, path: str, label: str) -> None:
    """Refuse a time sample keyed at inf on the prim at path (in any layer of its prim stack).
    USD lets a layer author one, but its composed queries skip it: a pose or weight keyed
    there would be silently dropped, and no frame or example can live at inf."""
    prim = scene.prim(path)
    for spec in prim.GetPrimStack() if prim else []:
        layer = spec.layer
        file = label if layer.realPath and os.path.realpath(layer.realPath) == os.path.realpath(label) else \
            (layer.realPath or label)
        for attr in spec.attributes:
            bad = [t for t in layer.ListTimeSamplesForPath(attr.path) if not np.isfinite(t)]
            if bad:
                raise InputError(f"{where(file, path, attr.name)}: time sample at time code {float(bad[0])!r}: "
                                 "time codes must be finite numbers (USD's queries skip this one)")


def require_psd_prims_skinned(scene: Scene, correctives: str, asset: str) -> None:
    """Every prim on which the CORRECTIVES file authors psd:version must be a skinned mesh of
    the stage: directly, or through a reference or instance of a corrected asset that
    sublayers CORRECTIVES (the instanced-shot workflow). Anything else (CORRECTIVES fitted on
    another asset) would be silently ignored by eval."""
    layer = open_layer(correctives)
    reached: set[str] = set()
    for info in scene.skinned_meshes():
        reached |= {str(s.path) for s in scene.prim(info.path).GetPrimStack() if s.layer.identifier == layer.identifier}
    stray = [p for p in psd_prims(layer) if p not in reached]
    if stray:
        raise InputError(f"{where(correctives, stray[0])}: has correctives but is not a skinned mesh of {asset} "
                         "(CORRECTIVES fitted on another asset?): eval would ignore them")


def check_corrective_indices(scene: Scene, mesh: str, channels: Sequence[str], point_count: int) -> None:
    """The BlendShapes behind channels must index only the mesh's points (a CORRECTIVES layer
    fitted on a denser mesh at the same path would be silently clipped by UsdSkel)."""
    for shape in read_corrective_shapes(scene, mesh, channels):
        if len(shape.indices) and (shape.indices.min() < 0 or shape.indices.max() >= point_count):
            raise InputError(f"{where(scene.label, mesh + '/' + shape.name, 'pointIndices')}: indices outside the "
                             f"{point_count} points of the asset's mesh")


def _same_property(prop: Usd.Property, other: Usd.Property | None) -> bool:
    """Same composed value: relationship targets, or attribute default and time samples."""
    if other is None or not other.IsValid():
        return False
    if isinstance(prop, Usd.Relationship) != isinstance(other, Usd.Relationship):
        return False
    if isinstance(prop, Usd.Relationship):
        return list(prop.GetTargets()) == list(other.GetTargets())
    times = list(prop.GetTimeSamples())
    if times != list(other.GetTimeSamples()):
        return False
    return all(_same_value(prop.Get(t), other.Get(t)) for t in [Usd.TimeCode.Default(), *times])


def _same_value(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    try:
        return bool(a == b)
    except (TypeError, ValueError):
        return False


def read_corrective_shapes(scene: Scene, mesh: str, channels: Sequence[str]) -> list:
    """The BlendShapes behind the given channels of mesh, as ``BlendShapeData`` (to carry
    groups a fit does not touch into the updated CORRECTIVES layer unchanged)."""
    from .write import BlendShapeData

    names, targets = existing_blend_shapes(scene, mesh)
    by_channel = dict(zip(names, targets, strict=True))
    out = []
    for channel in channels:
        target = by_channel.get(channel)
        prim = scene.prim(target) if target else None
        if not prim or not prim.IsA(UsdSkel.BlendShape):
            raise InputError(f"{where(scene.label, mesh, 'skel:blendShapeTargets')}: no BlendShape for channel {channel!r}")
        shape = UsdSkel.BlendShape(prim)
        offsets = np.array(shape.GetOffsetsAttr().Get() or [], dtype=np.float64).reshape(-1, 3)
        indices = np.array(shape.GetPointIndicesAttr().Get() or [], dtype=np.int64)
        normals = shape.GetNormalOffsetsAttr().Get()
        out.append(BlendShapeData(
            name=prim.GetName(), channel=channel, indices=indices, offsets=offsets,
            normal_offsets=np.array(normals, dtype=np.float64).reshape(-1, 3) if normals else None,
        ))
    return out


def psd_prims(layer: Sdf.Layer) -> list[str]:
    """Prims on which layer itself authors psd:version (a CORRECTIVES layer's meshes), sorted."""
    found: list[str] = []

    def visit(path: Sdf.Path) -> None:
        if path.IsPropertyPath() and path.name == "psd:version":
            found.append(str(path.GetPrimPath()))

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return sorted(found)


def stray_point_prims(layer: Sdf.Layer, skinned: set[str]) -> list[str]:
    """Prims that have points time samples in layer but are not skinned meshes (sorted)."""
    stray: list[str] = []

    def visit(path: Sdf.Path) -> None:
        if path.IsPropertyPath() and path.name == "points" and layer.ListTimeSamplesForPath(path):
            prim = str(path.GetPrimPath())
            if prim not in skinned:
                stray.append(prim)

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return sorted(stray)


def existing_blend_shapes(scene: Scene, mesh: str) -> tuple[list[str], list[str]]:
    """The mesh's authored skel:blendShapes channels and their BlendShape target paths."""
    binding = UsdSkel.BindingAPI(scene.prim(mesh))
    channels = [str(c) for c in (binding.GetBlendShapesAttr().Get() or [])]
    rel = binding.GetBlendShapeTargetsRel()
    targets = [str(t) for t in rel.GetTargets()] if rel else []
    if len(targets) != len(channels):
        raise InputError(
            f"{where(scene.label, mesh, 'skel:blendShapeTargets')}: {len(targets)} targets for "
            f"{len(channels)} skel:blendShapes"
        )
    return channels, targets


def animation_components(scene: Scene, mesh: str, times: Sequence[float]):
    """(anim path, joint order, blend-shape order, [(t, translations, rotations, scales, weights)])."""
    _, skel_query = scene.query(mesh)
    anim = skel_query.GetAnimQuery()
    path = str(anim.GetPrim().GetPath())
    order = [str(c) for c in anim.GetBlendShapeOrder()]
    samples = []
    for t in times:
        components = anim.ComputeJointLocalTransformComponents(t)
        if components is None:
            raise InputError(f"{where(scene.label, path)}: UsdSkel cannot read the joint transforms at time {t:g}")
        weights = anim.ComputeBlendShapeWeights(t) if order else None
        samples.append((t, *components, weights))
    return path, [str(j) for j in anim.GetJointOrder()], order, samples


def validate_skinning(scene: Scene, mesh: str) -> list[str]:
    """Refuse influences UsdSkel would mis-skin; return warnings (weights not summing to 1).

    Checks: jointIndices/jointWeights authored, sizes agree with the points and the element
    size, indices inside the joint list the mesh uses, weights finite, >= 0, not all zero."""
    query, skel_query = scene.query(mesh)
    label = where(scene.label, mesh)
    binding = UsdSkel.BindingAPI(scene.prim(mesh))
    ind_pv, w_pv = binding.GetJointIndicesPrimvar(), binding.GetJointWeightsPrimvar()
    if not ind_pv or not ind_pv.HasAuthoredValue() or not w_pv or not w_pv.HasAuthoredValue():
        raise InputError(f"{label}: no primvars:skel:jointIndices/jointWeights: the mesh has no skin influences")
    indices = np.array(ind_pv.Get() or [], dtype=np.int64)
    weights = np.array(w_pv.Get() or [], dtype=np.float64)
    k = max(1, int(ind_pv.GetElementSize()))
    k_weights, interp = max(1, int(w_pv.GetElementSize())), (ind_pv.GetInterpolation(), w_pv.GetInterpolation())
    if k_weights != k or interp[0] != interp[1]:
        raise InputError(
            f"{label}: jointWeights has elementSize {k_weights} ({interp[1]}) and jointIndices {k} ({interp[0]}): "
            "UsdSkel needs one weight per joint index, so it cannot skin these points"
        )
    n = len(scene.rest_points(mesh))
    constant = ind_pv.GetInterpolation() == UsdGeom.Tokens.constant
    expected = k if constant else n * k
    if len(indices) != expected or len(weights) != len(indices):
        raise InputError(
            f"{label}: jointWeights has {len(weights)} values and jointIndices {len(indices)}, for {n} points "
            f"with {k} influences each (expected {expected} of each)"
        )
    joints = query.GetJointOrder() or skel_query.GetJointOrder()
    if len(indices) and (indices.min() < 0 or indices.max() >= len(joints)):
        first = int(np.nonzero((indices < 0) | (indices >= len(joints)))[0][0])
        raise InputError(
            f"{label}: joint index {indices[first]} out of range at point {first // k} "
            f"(the mesh uses {len(joints)} joints, indices 0..{len(joints) - 1})"
        )
    w = weights.reshape(-1, k)
    if not np.all(np.isfinite(w)):
        raise InputError(f"{label}: jointWeights contain NaN or inf (point {int(np.nonzero(~np.isfinite(w))[0][0])})")
    if np.any(w < 0):
        raise InputError(f"{label}: negative jointWeights (point {int(np.nonzero(w < 0)[0][0])})")
    sums = w.sum(axis=1)
    if np.any(sums <= 0):
        raise InputError(f"{label}: all-zero jointWeights at point {int(np.nonzero(sums <= 0)[0][0])}: it follows no joint")
    notes = []
    off = np.abs(sums - 1.0) > 1e-3
    if off.any():
        notes.append(f"{label}: jointWeights of {int(off.sum())} point(s) do not sum to 1 (UsdSkel uses them as they are)")
    skel = skel_query.GetSkeleton()
    skel_joints = skel_query.GetJointOrder()
    for name, attr in (("bindTransforms", skel.GetBindTransformsAttr()), ("restTransforms", skel.GetRestTransformsAttr())):
        value = attr.Get()
        if value is None and name == "restTransforms":
            continue
        where_attr = where(scene.label, str(skel.GetPrim().GetPath()), name)
        if value is None or len(value) != len(skel_joints):
            raise InputError(f"{where_attr}: {0 if value is None else len(value)} matrices for {len(skel_joints)} joints")
        mats = _matrices(value)
        finite = np.nan_to_num(mats)
        singular = (np.abs(np.linalg.det(finite[:, :3, :3])) < 1e-12) | (np.abs(np.linalg.det(finite)) < 1e-12)
        bad = ~np.all(np.isfinite(mats), axis=(1, 2)) | singular
        if bad.any():
            raise InputError(f"{where_attr}: joint {str(skel_joints[int(np.argmax(bad))])!r} has a NaN, infinite, "
                             "zero-scale or singular matrix")
    return notes


def validate_animation(scene: Scene, mesh: str) -> None:
    """The bound animation must name only joints of the skeleton (UsdSkel drops others silently)."""
    _, skel_query = scene.query(mesh)
    anim = skel_query.GetAnimQuery()
    if not anim:
        return
    known = set(str(j) for j in skel_query.GetJointOrder())
    unknown = [str(j) for j in anim.GetJointOrder() if str(j) not in known]
    if unknown:
        raise InputError(
            f"{where(scene.label, str(anim.GetPrim().GetPath()), 'joints')}: joint {unknown[0]!r} is not in skeleton "
            f"<{skel_query.GetSkeleton().GetPrim().GetPath()}>"
        )
