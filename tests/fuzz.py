"""Mutation fuzzer: psdbake fit and eval on mutated fixture layers, in three modes.

``--mode text`` (the default; case numbers replay as before) takes the small good asset,
examples and animation from ``fixtures/``, applies a few random mutations to one of them as
text — a number replaced (NaN, inf, 1e30, 0, negative, huge integer), a type name changed,
an array element dropped or duplicated, a time-sample key moved, a line deleted or
duplicated, the file truncated — and runs ``psdbake fit`` and, when that succeeds,
``psdbake eval --points-cache``.

``--mode sdf`` is structure-aware: each case loads the good asset, examples, animation and
correctives layers with ``Sdf``, applies 1-3 mutations to one of them through the Sdf API —
attribute values replaced (NaN, inf, huge, zero, negative, wrong length, elements dropped or
duplicated), attributes retyped, time-sample keys moved (also to inf, -inf, 1e300), layer and
attribute metadata changed (timeCodesPerSecond, upAxis, metersPerUnit, elementSize,
interpolation, defaultPrim), prims retyped, duplicated or deleted, properties deleted,
relationships retargeted (skel:skeleton, skel:animationSource, skel:blendShapeTargets),
composition arcs added (sublayers, references, payloads, inherits: to a missing file, to a
missing prim, to the layer itself or an ancestor prim = cycle, to another case file, to a
file an output will overwrite), variant sets, ``psd:`` values tampered — exports the four
layers as .usda and runs ``fit`` then ``eval --points-cache`` (asset or examples mutated),
or ``eval --points-cache`` alone (animation or correctives mutated).

``--mode usdc`` exports the four good layers as .usdc and damages one: bits flipped, bytes
zeroed or set, 32-bit words overwritten (NaN, inf, huge counts), the file truncated, chunks
duplicated or moved — at offsets biased to the value area and the crate sections, not only
the header — and runs the same commands.

The only allowed outcomes of a command are success with finite output, or a clean psdbake
refusal (exactly one ``psdbake: error:`` line on stderr, after any ``psdbake: warning:``
lines, exit code 3-7, no output). A
failure is: exit 1 or any other code, a traceback, more than one stderr line on a refusal,
USD's C++ locations (``pxrInternal``, ``.cpp``) in stderr, a line other than a psdbake
warning on a successful run, a non-finite number in an output, an output missing after
exit 0, an input (or a layer an input composes) not byte-identical after the run, a
temporary or output file left behind, a hang (> CASE_SECONDS) or a crash of the process.

Cases run in worker subprocesses (a hang or crash inside USD's C++ cannot be interrupted
in-process; the parent kills the worker and starts another), one worker per core. Cases are
numbered and seeded per mode: ``python -m tests.fuzz --mode sdf --cases 20000 --seed 0``
(``make fuzz`` runs every mode; ``MODE=sdf CASES=N SEED=S`` to change), ``--only N``
replays case N and prints its mutations, commands and stderr (``--keep DIR`` keeps its
files). ``tests/test_fuzz.py`` runs a bounded number of each mode in ``make test``.
"""

from __future__ import annotations

import argparse
import atexit
import hashlib
import json
import math
import os
import re
import selectors
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BAD = os.path.join(ROOT, "fixtures", "bad")
SOURCES = {
    "asset": os.path.join(BAD, "good_asset.usda"),
    "examples": os.path.join(BAD, "good_examples.usda"),
    "anim": os.path.join(ROOT, "fixtures", "arm_anim.usda"),
}
LAYERS = dict(SOURCES, correctives=os.path.join(BAD, "good_correctives.usda"))
MODES = ("text", "sdf", "usdc")
CLEAN_EXITS = {3, 4, 5, 6, 7}  # 7: a fit whose product misses its examples (degraded): warned, then refused
NUMBER = re.compile(r"(?<![\w.])-?\d+(?:\.\d+)?(?:e[-+]?\d+)?(?![\w.])")
TYPES = ["float3[]", "point3f[]", "int[]", "float[]", "quatf[]", "half3[]", "token[]", "double[]", "matrix4d[]",
         "string", "bool", "vector3f[]"]
CASE_SECONDS = float(os.environ.get("PSDBAKE_FUZZ_CASE_SECONDS", 60))
RECYCLE = 1000  # cases per worker process before a fresh one (bounds any slow growth)
MEMORY_LIMIT = 4 << 30  # address space per worker: a runaway allocation fails instead of swamping the machine
OUTPUTS = {"fit": "fit_out.usda", "weights": "weights.usda", "cache": "cache.usda"}
CXX = re.compile(r"pxrInternal|\.cpp\b")


@dataclass(frozen=True)
class Outcome:
    case: int
    target: str
    ok: bool
    what: str
    mode: str = "text"
    mutations: tuple[str, ...] = ()
    command: str = ""
    stderr: str = ""
    seconds: float = 0.0
    files: dict = field(default_factory=dict, compare=False)


# ---------------------------------------------------------------------------------------
# text mode (unchanged mutations: the same seed and case give the same file as before)


