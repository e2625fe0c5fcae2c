"""psdbake.export.blender.simple and .graph, without Blender: the simple-expression subset Blender
evaluates without Python, its text, and the layout of expressions into drivers that each fit
Blender's 255 characters (graph.Evaluator predicts, with Blender's float32 between drivers,
what Blender computes; make interop checks Blender itself).
"""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT

from psdbake.errors import SimpleExpressionError
from psdbake.export.blender import graph, simple
from psdbake.export.blender.graph import BoneChannel, Evaluator, check_graph, lay_out
from psdbake.export.blender.simple import EXPRESSION_LIMIT, Named, Var, add, call, mul, num


def identity(v: float) -> float:
    return v


# --- simple expressions ----------------------------------------------------------------------

def test_numbers_read_back_exactly_in_the_shortest_text():
    rng = np.random.default_rng(0)
    values = [*rng.normal(size=200), *(10.0 ** rng.uniform(-20, 20, 200)), -0.5, 0.5, 2.0, -3.0, 1e-5, 1e15, 1e16]
    for v in values:
        text = simple.number(float(v))
        assert float(text) == v, text
        assert not text.startswith(("0.", "-0.")) and "e-0" not in text and "e+0" not in text, text
    assert simple.number(2.0) == "2" and simple.number(-0.25) == "-.25" and simple.number(1e-5) == "1e-5"
    with pytest.raises(SimpleExpressionError):
        simple.number(math.inf)


@pytest.mark.parametrize("text", [
    "a**2", "a.b", "x[0]", "lambda: 1", "'s'", "exp(a, b)", "pow(a)", "min()", "foo(a)", "e", "a if b else c if",
    "exp(x=a)", "sqrt(*a)", "a @ b", "a // b", "a % b", "abs", "a" * (EXPRESSION_LIMIT + 1),
])
def test_texts_outside_the_simple_subset_are_refused(text):
    with pytest.raises(SimpleExpressionError):
        simple.check_text(text, ["a", "b", "c"])


def test_every_function_of_the_subset_is_accepted_with_its_argument_counts():
    for name, (counts, _) in simple.FUNCTIONS.items():
        for n in list(counts)[:3]:
            text = f"{name}({','.join(['a'] * n)})"
            simple.check_text(text, ["a"])
    simple.check_text("1 if 0 < a <= 1 and not a == 2 or a != 3 else -pi*True+False", ["a"])


def test_blender_semantics_of_round_clamp_and_failures():
    assert simple.compile_text("round(a)", ["a"])(a=2.5) == 3.0  # C rounds halves away from zero
    assert simple.compile_text("round(a)", ["a"])(a=-2.5) == -3.0
    assert simple.compile_text("clamp(a)", ["a"])(a=1.5) == 1.0
    assert simple.compile_text("clamp(a,2,1)", ["a"])(a=0.0) == 2.0  # CLAMP: below the min first
    assert simple.compile_text("a if a>0 else 1/a", ["a"])(a=1.0) == 1.0  # only the branch taken runs
    for text, value in (("1/a", 0.0), ("sqrt(a)", -1.0), ("log(a)", 0.0)):
        with pytest.raises(SimpleExpressionError):  # Blender fails the driver: it then stays at 0
            simple.compile_text(text, ["a"])(a=value)


def _tree_value(e: simple.Expr, values: dict) -> float:
    """An independent evaluation of a tree (not through its text)."""
    sub = [_tree_value(c, values) for c in simple.children(e)]
    if isinstance(e, simple.Num):
        return e.value
    if isinstance(e, Var):
        return values[e.source]
    if isinstance(e, Named):
        return sub[0]
    if isinstance(e, simple.Add):
        return _fold(sub, lambda x, y: x + y)
    if isinstance(e, simple.Mul):
        return _fold(sub, lambda x, y: x * y)
    if isinstance(e, simple.Div):
        return sub[0] / sub[1]
    if isinstance(e, simple.Neg):
        return -sub[0]
    if isinstance(e, simple.Call):
        return simple.FUNCTIONS[e.name][1](*sub)
    if isinstance(e, simple.Cmp):
        return float({"<": sub[0] < sub[1], ">": sub[0] > sub[1], "<=": sub[0] <= sub[1], ">=": sub[0] >= sub[1],
                      "==": sub[0] == sub[1], "!=": sub[0] != sub[1]}[e.op])
    if isinstance(e, simple.IfElse):
        return sub[0] if sub[1] else sub[2]
    raise TypeError(e)


