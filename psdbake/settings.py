"""What a fit is asked to do: the options of ``psdbake fit``, validated in parameter names.

The library speaks in its own parameter names (``rtol``, ``sigma``); the CLI maps them to
its flags (``--tolerance``, ``--sigma``) when it shows a refusal.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from . import tolerances as tol
from .errors import SettingError
from .model.data import RESERVED_GROUP_NAMES
from .model.posespace import POSE_SPACES
from .model.rbf import KERNELS


@dataclass(frozen=True)
class FitSettings:
    """Options of ``psdbake fit``; defaults are the documented ones."""

    drivers: tuple[str, ...] = ()  # empty: every joint rotated in any example
    kernel: str = "gaussian"
    sigma: float | None = None  # None: automatic (rbf.auto_sigma)
    degree: int | None = None  # None: rbf.default_degree(kernel)
    smoothing: float = 0.0
    rest_example: bool = True
    pose_space: str = "rotationVector"  # a key of posespace.POSE_SPACES
    twist_axis: tuple[float, float, float] | None = None  # swingTwist: axis in each driver's bind frame
    clamp_weights: bool = False  # clamp b(x) to [0, 1] at eval time (stored, off by default)
    normalize_weights: bool = False  # divide b(x) by max(1, sum) at eval time (stored, off by default)
    rtol: float = tol.INVERSE_RTOL
    meshes: tuple[str, ...] = ()  # empty: every mesh with examples
    deformers: tuple[str, ...] = ()
    group: str | None = None  # one named correctives group; None: local, additive groups (regions.py)

    def __post_init__(self) -> None:
        for name in ("drivers", "meshes", "deformers"):  # one name alone is a list of one, not of its letters
            value = getattr(self, name)
            if isinstance(value, str):
                object.__setattr__(self, name, (value,))
            elif not isinstance(value, tuple | list) or not all(isinstance(v, str) for v in value):
                raise SettingError(name, value, "must be a list of names")
            else:
                object.__setattr__(self, name, tuple(value))
        for name, allow_zero in (("sigma", False), ("smoothing", True), ("rtol", False)):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int | float | np.floating)):
                raise SettingError(name, value, "must be a number")
            if value is not None and not (np.isfinite(value) and (value >= 0 if allow_zero else value > 0)):
                raise SettingError(name, value, f"must be a {'non-negative' if allow_zero else 'positive'} number")
        if self.group is not None and (
            not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", self.group) or self.group in RESERVED_GROUP_NAMES
        ):
            raise SettingError("group", self.group, "must be an identifier (letters, digits, _; not "
                               f"{' or '.join(repr(n) for n in RESERVED_GROUP_NAMES)})")
        if self.kernel not in KERNELS:
            raise SettingError("kernel", self.kernel, f"choose one of {', '.join(sorted(KERNELS))}")
        if self.pose_space not in POSE_SPACES:
            raise SettingError("pose_space", self.pose_space, f"choose one of {', '.join(POSE_SPACES)}")
        if self.twist_axis is not None and not (
            np.all(np.isfinite(self.twist_axis)) and np.linalg.norm(self.twist_axis) > 0
        ):
            raise SettingError("twist_axis", self.twist_axis, "must be a non-zero finite vector")
        if POSE_SPACES[self.pose_space].needs_twist_axis and self.twist_axis is None:
            raise SettingError("pose_space", self.pose_space, "needs twist_axis (the twist axis in each driver's "
                               "bind frame)")


#: Mirror planes of ``psdbake mirror``: the skeleton-space plane through the origin normal to this axis.
MIRROR_PLANES = ("x", "y", "z")


def is_group_name(name: str) -> bool:
    """A group name becomes a psd: attribute namespace: an identifier, not one of the schema's own names."""
    return bool(re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name)) and name not in RESERVED_GROUP_NAMES


@dataclass(frozen=True)
class MirrorSettings:
    """Options of ``psdbake mirror``: the joint map (``REGEX=REPLACEMENT`` rules), the mirror
    plane, and one group (renamed ``as_name``) or, without ``group``, every mappable group."""

    joints: tuple[str, ...]  # REGEX=REPLACEMENT rules: a name takes the first rule whose REGEX it contains
    plane: str = "x"
    group: str | None = None
    as_name: str | None = None

    def __post_init__(self) -> None:
        if not self.joints:
            raise SettingError("joints", "", "give at least one REGEX=REPLACEMENT rule (e.g. 'L_=R_')")
        for rule in self.joints:
            pattern, eq, _ = rule.rpartition("=")
            if not eq or not pattern:
                raise SettingError("joints", rule, "must be REGEX=REPLACEMENT (e.g. 'L_=R_' or '(^|/)l_=\\1r_')")
            try:
                re.compile(pattern)
            except re.error as exc:
                raise SettingError("joints", rule, f"REGEX is not a regular expression ({exc})") from None
        if self.plane not in MIRROR_PLANES:
            raise SettingError("plane", self.plane, f"choose one of {', '.join(MIRROR_PLANES)}")
        if self.as_name is not None and self.group is None:
            raise SettingError("as_name", self.as_name, "needs group (the group to mirror under this name)")
        for name, value in (("group", self.group), ("as_name", self.as_name)):
            if value is not None and not is_group_name(value):
                raise SettingError(name, value, "must be an identifier (letters, digits, _; not "
                                   f"{' or '.join(repr(n) for n in RESERVED_GROUP_NAMES)})")
