"""Blender's simple expressions: the expression tree psdbake builds, its text, and its value.

Blender evaluates a driver whose expression parses as a *simple expression*
(``BLI_expr_pylike_eval``) in C, with no Python, so it runs in files opened with Python
auto-run off, Blender's default. The subset (Blender 2.8 to 5.0, checked in bpy 5.0.1 with
``driver.is_simple_expression``):

- decimal and float literals (``.5``, ``1e-5``); the constants ``pi``, ``True``, ``False``;
  the driver's variable names;
- ``+ - * /``, unary ``-`` and ``+``, ``== != < <= > >=`` (chained), ``and or not`` and the
  conditional ``a if c else b``, which evaluates only the branch taken;
- ``min`` and ``max`` of any number of arguments, ``radians degrees abs fabs floor ceil trunc
  round int sin cos tan asin acos atan atan2 exp log`` (one or two arguments) ``sqrt pow fmod
  lerp clamp`` (one or three) ``smoothstep``. Not ``**``, which makes an expression Python.

Numbers: a variable's value reaches the expression as float32 (``DriverVar.curval``), the
expression is evaluated in float64, and its result is stored as float32 (the driven property,
``ChannelDriver.curval``). So every quantity handed from one driver to the next is rounded
to float32, while everything inside one expression stays float64. A division by zero or an
invalid operation (``sqrt`` of a negative, ``log(0)``) fails the driver: Blender marks it
invalid and writes 0, so psdbake guards every such operation with a conditional. The text is
cut at 255 characters (``ChannelDriver.expression`` is ``char[256]``).

The tree (``Expr`` and its subclasses) is what the compiler builds; ``render`` writes its
text with the fewest parentheses Python's precedence allows and names its variables;
``compile_text`` checks a text against the subset above and returns a Python function with
Blender's semantics (C ``round``, ``clamp``'s comparisons), which the tests run with float32
between drivers to predict what Blender computes.
"""

from __future__ import annotations

import ast
import itertools
import math
import string
from collections.abc import Callable, Hashable, Iterator, Sequence
from dataclasses import dataclass, fields

import numpy as np

from ...errors import SimpleExpressionError

#: ``ChannelDriver.expression`` is ``char[256]``: longer text is cut.
EXPRESSION_LIMIT = 255

# Python's operator precedence, low to high: the renderer parenthesises a child whose
# precedence is below what its place needs.
_IF, _OR, _AND, _NOT, _CMP, _ADD, _MUL, _NEG, _ATOM = range(1, 10)


class Expr:
    """A node of an expression tree: immutable, compared and hashed by value.

    The compiler shares sub-trees (a joint's coordinates feed every distance), so a tree is a
    DAG whose expansion can be far larger than its nodes: hashes are cached, and the walks
    below (``text_bounds``, ``named_parts``) visit each node object once."""

    def _fields(self) -> tuple:
        return tuple(getattr(self, f.name) for f in fields(self))  # type: ignore[arg-type]

    def __hash__(self) -> int:
        cached = self.__dict__.get("_hash")
        if cached is None:
            cached = hash((type(self).__name__, self._fields()))
            object.__setattr__(self, "_hash", cached)
        return cached

    def __eq__(self, other: object) -> bool:
        if self is other:
            return True
        if type(self) is not type(other) or hash(self) != hash(other):
            return False
        return self._fields() == other._fields()


@dataclass(frozen=True, eq=False)
class Num(Expr):
    value: float


@dataclass(frozen=True, eq=False)
class Var(Expr):
    """A driver variable: ``source`` is what it reads (``graph.BoneChannel``, ``graph.Prop``)."""

    source: Hashable


@dataclass(frozen=True, eq=False)
class Add(Expr):
    terms: tuple[Expr, ...]


@dataclass(frozen=True, eq=False)
class Mul(Expr):
    factors: tuple[Expr, ...]


