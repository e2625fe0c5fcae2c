"""Correctives groups in one CORRECTIVES layer: read, merged with a new fit, checked, authored.

``fit --group`` replaces one group and carries every other group over unchanged; groups add
at eval, so a group must be (nearly) off at the other groups' examples (``cross_talk``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import FitError, InputError, SettingError, where
from ..lookup import did_you_mean
from ..model.channels import channel_names, short_name
from ..model.data import BlendShapeData, DriverData
from ..model.weights import weights_at_pose
from ..results import FitResult, MeshFit
from ..usd import provenance
from ..usd import write as usdwrite
from ..usd.author import Layer
from ..usd.compose import open_layer
from ..usd.read import Scene, existing_blend_shapes, read_corrective_shapes
from ..usd.schema import author_driver_data, psd_prims


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


def fitted_groups(result: FitResult) -> Groups:
    """The groups one fit made, as written (mesh -> group -> driver data and BlendShapes)."""
    out: Groups = {}
    for m in result.meshes:
        out.setdefault(m.mesh, {})[m.group] = (m.driver_data, shapes_of(m))
    return out


def read_correctives(asset: str, correctives: str) -> Groups:
    """Every group of an existing CORRECTIVES layer over asset: its driver data and BlendShapes."""
    owners = psd_prims(open_layer(correctives))
    scene = Scene([correctives, asset], label=correctives)
    skinned = {m.path: m for m in scene.skinned_meshes()}
    if not owners:
        if provenance.existing_kind(correctives) == "stack":
            raise InputError(f"{correctives}: a stack, not a CORRECTIVES layer: give the CORRECTIVES layer it stacks "
                             f"(psdbake inspect {correctives} names each layer's role)")
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
    return bool(len(data.gates) or data.gate_groups or len(data.ramp_gates))


def cross_talk(result: FitResult, others: Groups) -> list[str]:
    """Groups fitted independently must leave each other's examples alone: another group's
    correctives must be (nearly) off at this group's examples, its weight times its largest
    offset, relative to the mesh's diagonal, under the fit tolerance, or that sculpt is not
    reproduced. The groups of one default fit of a mesh are fitted together, each example
    against all of them (``decompose``): among themselves there is nothing to check."""
    notes = []
    together = {(m.mesh, m.group) for m in result.meshes if m.role}
    for m in result.meshes:
        infos = dict(others.get(m.mesh, {}))
        infos.pop(m.group, None)
        if m.role:
            infos = {g: v for g, v in infos.items() if (m.mesh, g) not in together}
            if not infos:
                continue
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


@dataclass(frozen=True)
class GroupChanges:
    """What writing a CORRECTIVES layer did to the groups already there (by group name)."""

    added: tuple[str, ...] = ()
    replaced: tuple[str, ...] = ()
    kept: tuple[str, ...] = ()
    removed: tuple[str, ...] = ()
    protected: tuple[str, ...] = ()  # mirror: fitted from sculpts, so left alone
    renamed: tuple[str, ...] = ()  # "old -> new"
    origins: Mapping[str, str] = field(default_factory=dict)  # replaced and protected groups: where they came from
    routine: str = ""  # the origin text a group replaced by this kind of write has routinely ("fit of", ...)

    def shown(self, names: Sequence[str], limit: int | None = None, width: int | None = None) -> str:
        """Group names, each with where it came from unless that is routine for this write (a fit
        replacing an earlier fit's group): a TD wants to see the others, every one of them. Of
        the routine ones at most ``limit`` are named (the rest counted), each shortened to
        ``width`` bytes as the layer's names are (``short_name``)."""
        parts, routine = [], 0
        for n in names:
            if not (self.routine and self.origins.get(n, "").startswith(self.routine)):
                parts.append(f"{n} ({self.origins.get(n, 'origin not recorded')})")
            elif limit is None or routine < limit:
                parts.append(n if width is None else short_name(n, width))
                routine += 1
        more = len(names) - len(parts)
        return ", ".join(parts) + (f" and {more} more" if more else "")


def names_of(groups: Groups) -> set[str]:
    return {g for per in groups.values() for g in per}


def origin_text(record: Mapping[str, Any] | None) -> str:
    """Where a group came from, in words, from its provenance record."""
    if not record:
        return "origin not recorded"
    origin = str(record.get("origin", "?"))
    if origin == "mirror":
        return f"mirrored from {record.get('source', '?')}"
    examples = [e.get("path", "?") if isinstance(e, Mapping) else str(e) for e in record.get("examples") or []]
    return f"{origin} of {', '.join(examples)}" if examples else origin


def is_sculpted(record: Mapping[str, Any] | None) -> bool:
    """A group fitted from sculpts (or of unknown origin, which is treated the same: it may be)."""
    return not record or record.get("origin") != "mirror"


def merged_groups(existing: Groups, new: Groups, meshes: Sequence[str] = ()) -> Groups:
    """existing with every group of new written in: each replaces its namesake (on every mesh
    when ``meshes`` is empty, else only on those), every other group carried over unchanged."""
    out: Groups = {mesh: dict(per) for mesh, per in existing.items()}
    names = names_of(new)
    for mesh, per_group in out.items():
        if not meshes or mesh in meshes:
            for group in names:
                per_group.pop(group, None)
    for mesh, per_group in new.items():
        out.setdefault(mesh, {}).update(per_group)
    return out


def changes_between(before: Groups, after: Groups, written: Groups,
                    records: Mapping[str, Mapping[str, Any]], routine: str = "") -> GroupChanges:
    """Which groups a write added, replaced (and where those came from), kept and removed."""
    old, new, mine = names_of(before), names_of(after), names_of(written)
    return GroupChanges(
        added=tuple(sorted(mine - old)),
        replaced=tuple(sorted(mine & old)),
        kept=tuple(sorted((old & new) - mine)),
        removed=tuple(sorted(old - new)),
        origins={g: origin_text(records.get(g)) for g in old},
        routine=routine,
    )


def _driver_names(data: DriverData) -> str:
    return ", ".join(d.split("/")[-1] for d in data.drivers)


def check_not_doubled(groups: Groups, written: Groups, label: str) -> None:
    """Refuse two groups that would both correct the same joint's poses: groups add at eval, so
    a second group driven by a joint another group already corrects applies that correction
    twice. Combinations (gated groups) sit on their joints' groups by design and are exempt."""
    for mesh in sorted(written):
        for group, (data, _) in sorted(written[mesh].items()):
            if _combination_of(data):
                continue
            for other, (odata, _) in sorted(groups.get(mesh, {}).items()):
                if other == group or _combination_of(odata):
                    continue
                shared = sorted(set(data.drivers) & set(odata.drivers))
                if shared:
                    joints = ", ".join(j.split("/")[-1] for j in shared)
                    raise FitError(
                        f"{where(label, mesh)}: group {group!r} (drivers {_driver_names(data)}) would double the "
                        f"correction of group {other!r} (drivers {_driver_names(odata)}): both are driven by {joints}. "
                        f"Fit into {other!r} instead (--group {other}), or remove it first (psdbake groups {label} "
                        f"--remove {other})"
                    )


def check_name_case(existing: Groups, written: Groups, label: str) -> None:
    """A group name that differs from an existing one only in case (``l_elbow`` beside
    ``L_Elbow``) is almost always the same region named twice: refused, naming the existing one."""
    old = names_of(existing)
    for name in sorted(names_of(written)):
        twins = sorted(g for g in old if g != name and g.lower() == name.lower())
        if twins:
            raise SettingError("group", name, f"{label} already has group {twins[0]!r}: did you mean {twins[0]}?")


def without_groups(groups: Groups, names: Sequence[str], label: str) -> Groups:
    """groups without the named ones, on every mesh; refuses a name the layer lacks and a group
    that a remaining combination is gated by (the combination would lose its gate)."""
    have = sorted(names_of(groups))
    for name in names:
        if name not in have:
            raise SettingError("remove", name, f"{label} has no such group (groups: {', '.join(have)})"
                               f"{did_you_mean(name, have)}")
    out: Groups = {mesh: {g: v for g, v in per.items() if g not in names} for mesh, per in groups.items()}
    for mesh, per in out.items():
        for group, (data, _) in sorted(per.items()):
            lost = sorted(set(data.gate_groups) & set(names))
            if lost:
                raise SettingError("remove", lost[0], f"{where(label, mesh)}: combination {group!r} is gated by it: "
                                   f"remove {group!r} too, or keep {lost[0]!r}")
    return {mesh: per for mesh, per in out.items() if per}


def renamed_group(groups: Groups, old: str, new: str, label: str) -> Groups:
    """groups with group old named new on every mesh: its psd: namespace, its BlendShapes and
    channels (``psd_<group>_...``, so the names keep saying whose they are) and the gates of
    combinations that sit on it."""
    from ..settings import is_group_name

    have = sorted(names_of(groups))
    if old not in have:
        raise SettingError("rename", old, f"{label} has no such group (groups: {', '.join(have)}){did_you_mean(old, have)}")
    if not is_group_name(new):
        raise SettingError("rename", new, "must be an identifier (letters, digits, _)")
    if any(g != old and g.lower() == new.lower() for g in have):
        raise SettingError("rename", new, f"{label} already has a group of that name")
    before, after = f"psd_{old}_", f"psd_{new}_"

    def swap(name: str) -> str:
        return after + name[len(before):] if name.startswith(before) else name

    out: Groups = {}
    for mesh, per in groups.items():
        out[mesh] = {}
        for group, (data, shapes) in per.items():
            if group == old:
                data = dataclasses.replace(data, shapes=[swap(n) for n in data.shapes],
                                           channels=[swap(n) for n in data.channels])
                shapes = [dataclasses.replace(b, name=swap(b.name), channel=swap(b.channel)) for b in shapes]
            data = dataclasses.replace(data, gate_groups=[new if g == old else g for g in data.gate_groups])
            out[mesh][new if group == old else group] = (data, shapes)
    return out


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