def _fold(xs, fn):
    out = xs[0]
    for x in xs[1:]:
        out = fn(out, x)
    return out


def _random_tree(rng, depth: int) -> simple.Expr:
    if depth == 0 or rng.random() < 0.2:
        return Var(str(rng.choice(list("pqrs")))) if rng.random() < 0.6 else num(round(float(rng.normal()), 3))
    kind = rng.integers(0, 8)
    a, b = _random_tree(rng, depth - 1), _random_tree(rng, depth - 1)
    if kind == 0:
        return simple.Add((a, b, _random_tree(rng, depth - 1)))
    if kind == 1:
        return simple.Mul((a, b))
    if kind == 2:
        return simple.Div(a, call("max", num(1.0), call("abs", b)))
    if kind == 3:
        return simple.Neg(a)
    if kind == 4:
        return simple.Add((a, simple.Neg(b)))
    if kind == 5:
        return simple.IfElse(a, simple.Cmp(">", b, num(0.0)), _random_tree(rng, depth - 1))
    if kind == 6:
        return simple.Mul((num(-round(float(rng.uniform(0.5, 2)), 2)), simple.Add((a, b))))
    return call("atan2", a, b)


def test_rendered_text_computes_what_the_tree_says():
    """Precedence and signs: every random tree's text evaluates, by Python's own parser, to the
    tree's value (a wrong parenthesis changes the value)."""
    rng = np.random.default_rng(1)
    for _ in range(400):
        tree = _random_tree(rng, 3)
        text, variables = simple.render(tree)
        values = {s: float(rng.normal()) for s in "pqrs"}
        fn = simple.compile_text(text, [v for v, _ in variables])
        got = fn(**{v: values[s] for v, s in variables})
        assert got == pytest.approx(_tree_value(tree, values), rel=1e-12, abs=1e-12), text


# --- layout ------------------------------------------------------------------------------------

def _bone(j: int) -> Var:
    return Var(BoneChannel(f"J{j}", "W"))


def test_a_long_sum_is_split_into_nodes_that_each_fit():
    terms = [mul(num(1.0 / (i + 3)), call("exp", _bone(i))) for i in range(120)]
    g = lay_out([("out", call("max", num(0.0), add(*terms)))])
    check_graph(g)
    assert all(len(d.expression) <= EXPRESSION_LIMIT for d in g.drivers)
    assert len(g.nodes) >= 10 and len(g.channels) == 1
    inputs = {BoneChannel(f"J{i}", "W"): 0.01 * i for i in range(120)}
    exact = max(0.0, sum(math.exp(0.01 * i) / (i + 3) for i in range(120)))
    assert Evaluator(g, store=identity)(inputs)["out"] == pytest.approx(exact, rel=1e-14)
    assert Evaluator(g)(inputs)["out"] == pytest.approx(exact, rel=len(g.nodes) * 2**-23)


def test_a_shared_quantity_is_made_once_and_inlined_while_it_fits():
    shared = Named("psd:s", add(*(mul(num(0.123456789 * i), _bone(i)) for i in range(12))))
    small = Named("psd:small", mul(num(2.0), _bone(0)))
    g = lay_out([("a", add(shared, small)), ("b", mul(shared, shared, small)), ("c", small)])
    check_graph(g)
    # "a" holds s inline (it fits there); "b" cannot hold it twice, so s becomes one node, and
    # "small" always fits inline
    assert [d.target for d in g.nodes] == ["psd:s"]
    reads = {d.target: [s.name for _, s in d.variables if isinstance(s, graph.Prop)] for d in g.channels}
    assert reads == {"a": [], "b": ["psd:s"], "c": []}
    inputs = {BoneChannel(f"J{i}", "W"): 0.1 * i for i in range(12)}
    s_value = sum(0.123456789 * i * 0.1 * i for i in range(12))
    got = Evaluator(g, store=identity)(inputs)
    assert (got["a"], got["b"]) == pytest.approx((s_value, s_value * s_value * 0.0), abs=1e-12)


def test_property_names_fit_blender():
    assert graph.property_name('psd:"x"\\y') == "psd:_x__y"
    long = graph.property_name("psd:" + "g" * 100 + ":t1")
    assert len(long.encode()) == graph.MAX_NAME_BYTES and long != graph.property_name("psd:" + "g" * 100 + ":t2")


def test_the_pure_modules_load_neither_usd_nor_blender():
    code = ("import sys, psdbake.export.blender.simple, psdbake.export.blender.graph; "
            "assert 'pxr' not in sys.modules and 'bpy' not in sys.modules, sorted(sys.modules)")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