@dataclass(frozen=True, eq=False)
class Div(Expr):
    num: Expr
    den: Expr


@dataclass(frozen=True, eq=False)
class Neg(Expr):
    arg: Expr


@dataclass(frozen=True, eq=False)
class Call(Expr):
    name: str
    args: tuple[Expr, ...]


@dataclass(frozen=True, eq=False)
class Cmp(Expr):
    op: str  # one of _COMPARISONS
    left: Expr
    right: Expr


@dataclass(frozen=True, eq=False)
class IfElse(Expr):
    """``then if test else other``: Blender evaluates ``test`` first and only the branch taken."""

    then: Expr
    test: Expr
    other: Expr


@dataclass(frozen=True, eq=False)
class Named(Expr):
    """A quantity that may become a driven property of its own (``graph.lay_out`` decides):
    rendered inline while it fits, else stored under ``name`` and read through a variable.
    ``exact``: stored, it takes two float32 properties (value and remainder), because its
    float32 rounding would be amplified on the way to a weight (``graph``)."""

    name: str
    expr: Expr
    exact: bool = False


_PRECEDENCE: dict[type, int] = {Add: _ADD, Mul: _MUL, Div: _MUL, Neg: _NEG, Cmp: _CMP, IfElse: _IF}


def precedence(e: Expr) -> int:
    """Python's precedence of e's outermost operation (a negative number counts as unary minus)."""
    while isinstance(e, Named):
        e = e.expr
    if isinstance(e, Num):
        return _NEG if e.value < 0 else _ATOM
    return _PRECEDENCE.get(type(e), _ATOM)


# --- building ------------------------------------------------------------------------------

def num(value: float) -> Num:
    if not math.isfinite(value):
        raise SimpleExpressionError(f"constant {value!r} is not finite")
    return Num(float(value))


def add(*terms: Expr) -> Expr:
    """The sum, nested sums spliced in (left to right, as Blender adds); 0 for none."""
    flat: list[Expr] = []
    for t in terms:
        flat.extend(t.terms if isinstance(t, Add) else (t,))
    flat = [t for t in flat if not (isinstance(t, Num) and t.value == 0.0)]
    if not flat:
        return Num(0.0)
    return flat[0] if len(flat) == 1 else Add(tuple(flat))


def mul(*factors: Expr) -> Expr:
    """The product, nested products spliced in; a factor of 1 dropped, a factor of -1 made a
    negation (exact either way), 0 for a factor of 0."""
    flat: list[Expr] = []
    for f in factors:
        flat.extend(f.factors if isinstance(f, Mul) else (f,))
    if any(isinstance(f, Num) and f.value == 0.0 for f in flat):
        return Num(0.0)
    flips = sum(1 for f in flat if isinstance(f, Num) and f.value == -1.0)
    flat = [f for f in flat if not (isinstance(f, Num) and abs(f.value) == 1.0)]
    product = Num(1.0) if not flat else flat[0] if len(flat) == 1 else Mul(tuple(flat))
    return neg(product) if flips % 2 else product


def sub(a: Expr, b: Expr) -> Expr:
    return add(a, neg(b))


def neg(a: Expr) -> Expr:
    if isinstance(a, Num):
        return Num(-a.value)
    if isinstance(a, Neg):
        return a.arg
    return Neg(a)


def div(a: Expr, b: Expr) -> Expr:
    return Div(a, b)


def call(name: str, *args: Expr) -> Call:
    if name not in FUNCTIONS or len(args) not in FUNCTIONS[name][0]:
        raise SimpleExpressionError(f"{name}() with {len(args)} argument(s) is not a simple-expression function")
    return Call(name, tuple(args))


def cmp(op: str, left: Expr, right: Expr) -> Cmp:
    if op not in _COMPARISONS:
        raise SimpleExpressionError(f"{op!r} is not a comparison")
    return Cmp(op, left, right)


