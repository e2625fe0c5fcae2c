"""A driver graph: expressions laid out as Blender drivers that each fit 255 characters.

A mesh's live correctives are a list of drivers on its shape-key datablock (``Key``): each
either drives a custom property of the Key (an intermediate quantity, a *node*) or a shape
key's value (a *channel*). A driver's variables read a bone's rotation (``BoneChannel``:
a ``TRANSFORMS`` variable, quaternion component, local space, so constraints such as IK
count) or a node (``Prop``: a ``SINGLE_PROP`` variable on the same Key). Drivers are listed
in dependency order.

Layout (``lay_out``): every channel's expression is built whole by the compiler, with the
quantities worth sharing marked ``Named`` (pose coordinates, squared distances, RBF outputs,
gate activations). A ``Named`` part is written inline as long as the expression holding it
fits in ``simple.EXPRESSION_LIMIT`` characters, and becomes a node of its own otherwise,
longest first; a sum too long even then is split into partial sums, each a node. Inline parts
are computed in float64 within one expression, nodes are rounded to float32 (``simple``):
so inlining is both cheaper (Blender pays per driver, measured in docs/decisions/
blender-live-drivers.md) and more exact. A node, once made, serves every later expression
that needs the same quantity.

Exact nodes: a float32 node loses 2^-24 of its value, and some quantities pass that loss on
amplified: a partial sum of a kernel sum whose coefficients cancel (a well-fitted weight of
0.3 can be the sum of terms of 10^3), or a squared distance multiplied on its way by a large
coefficient. Those (the compiler's ``Named(..., exact=True)`` and every partial sum made here)
are stored as two properties, the value v rounded (``name``) and what the rounding lost,
v - float32(v) rounded (``name~lo``, its driver the same expression minus the first), and read
as their sum: 48 bits instead of 24, for one more driver. Measured on the shot sculpts
(docs/decisions/blender-live-drivers.md): weights 2.9e-5 off eval's with every node float32,
4e-7 with these stored exactly.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from ...errors import LayoutError, SimpleExpressionError
from .simple import (
    EXPRESSION_LIMIT,
    Add,
    Expr,
    Named,
    Neg,
    TextBounds,
    Var,
    children,
    compile_text,
    float32,
    named_parts,
    render,
    with_children,
)

#: Blender's name limit (``MAX_IDPROP_NAME`` - 1 bytes, as shape-key names).
MAX_NAME_BYTES = 63
#: Quaternion components a bone variable reads (``transform_type`` ``ROT_W`` ...).
QUATERNION_CHANNELS = ("W", "X", "Y", "Z")
#: Characters an exact node's remainder driver adds to its value's expression: ``(...)-v``,
#: v a variable name of at most 3 characters (``simple.variable_names``).
REMAINDER_MARGIN = 6


@dataclass(frozen=True)
class BoneChannel:
    """One component of a joint's rotation away from its rest (= bind) pose, as Blender's
    ``TRANSFORMS`` driver variable reads it (``rotation_mode`` QUATERNION, ``LOCAL_SPACE``: after
    constraints such as IK, relative to the rest pose and the parent)."""

    joint: str  # skeleton joint path
    channel: str  # one of QUATERNION_CHANNELS


@dataclass(frozen=True)
class Prop:
    """A node: a custom property of the mesh's Key, driven in turn."""

    name: str


@dataclass(frozen=True)
class Driver:
    """One Blender driver: ``target`` is a node's property name (``kind`` "node") or a shape
    key's name (``kind`` "channel"); ``variables`` name what each variable reads."""

    kind: str
    target: str
    expression: str
    variables: tuple[tuple[str, BoneChannel | Prop], ...]


@dataclass(frozen=True)
class DriverGraph:
    """A mesh's drivers in dependency order (a node before every driver that reads it)."""

    drivers: tuple[Driver, ...]

    @property
    def nodes(self) -> tuple[Driver, ...]:
        return tuple(d for d in self.drivers if d.kind == "node")

    @property
    def channels(self) -> tuple[Driver, ...]:
        return tuple(d for d in self.drivers if d.kind == "channel")

    @property
    def joints(self) -> tuple[str, ...]:
        """The joints whose rotations the graph reads, sorted."""
        return tuple(sorted({s.joint for d in self.drivers for _, s in d.variables if isinstance(s, BoneChannel)}))


