"""Joint, mesh and group names as users type them: a full path or an unambiguous leaf name
(``L_Elbow`` for ``Hips/Spine/Chest/L_Shoulder/L_Elbow``, ``Body`` for ``/Char/Geo/Body``), and a
"did you mean" when a name matches nothing, so every command accepts the same spellings."""

from __future__ import annotations

import difflib
from collections.abc import Sequence


def leaf(path: str) -> str:
    return path.rstrip("/").rsplit("/", 1)[-1]


def matches(name: str, paths: Sequence[str]) -> list[str]:
    """The paths name means: itself when it is one of them, else those whose leaf is name."""
    if name in paths:
        return [name]
    return [p for p in paths if leaf(p) == leaf(name) and (name.count("/") == 0 or p.endswith(name))]


def did_you_mean(name: str, names: Sequence[str]) -> str:
    """"; did you mean X?" for the closest of names, by leaf and ignoring case, or ""."""
    by_leaf = {leaf(n).lower(): n for n in reversed(names)} | {n.lower(): n for n in reversed(names)}
    close = difflib.get_close_matches(name.lower(), list(by_leaf), n=1, cutoff=0.6) or \
        difflib.get_close_matches(leaf(name).lower(), list(by_leaf), n=1, cutoff=0.6)
    return f"; did you mean {by_leaf[close[0]]}?" if close else ""