def if_else(then: Expr, test: Expr, other: Expr) -> IfElse:
    return IfElse(then, test, other)


def square(a: Expr) -> Expr:
    """a squared, as ``pow(a,2)`` (``**`` is not simple); ``pow`` of a float and 2 is a*a."""
    return call("pow", a, Num(2.0))


# --- text ----------------------------------------------------------------------------------

def number(value: float) -> str:
    """The shortest text Blender and Python both read back as exactly ``value``: Python's
    ``repr`` (round-trip), an integral value without ``.0``, no leading ``0`` before the point
    and no zero padding in the exponent (``-.5``, ``1e-5``)."""
    if not math.isfinite(value):
        raise SimpleExpressionError(f"constant {value!r} is not finite")
    text = str(int(value)) if value == int(value) and abs(value) < 1e15 else repr(value)
    text = text.replace("e-0", "e-").replace("e+0", "e+")
    if text.startswith("0."):
        text = text[1:]
    elif text.startswith("-0."):
        text = "-" + text[2:]
    return text


def variable_names() -> Iterator[str]:
    """a, b, ..., z, then a0, a1, ...: never a keyword, function or constant of the subset."""
    yield from string.ascii_lowercase
    for letter, digit in itertools.product(string.ascii_lowercase, string.digits):
        yield letter + digit


Swap = Callable[["Named"], "Expr | None"]  # a Named part's stand-in (its node's variable), or None


class Renderer:
    """Writes expressions as text, naming each distinct variable source on first use. A
    ``Named`` part for which ``swap`` gives a stand-in is written as that stand-in."""

    def __init__(self, swap: Swap | None = None) -> None:
        self.names: dict[Hashable, str] = {}
        self._fresh = variable_names()
        self._swap = swap

    def variables(self) -> list[tuple[str, Hashable]]:
        return [(name, source) for source, name in self.names.items()]

    def text(self, e: Expr, need: int = _IF) -> str:
        while isinstance(e, Named):
            stand_in = self._swap(e) if self._swap is not None else None
            e = stand_in if stand_in is not None else e.expr
        inner = self._text(e)
        return f"({inner})" if precedence(e) < need else inner

    def _text(self, e: Expr) -> str:
        if isinstance(e, Num):
            return number(e.value)
        if isinstance(e, Var):
            if e.source not in self.names:
                self.names[e.source] = next(self._fresh)
            return self.names[e.source]
        if isinstance(e, Add):
            out = self.text(e.terms[0], _ADD)
            for t in e.terms[1:]:
                negated = _negated(t)
                out += f"-{self.text(negated, _MUL)}" if negated is not None else f"+{self.text(t, _MUL)}"
            return out
        if isinstance(e, Mul):
            return "*".join([self.text(e.factors[0], _MUL), *(self.text(f, _NEG) for f in e.factors[1:])])
        if isinstance(e, Div):
            return f"{self.text(e.num, _MUL)}/{self.text(e.den, _NEG)}"
        if isinstance(e, Neg):
            return f"-{self.text(e.arg, _NEG)}"
        if isinstance(e, Call):
            return f"{e.name}({','.join(self.text(a, _IF) for a in e.args)})"
        if isinstance(e, Cmp):
            return f"{self.text(e.left, _ADD)}{e.op}{self.text(e.right, _ADD)}"
        if isinstance(e, IfElse):
            return f"{self.text(e.then, _OR)} if {self.text(e.test, _OR)} else {self.text(e.other, _IF)}"
        raise TypeError(f"not an expression: {e!r}")


def _negated(t: Expr) -> Expr | None:
    """-t as a tree that renders without a sign, when t carries one (``a+-b`` -> ``a-b``)."""
    if isinstance(t, Neg):
        return t.arg
    if isinstance(t, Num) and t.value < 0:
        return Num(-t.value)
    if isinstance(t, Mul) and isinstance(t.factors[0], Num) and t.factors[0].value < 0:
        return mul(Num(-t.factors[0].value), *t.factors[1:])
    return None


