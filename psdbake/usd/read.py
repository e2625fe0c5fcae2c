"""Stage -> skinned meshes, rest points, poses and sculpted examples (validated, sorted).

Composition: every command opens an in-memory root layer whose sublayers are the
given files, strongest first (e.g. ``[EXAMPLES, ASSET]``), so ``POSES``/``EXAMPLES``/
``ANIM`` layers need not reference ASSET. Inputs are opened read-only and never
saved.

Gf convention: matrices are row-vector (p' = p . M); they are converted to numpy
(4, 4) arrays unchanged and interpreted in ``posespace``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from pxr import Sdf, Usd, UsdGeom, UsdSkel, Vt

from ..errors import InputError, where
from ..model.posespace import undefined_rotations
from ..model.rig import Skin, SkinnedMesh
from .compose import compose
from .diagnostics import first_line
from .schema import BlendShapeData, DriverData, read_blend_shape, read_groups
from .valuetypes import Checked, check_value_types


def hidden_from_usdskel(stage: Usd.Stage) -> list[tuple[str, str]]:
    """(mesh, ancestor) for each point-based prim bound to a skeleton below a SkelRoot that
    UsdSkel never reaches: its traversal does not descend below a prim that is not imageable
    (a typeless ``def "Geo"``, a Material), so no viewer, no BakeSkinning and no psdbake
    command skins that mesh, although its binding is authored."""
    out = []
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        if not (prim.IsA(UsdGeom.PointBased) and prim.HasAPI(UsdSkel.BindingAPI)):
            continue
        if not UsdSkel.BindingAPI(prim).GetInheritedSkeleton():
            continue
        blocker, parent = None, prim.GetParent()
        while parent and not parent.IsPseudoRoot() and not parent.IsA(UsdSkel.Root):
            if not parent.IsA(UsdGeom.Imageable):
                blocker = parent
            parent = parent.GetParent()
        if blocker is not None and parent and parent.IsA(UsdSkel.Root):
            out.append((str(prim.GetPath()), str(blocker.GetPath())))
    return out


def skel_roots(stage: Usd.Stage) -> list[Usd.Prim]:
    """The stage's SkelRoot prims, instance proxies included."""
    return [p for p in stage.Traverse(Usd.TraverseInstanceProxies()) if p.IsA(UsdSkel.Root)]


def why_hidden(stage: Usd.Stage, blocker: str) -> str:
    """Why UsdSkel does not skin a mesh below ``blocker`` (``hidden_from_usdskel``), and the fix."""
    kind = stage.GetPrimAtPath(blocker).GetTypeName()
    what = f'has no type (def "{blocker.rsplit("/", 1)[-1]}")' if not kind else f"is a {kind}, not an imageable prim"
    return (f"bound to a skeleton, but UsdSkel never skins it: its ancestor <{blocker}> {what}, and UsdSkel does not "
            f"look below such prims; give <{blocker}> a type such as Xform or Scope")


def _invalid_skeleton(prim: Usd.Prim) -> str:
    """Why UsdSkel refuses a skeleton's joint list (its query is invalid), in the list's terms."""
    joints = [str(j) for j in UsdSkel.Skeleton(prim).GetJointsAttr().Get() or []]
    if not joints:
        return "the skeleton lists no joints"
    index: dict[str, int] = {}
    for i, joint in enumerate(joints):
        if joint in index:
            return f"joint {joint!r} is listed twice (indices {index[joint]} and {i})"
        index.setdefault(joint, i)
    for i, joint in enumerate(joints):
        parent = joint.rpartition("/")[0]
        if parent in index and index[parent] > i:
            return (f"joint {joint!r} (index {i}) is listed before its parent {parent!r} (index {index[parent]}): "
                    "UsdSkel needs every joint after its parent")
    valid, reason = UsdSkel.Topology(Vt.TokenArray(joints)).Validate()
    if not valid:
        return f"UsdSkel refuses the joint hierarchy ({first_line(reason)})"
    return "UsdSkel refuses the skeleton"


def matrices(values) -> NDArray[np.float64]:
    """Vt.Matrix4dArray (or a list of Gf.Matrix4d) -> (n, 4, 4) float64, row-vector convention."""
    return np.array(values, dtype=np.float64).reshape(-1, 4, 4)


#: The prim fields that author a composition arc: where an instance's prototype comes from.
_ARC_KEYS = ("references", "payload", "inheritPaths", "specializes")