def property_name(name: str) -> str:
    """A custom-property name Blender keeps whole and a driver path can quote: at most
    ``MAX_NAME_BYTES`` bytes (longer names keep a prefix and 8 hex digits of their SHA-1, as
    ``channels.short_name``) and no quote or backslash."""
    name = name.replace('"', "_").replace("\\", "_")
    if len(name.encode()) <= MAX_NAME_BYTES:
        return name
    digest = hashlib.sha1(name.encode()).hexdigest()[:8]
    return name.encode()[: MAX_NAME_BYTES - 9].decode(errors="ignore") + "_" + digest


@dataclass
class _Layout:
    drivers: list[Driver] = field(default_factory=list)
    made: dict[Expr, Expr] = field(default_factory=dict)  # a node's expression -> what reads it
    used: set[str] = field(default_factory=set)
    bounds: TextBounds = field(init=False)

    def __post_init__(self) -> None:
        self.bounds = TextBounds(self.known)

    def known(self, n: Named) -> Expr | None:
        return self.made.get(_quantity(n))

    def fits(self, e: Expr, limit: int = EXPRESSION_LIMIT) -> bool:
        """Whether e's text is within the limit: decided by its bounds, rendered only in between."""
        chars, names = self.bounds.of(e)
        if chars + 2 * names <= limit:
            return True
        if chars + names > limit:
            return False
        return len(render(e, self.known)[0]) <= limit

    def node(self, n: Named) -> Expr:
        """n as a node (made once, its own parts laid out first): its property's variable, or
        for an exact node the sum of its two properties' variables."""
        have = self.known(n)
        if have is not None:
            return have
        body = self.fit(n.expr, n.name, EXPRESSION_LIMIT - REMAINDER_MARGIN if n.exact else EXPRESSION_LIMIT)
        name = self.fresh(n.name)
        self.drivers.append(self.driver("node", name, body))
        value: Expr = Var(Prop(name))
        if n.exact:
            rest = self.fresh(f"{n.name}~lo")
            self.drivers.append(self.driver("node", rest, Add((body, Neg(value)))))
            value = Add((value, Var(Prop(rest))))
        self.made[_quantity(n)] = value
        self.bounds = TextBounds(self.known)  # n is a variable from now on
        return value

    def fresh(self, wanted: str) -> str:
        """A property name not used yet: ``wanted`` as Blender keeps it, else numbered."""
        name, k = property_name(wanted), 1
        while name in self.used:
            k += 1
            name = property_name(f"{wanted}~{k}")
        self.used.add(name)
        return name

    def fit(self, e: Expr, name: str, limit: int = EXPRESSION_LIMIT) -> Expr:
        """e, with enough of its parts made nodes that its text fits ``limit``: the longest
        part first, then, when no part is left to make, its longest sum split."""
        while isinstance(e, Named):  # a renamed quantity: its node's variable, or what it names
            e = self.known(e) or e.expr
        while not self.fits(e, limit):
            parts = sorted(named_parts(e, self.known), key=lambda n: (-self.bounds.low(n), n.name))
            if parts:
                self.node(parts[0])
                continue
            sums = sorted(_sums(e), key=lambda a: -self.bounds.low(a))
            if not sums or len(sums[0].terms) < 2:
                raise LayoutError(f"{name}: {render(e, self.known)[0][:80]}... does not fit {limit} characters")
            e = _swapped(e, sums[0], self.split(sums[0], name))
        return e

    def split(self, e: Add, name: str) -> Expr:
        """A long sum as a sum of partial sums, each filling one expression, or, if it fits
        one, as a part of its own (made a node by the next step of ``fit``). Partial sums are
        exact nodes: their terms may cancel, and each keeps its share of the total's bits."""
        limit = EXPRESSION_LIMIT - REMAINDER_MARGIN
        terms = [self.fit(t, name, limit) for t in e.terms]
        chunks: list[list[Expr]] = [[]]
        for t in terms:
            if chunks[-1] and not self.fits(Add((*chunks[-1], t)), limit):
                chunks.append([])
            chunks[-1].append(t)
        if len(chunks) == 1:  # the sum fits one expression of its own, not inside e: a node
            return Named(f"{name}+", Add(tuple(terms)), exact=True)
        return Add(tuple(Named(f"{name}+{i}", Add(tuple(c)) if len(c) > 1 else c[0], exact=True)
                         for i, c in enumerate(chunks)))

    def driver(self, kind: str, target: str, e: Expr) -> Driver:
        text, variables = render(e, self.known)
        if len(text) > EXPRESSION_LIMIT:
            raise LayoutError(f"{target}: {len(text)} characters")
        sources: list[tuple[str, BoneChannel | Prop]] = []
        for v, source in variables:
            if not isinstance(source, BoneChannel | Prop):
                raise LayoutError(f"{target}: variable {v} reads {source!r}, neither a bone nor a node")
            sources.append((v, source))
        return Driver(kind, target, text, tuple(sources))