def mutate(text: str, rng: np.random.Generator) -> str:
    """1-3 random edits of a usda text."""
    for _ in range(int(rng.integers(1, 4))):
        kind = rng.integers(0, 8)
        lines = text.split("\n")
        if kind == 0:  # a number replaced
            spans = [m.span() for m in NUMBER.finditer(text)]
            if spans:
                a, b = spans[int(rng.integers(len(spans)))]
                value = rng.choice(["nan", "inf", "-inf", "1e30", "0", "-1", "-0.5", "3", "99999999999", "1e-30", "7"])
                text = text[:a] + str(value) + text[b:]
        elif kind == 1:  # a type name changed
            found = [t for t in TYPES if t in text]
            if found:
                old = str(rng.choice(found))
                text = text.replace(old, str(rng.choice(TYPES)), 1)
        elif kind == 2:  # an array element dropped
            idx = [m.start() for m in re.finditer(r", \(", text)]
            if idx:
                a = idx[int(rng.integers(len(idx)))]
                b = text.find(")", a + 3)
                text = text[:a] + text[b + 1:] if b > a else text
        elif kind == 3:  # an array element duplicated
            m = list(re.finditer(r"\([^()]*\)", text))
            if m:
                pick = m[int(rng.integers(len(m)))]
                text = text[:pick.end()] + ", " + pick.group(0) + text[pick.end():]
        elif kind == 4:  # a time-sample key moved
            keys = list(re.finditer(r"^(\s*)(-?\d+(?:\.\d+)?): ", text, flags=re.M))
            if keys:
                k = keys[int(rng.integers(len(keys)))]
                new = str(rng.choice(["1", "2", "3", "-5", "1.5", "1000000"]))
                text = text[:k.start(2)] + new + text[k.end(2):]
        elif kind == 5 and len(lines) > 3:  # a line deleted
            del lines[int(rng.integers(len(lines)))]
            text = "\n".join(lines)
        elif kind == 6 and len(lines) > 3:  # a line duplicated
            i = int(rng.integers(len(lines)))
            lines.insert(i, lines[i])
            text = "\n".join(lines)
        elif kind == 7:  # truncated
            text = text[: int(rng.integers(len(text) // 2, len(text)))]
    return text


def _prepare_text(rng: np.random.Generator, folder: str) -> tuple[str, dict[str, str], list[str]]:
    target = str(rng.choice(sorted(SOURCES)))
    paths = dict(SOURCES)
    with open(SOURCES[target], encoding="utf-8") as fh:
        mutated = mutate(fh.read(), rng)
    paths[target] = os.path.join(folder, f"{target}.usda")
    with open(paths[target], "w", encoding="utf-8") as fh:
        fh.write(mutated)
    return target, paths, [f"text edits of {os.path.basename(SOURCES[target])}"]


# ---------------------------------------------------------------------------------------
# sdf mode: structural mutations through the Sdf API

_PRISTINE: dict = {}
SPECIAL_FLOATS = [math.nan, math.inf, -math.inf, 1e30, 1e300, 3.5e38, 0.0, -1.0, -0.5, 1e-30, 1e-300, 7.0]
SPECIAL_INTS = [-1, 0, 1, 3, 16, 99, 2**31 - 1, -2**31]
SPECIAL_TIMES = [math.inf, -math.inf, math.nan, 1e300, -1e300, 1e15, 0.0, -5.0, 1.5, 2.0, 1000000.0]
SPECIAL_STRINGS = ["", "bogus", "main", "Shoulder", "Shoulder/Elbow/Wrist/Hand", "x" * 300, "caf\u00e9", "a b", "/Arm"]
PRIM_TYPES = ["Xform", "Mesh", "Skeleton", "SkelAnimation", "SkelRoot", "BlendShape", "Scope", "", "Bogus", "Cube"]
REL_NAMES = ["skel:skeleton", "skel:animationSource", "skel:blendShapeTargets"]
PSD_SPECIAL = {
    "sigma": [0.0, -1.0, math.nan, math.inf, 1e-300, 1e300],
    "smoothing": [-1.0, math.nan, math.inf, 1e300],
    "kernel": ["bogus", "", "linear", "cubic", "thinPlate", "multiquadric", "inverseMultiquadric"],
    "poseSpace": ["swingTwist", "quaternion", "bogus", ""],
    "version": [0, 1, 3, 99, -1, 2**31 - 1],
    "degree": [-2, 0, 1, 2, 3, 99, -2**31],
    "groups": [[], ["main", "main"], ["other"], ["main", "other"], [""]],
    "drivers": [[], ["Nope", "Shoulder/Elbow/Wrist"], ["Shoulder/Elbow"], ["Shoulder/Elbow"] * 2],
    "dimensions": [[], [0, 1, 2, 3, 4, 99], [-1, 1, 2, 3, 4, 5], [0, 0, 0, 0, 0, 0]],
    "polyScale": [[0.0] * 6, [1.0] * 5, [math.nan] * 6, [1e-300] * 6],
    "polyPowers": [[0], [-1, 0], [99], [0, 1, 2, 3, 4, 5, 6]],
    "clampWeights": [True], "normalizeWeights": [True],
}


def _pristine():
    """The four good layers, loaded once per process (never modified)."""
    if not _PRISTINE:
        from pxr import Sdf

        for name, path in LAYERS.items():
            with open(path, encoding="utf-8") as fh:
                layer = Sdf.Layer.CreateAnonymous(".usda")
                layer.ImportFromString(fh.read())
            _PRISTINE[name] = layer
    return _PRISTINE


def _specs(layer) -> list:
    from pxr import Sdf

    paths: list = []
    layer.Traverse(Sdf.Path.absoluteRootPath, paths.append)
    return [layer.GetObjectAtPath(p) for p in sorted(paths, key=str)]


def _attrs(layer) -> list:
    from pxr import Sdf

    return [s for s in _specs(layer) if isinstance(s, Sdf.AttributeSpec)]


def _prims(layer) -> list:
    from pxr import Sdf

    return [s for s in _specs(layer) if isinstance(s, Sdf.PrimSpec) and s.path != Sdf.Path.absoluteRootPath
            and not s.path.ContainsPropertyElements()]


def _rels(layer) -> list:
    from pxr import Sdf

    return [s for s in _specs(layer) if isinstance(s, Sdf.RelationshipSpec)]


def _pick(rng, items):
    return items[int(rng.integers(len(items)))] if len(items) else None


def _fmt(v) -> str:
    text = repr(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _new_value(v, rng, name: str = ""):
    """A mutated value of the same Python type as v (Sdf refuses another type): (value, what)."""
    from pxr import Gf

    key = name.rsplit(":", 1)[-1]
    if key in PSD_SPECIAL and rng.random() < 0.6:
        special = _pick(rng, PSD_SPECIAL[key])
        try:
            return type(v)(special), f"= {_fmt(special)}"
        except (TypeError, ValueError, OverflowError):
            pass
    if isinstance(v, bool):
        return (not v), f"= {not v}"
    if isinstance(v, int):
        n = int(_pick(rng, SPECIAL_INTS))
        return n, f"= {n}"
    if isinstance(v, float):
        x = float(_pick(rng, SPECIAL_FLOATS))
        return x, f"= {x}"
    if isinstance(v, str):
        s = str(_pick(rng, SPECIAL_STRINGS))
        return s, f"= {_fmt(s)}"
    is_array = type(v).__name__.endswith("Array")
    if is_array:
        items = list(v)
        n = len(items)
        kind = int(rng.integers(0, 8))
        if n == 0 or kind == 0:
            new = items * 2 if n else []
            what = f"length {n} -> {len(new)}"
            if not n:
                return v, "unchanged (empty)"
            return type(v)(new), what
        if kind == 1:  # element dropped
            i = int(rng.integers(n))
            return type(v)(items[:i] + items[i + 1:]), f"element {i} of {n} dropped"
        if kind == 2:  # element duplicated
            i = int(rng.integers(n))
            return type(v)(items[:i + 1] + items[i:]), f"element {i} of {n} duplicated"
        if kind == 3:  # emptied or cut to one
            new = items[:1] if rng.random() < 0.5 else []
            return type(v)(new), f"length {n} -> {len(new)}"
        a = np.array(v)
        i = int(rng.integers(n))
        if a.dtype.kind in "US":
            a = a.astype(object)
            a[i] = str(_pick(rng, SPECIAL_STRINGS))
            return type(v)(list(a)), f"element {i} = {_fmt(a[i])}"
        if a.dtype.kind in "iu":
            x = int(_pick(rng, SPECIAL_INTS))
            a = a.astype(np.int64)
            a = np.clip(a, -2**31, 2**31 - 1)
            a.reshape(n, -1)[i, int(rng.integers(a.reshape(n, -1).shape[1]))] = x
            return type(v)(a.astype(np.int32).tolist()), f"element {i} = {x}"
        if a.dtype.kind == "b":
            return type(v)([not b for b in items]), "booleans inverted"
        x = float(_pick(rng, SPECIAL_FLOATS))
        flat = a.reshape(n, -1).astype(np.float64)
        if kind == 4:  # every element, one component
            flat[:, int(rng.integers(flat.shape[1]))] = x
            what = f"every element's component = {x}"
        elif kind == 5:  # whole array scaled
            flat = flat * x
            what = f"all values * {x}"
        else:
            flat[i, int(rng.integers(flat.shape[1]))] = x
            what = f"element {i} component = {x}"
        with np.errstate(all="ignore"):
            out = flat.reshape(a.shape).astype(a.dtype)
        return type(v).FromNumpy(np.ascontiguousarray(out)), what
    # a Gf scalar: vector, matrix or quaternion
    x = float(_pick(rng, SPECIAL_FLOATS))
    if isinstance(v, (Gf.Quatf, Gf.Quatd, Gf.Quath)):
        im = list(v.GetImaginary())
        return type(v)(x, *im), f"real = {x}"
    a = np.array(v, dtype=np.float64)
    flat = a.reshape(-1)
    if rng.random() < 0.3:
        flat[:] = x
        what = f"all components = {x}"
    else:
        j = int(rng.integers(flat.size))
        flat[j] = x
        what = f"component {j} = {x}"
    return type(v)(a.tolist()), what


def _wrong_type_values():
    from pxr import Gf, Sdf, Vt

    t = Sdf.ValueTypeNames
    return [
        (t.String, "fuzz"), (t.Int, 3), (t.Float, 1.5), (t.Bool, True), (t.Token, "fuzz"), (t.Double, 2.0),
        (t.FloatArray, Vt.FloatArray([1.0, 2.0, 3.0])), (t.IntArray, Vt.IntArray([0, 1, 2])),
        (t.TokenArray, Vt.TokenArray(["a", "b"])), (t.Matrix4d, Gf.Matrix4d(1)),
        (t.Point3fArray, Vt.Vec3fArray([(0, 0, 0)])), (t.QuatfArray, Vt.QuatfArray([Gf.Quatf(1)])),
        (t.Double3, Gf.Vec3d(1, 2, 3)), (t.Half3Array, Vt.Vec3hArray([(1, 1, 1)])),
        (t.Matrix4dArray, Vt.Matrix4dArray([Gf.Matrix4d(1)])), (t.StringArray, Vt.StringArray(["a"])),
        (t.Asset, Sdf.AssetPath("./missing.usda")), (t.Float3, Gf.Vec3f(1, 2, 3)),
        (t.DoubleArray, Vt.DoubleArray([1.0])), (t.QuatdArray, Vt.QuatdArray([Gf.Quatd(1)])),
    ]


class _Ctx:
    """What a mutation may refer to: the case's layers, their file names, known prim paths."""

    def __init__(self, layers: dict, names: dict[str, str], target: str, rng):
        self.layers, self.names, self.target, self.rng = layers, names, target, rng
        self.layer = layers[target]
        self.arc_files: set[str] = set()  # files in the case folder that a mutation makes an input
        self.precreate: set[str] = set()  # output names to create before the run (a previous run's output)
        self.prim_paths = sorted({str(p.path) for lay in layers.values() for p in _prims(lay)})

    def file_choice(self) -> str:
        rng = self.rng
        r = rng.random()
        if r < 0.2:
            return "./missing.usda"
        if r < 0.35:
            return "./" + self.names[self.target]  # itself
        if r < 0.65:
            other = str(_pick(rng, sorted(n for n in self.names if n != self.target)))
            self.arc_files.add(self.names[other])
            return "./" + self.names[other]
        if r < 0.85:  # a file an output of this case will be written to
            out = str(_pick(rng, sorted(OUTPUTS.values())))
            if rng.random() < 0.7:
                self.precreate.add(out)
            self.arc_files.add(out)
            return "./" + out
        return str(_pick(rng, ["./", "/dev/null", "./notes.txt", "../missing/x.usda", "missing.usdc",
                               "./" + self.names[self.target].replace(".usda", ".usdz")]))

    def path_choice(self, prim=None) -> str:
        rng = self.rng
        options = ["/Nope", "/Arm", "/Arm/Skel/Anim", "/Arm/Skel", "/Arm/Geo/Tube", *self.prim_paths]
        if prim is not None:
            options += [str(prim.path), str(prim.path.GetParentPath())]
        return str(_pick(rng, options))


def _m_value(ctx: _Ctx) -> str | None:
    attrs = [a for a in _attrs(ctx.layer) if a.HasDefaultValue() or ctx.layer.GetNumTimeSamplesForPath(a.path)]
    attr = _pick(ctx.rng, attrs)
    if attr is None:
        return None
    times = ctx.layer.ListTimeSamplesForPath(attr.path)
    if times and (not attr.HasDefaultValue() or ctx.rng.random() < 0.8):
        t = _pick(ctx.rng, times)
        new, what = _new_value(ctx.layer.QueryTimeSample(attr.path, t), ctx.rng, attr.name)
        ctx.layer.SetTimeSample(attr.path, t, new)
        return f"value {attr.path} @{t}: {what}"
    new, what = _new_value(attr.default, ctx.rng, attr.name)
    attr.default = new
    return f"value {attr.path}: {what}"


def _m_retype(ctx: _Ctx) -> str | None:
    from pxr import Sdf

    attr = _pick(ctx.rng, _attrs(ctx.layer))
    if attr is None:
        return None
    typename, value = _pick(ctx.rng, _wrong_type_values())
    prim = ctx.layer.GetObjectAtPath(attr.path.GetPrimPath())
    name, variability, custom, path = attr.name, attr.variability, attr.custom, attr.path
    old = str(attr.typeName)
    prim.RemoveProperty(attr)
    new = Sdf.AttributeSpec(prim, name, typename, variability)
    new.custom = custom
    new.default = value
    return f"retype {path}: {old} -> {typename} = {_fmt(value)}"


def _m_time(ctx: _Ctx) -> str | None:
    layer, rng = ctx.layer, ctx.rng
    attrs = [a for a in _attrs(layer) if layer.GetNumTimeSamplesForPath(a.path)]
    attr = _pick(rng, attrs)
    if attr is None:
        return None
    times = list(layer.ListTimeSamplesForPath(attr.path))
    kind = rng.random()
    if kind < 0.7:  # a key moved
        t = _pick(rng, times)
        new = float(_pick(rng, SPECIAL_TIMES + times))
        value = layer.QueryTimeSample(attr.path, t)
        layer.EraseTimeSample(attr.path, t)
        layer.SetTimeSample(attr.path, new, value)
        return f"time sample {attr.path} key {t} -> {new}"
    if kind < 0.85:  # one more key, a mutated copy of one sample
        t = _pick(rng, times)
        new_t = float(_pick(rng, SPECIAL_TIMES))
        value, what = _new_value(layer.QueryTimeSample(attr.path, t), rng, attr.name)
        layer.SetTimeSample(attr.path, new_t, value)
        return f"time sample {attr.path} added @{new_t}: copy of @{t} {what}"
    # all samples cleared (the attribute keeps only its default, if any)
    attr.ClearInfo("timeSamples")
    return f"time samples of {attr.path} cleared"


def _m_metadata(ctx: _Ctx) -> str | None:
    layer, rng = ctx.layer, ctx.rng
    if rng.random() < 0.55:
        key, values = _pick(rng, [
            ("timeCodesPerSecond", [0.0, -24.0, math.nan, math.inf, 1e-300, 1e300, 1.0]),
            ("framesPerSecond", [0.0, -24.0, math.nan, math.inf, 1e300]),
            ("startTimeCode", [math.nan, math.inf, -math.inf, 1e300, 100.0, -1e15]),
            ("endTimeCode", [math.nan, math.inf, -math.inf, 1e300, 0.0, -5.0]),
            ("upAxis", ["X", "Z", "y", "", " Y", "bogus"]),
            ("metersPerUnit", [0.0, -1.0, math.nan, math.inf, 1e30, 1e-30]),
            ("defaultPrim", ["Nope", "Skel", "", "Arm/Geo"]),
        ])
        value = _pick(rng, values)
        layer.pseudoRoot.SetInfo(key, value)
        return f"layer metadata {key} = {_fmt(value)}"
    attrs = _attrs(layer)
    primvars = [a for a in attrs if a.name.startswith("primvars:")]
    attr = _pick(rng, primvars if primvars and rng.random() < 0.7 else attrs)
    if attr is None:
        return None
    if rng.random() < 0.5:
        n = int(_pick(rng, [0, -1, 1, 2, 3, 5, 8, 64, 2**31 - 1]))
        attr.SetInfo("elementSize", n)
        return f"metadata {attr.path} elementSize = {n}"
    token = str(_pick(rng, ["constant", "uniform", "varying", "faceVarying", "bogus", ""]))
    attr.SetInfo("interpolation", token)
    return f"metadata {attr.path} interpolation = {token!r}"


def _m_prim(ctx: _Ctx) -> str | None:
    from pxr import Sdf

    layer, rng = ctx.layer, ctx.rng
    prim = _pick(rng, _prims(layer))
    if prim is None:
        return None
    kind = rng.random()
    if kind < 0.35:
        old, new = prim.typeName, str(_pick(rng, PRIM_TYPES))
        prim.typeName = new
        return f"prim {prim.path} retyped {old!r} -> {new!r}"
    if kind < 0.5:
        new = _pick(rng, [Sdf.SpecifierOver, Sdf.SpecifierClass, Sdf.SpecifierDef])
        prim.specifier = new
        return f"prim {prim.path} specifier -> {new}"
    if kind < 0.6:
        prim.ClearInfo("apiSchemas")
        return f"prim {prim.path} apiSchemas removed"
    if kind < 0.8:
        copy = prim.path.GetParentPath().AppendChild(prim.name + "_dup")
        if not Sdf.CopySpec(layer, prim.path, layer, copy):
            return None
        return f"prim {prim.path} duplicated as {copy}"
    parent = prim.nameParent if prim.nameParent else layer.pseudoRoot
    path = prim.path
    del parent.nameChildren[prim.name]
    return f"prim {path} deleted"


def _m_property_delete(ctx: _Ctx) -> str | None:
    from pxr import Sdf

    props = [s for s in _specs(ctx.layer) if isinstance(s, Sdf.PropertySpec)]
    prop = _pick(ctx.rng, props)
    if prop is None:
        return None
    path = prop.path
    ctx.layer.GetObjectAtPath(path.GetPrimPath()).RemoveProperty(prop)
    return f"property {path} deleted"


def _m_rel(ctx: _Ctx) -> str | None:
    from pxr import Sdf

    layer, rng = ctx.layer, ctx.rng
    rels = _rels(layer)
    if not rels or rng.random() < 0.3:
        prim = _pick(rng, _prims(layer))
        if prim is None:
            return None
        name = str(_pick(rng, REL_NAMES))
        rel = prim.relationships.get(name) or Sdf.RelationshipSpec(prim, name, custom=False)
    else:
        rel = _pick(rng, rels)
    r = rng.random()
    if r < 0.15:
        targets = []
    elif r < 0.3:
        targets = [ctx.path_choice(), ctx.path_choice()]
    elif r < 0.4:
        targets = [str(rel.path.GetPrimPath().AppendProperty("points"))]
    else:
        targets = [ctx.path_choice(layer.GetObjectAtPath(rel.path.GetPrimPath()))]
    rel.targetPathList.ClearEdits()
    rel.targetPathList.explicitItems = [Sdf.Path(t) for t in targets]
    return f"relationship {rel.path} -> {targets}"


def _offset(rng):
    from pxr import Sdf

    if rng.random() < 0.6:
        return Sdf.LayerOffset(), ""
    offset = float(_pick(rng, [0.0, 0.0, 10.0, math.nan, math.inf, 1e300]))
    scale = float(_pick(rng, [1.0, 0.0, -1.0, math.nan, math.inf, 1e300, 1e-300]))
    return Sdf.LayerOffset(offset, scale), f" (offset {offset}, scale {scale})"


def _m_sublayer(ctx: _Ctx) -> str | None:
    layer, rng = ctx.layer, ctx.rng
    path = ctx.file_choice()
    offset, shown = _offset(rng)
    if rng.random() < 0.5:
        layer.subLayerPaths.insert(0, path)
        index = 0
    else:
        layer.subLayerPaths.append(path)
        index = len(layer.subLayerPaths) - 1
    if shown:
        layer.subLayerOffsets[index] = offset
    return f"sublayer {path}{shown}"


def _m_reference(ctx: _Ctx) -> str | None:
    from pxr import Sdf

    layer, rng = ctx.layer, ctx.rng
    prim = _pick(rng, _prims(layer))
    if prim is None:
        return None
    r = rng.random()
    kind = "reference" if r < 0.45 else "payload" if r < 0.75 else "inherit" if r < 0.9 else "specialize"
    if kind in ("inherit", "specialize"):
        path = ctx.path_choice(prim)
        (prim.inheritPathList if kind == "inherit" else prim.specializesList).Prepend(Sdf.Path(path))
        return f"{kind} {prim.path} -> <{path}>"
    asset = "" if rng.random() < 0.3 else ctx.file_choice()
    target = ctx.path_choice(prim) if (not asset or rng.random() < 0.7) else ""
    offset, shown = _offset(rng)
    arc = (Sdf.Reference if kind == "reference" else Sdf.Payload)(asset, target, offset)
    arcs = prim.referenceList if kind == "reference" else prim.payloadList
    arcs.Prepend(arc) if rng.random() < 0.7 else arcs.Append(arc)
    return f"{kind} {prim.path} -> @{asset}@<{target}>{shown}"


def _m_variant(ctx: _Ctx) -> str | None:
    from pxr import Sdf

    layer, rng = ctx.layer, ctx.rng
    prims = [p for p in _prims(layer) if "{" not in str(p.path)]
    prim = _pick(rng, prims)
    if prim is None:
        return None
    vset = Sdf.VariantSetSpec(prim, "fuzz")
    variant = Sdf.VariantSpec(vset, "a")
    prim.variantSetNameList.Prepend("fuzz")
    selection = "a" if rng.random() < 0.8 else "missing"
    prim.variantSelections["fuzz"] = selection
    inner = variant.primSpec
    attrs = [prim.attributes[n] for n in prim.attributes.keys()]
    r = rng.random()
    if attrs and r < 0.6:
        attr = _pick(rng, attrs)
        dest = inner.path.AppendProperty(attr.name)
        Sdf.CopySpec(layer, attr.path, layer, dest)
        copy = layer.GetAttributeAtPath(dest)
        times = layer.ListTimeSamplesForPath(dest)
        if times:
            t = _pick(rng, times)
            new, what = _new_value(layer.QueryTimeSample(dest, t), rng, attr.name)
            layer.SetTimeSample(dest, t, new)
        elif copy.HasDefaultValue():
            new, what = _new_value(copy.default, rng, attr.name)
            copy.default = new
        else:
            what = "copied"
        return f"variant {prim.path}{{fuzz={selection}}}: {attr.name} {what}"
    if r < 0.8:
        child = Sdf.PrimSpec(inner, "Extra", Sdf.SpecifierDef, str(_pick(rng, PRIM_TYPES[:6])))
        if prim.nameChildren:
            src = prim.nameChildren[0]
            Sdf.CopySpec(layer, src.path, layer, child.path)
        return f"variant {prim.path}{{fuzz={selection}}}: child prim {child.typeName}"
    asset = ctx.file_choice()
    inner.referenceList.Prepend(Sdf.Reference(asset, ctx.path_choice(prim)))
    return f"variant {prim.path}{{fuzz={selection}}}: reference @{asset}@"


def _m_psd(ctx: _Ctx) -> str | None:
    layer = ctx.layer
    attrs = [a for a in _attrs(layer) if a.name.startswith("psd:") or a.name == "skel:blendShapes"
             or a.path.GetPrimPath().name.startswith("psd_")]
    attr = _pick(ctx.rng, attrs)
    if attr is None or not attr.HasDefaultValue():
        return None
    new, what = _new_value(attr.default, ctx.rng, attr.name)
    attr.default = new
    return f"psd {attr.path}: {what}"


SDF_MUTATIONS: list[tuple[str, Callable, float]] = [
    ("value", _m_value, 0.22), ("retype", _m_retype, 0.05), ("time", _m_time, 0.08),
    ("metadata", _m_metadata, 0.09), ("prim", _m_prim, 0.08), ("delete", _m_property_delete, 0.07),
    ("rel", _m_rel, 0.08), ("sublayer", _m_sublayer, 0.08), ("reference", _m_reference, 0.10),
    ("variant", _m_variant, 0.05), ("psd", _m_psd, 0.10),
]


def _prepare_sdf(rng: np.random.Generator, folder: str) -> tuple[str, dict[str, str], list[str], dict[str, set[str]]]:
    from pxr import Sdf, Tf

    target = str(rng.choice(sorted(LAYERS)))
    pristine = _pristine()
    layers = {}
    for name, good in pristine.items():
        layers[name] = Sdf.Layer.CreateAnonymous(".usda")
        layers[name].TransferContent(good)
    names = {name: f"{name}.usda" for name in layers}
    ctx = _Ctx(layers, names, target, rng)
    weights = np.array([w for _, _, w in SDF_MUTATIONS])
    if target == "correctives":
        weights[next(i for i, (k, _, _) in enumerate(SDF_MUTATIONS) if k == "psd")] *= 4
    weights = weights / weights.sum()
    done: list[str] = []
    for _ in range(int(rng.integers(1, 4))):
        name, fn, _ = SDF_MUTATIONS[int(rng.choice(len(SDF_MUTATIONS), p=weights))]
        arc_files, precreate = set(ctx.arc_files), set(ctx.precreate)
        try:
            what = fn(ctx)
        except (Tf.ErrorException, ValueError, TypeError, RuntimeError, OverflowError, IndexError) as exc:
            what = None
            ctx.arc_files, ctx.precreate = arc_files, precreate  # the arc was not added
            done.append(f"({name} not applied: {type(exc).__name__})")
        if what:
            done.append(what)
    paths = {}
    for name, layer in layers.items():
        paths[name] = os.path.join(folder, names[name])
        if not layer.Export(paths[name]):
            raise RuntimeError(f"cannot export {names[name]}")
    with open(os.path.join(folder, "notes.txt"), "w", encoding="utf-8") as fh:
        fh.write("not a layer\n")
    for out in ctx.precreate:  # a previous run's output, now also composed by an input
        source = {"fit_out.usda": "correctives", "weights.usda": "anim", "cache.usda": "anim"}[out]
        shutil.copyfile(paths[source], os.path.join(folder, out))
    return target, paths, done, {names[target]: ctx.arc_files | {"notes.txt"}}


# ---------------------------------------------------------------------------------------
# usdc mode: damaged crate bytes

_CRATES: dict[str, bytes] = {}


def _crates() -> dict[str, bytes]:
    if not _CRATES:

        folder = tempfile.mkdtemp(prefix="psdbake-fuzz-crate-")
        try:
            for name, layer in _pristine().items():
                path = os.path.join(folder, f"{name}.usdc")
                layer.Export(path)
                with open(path, "rb") as fh:
                    _CRATES[name] = fh.read()
        finally:
            shutil.rmtree(folder, ignore_errors=True)
    return _CRATES


def crate_regions(data: bytes) -> dict[str, tuple[int, int]]:
    """Byte ranges of a .usdc file: header, values (between header and the first section),
    each section of the table of contents, and the table itself."""
    regions = {"header": (0, min(88, len(data)))}
    try:
        toc = int.from_bytes(data[16:24], "little")
        count = int.from_bytes(data[toc:toc + 8], "little")
        sections = []
        for i in range(count):
            at = toc + 8 + i * 32
            name = data[at:at + 16].split(b"\0")[0].decode("ascii")
            start = int.from_bytes(data[at + 16:at + 24], "little")
            size = int.from_bytes(data[at + 24:at + 32], "little")
            sections.append((name, start, size))
        first = min(s for _, s, _ in sections)
        regions["values"] = (88, first)
        for name, start, size in sections:
            regions[name] = (start, start + size)
        regions["toc"] = (toc, len(data))
    except (ValueError, UnicodeDecodeError):
        pass
    return {k: (a, b) for k, (a, b) in regions.items() if b > a}


def mutate_bytes(data: bytes, rng: np.random.Generator) -> tuple[bytes, list[str]]:
    regions = crate_regions(data)
    names = sorted(regions)
    weights = np.array([0.45 if n == "values" else 0.05 if n in ("header", "toc") else 0.1 for n in names])
    done = []
    buf = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        if len(buf) < 16:
            break
        region = names[int(rng.choice(len(names), p=weights / weights.sum()))] if rng.random() < 0.9 else "anywhere"
        a, b = regions.get(region, (0, len(buf)))
        a, b = min(a, len(buf) - 1), min(max(b, a + 1), len(buf))
        at = int(rng.integers(a, b))
        kind = int(rng.integers(0, 7))
        if kind == 0:
            bits = int(rng.integers(1, 9))
            for _ in range(bits):
                i = int(rng.integers(a, b))
                buf[i] ^= 1 << int(rng.integers(8))
            done.append(f"{bits} bits flipped in {region} [{a}:{b}]")
        elif kind == 1:
            n = int(rng.integers(1, 65))
            fill = int(_pick(rng, [0, 0xFF]))
            buf[at:at + n] = bytes([fill]) * len(buf[at:at + n])
            done.append(f"{n} bytes at {at} ({region}) set to {fill:#x}")
        elif kind == 2:
            at -= at % 4
            word = _pick(rng, [b"\x00\x00\xc0\x7f", b"\x00\x00\x80\x7f", b"\xff\xff\xff\x7f", b"\xff\xff\xff\xff",
                               b"\x00\x00\x00\x80", b"\x00\x00\x00\x00", b"\x10\x00\x00\x00", b"\xf9\x02\x15\x50"])
            buf[at:at + 4] = word
            done.append(f"word at {at} ({region}) = {word.hex()}")
        elif kind == 3:
            buf = buf[:at]
            done.append(f"truncated at {at} ({region}) of {len(data)}")
        elif kind == 4:
            n = int(rng.integers(1, 257))
            chunk = bytes(buf[at:at + n])
            dest = int(rng.integers(0, len(buf)))
            buf[dest:dest] = chunk
            done.append(f"{len(chunk)} bytes at {at} ({region}) duplicated at {dest}")
        elif kind == 5:
            n = int(rng.integers(1, 257))
            chunk = bytes(buf[at:at + n])
            dest = int(rng.integers(0, max(1, len(buf) - len(chunk))))
            buf[dest:dest + len(chunk)] = chunk
            done.append(f"{len(chunk)} bytes at {at} ({region}) copied over {dest}")
        else:
            n = int(rng.integers(1, 33))
            del buf[at:at + n]
            done.append(f"{n} bytes at {at} ({region}) removed")
    return bytes(buf), done


def _prepare_usdc(rng: np.random.Generator, folder: str) -> tuple[str, dict[str, str], list[str], dict[str, set[str]]]:
    target = str(rng.choice(sorted(LAYERS)))
    paths, done = {}, []
    for name, data in _crates().items():
        if name == target:
            data, done = mutate_bytes(data, rng)
        paths[name] = os.path.join(folder, f"{name}.usdc")
        with open(paths[name], "wb") as fh:
            fh.write(data)
    return target, paths, [f"{target}.usdc: {d}" for d in done], {}


# ---------------------------------------------------------------------------------------
# running one case: commands, outcome rules


class _Capture:
    """psdbake's stdout and stderr at the file-descriptor level (USD prints from C++ to fd 2)."""

    def __init__(self, path: str | None = None):
        self.err = open(path, "w+b") if path else tempfile.TemporaryFile()
        self.out = tempfile.TemporaryFile()

    def run(self, argv: list[str]) -> tuple[int, str, str]:
        from psdbake.cli import main

        sys.stdout.flush()
        sys.stderr.flush()
        for f in (self.err, self.out):
            f.seek(0)
            f.truncate()
        saved = os.dup(1), os.dup(2)
        os.dup2(self.out.fileno(), 1)
        os.dup2(self.err.fileno(), 2)
        code = 0
        try:
            main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except BaseException as exc:
            code = -1000
            print(f"Traceback (fuzz: {type(exc).__name__} escaped psdbake.cli.main: {exc})", file=sys.stderr)
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
        self.err.seek(0)
        self.out.seek(0)
        return code, self.out.read().decode("utf-8", "replace"), self.err.read().decode("utf-8", "replace")


def _finite_layer(path: str) -> bool:
    """Every number written in a usda output is finite."""
    with open(path, encoding="utf-8", errors="replace") as fh:
        text = fh.read()
    return not re.search(r"(?<![\w])(nan|inf)(?![\w])", text, flags=re.I)


def _digest(paths) -> dict[str, str]:
    out = {}
    for p in paths:
        if os.path.isfile(p):
            with open(p, "rb") as fh:
                out[p] = hashlib.sha256(fh.read()).hexdigest()
        else:
            out[p] = "absent"
    return out


def _judge(code: int, out: str, err: str, outputs: list[str], old: dict[str, str]) -> tuple[bool, str]:
    """The outcome rules for one command; old: the outputs' digests before it ran."""
    if "Traceback" in err or "Traceback" in out:
        return False, "traceback: " + (err.strip().splitlines() or [""])[-1][:300]
    lines = [ln for ln in err.splitlines() if ln.strip()]
    if CXX.search(err):
        bad = next(ln for ln in lines if CXX.search(ln))
        return False, f"C++ location in stderr (exit {code}): {bad.strip()[:300]}"
    if code == 0:
        stray = [ln for ln in lines if not ln.startswith("psdbake: warning:")]
        if stray:
            return False, f"exit 0 with stray stderr: {stray[0][:300]}"
        missing = [os.path.basename(p) for p in outputs if not os.path.exists(p)]
        if missing:
            return False, "exit 0 but no output " + ", ".join(missing)
        bad = [os.path.basename(p) for p in outputs if not _finite_layer(p)]
        return (not bad), ("non-finite numbers in " + ", ".join(bad)) if bad else "ok"
    if code in CLEAN_EXITS:
        errors = [ln for ln in lines if ln.startswith("psdbake: error:")]
        others = [ln for ln in lines if not ln.startswith(("psdbake: error:", "psdbake: warning:"))]
        if len(errors) != 1 or others or lines[-1] != errors[0]:
            return False, f"exit {code} with {len(lines)} stderr lines: " + " | ".join(lines)[:300]
        written = [os.path.basename(p) for p in outputs if _digest([p]) != {p: old.get(p, "absent")}]
        return (not written), "refused" if not written else f"refused but wrote {written}"
    return False, f"exit {code}: " + " | ".join(lines)[:300]


def _commands(mode: str, target: str, paths: dict[str, str], folder: str):
    """(name, argv, outputs) in order; each runs only if the one before succeeded."""
    fit_out, weights, cache = (os.path.join(folder, OUTPUTS[k]) for k in ("fit", "weights", "cache"))
    fit = ("fit", ["fit", paths["asset"], paths["examples"], "-o", fit_out, "-q", "-j", "1"], [fit_out])
    if mode == "text" or target in ("asset", "examples"):
        correctives = fit_out
        steps = [fit]
    else:
        correctives = paths["correctives"]
        steps = []
    steps.append(("eval", ["eval", paths["asset"], correctives, "--anim", paths["anim"], "-o", weights,
                           "--points-cache", cache, "-q"], [weights, cache]))
    return steps


def _composed(files: set[str], arcs: dict[str, set[str]]) -> set[str]:
    """The case files reached from files through the arcs the mutations added (file -> files)."""
    seen, todo = set(), list(files)
    while todo:
        f = todo.pop()
        for g in arcs.get(f, ()):
            if g not in seen and g not in files:
                seen.add(g)
                todo.append(g)
    return seen


def _rng(mode: str, seed: int, case: int) -> np.random.Generator:
    if mode == "text":
        return np.random.default_rng([seed, case])  # as before: old case numbers replay
    return np.random.default_rng([seed, case, MODES.index(mode)])


def run_case(case: int, seed: int, folder: str, mode: str = "text", *, capture: _Capture | None = None,
             report: Callable[[str, object], None] | None = None, keep: bool = False) -> Outcome:
    """One case in this process: prepare its files in folder/caseN, run the commands, judge."""
    capture = capture or _Capture()
    report = report or (lambda kind, value: None)
    started = time.perf_counter()
    rng = _rng(mode, seed, case)
    cdir = os.path.join(folder, f"{mode}{case}")
    shutil.rmtree(cdir, ignore_errors=True)
    os.makedirs(cdir)
    try:
        if mode == "text":
            target, paths, mutations = _prepare_text(rng, cdir)
            arcs: dict[str, set[str]] = {}
        else:
            try:
                target, paths, mutations, arcs = (_prepare_sdf if mode == "sdf" else _prepare_usdc)(rng, cdir)
            except Exception as exc:
                return Outcome(case, "?", True, f"skipped: case not built ({type(exc).__name__}: {exc})", mode)
        report("target", target)
        report("mutations", mutations)
        ok, what, command, err = True, "", "", ""
        for name, argv, outputs in _commands(mode, target, paths, cdir):
            inputs = [a for a in argv[1:] if os.path.isabs(a) and a not in outputs]
            # and the case files that the mutated layer now composes, when this command reads it
            inputs += [os.path.join(cdir, f) for f in sorted(_composed({os.path.basename(p) for p in inputs}, arcs))]
            before_files = set(os.listdir(cdir))
            before = _digest(p for p in inputs if os.path.exists(p))
            old_outputs = _digest(outputs)
            command = "psdbake " + " ".join(os.path.relpath(a, cdir) if os.path.isabs(a) and a.startswith(cdir)
                                            else os.path.relpath(a, ROOT) if os.path.isabs(a) else a for a in argv)
            report("command", command)
            code, out, err = capture.run(argv)
            ok, what = _judge(code, out, err, outputs, old_outputs)
            if ok:
                changed = [os.path.basename(p) for p, h in before.items() if _digest([p])[p] != h]
                if changed:
                    ok, what = False, f"input modified (exit {code}): {', '.join(changed)}"
            if ok:
                allowed = before_files | ({os.path.basename(p) for p in outputs} if code == 0 else set())
                left = sorted(set(os.listdir(cdir)) - allowed)
                if left:
                    ok, what = False, f"files left (exit {code}): {', '.join(left)}"
            what = f"{name} {what}"
            if not ok or code != 0:
                break
        files = {}
        if keep:
            files = {os.path.basename(p): p for p in paths.values()}
    finally:
        if not keep:
            shutil.rmtree(cdir, ignore_errors=True)
    last = next((ln for ln in err.splitlines() if ln.strip()), "")
    return Outcome(case, target, ok, what, mode, tuple(mutations), command, "" if ok and not last else err.strip()[:2000],
                   time.perf_counter() - started, files)


# ---------------------------------------------------------------------------------------
# workers: each case in a subprocess that the parent kills on a hang and replaces on a crash


def _worker(mode: str, seed: int, folder: str, err_path: str) -> None:
    import resource

    try:
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
    except (ValueError, OSError):
        pass
    proto = os.fdopen(os.dup(1), "w", buffering=1)
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    log = os.open(err_path + ".log", os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    os.dup2(log, 2)  # USD's diagnostics while mutating, and any fuzzer error
    capture = _Capture(err_path)
    # the CLI and the library it loads per command, before the first case: their time is not a case's
    import psdbake.cli  # noqa: F401

    _pristine()
    if mode == "usdc":
        _crates()

    def report(kind: str, value) -> None:
        proto.write(json.dumps({"kind": kind, "value": value}) + "\n")

    report("ready", True)
    for line in sys.stdin:
        if not line.strip():
            break
        case = int(line)
        outcome = run_case(case, seed, folder, mode, capture=capture, report=report)
        report("outcome", asdict(outcome))


class _Worker:
    def __init__(self, mode: str, seed: int, folder: str, index: int):
        self.err_path = os.path.join(folder, f".worker{index}.stderr")
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
                   PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
        env.pop("PSDBAKE_DEBUG", None)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tests.fuzz", "--worker", "--mode", mode, "--seed", str(seed),
             "--folder", folder, "--err", self.err_path],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, cwd=ROOT, env=env)
        os.set_blocking(self.proc.stdout.fileno(), False)
        self.buf = b""
        self.case: int | None = None
        self.started = 0.0
        self.done = 0
        self.ready = False
        self.mutations: list[str] = []
        self.command = ""
        self.target = "?"

    def send(self, case: int) -> None:
        self.case, self.started, self.mutations, self.command, self.target = case, time.perf_counter(), [], "", "?"
        self.proc.stdin.write(f"{case}\n".encode())
        self.proc.stdin.flush()

    def messages(self) -> list[dict] | None:
        """Complete messages read so far; None when the worker has ended."""
        try:
            data = os.read(self.proc.stdout.fileno(), 1 << 16)
        except BlockingIOError:
            return []
        if not data:
            return None
        self.buf += data
        *lines, self.buf = self.buf.split(b"\n")
        return [json.loads(ln) for ln in lines if ln.strip()]

    def stderr_tail(self) -> str:
        try:
            with open(self.err_path if self.command else self.err_path + ".log", "rb") as fh:
                return fh.read()[-2000:].decode("utf-8", "replace").strip()
        except OSError:
            return ""

    def stop(self, kill: bool = False) -> None:
        if kill:
            self.proc.kill()
        else:
            try:
                self.proc.stdin.write(b"\n")
                self.proc.stdin.close()
            except OSError:
                pass
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        for f in (self.proc.stdin, self.proc.stdout):
            try:
                f.close()
            except OSError:
                pass


def _dead(w: _Worker, mode: str, seed: int, hang: bool) -> Outcome:
    if hang:
        what = f"hang: more than {CASE_SECONDS:g} s"
    else:
        rc = w.proc.returncode
        what = f"crash: killed by {signal.Signals(-rc).name}" if rc is not None and rc < 0 else f"crash: exit {rc}"
    step = w.command.split(" ", 2)[1] if w.command else "prepare"
    return Outcome(w.case, w.target, False, f"{step} {what}", mode, tuple(w.mutations), w.command, w.stderr_tail(),
                   time.perf_counter() - w.started)


def _scratch() -> str | None:
    """Where cases are written: memory-backed when there is one (psdbake fsyncs every output;
    on a disk that, not psdbake, would set the pace); PSDBAKE_FUZZ_TMP to choose."""
    chosen = os.environ.get("PSDBAKE_FUZZ_TMP")
    if chosen:
        return chosen
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else None


def run(cases: int, seed: int = 0, only: int | None = None, progress: bool = False, mode: str = "text",
        workers: int | None = None, first: int = 0) -> list[Outcome]:
    """Cases first..first+cases-1 (or only one) of a mode, in worker subprocesses."""
    todo = [only] if only is not None else list(range(first, first + cases))
    workers = max(1, min(workers or os.cpu_count() or 1, len(todo)))
    outcomes: list[Outcome] = []
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="psdbake-fuzz-", dir=_scratch()) as folder:
        pool = [_Worker(mode, seed, folder, i) for i in range(workers)]
        sel = selectors.DefaultSelector()
        for w in pool:
            sel.register(w.proc.stdout, selectors.EVENT_READ, w)
        queue = list(reversed(todo))
        trace = bool(os.environ.get("PSDBAKE_FUZZ_TRACE"))

        def replace(w: _Worker) -> None:
            sel.unregister(w.proc.stdout)
            index = pool.index(w)
            pool[index] = _Worker(mode, seed, folder, index)
            sel.register(pool[index].proc.stdout, selectors.EVENT_READ, pool[index])

        def finished(outcome: Outcome) -> None:
            outcomes.append(outcome)
            n = len(outcomes)
            if progress and n % 500 == 0:
                bad = sum(not o.ok for o in outcomes)
                rate = n / (time.perf_counter() - started)
                print(f"  {mode}: {n} cases, {bad} failures, {rate:.1f} cases/s", file=sys.stderr, flush=True)

        try:
            while queue or any(w.case is not None for w in pool):
                for w in list(pool):
                    if w.ready and w.case is None and queue:
                        if w.done >= RECYCLE:
                            w.stop()
                            replace(w)
                            continue
                        case = queue.pop()
                        if trace:
                            print(f"{mode} case {case}", file=sys.stderr, flush=True)
                        w.send(case)
                now = time.perf_counter()
                deadlines = [w.started + CASE_SECONDS - now for w in pool if w.case is not None]
                for key, _ in sel.select(timeout=max(0.0, min(deadlines)) if deadlines else 1.0):
                    w = key.data
                    msgs = w.messages()
                    if msgs is None:  # the worker died: a crash inside the case
                        w.proc.wait()
                        if w.case is not None:
                            finished(_dead(w, mode, seed, hang=False))
                            shutil.rmtree(os.path.join(folder, f"{mode}{w.case}"), ignore_errors=True)
                        w.stop(kill=True)
                        replace(w)
                        continue
                    for msg in msgs:
                        if msg["kind"] == "ready":
                            w.ready = True
                        elif msg["kind"] == "target":
                            w.target = msg["value"]
                        elif msg["kind"] == "mutations":
                            w.mutations = msg["value"]
                        elif msg["kind"] == "command":
                            w.command = msg["value"]
                        elif msg["kind"] == "outcome":
                            value = msg["value"]
                            value["mutations"] = tuple(value["mutations"])
                            finished(Outcome(**value))
                            w.case = None
                            w.done += 1
                now = time.perf_counter()
                for w in list(pool):
                    if w.case is not None and now - w.started > CASE_SECONDS:
                        w.stop(kill=True)
                        finished(_dead(w, mode, seed, hang=True))
                        shutil.rmtree(os.path.join(folder, f"{mode}{w.case}"), ignore_errors=True)
                        replace(w)
        finally:
            for w in pool:
                w.stop(kill=w.case is not None)
    outcomes.sort(key=lambda o: o.case)
    return outcomes


# ---------------------------------------------------------------------------------------
# reporting


def failure_class(o: Outcome) -> str:
    """A failure's class: the command, the rule broken and the message with numbers, paths
    and names blanked (so one defect counts once however many cases reach it)."""
    text = o.what
    text = re.sub(r"/[^\s:'\"]+/", "", text)  # folders
    text = re.sub(r"<[^>]*>", "<P>", text)
    text = re.sub(r"'[^']*'|\"[^\"]*\"", "'S'", text)
    text = re.sub(r"0x[0-9a-f]+", "N", text)
    text = re.sub(r"-?\b\d+(\.\d+)?(e[-+]?\d+)?\b", "N", text)
    text = re.sub(r"\b(asset|examples|anim|correctives|fit_out|weights|cache)\.usd[ac]\b", "FILE", text)
    return text[:140]


def summary(mode: str, outcomes: list[Outcome], seed: int, seconds: float, samples: int = 1) -> list[str]:
    failures = [o for o in outcomes if not o.ok]
    kinds: dict[str, int] = {}
    for o in outcomes:
        key = o.what.split(":")[0] if o.ok else "FAIL"
        kinds[key] = kinds.get(key, 0) + 1
    classes: dict[str, list[Outcome]] = {}
    for o in failures:
        classes.setdefault(failure_class(o), []).append(o)
    lines = []
    for klass, members in sorted(classes.items(), key=lambda kv: -len(kv[1])):
        lines.append(f"FAIL [{mode}] {len(members)} case(s): {klass}")
        for o in members[:samples]:
            lines.append(f"  case {o.case} ({o.target}): replay: python -m tests.fuzz --mode {mode} --seed {seed} "
                         f"--only {o.case}")
            for m in o.mutations:
                lines.append(f"    mutation: {m}")
            lines.append(f"    command:  {o.command}")
            for ln in o.stderr.splitlines()[:3]:
                lines.append(f"    stderr:   {ln[:300]}")
    rate = len(outcomes) / seconds if seconds else 0.0
    lines.append(f"fuzz [{mode}]: {len(outcomes)} cases tried (seed {seed}), {len(failures)} failures in "
                 f"{len(classes)} classes, {seconds:.0f} s ({rate:.1f} cases/s); outcomes: "
                 + ", ".join(f"{k} {v}" for k, v in sorted(kinds.items())))
    return lines


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", default="text",
                        help="text (default), sdf, usdc, or several separated by commas, or all")
    parser.add_argument("--cases", type=int, default=20000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--only", type=int, default=None, help="replay one case and show it in full")
    parser.add_argument("--first", type=int, default=0, help="number of the first case")
    parser.add_argument("--workers", type=int, default=None, help="worker processes (default: one per core)")
    parser.add_argument("--samples", type=int, default=1, help="sample cases printed per failure class")
    parser.add_argument("--keep", metavar="DIR", help="with --only: copy the case's input files to DIR")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--folder", help=argparse.SUPPRESS)
    parser.add_argument("--err", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    modes = list(MODES) if args.mode == "all" else args.mode.split(",")
    for m in modes:
        if m not in MODES:
            parser.error(f"unknown mode {m!r} (choose from {', '.join(MODES)}, all)")
    if args.worker:
        _worker(modes[0], args.seed, args.folder, args.err)
        return
    # every fuzzed crate file that passes the probe would leave a verdict in the user's cache:
    # one cache folder of the run's own, inherited by the workers, removed at the end
    cache = tempfile.mkdtemp(prefix="psdbake-fuzz-cache-")
    os.environ["PSDBAKE_CACHE_DIR"] = cache
    atexit.register(shutil.rmtree, cache, True)
    if args.keep and args.only is None:
        parser.error("--keep needs --only")
    # SIGTERM unwinds like Ctrl-C: workers stopped, case folders removed
    signal.signal(signal.SIGTERM, _interrupt)
    failed = False
    for mode in modes:
        started = time.perf_counter()
        if args.keep:
            os.makedirs(args.keep, exist_ok=True)
            folder = tempfile.mkdtemp(prefix="psdbake-fuzz-")
            outcome = run_case(args.only, args.seed, folder, mode, keep=True)
            kept = os.path.join(folder, f"{mode}{args.only}")
            for name in os.listdir(kept):
                shutil.copy2(os.path.join(kept, name), os.path.join(args.keep, name))
            shutil.rmtree(folder, ignore_errors=True)
            outcomes = [outcome]
            print(f"case files copied to {args.keep}")
        else:
            outcomes = run(args.cases, args.seed, args.only, progress=True, mode=mode, workers=args.workers,
                           first=args.first)
        seconds = time.perf_counter() - started
        if args.only is not None:
            o = outcomes[0]
            print(f"[{mode}] case {o.case} ({o.target}): {'ok' if o.ok else 'FAIL'}: {o.what}")
            for m in o.mutations:
                print(f"  mutation: {m}")
            print(f"  last command: {o.command}")
            if o.stderr:
                print("  stderr:\n" + "\n".join("    " + ln for ln in o.stderr.splitlines()))
        for line in summary(mode, outcomes, args.seed, seconds, args.samples):
            print(line, flush=True)
        failed |= any(not o.ok for o in outcomes)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
