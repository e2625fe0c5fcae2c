"""``python -m psdbake.stack OUT LAYER...``: write a layer that sublayers the given files.

Layers are given weakest first (ASSET, CORRECTIVES, ANIM, WEIGHTS) and stored strongest
first, as USD wants; paths are made relative to OUT so the stack can move with its files.
"""

from __future__ import annotations

import os
import sys

from .atomic import replacing


def stack_text(out: str, layers: list[str]) -> str:
    folder = os.path.dirname(os.path.abspath(out))
    rel = [os.path.relpath(os.path.abspath(p), folder) for p in reversed(layers)]
    body = ",\n".join(f"        @{p}@" for p in rel)
    return f"#usda 1.0\n(\n    subLayers = [\n{body}\n    ]\n)\n\n"


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    if len(args) < 2:
        sys.exit("usage: python -m psdbake.stack OUT.usda LAYER [LAYER ...]  (weakest first)")
    out, layers = args[0], args[1:]
    text = stack_text(out, layers)
    with replacing(out, layers, (".usda",)) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text)


if __name__ == "__main__":
    main()