def _sums(e: Expr) -> list[Add]:
    """The sums in e, e included, outside its Named parts."""
    out = [e] if isinstance(e, Add) else []
    for c in children(e):
        if not isinstance(c, Named):
            out += _sums(c)
    return out


def _swapped(e: Expr, old: Expr, new: Expr) -> Expr:
    """e with the sub-expression ``old`` (this very object) replaced by new."""
    if e is old:
        return new
    if isinstance(e, Named):
        return e
    return with_children(e, [_swapped(c, old, new) for c in children(e)])


def _quantity(n: Named) -> Expr:
    """What n stands for: a Named that only renames another stands for the same quantity."""
    e = n.expr
    while isinstance(e, Named):
        e = e.expr
    return e


def lay_out(channels: Iterable[tuple[str, Expr]]) -> DriverGraph:
    """The drivers computing each (shape key name, value expression), in dependency order."""
    layout = _Layout()
    for channel, e in channels:
        layout.drivers.append(layout.driver("channel", channel, layout.fit(e, f"psd:{channel}")))
    return DriverGraph(tuple(layout.drivers))


class Evaluator:
    """A graph's drivers as Python functions with Blender's semantics: variables read as
    float32, each expression in float64, each result stored as float32 (``simple``).
    ``store``: what storing a value does (``simple.float32``; the identity shows what the
    expressions compute before Blender's rounding)."""

    def __init__(self, graph: DriverGraph, store: Callable[[float], float] = float32) -> None:
        self.graph = graph
        self.store = store
        self._steps: list[tuple[Driver, Callable[..., float]]] = [
            (d, compile_text(d.expression, [v for v, _ in d.variables])) for d in graph.drivers]

    def __call__(self, bones: Mapping[BoneChannel, float]) -> dict[str, float]:
        """Every driven value (node property or shape key name -> value) for the bone
        rotations ``bones`` (each component as Blender's variable reads it)."""
        props: dict[str, float] = {}
        out: dict[str, float] = {}
        for d, fn in self._steps:
            values = {v: self.store(bones[s]) if isinstance(s, BoneChannel) else props[s.name] for v, s in d.variables}
            try:
                result = self.store(fn(**values))
            except SimpleExpressionError as exc:
                raise SimpleExpressionError(f"{d.kind} {d.target}: {exc}") from None
            if d.kind == "node":
                props[d.target] = result
            out[d.target] = result
        return out


def bone_inputs(joints: Sequence[str], quaternions: Sequence[Sequence[float]]) -> dict[BoneChannel, float]:
    """The variables' inputs from each joint's (w, x, y, z) rotation away from its rest pose."""
    return {BoneChannel(j, c): float(q[i]) for j, q in zip(joints, quaternions, strict=True)
            for i, c in enumerate(QUATERNION_CHANNELS)}


def check_graph(graph: DriverGraph) -> None:
    """Every driver simple, within the limit, reading only nodes made before it."""
    seen: set[str] = set()
    for d in graph.drivers:
        compile_text(d.expression, [v for v, _ in d.variables])
        for _, s in d.variables:
            if isinstance(s, Prop) and s.name not in seen:
                raise LayoutError(f"{d.target} reads {s.name} before it is driven")
        if d.kind == "node":
            seen.add(d.target)