def render(e: Expr, swap: Swap | None = None) -> tuple[str, list[tuple[str, Hashable]]]:
    """(text, [(variable name, source)]) of one driver expression."""
    r = Renderer(swap)
    text = r.text(e)
    return text, r.variables()


def children(e: Expr) -> tuple[Expr, ...]:
    """e's direct sub-expressions."""
    if isinstance(e, Named):
        return (e.expr,)
    if isinstance(e, Add):
        return e.terms
    if isinstance(e, Mul):
        return e.factors
    if isinstance(e, Div):
        return (e.num, e.den)
    if isinstance(e, Neg):
        return (e.arg,)
    if isinstance(e, Call):
        return e.args
    if isinstance(e, Cmp):
        return (e.left, e.right)
    if isinstance(e, IfElse):
        return (e.then, e.test, e.other)
    return ()


def with_children(e: Expr, new: Sequence[Expr]) -> Expr:
    """e's node with ``new`` in place of its direct sub-expressions (``children``)."""
    if isinstance(e, Named):
        return Named(e.name, new[0], e.exact)
    if isinstance(e, Add):
        return Add(tuple(new))
    if isinstance(e, Mul):
        return Mul(tuple(new))
    if isinstance(e, Div):
        return Div(new[0], new[1])
    if isinstance(e, Neg):
        return Neg(new[0])
    if isinstance(e, Call):
        return Call(e.name, tuple(new))
    if isinstance(e, Cmp):
        return Cmp(e.op, new[0], new[1])
    if isinstance(e, IfElse):
        return IfElse(new[0], new[1], new[2])
    return e


def named_parts(e: Expr, swap: Swap | None = None) -> list[Named]:
    """The outermost ``Named`` sub-expressions of e (e itself excluded) that ``swap`` has no
    stand-in for, each once, in first-seen order (every node object visited once)."""
    out: dict[Named, None] = {}
    seen: set[int] = set()
    stack = list(reversed(children(e)))
    while stack:
        c = stack.pop()
        if id(c) in seen:
            continue
        seen.add(id(c))
        if isinstance(c, Named):
            if swap is None or swap(c) is None:
                out.setdefault(c)
        else:
            stack.extend(reversed(children(c)))
    return list(out)


class TextBounds:
    """Bounds on the length of ``render(e, swap)``'s text without rendering it: (characters
    other than variable names, variable occurrences), each node object computed once, so a
    tree whose expansion is huge costs its node count. Real names take 1 character (the first
    26 distinct variables) or 2, so the text is between chars + occurrences and chars + 2
    occurrences long. Valid while ``swap`` answers the same (``graph`` makes a new one per node)."""

    def __init__(self, swap: Swap | None = None) -> None:
        self._swap = swap
        self._memo: dict[int, tuple[Expr, tuple[int, int]]] = {}

    def low(self, e: Expr) -> int:
        chars, names = self.of(e)
        return chars + names

    def of(self, e: Expr, need: int = _IF) -> tuple[int, int]:
        while isinstance(e, Named):
            stand_in = self._swap(e) if self._swap is not None else None
            e = stand_in if stand_in is not None else e.expr
        hit = self._memo.get(id(e))
        if hit is not None and hit[0] is e:
            chars, names = hit[1]
        else:
            chars, names = self._inner(e)
            self._memo[id(e)] = (e, (chars, names))
        return (chars + 2, names) if precedence(e) < need else (chars, names)

    def _sum(self, parts: Iterator[tuple[int, int]], extra: int) -> tuple[int, int]:
        chars, names = extra, 0
        for c, n in parts:
            chars, names = chars + c, names + n
        return chars, names

    def _inner(self, e: Expr) -> tuple[int, int]:  # mirrors Renderer._text
        if isinstance(e, Num):
            return len(number(e.value)), 0
        if isinstance(e, Var):
            return 0, 1
        if isinstance(e, Add):
            rest = ((_negated(t) or t) for t in e.terms[1:])
            return self._sum(iter([self.of(e.terms[0], _ADD), *(self.of(t, _MUL) for t in rest)]), len(e.terms) - 1)
        if isinstance(e, Mul):
            return self._sum(iter([self.of(e.factors[0], _MUL), *(self.of(f, _NEG) for f in e.factors[1:])]),
                             len(e.factors) - 1)
        if isinstance(e, Div):
            return self._sum(iter([self.of(e.num, _MUL), self.of(e.den, _NEG)]), 1)
        if isinstance(e, Neg):
            return self._sum(iter([self.of(e.arg, _NEG)]), 1)
        if isinstance(e, Call):
            return self._sum((self.of(a, _IF) for a in e.args), len(e.name) + 2 + max(0, len(e.args) - 1))
        if isinstance(e, Cmp):
            return self._sum(iter([self.of(e.left, _ADD), self.of(e.right, _ADD)]), len(e.op))
        if isinstance(e, IfElse):
            return self._sum(iter([self.of(e.then, _OR), self.of(e.test, _OR), self.of(e.other, _IF)]), 10)
        raise TypeError(f"not an expression: {e!r}")


