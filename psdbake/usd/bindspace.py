"""A skinned mesh in its skeleton's bind space: what ``psdbake mirror`` reads from the asset.

Mirroring is a reflection of the skeleton's bind space (where UsdSkel's ``bindTransforms``
live), so it needs every joint's skeleton-space bind transform, the joints' hierarchy, their
bind local transforms (the new group's ``psd:driverBindRotations``) and the mesh's rest
points taken into that space by its ``geomBindTransform``. Matrices stay in Gf's row-vector
convention (p' = p . M), as ``read`` returns them.
"""

from __future__ import annotations

import numpy as np

from ..arrays import is_singular
from ..errors import InputError, where
from ..model.rig import BindSpace, SkinnedMesh
from .read import Scene, matrices


def read_bind_space(scene: Scene, info: SkinnedMesh) -> BindSpace:
    """The mesh's bind space; refuses a geomBindTransform that is not finite and invertible
    (its offsets could not be carried into skeleton space and back)."""
    mesh = info.path
    query, skel_query = scene.query(mesh)
    skel = skel_query.GetSkeleton()
    skel_path = str(skel.GetPrim().GetPath())
    bind_local = scene.bind_local_transforms(mesh)  # validates bindTransforms
    world = matrices(skel.GetBindTransformsAttr().Get() or [])
    parents = np.array(skel_query.GetTopology().GetParentIndices(), dtype=np.int64)
    geom = matrices([query.GetGeomBindTransform()])[0]
    if is_singular(geom[:3, :3]):
        raise InputError(f"{where(scene.label, mesh, 'primvars:skel:geomBindTransform')}: not a finite, invertible "
                         "transform: the mesh's points cannot be taken to skeleton space")
    rest = scene.rest_points(mesh)
    return BindSpace(
        mesh=mesh, skeleton=skel_path, skel_root=info.skel_root, joints=info.joints, parents=parents,
        bind_world=world, bind_local=bind_local, geom_bind=geom, rest=rest @ geom[:3, :3] + geom[3, :3],
    )
