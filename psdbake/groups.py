"""Correctives groups in one CORRECTIVES layer: read, merged with a new fit, checked, authored.

``fit --group`` replaces one group and carries every other group over unchanged; groups add
at eval, so a group must be (nearly) off at the other groups' examples (``cross_talk``).
"""

from __future__ import annotations

import warnings

import numpy as np

from .channels import channel_names
from .errors import InputError, PsdWarning, where
from .results import FitResult, MeshFit
from .usd import write as usdwrite
from .usd.author import Layer
from .usd.compose import open_layer
from .usd.read import Scene, existing_blend_shapes, read_corrective_shapes
from .usd.schema import BlendShapeData, DriverData, author_driver_data, psd_prims
from .weights import weights_at_pose


def shapes_of(m: MeshFit) -> list[BlendShapeData]:
    """The corrective BlendShapes of one fitted mesh (examples equal to plain skinning have none)."""
    if m.shapes is not None:
        return list(m.shapes)
    out = []
    for k, (ch, inv) in enumerate(zip(m.channels, m.inverses, strict=True)):
        if not ch:
            continue
        name = f"psd_{m.group}_{k:02d}"
        cn = m.normals[k] if m.normals else None
        if cn is None:
            out.append(BlendShapeData(name=name, channel=ch, indices=inv.indices, offsets=inv.offsets))
        else:  # pointIndices grown to the sculpt's 1-ring: normals change there too
            out.append(BlendShapeData(name=name, channel=ch, indices=cn.indices, offsets=cn.offsets,
                                               normal_offsets=cn.normal_offsets))
    return out


Groups = dict[str, dict[str, tuple[DriverData, list[BlendShapeData]]]]  # mesh -> group -> data


def read_correctives(asset: str, correctives: str) -> Groups:
    """Every group of an existing CORRECTIVES layer over asset: its driver data and BlendShapes."""
    owners = psd_prims(open_layer(correctives))
    scene = Scene([correctives, asset], label=correctives)
    skinned = {m.path: m for m in scene.skinned_meshes()}
    if not owners:
        raise InputError(f"{correctives}: holds no psd: correctives (not a CORRECTIVES layer written by psdbake fit)")
    out: Groups = {}
    for mesh in owners:
        if mesh not in skinned:
            raise InputError(f"{where(correctives, mesh)}: has correctives but is not a skinned mesh of {asset}")
        for group, data in scene.driver_groups(mesh):
            shapes = read_corrective_shapes(scene, mesh, channel_names(data))
            for shape in shapes:
                if len(shape.indices) and (shape.indices.min() < 0 or shape.indices.max() >= skinned[mesh].point_count):
                    raise InputError(
                        f"{where(correctives, mesh + '/' + shape.name, 'pointIndices')}: indices outside the "
                        f"{skinned[mesh].point_count} points of the asset's mesh"
                    )
            out.setdefault(mesh, {})[group] = (data, shapes)
    return out


def _combination_of(data: DriverData) -> bool:
    return bool(len(data.gates) or data.gate_groups)


def cross_talk(result: FitResult, others: Groups) -> list[str]:
    """Groups are fitted independently, so another group's correctives must be (nearly) off
    at this group's examples: its weight times its largest offset, relative to the mesh's
    diagonal, must stay under the fit tolerance, or that sculpt is not reproduced."""
    notes = []
    for m in result.meshes:
        infos = dict(others.get(m.mesh, {}))
        infos.pop(m.group, None)
        # eval refuses a layer whose drivers are not the mesh's joints, or whose gate groups are missing
        usable = {g: v for g, v in infos.items() if set(v[0].drivers) <= set(m.joints)}
        usable = {g: v for g, v in usable.items() if set(v[0].gate_groups) <= set(usable)}
        for ex, inv in zip(m.examples, m.inverses, strict=True):
            weights = weights_at_pose([(g, v[0]) for g, v in sorted(usable.items())], ex.pose, m.joints)
            for group, (data, shapes) in sorted(usable.items()):
                if _combination_of(m.driver_data) and set(data.drivers) <= set(m.drivers):
                    continue  # a combination sits on its joints' groups by design
                reach = np.array([np.abs(s.offsets).max() if len(s.offsets) else 0.0 for s in shapes])
                spill = float(np.max(np.abs(weights[group][0]) * reach)) / (inv.diagonal or 1.0)
                if spill > result.settings.rtol:
                    notes.append(
                        f"{where(result.asset, m.mesh)}: group {group!r} moves points by {spill:.2g} of the diagonal "
                        f"at example {ex.label} of group {m.group!r} (its own examples: "
                        f"{', '.join(c for c in data.center_labels if c != 'bind')}): the two groups' drivers overlap, "
                        "so that sculpt is not reproduced exactly"
                    )
    return notes


def correctives_layer(result: FitResult, update: str | None = None):
    """CORRECTIVES as an in-memory layer: BlendShapes, bindings and psd: driver data.

    update: an existing CORRECTIVES layer whose other groups are carried over unchanged;
    this fit's group replaces its namesake on the fitted meshes (on every mesh when the
    fit was not restricted with ``--mesh``). Groups are written sorted by name, so the
    layer does not depend on the order the groups were fitted in.
    """
    from . import __version__

    groups: Groups = read_correctives(result.asset, update) if update else {}
    fitted = {m.mesh for m in result.meshes}
    for mesh, per_group in groups.items():
        if not result.settings.meshes or mesh in fitted:
            for group in {m.group for m in result.meshes}:
                per_group.pop(group, None)
    for m in result.meshes:
        groups.setdefault(m.mesh, {})[m.group] = (m.driver_data, shapes_of(m))
    for note in cross_talk(result, groups):  # this fit's groups and the ones carried over
        warnings.warn(note, PsdWarning, stacklevel=2)
    return groups_layer(result.asset, groups, f"psdbake {__version__} fit: rest-space correctives (inverse PSD)")


def updated_layer(asset: str, base: str, new: Groups, doc: str) -> Layer:
    """CORRECTIVES ``base`` (a layer over asset) with the groups ``new`` written into it: each
    replaces its namesake on its mesh, every other group is carried over unchanged."""
    groups = read_correctives(asset, base)
    for mesh, per_group in new.items():
        groups.setdefault(mesh, {}).update(per_group)
    return groups_layer(asset, groups, doc)


def groups_layer(asset: str, groups: Groups, doc: str) -> Layer:
    """The correctives groups as an in-memory CORRECTIVES layer over asset (groups sorted by
    name; the asset's own blend shapes kept first on each mesh)."""
    asset_scene = Scene([asset])
    layer = usdwrite.new_layer(doc, metadata=usdwrite.asset_metadata(asset))
    for mesh in sorted(groups):
        names = sorted(groups[mesh])
        if not names:
            continue
        existing, targets = existing_blend_shapes(asset_scene, mesh)
        ours = {s.channel for g in names for s in groups[mesh][g][1]}
        keep = [(c, t) for c, t in zip(existing, targets, strict=True) if c not in ours]
        shapes = [s for g in names for s in groups[mesh][g][1]]
        usdwrite.author_blend_shapes(layer, mesh, shapes, [c for c, _ in keep], [t for _, t in keep])
        author_driver_data(layer, mesh, [(g, groups[mesh][g][0]) for g in names])
    return layer