# --- value ---------------------------------------------------------------------------------

def _c_round(x: float) -> float:
    """C's ``round``: halves away from zero (Python's rounds them to even)."""
    a = abs(x)
    r = math.floor(a)
    if a - r >= 0.5:
        r += 1
    return math.copysign(float(r), x)


def _clamp(x: float, lo: float = 0.0, hi: float = 1.0) -> float:
    """Blender's CLAMP macro: below lo -> lo, else above hi -> hi."""
    if x < lo:
        return lo
    if x > hi:
        return hi
    return x


def _log(a: float, b: float | None = None) -> float:
    return math.log(a) if b is None else math.log(a) / math.log(b)


def _smoothstep(a: float, b: float, x: float) -> float:
    t = _clamp((x - a) / (b - a), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


#: name -> (argument counts, Python function with Blender's semantics). ``min``/``max`` take
#: any positive count.
FUNCTIONS: dict[str, tuple[range | tuple[int, ...], Callable[..., float]]] = {
    "radians": ((1,), lambda a: a * math.pi / 180.0),
    "degrees": ((1,), lambda a: a * 180.0 / math.pi),
    "abs": ((1,), math.fabs),
    "fabs": ((1,), math.fabs),
    "floor": ((1,), lambda a: float(math.floor(a))),
    "ceil": ((1,), lambda a: float(math.ceil(a))),
    "trunc": ((1,), lambda a: float(math.trunc(a))),
    "int": ((1,), lambda a: float(math.trunc(a))),
    "round": ((1,), _c_round),
    "sin": ((1,), math.sin),
    "cos": ((1,), math.cos),
    "tan": ((1,), math.tan),
    "asin": ((1,), math.asin),
    "acos": ((1,), math.acos),
    "atan": ((1,), math.atan),
    "atan2": ((2,), math.atan2),
    "exp": ((1,), math.exp),
    "log": ((1, 2), _log),
    "sqrt": ((1,), math.sqrt),
    "pow": ((2,), math.pow),
    "fmod": ((2,), math.fmod),
    "lerp": ((3,), lambda a, b, x: a * (1.0 - x) + b * x),
    "clamp": ((1, 3), _clamp),
    "smoothstep": ((3,), _smoothstep),
    "min": (range(1, 1 << 16), min),
    "max": (range(1, 1 << 16), max),
}

_CONSTANTS = {"pi": math.pi}
_COMPARISONS = {"==": ast.Eq, "!=": ast.NotEq, "<": ast.Lt, "<=": ast.LtE, ">": ast.Gt, ">=": ast.GtE}
_BINARY = (ast.Add, ast.Sub, ast.Mult, ast.Div)
_UNARY = (ast.USub, ast.UAdd, ast.Not)
_STRUCTURE = (ast.Expression, ast.Load, ast.And, ast.Or, *_BINARY, *_UNARY)


def check_text(text: str, variables: Sequence[str]) -> ast.Expression:
    """The parsed text, if it is a simple expression over ``variables`` that Blender keeps
    whole (at most ``EXPRESSION_LIMIT`` ASCII characters); else SimpleExpressionError."""
    if len(text) > EXPRESSION_LIMIT:
        raise SimpleExpressionError(f"{len(text)} characters: Blender keeps {EXPRESSION_LIMIT}")
    if not text.isascii():
        raise SimpleExpressionError("not ASCII")
    try:
        tree = ast.parse(text, mode="eval")
    except SyntaxError as exc:
        raise SimpleExpressionError(f"not an expression: {exc.msg}") from None
    known = set(variables)
    for node in ast.walk(tree):
        if isinstance(node, _STRUCTURE):
            continue
        if isinstance(node, ast.BinOp) and isinstance(node.op, _BINARY):
            continue
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, _UNARY):
            continue
        if isinstance(node, ast.BoolOp | ast.IfExp):
            continue
        if isinstance(node, ast.Compare) and all(type(op) in _COMPARISONS.values() for op in node.ops):
            continue
        if isinstance(node, ast.cmpop) and type(node) in _COMPARISONS.values():
            continue
        if isinstance(node, ast.Constant) and type(node.value) in (int, float, bool):
            continue
        if isinstance(node, ast.Call):
            name = node.func.id if isinstance(node.func, ast.Name) else None
            if name in FUNCTIONS and not node.keywords and len(node.args) in FUNCTIONS[name][0] \
                    and not any(isinstance(a, ast.Starred) for a in node.args) and name not in known:
                continue
            raise SimpleExpressionError(f"call {ast.unparse(node)!r} is not a simple-expression function call")
        if isinstance(node, ast.Name):
            if node.id in known or node.id in _CONSTANTS or node.id in FUNCTIONS:
                continue  # a function name is checked with its call
            raise SimpleExpressionError(f"unknown name {node.id!r}")
        raise SimpleExpressionError(f"{type(node).__name__} is not in Blender's simple expressions")
    bare = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} - known - set(_CONSTANTS)
    called = {n.func.id for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
    if bare - called:
        raise SimpleExpressionError(f"function {sorted(bare - called)[0]!r} used as a value")
    return tree


def compile_text(text: str, variables: Sequence[str]) -> Callable[..., float]:
    """A function of the variables' values (keyword arguments) computing the text as Blender
    does, in float64; raises SimpleExpressionError where Blender would fail the driver
    (division by zero, an invalid operation, a result that is not finite)."""
    tree = check_text(text, variables)
    code = compile(tree, "<simple expression>", "eval")
    scope: dict[str, object] = {"__builtins__": {}, **_CONSTANTS, **{k: f for k, (_, f) in FUNCTIONS.items()}}

    def value(**values: float) -> float:
        try:
            result = float(eval(code, scope, values))  # the text passed check_text: the simple subset only
        except ZeroDivisionError:
            raise SimpleExpressionError(f"division by zero in {text!r} at {values}") from None
        except (ValueError, OverflowError) as exc:
            raise SimpleExpressionError(f"invalid operation ({exc}) in {text!r} at {values}") from None
        if not math.isfinite(result):
            raise SimpleExpressionError(f"{text!r} is not finite at {values}")
        return result

    return value


def float32(value: float) -> float:
    """value as Blender stores a driver's result or reads a variable: rounded to float32."""
    with np.errstate(over="raise"):
        try:
            return float(np.float32(value))
        except FloatingPointError:
            raise SimpleExpressionError(f"{value!r} overflows float32") from None
