"""Load the studio's own deformers named on the command line (``--deformer``).

A deformer spec is ``package.module:factory`` (importable) or ``path/to/file.py:factory``.
psdbake calls ``factory(stage, mesh_path, time)`` once per mesh and time code and gets a
function mapping posed points (n, 3) float64 -> (n, 3), applied after UsdSkel skinning
in mesh local space. Fit, eval's points cache and ``pose`` apply the same chain.

This is code execution by design: specs are only ever taken from the command line
(or a batch file a user wrote), never from data inside a USD file.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from collections.abc import Callable, Sequence
from typing import Any

from .arrays import Points
from .errors import DeformerError

PointFn = Callable[[Points], Points]  # posed points -> deformed points, mesh local space
#: ``factory(stage, mesh_path, time)`` -> the deformer's function for that mesh and time.
DeformerFactory = Callable[[Any, str, float], PointFn]


def load_deformer(spec: str) -> DeformerFactory:
    """Resolve one spec to its factory, or raise DeformerError saying why."""
    module_name, sep, attr = spec.rpartition(":")
    if not sep or not module_name or not attr:
        raise DeformerError(f"deformer {spec!r}: expected package.module:factory or file.py:factory")
    try:
        if module_name.endswith(".py"):
            if not os.path.isfile(module_name):
                raise DeformerError(f"deformer {spec!r}: file {module_name} not found")
            name = "psdbake_user_deformer_" + os.path.splitext(os.path.basename(module_name))[0]
            loader_spec = importlib.util.spec_from_file_location(name, module_name)
            if loader_spec is None or loader_spec.loader is None:
                raise DeformerError(f"deformer {spec!r}: {module_name} cannot be loaded as a Python module")
            module = importlib.util.module_from_spec(loader_spec)
            loader_spec.loader.exec_module(module)
        else:
            if os.getcwd() not in sys.path:
                sys.path.append(os.getcwd())
            module = importlib.import_module(module_name)
    except DeformerError:
        raise
    except SystemExit as exc:  # a deformer module cannot end the run: it fails to load (exit 5)
        raise DeformerError(
            f"deformer {spec!r}: importing {module_name} called sys.exit({exc.code!r}) (SystemExit): a deformer "
            "module must not end the process"
        ) from None
    except Exception as exc:
        first = (str(exc).strip().splitlines() or [""])[0]
        if "pxrInternal" in str(exc):  # a USD error: its words, not its C++ location
            from .usd.diagnostics import first_line

            first = first_line(exc)
        raise DeformerError(f"deformer {spec!r}: cannot import {module_name}: {type(exc).__name__}: {first}") from None
    factory = getattr(module, attr, None)
    if not callable(factory):
        raise DeformerError(f"deformer {spec!r}: {module_name} has no callable {attr!r}")
    return factory


def load_deformers(specs: Sequence[str]) -> list[tuple[str, DeformerFactory]]:
    """Load a chain of specs, in order."""
    return [(spec, load_deformer(spec)) for spec in specs]


def deformer_files(specs: Sequence[str]) -> list[str]:
    """The source files behind deformer specs (``file.py:factory`` or an importable module),
    as real paths: inputs no output may overwrite. Specs that do not resolve are skipped
    (``load_deformer`` refuses them with its own message)."""
    found = []
    for spec in specs:
        module_name = spec.rpartition(":")[0]
        if module_name.endswith(".py"):
            origin: str | None = module_name
        else:
            module = sys.modules.get(module_name)
            origin = getattr(module, "__file__", None)
            if origin is None:
                try:
                    found_spec = importlib.util.find_spec(module_name)
                except (ImportError, ValueError):
                    found_spec = None
                origin = found_spec.origin if found_spec else None
        if origin and os.path.isfile(origin):
            found.append(os.path.realpath(origin))
    return found