class Scene:
    """A composed stage with its UsdSkel cache: the skinned meshes and their skeletons."""

    def __init__(self, files: Sequence[str | Sdf.Layer], label: str | None = None, *, checked: Checked = Checked.ALL
                 ) -> None:
        """checked: which attributes' value types to check (``valuetypes.Checked``): a stage
        that never reads its BlendShapes' offsets (eval's weights) leaves them unchecked."""
        self.files = list(files)
        self.label = label or str(self.files[0])
        self.stage = compose(self.files)
        check_value_types(self.stage, self.label, checked)
        self.cache = UsdSkel.Cache()
        self._instances: dict[str, tuple[str, str] | None] = {}  # instance_of, per path
        # mesh -> (skinning query, skeleton query, owning SkelRoot, bound Skeleton's path)
        self._targets: dict[str, tuple[UsdSkel.SkinningQuery, UsdSkel.SkeletonQuery, str, str]] = {}
        predicate = Usd.TraverseInstanceProxies()
        self._roots = roots = skel_roots(self.stage)
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
                raise InputError(f"{where(self.label, skeleton, 'joints')}: {_invalid_skeleton(self.prim(skeleton))}, "
                                 f"so it cannot skin <{path}>")
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
                    point_count=self.point_count(path),
                )
            )
        return out

    def instance_of(self, path: str) -> tuple[str, str] | None:
        """(instance root, '@asset@</prim>' it instances) when path is inside an instance,
        else None: where psdbake's output for path would have to go instead. Remembered per
        path: every black box asks (once per frame of a points cache)."""
        if path not in self._instances:
            self._instances[path] = self._instance_of(path)
        return self._instances[path]

    def _instance_of(self, path: str) -> tuple[str, str] | None:
        prim = self.stage.GetPrimAtPath(path)
        if not prim or not prim.IsInstanceProxy():
            return None
        while prim and not prim.IsInstance():
            prim = prim.GetParent()
        arcs = list(prim.GetPrimIndex().rootNode.children)
        if not arcs:
            return str(prim.GetPath()), "its prototype"
        source = arcs[0].layerStack.identifier.rootLayer
        if source.anonymous:  # an arc inside the inputs (``references = </Proto>``): name the file authoring it
            authors = [spec.layer for spec in prim.GetPrimStack() if not spec.layer.anonymous
                       and any(spec.HasInfo(key) for key in _ARC_KEYS)]
            source = authors[0] if authors else source
        name = self.label if source.anonymous else source.identifier
        return str(prim.GetPath()), f"@{name}@<{arcs[0].path}>"

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

    def has_skel_root(self) -> bool:
        """Whether the composed stage holds a SkelRoot (``require_skinned`` refuses one without)."""
        return bool(self._roots)

    def require_skinned(self) -> None:
        """Raise InputError when the stage has no SkelRoot or no skinned mesh."""
        roots = self._roots
        if not roots:
            raise InputError(f"{self.label}: no SkelRoot prim found (UsdSkel needs one above the skinned meshes)")
        if not self._targets:
            for mesh, blocker in hidden_from_usdskel(self.stage)[:1]:
                raise InputError(f"{where(self.label, mesh)}: {why_hidden(self.stage, blocker)}")
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

    def file_layers(self) -> tuple[Sdf.Layer, ...]:
        """Every file layer the stage reads (sorted by identifier; in-memory ones left out):
        what a caller holds to read the same files again later without parsing them twice
        (USD finds an open layer instead of reading its file)."""
        return tuple(sorted((layer for layer in self.stage.GetUsedLayers() if not layer.anonymous),
                            key=lambda layer: layer.identifier))

    def driver_groups(self, mesh: str) -> list[tuple[str, DriverData]]:
        """Every correctives group's psd: driver data on mesh, validated against the bound
        skeleton's joints, sorted by group name; empty if the mesh has none."""
        _, skel_query = self.query(mesh)
        joints = [str(j) for j in skel_query.GetJointOrder()]
        return read_groups(self.prim(mesh), self.label, joints, str(skel_query.GetSkeleton().GetPrim().GetPath()))

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

    def point_count(self, mesh: str) -> int:
        """``len(self.rest_points(mesh))``, refusing the same points, without their float64
        copy: UsdGeom's float32 array read in place (25 ms of copying at 1M points, and a fit
        lists the skinned meshes several times). Anything unusual takes rest_points' path."""
        value = UsdGeom.PointBased(self.prim(mesh)).GetPointsAttr().Get(Usd.TimeCode.Default())
        try:
            view = np.asarray(value)
        except (TypeError, ValueError):
            view = None
        if view is not None and view.dtype.kind == "f" and view.size % 3 == 0 and np.isfinite(view).all():
            return view.size // 3
        return len(self.rest_points(mesh))

    def animation_times(self, mesh: str) -> list[float]:
        """Authored time samples of the skeleton's animation (joints and blend shapes)."""
        _, skel_query = self.query(mesh)
        anim = skel_query.GetAnimQuery()
        if not anim:
            return []
        times = set(anim.GetJointTransformTimeSamples()) | set(anim.GetBlendShapeWeightTimeSamples())
        return sorted(float(t) for t in times)

    def blend_shape_weights(self, mesh: str, times: NDArray[np.float64]) -> tuple[list[str], NDArray[np.float64]]:
        """The bound animation's own blend-shape channels and their weights at times (f, c)."""
        _, skel_query = self.query(mesh)
        anim = skel_query.GetAnimQuery()
        order = [str(c) for c in anim.GetBlendShapeOrder()] if anim else []
        weights = np.zeros((len(times), len(order)))
        if order:
            for f, t in enumerate(times):
                w = anim.ComputeBlendShapeWeights(float(t))
                if w is not None and len(w) == len(order):
                    weights[f] = np.array(w, dtype=np.float64)
        return order, weights

    def animation_prim(self, mesh: str) -> str | None:
        _, skel_query = self.query(mesh)
        anim = skel_query.GetAnimQuery()
        return str(anim.GetPrim().GetPath()) if anim else None

    def joint_local_transforms(self, mesh: str, time: float) -> NDArray[np.float64]:
        """Skeleton-order local joint transforms at time (UsdSkel's own computation)."""
        _, skel_query = self.query(mesh)
        local = matrices(skel_query.ComputeJointLocalTransforms(Usd.TimeCode(time)) or [])
        if len(local) != len(skel_query.GetJointOrder()):
            skel = str(skel_query.GetSkeleton().GetPrim().GetPath())
            raise InputError(
                f"{where(self.label, skel)}: UsdSkel cannot pose the skeleton at time {time:g} "
                "(restTransforms missing or the wrong size for joints the animation does not cover)"
            )
        return local

    def skin(self, mesh: str) -> Skin:
        """Each point's joint influences in skeleton order (UsdSkel's own: a rigid binding's one
        set given to every point, the mesh's own ``skel:joints`` order mapped onto the
        skeleton's) and the skeleton's parent indices."""
        query, skel_query = self.query(mesh)
        count = self.point_count(mesh)
        influences = query.ComputeVaryingJointInfluences(count, Usd.TimeCode.Default())
        if influences is None:
            raise InputError(f"{where(self.label, mesh)}: UsdSkel cannot compute joint influences")
        skeleton = [str(j) for j in skel_query.GetJointOrder()]
        own = [str(j) for j in query.GetJointOrder() or []]
        remap = np.array([skeleton.index(j) if j in skeleton else -1 for j in own] if own else range(len(skeleton)),
                         dtype=np.int64)
        per_point = max(len(influences[0]) // max(count, 1), 1)
        raw = np.array(influences[0], dtype=np.int64).reshape(-1, per_point)
        valid = (raw >= 0) & (raw < len(remap))
        indices = np.where(valid, remap[np.clip(raw, 0, max(len(remap) - 1, 0))], -1)
        weights = np.where(valid, np.array(influences[1], dtype=np.float64).reshape(-1, per_point), 0.0)
        parents = np.array(skel_query.GetTopology().GetParentIndices(), dtype=np.int64)
        return Skin(indices=indices, weights=weights, parents=parents)

    def bind_local_transforms(self, mesh: str) -> NDArray[np.float64]:
        """Local transforms of the bind pose (where skinning is the identity).

        UsdSkel's bindTransforms are skeleton-space; local_j = bind_j . bind_parent^-1.
        """
        _, skel_query = self.query(mesh)
        skel = skel_query.GetSkeleton()
        world = matrices(skel.GetBindTransformsAttr().Get() or [])
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


def corrective_targets(scene: Scene, mesh: str, channels: Sequence[str]) -> list[Usd.Prim]:
    """The BlendShape prim behind each of the given channels of mesh, in order."""
    names, targets = existing_blend_shapes(scene, mesh)
    by_channel = dict(zip(names, targets, strict=True))
    out = []
    for channel in channels:
        target = by_channel.get(channel)
        prim = scene.prim(target) if target else None
        if not prim or not prim.IsA(UsdSkel.BlendShape):
            raise InputError(f"{where(scene.label, mesh, 'skel:blendShapeTargets')}: no BlendShape for channel {channel!r}")
        out.append(prim)
    return out


def holds_skel_root(path: str) -> bool:
    """Whether the file on its own defines a SkelRoot: for a refusal's hint only (an unreadable
    file holds none; the command's own checks say what is wrong with it)."""
    try:
        stage = Usd.Stage.Open(path, Usd.Stage.LoadAll)
    except Exception:  # USD raises Tf errors of its own types for unreadable files
        return False
    return bool(stage) and bool(skel_roots(stage))


def open_layers(paths: Sequence[str]) -> tuple[Sdf.Layer, ...]:
    """The layers of these files that are open now (by anyone); none is opened or parsed."""
    found = (Sdf.Layer.Find(path) for path in paths)
    return tuple(layer for layer in found if layer)


def read_corrective_shapes(scene: Scene, mesh: str, channels: Sequence[str]) -> list[BlendShapeData]:
    """The BlendShapes behind the given channels of mesh (to carry groups a fit does not
    touch into the updated CORRECTIVES layer unchanged)."""
    return [read_blend_shape(prim, channel)
            for prim, channel in zip(corrective_targets(scene, mesh, channels), channels, strict=True)]


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




