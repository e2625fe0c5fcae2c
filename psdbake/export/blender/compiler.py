"""The ``psd:`` weight formula compiled into Blender driver expressions, one building block
per function.

What is compiled is the weights formula of docs/reference/psd-schema.md (``weights`` is the
reference evaluator), term by term, from a mesh's ``DriverData`` alone:

    delta_j   = q_bind_j^-1 R_j                         joint_rotation
    x         = coordinates of every delta_j            POSE_COORDINATES[psd:poseSpace]
    t_i       = eps^2 |x[dims] - c_i|^2                 squared_distance
    r_s       = sum_i C[i,s] phi(t_i)                   KERNELS[psd:kernel] (phi of t = r^2)
              + sum_m C[k+m,s] prod_d xhat_d^P[m,d]     monomial
              (x) v3 joint gates                        joint_gate
              (x) v5 ramp gates                         ramp_gate
    w_s       = r_s prod_H a_{s,H}                      gate_activation (v4 combinations)
              then clamp / normalise                    apply_options
    channel c = max(0, w_col / M_c)                     channel_weight (client-safe channels)

Each function returns expression trees (``simple``); quantities worth sharing are ``Named``
and ``graph.lay_out`` decides which become driven properties. A new term type (the additive
per-joint terms of a later schema, say) is a new function here composing these, not a new
layout. Registries are keyed by the schema's own tokens (``POSE_COORDINATES`` by
``psd:poseSpace``, ``KERNELS`` by ``psd:kernel``), like ``posespace.POSE_SPACES`` and
``rbf_model.KERNELS``, so a pose space or kernel the schema gains without an entry here is
refused at compile time, naming it.

Blender side of delta_j: the variables read each bone's rotation away from its rest pose
(quaternion, ``LOCAL_SPACE``: after constraints, before parenting). Blender's USD importer
makes every bone's rest the joint's bind transform (``bindTransforms``; the script Blender
runs checks this), so the joint's local rotation is R_j = q_rest,j b_j, b_j the bone's
rotation, and delta_j = (q_bind,j^-1 q_rest,j) b_j. psdbake writes q_bind from the same
bindTransforms, so the constant factor is the identity and delta_j = b_j; where it is not
(a layer fitted against other bind transforms), delta_j is a linear combination of b_j's
components, made in ``joint_rotation``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ... import tolerances as tol
from ...errors import CompileError
from ...model.channels import channel_names
from ...model.quaternions import Rotations
from ...model.weights import gate_slices
from ...names import KERNEL_NAMES, POSE_SPACE_NAMES
from .graph import QUATERNION_CHANNELS, BoneChannel, DriverGraph, lay_out
from .simple import Expr, Named, Num, Var, add, call, cmp, div, if_else, mul, neg, num, square, sub

if TYPE_CHECKING:
    from ...model.data import DriverData

Quaternion = tuple[Expr, Expr, Expr, Expr]  # (w, x, y, z)
Floats = Sequence[float] | NDArray[np.float64]


def _zero() -> Num:
    return Num(0.0)


def joint_label(joint: str) -> str:
    """The short name properties about a joint carry: its last path element."""
    return joint.rsplit("/", 1)[-1]


# --- pose coordinates of a driver joint -----------------------------------------------------

def joint_rotation(joint: str, bind: NDArray[np.float64], rest: NDArray[np.float64] | None = None) -> Quaternion:
    """delta_j = bind^-1 R_j as an expression of the bone's rotation away from its rest pose.

    bind: the group's stored ``psd:driverBindRotations`` entry; rest: the joint's bind local
    rotation in the asset, which Blender's bones rest at (both x, y, z, w); None: the same."""
    w, x, y, z = (Var(BoneChannel(joint, c)) for c in QUATERNION_CHANNELS)
    if rest is None:
        return w, x, y, z
    ax, ay, az, aw = (Rotations.from_quat(bind).inv() * Rotations.from_quat(rest)).as_quat()[0]
    if math.sqrt(ax * ax + ay * ay + az * az) <= tol.BLENDER_REST_MATCH:
        return w, x, y, z
    label = f"psd:{joint_label(joint)}:q"
    return (  # a * b, Hamilton product, a constant
        Named(f"{label}w", add(mul(num(aw), w), mul(num(-ax), x), mul(num(-ay), y), mul(num(-az), z))),
        Named(f"{label}x", add(mul(num(aw), x), mul(num(ax), w), mul(num(ay), z), mul(num(-az), y))),
        Named(f"{label}y", add(mul(num(aw), y), mul(num(ay), w), mul(num(az), x), mul(num(-ax), z))),
        Named(f"{label}z", add(mul(num(aw), z), mul(num(az), w), mul(num(ax), y), mul(num(-ay), x))),
    )


def canonical_sign(q: Quaternion) -> Expr:
    """+1 or -1: the sign that makes q canonical as psdbake's rotations are (w > 0; at w = 0,
    the first non-zero of x, y, z positive: ``quaternions._canonical``)."""
    w, x, y, z = q
    ties = if_else(Num(-1.0), cmp("<", x, _zero()), if_else(Num(1.0), cmp(">", x, _zero()), if_else(
        Num(-1.0), cmp("<", y, _zero()), if_else(Num(1.0), cmp(">", y, _zero()),
                                                 if_else(Num(-1.0), cmp("<", z, _zero()), Num(1.0))))))
    return if_else(Num(1.0), cmp(">", w, _zero()), if_else(Num(-1.0), cmp("<", w, _zero()), ties))


def _norm2(*v: Expr) -> Expr:
    return add(*(mul(c, c) for c in v))


def rotation_vector(q: Quaternion, axis: Sequence[float] | None, label: str) -> list[Expr]:
    """rotvec(delta): v f with f = 2 atan2(|v|, |w|) / |v| (2 at the identity) times the
    canonical sign; f, one property per joint, carries the three coordinates."""
    w, x, y, z = q
    s2 = _norm2(x, y, z)
    s = call("sqrt", s2)
    ratio = if_else(div(mul(Num(2.0), call("atan2", s, call("abs", w))), s), cmp(">", s2, _zero()), Num(2.0))
    f = Named(f"{label}:rv", mul(ratio, canonical_sign(q)), exact=True)
    return [mul(x, f), mul(y, f), mul(z, f)]


def swing_twist(q: Quaternion, axis: Sequence[float] | None, label: str) -> list[Expr]:
    """[rotvec(swing), twist angle], delta = swing twist, twist about the unit axis a.

    With t = v.a and n = sqrt(w^2 + t^2): twist = (t a, w) / n, swing = delta twist^-1 =
    (n, u / n) with u = w (v - t a) - t (v x a), so rotvec(swing) = u h, h = 2 atan2(m, n) / (m n),
    m = |u| / n = sqrt(|v|^2 - t^2). The twist angle 2 atan2(t, w) is wrapped to [-pi, pi) as
    ``posespace.swing_twist`` wraps it (numpy's floor modulo). At n = 0 (a half-turn swing and no
    twist component) the twist is the identity and the swing delta itself."""
    if axis is None:
        raise CompileError("swingTwist pose space without psd:twistAxis")
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    w, x, y, z = q
    v = (x, y, z)
    t = Named(f"{label}:st.t", add(*(mul(num(ai), c) for c, ai in zip(v, a, strict=True) if ai != 0.0)))
    n2 = add(mul(w, w), mul(t, t))
    s2 = _norm2(x, y, z)
    m = call("sqrt", call("max", _zero(), sub(s2, mul(t, t))))
    mn = mul(m, call("sqrt", n2))
    h = Named(f"{label}:st.h", if_else(div(mul(Num(2.0), call("atan2", m, call("sqrt", n2))), mn), cmp(">", mn, _zero()),
                                       if_else(div(Num(2.0), n2), cmp(">", n2, _zero()), _zero())))
    cross = (sub(mul(num(a[2]), y), mul(num(a[1]), z)), sub(mul(num(a[0]), z), mul(num(a[2]), x)),
             sub(mul(num(a[1]), x), mul(num(a[0]), y)))
    half_turn = Named(f"{label}:st.p", if_else(div(mul(Num(math.pi), canonical_sign(q)), call("sqrt", s2)),
                                               cmp(">", s2, _zero()), _zero()))
    swing = [Named(f"{label}:st.{i}", if_else(
        mul(h, sub(mul(w, sub(vi, mul(num(ai), t))), mul(t, ci))), cmp(">", n2, _zero()), mul(vi, half_turn)), exact=True)
        for i, (vi, ai, ci) in enumerate(zip(v, a, cross, strict=True))]
    shifted = Named(f"{label}:st.m", call("fmod", add(mul(Num(2.0), call("atan2", t, w)), Num(math.pi)), Num(2.0 * math.pi)))
    twist = Named(f"{label}:st.3", sub(if_else(add(shifted, Num(2.0 * math.pi)), cmp("<", shifted, _zero()), shifted),
                                       Num(math.pi)), exact=True)
    return [*swing, twist]


def chordal(q: Quaternion, axis: Sequence[float] | None, label: str) -> list[Expr]:
    """R(delta) - I, row-major, of q normalised (``Rotations.as_matrix``'s formulas over |q|^2)."""
    w, x, y, z = q
    n2 = Named(f"{label}:qn", _norm2(w, x, y, z))
    x2, y2, z2, w2 = mul(x, x), mul(y, y), mul(z, z), mul(w, w)
    xy, zw, xz, yw, yz, xw = mul(x, y), mul(z, w), mul(x, z), mul(y, w), mul(y, z), mul(x, w)
    two = Num(2.0)
    entries = (
        add(x2, neg(y2), neg(z2), w2), mul(two, sub(xy, zw)), mul(two, add(xz, yw)),
        mul(two, add(xy, zw)), add(neg(x2), y2, neg(z2), w2), mul(two, sub(yz, xw)),
        mul(two, sub(xz, yw)), mul(two, add(yz, xw)), add(neg(x2), neg(y2), z2, w2),
    )
    out: list[Expr] = []
    for i, entry in enumerate(entries):
        value = div(entry, n2)
        out.append(Named(f"{label}:m{i // 3}{i % 3}", sub(value, Num(1.0)) if i % 4 == 0 else value, exact=True))
    return out


#: Pose coordinates of one driver joint from its delta quaternion, by ``psd:poseSpace`` token
#: (``names.POSE_SPACE_NAMES``, the order of ``posespace.POSE_SPACES``).
POSE_COORDINATES: dict[str, Callable[[Quaternion, Sequence[float] | None, str], list[Expr]]] = dict(zip(
    POSE_SPACE_NAMES, (rotation_vector, swing_twist, chordal), strict=True))


def pose_coordinates(data: DriverData, rest: Mapping[str, NDArray[np.float64]]) -> list[Expr]:
    """x: the group's pose coordinates, every driver's concatenated in ``psd:drivers`` order."""
    if data.pose_space not in POSE_COORDINATES:
        raise CompileError(f"psd:poseSpace {data.pose_space!r} has no Blender expression")
    coordinates = POSE_COORDINATES[data.pose_space]
    x: list[Expr] = []
    for d, joint in enumerate(data.drivers):
        q = joint_rotation(joint, np.asarray(data.bind_rotations[d]), rest.get(joint))
        x += coordinates(q, data.twist_axis, f"psd:{joint_label(joint)}")
    return x


# --- the cardinal RBF -----------------------------------------------------------------------

#: What the squared distances left in one float32 may move a weight by, together, whatever the
#: pose: half of the 1e-6 within which the drivers, replayed in float32, must give eval's
#: weights (tests/test_blender_compiler.py).
FLOAT32_DISTANCE_BUDGET = 5e-7
#: max over t >= 0 of |t phi'(t)|, phi of t = r^2: how much a relative error of t moves phi.
#: Kernels that grow without bound have none; their squared distances are always exact.
KERNEL_SLOPES = {"gaussian": 1.0 / math.e, "inverse_multiquadric": 3.0**-1.5,
                 "inverse_quadratic": 0.25}


def exact_centres(coefficients: NDArray[np.float64], kernel: str) -> NDArray[np.bool_]:
    """Which centres' squared distances are stored exact (two float32, ``graph``).

    A float32 t_i is off by up to 2^-24 t_i, which moves phi(t_i) by 2^-24 |t phi'(t)|
    (``KERNEL_SLOPES``) and a weight by |C[i, s]| times that. The centres with the largest
    coefficients are made exact until what the others can move a weight by together is within
    ``FLOAT32_DISTANCE_BUDGET``: a fit whose coefficients cancel (an ill-conditioned kernel
    matrix, 10^3 and more) pays a driver per centre, a smooth one (about 10) none."""
    if kernel not in KERNEL_SLOPES:
        return np.ones(len(coefficients), dtype=bool)
    size = np.abs(coefficients).max(axis=1, initial=0.0) * 2.0**-24 * KERNEL_SLOPES[kernel]
    order = np.argsort(-size, kind="stable")
    left = np.cumsum(size[order][::-1])[::-1]  # what the centres from the k-th largest on move a weight by
    exact = np.zeros(len(size), dtype=bool)
    exact[order[left > FLOAT32_DISTANCE_BUDGET]] = True
    return exact


def squared_distance(x: Sequence[Expr], centre: Floats, epsilon: float, label: str, exact: bool = False) -> Named:
    """t = (eps |x - c|)^2, the kernel's argument squared; ``exact``: stored in two float32
    (``graph``), for a centre whose coefficients would amplify t's rounding past a weight's own."""
    total = add(*(square(sub(xd, num(cd))) if cd != 0.0 else square(xd) for xd, cd in zip(x, centre, strict=True)))
    return Named(label, mul(total, num(epsilon * epsilon)), exact)


#: phi as a function of t = r^2 (``rbf_model.KERNELS`` takes r), by ``psd:kernel`` token.
KERNELS: dict[str, Callable[[Expr], Expr]] = dict(zip(KERNEL_NAMES, (
    lambda t: call("exp", neg(t)),  # gaussian: exp(-r^2)
    lambda t: neg(call("sqrt", t)),  # linear: -r
    lambda t: if_else(div(mul(t, call("log", t)), Num(2.0)), cmp(">", t, _zero()), _zero()),  # thin plate: r^2 log r
    lambda t: mul(t, call("sqrt", t)),  # cubic: r^3
    lambda t: neg(mul(t, t, call("sqrt", t))),  # quintic: -r^5
    lambda t: neg(call("sqrt", add(t, Num(1.0)))),  # multiquadric: -sqrt(r^2 + 1)
    lambda t: div(Num(1.0), call("sqrt", add(t, Num(1.0)))),  # inverse multiquadric
    lambda t: div(Num(1.0), add(t, Num(1.0))),  # inverse quadratic
), strict=True))


def monomial(x: Sequence[Expr], powers: Sequence[int] | NDArray[np.int64], shift: Floats, scale: Floats) -> Expr:
    """prod_d xhat_d ^ P[d], xhat = (x - shift) / scale; 1 for the constant monomial."""
    factors = []
    for xd, p, sh, sc in zip(x, powers, shift, scale, strict=True):
        if p == 0:
            continue
        xhat = div(sub(xd, num(sh)), num(sc))
        factors.append(xhat if p == 1 else call("pow", xhat, num(float(p))))
    return mul(*factors)


def weighted_sum(coefficients: Floats, terms: Sequence[Expr]) -> Expr:
    """sum_i c_i term_i, the terms with a zero coefficient left out."""
    return add(*(mul(num(c), term) for c, term in zip(coefficients, terms, strict=True) if c != 0.0))


def joint_gate(x: Sequence[Expr], pose: Floats) -> Expr:
    """A v3 gate: clamp(x_j . g_j / g_j . g_j, 0, 1), x_j the gate driver's coordinates."""
    g = np.asarray(pose, dtype=np.float64)
    dot = add(*(mul(num(gd), xd) for xd, gd in zip(x, g, strict=True) if gd != 0.0))
    return call("clamp", div(dot, num(float(g @ g))), _zero(), Num(1.0))


def ramp_gate(x: Sequence[Expr], radius: float, label: str) -> Expr:
    """A v5 ramp gate: min(1, |x_j| / r_j), x_j the gate driver's coordinates (``weights.ramp_gate``)."""
    norm = Named(f"{label}:n", call("sqrt", add(*(square(xd) for xd in x))))
    return call("min", Num(1.0), div(norm, num(float(radius))))


def rbf_outputs(data: DriverData, x: Sequence[Expr], label: str) -> list[Expr]:
    """r_s: the group's cardinal RBF at x (times its v3 joint gates and v5 ramp gates), before
    group gates and options (``weights.rbf_weights``)."""
    if data.kernel not in KERNELS:
        raise CompileError(f"psd:kernel {data.kernel!r} has no Blender expression")
    xs = [x[int(d)] for d in data.dims]
    eps = 1.0 / data.sigma
    coef = np.asarray(data.coefficients)
    exact = exact_centres(coef[: len(data.centers)], data.kernel)
    phi = [KERNELS[data.kernel](squared_distance(xs, c, eps, f"{label}:t{i}", bool(exact[i])))
           for i, c in enumerate(data.centers)]
    monos = [monomial(xs, p, data.shift, data.scale) for p in data.powers]
    width = len(x) // max(1, len(data.drivers))
    gates = [joint_gate(x[data.drivers.index(g) * width:(data.drivers.index(g) + 1) * width], pose)
             for g, pose in zip(data.gates, data.gate_poses, strict=True)]
    gates += [Named(f"{label}:ramp{j}", ramp_gate(x[data.drivers.index(g) * width:(data.drivers.index(g) + 1) * width],
                                                  float(radius), f"{label}:ramp{j}"))
              for j, (g, radius) in enumerate(zip(data.ramp_gates, data.ramp_radii, strict=True))]
    return [Named(f"{label}:r{s}", mul(weighted_sum(coef[:, s], [*phi, *monos]), *gates))
            for s in range(len(data.shapes))]


# --- combinations, options, channels --------------------------------------------------------

def gate_activation(raw: Sequence[Expr], x: Sequence[Expr], direction: Floats, label: str) -> Expr:
    """a gate group's activation toward one combination shape: max(0, sum_t r_t) times
    max(0, x . u / |x|), 0 where x = 0 (``weights.activation``)."""
    total = Named(f"{label}:sum", add(*raw))
    n2 = Named(f"{label}:n2", add(*(square(xd) for xd in x)))
    dot = add(*(mul(num(ud), xd) for xd, ud in zip(x, direction, strict=True) if ud != 0.0))
    cos = if_else(call("max", _zero(), div(dot, call("sqrt", n2))), cmp(">", n2, _zero()), _zero())
    return mul(call("max", _zero(), total), cos)


def apply_options(data: DriverData, w: Sequence[Expr], label: str) -> list[Expr]:
    """The stored clamp and normalise options (``weights.apply_options``)."""
    out = list(w)
    if data.clamp_weights:
        out = [call("clamp", ws, _zero(), Num(1.0)) for ws in out]
    if data.normalize_weights:
        total = Named(f"{label}:total", add(*out))
        out = [div(ws, call("max", Num(1.0), total)) for ws in out]
    return out


def channel_weight(w: Expr, scale: float) -> Expr:
    """A client-safe channel's weight, max(0, w / M) (``channels.channel_weights``)."""
    return call("max", _zero(), div(w, num(scale)))


def mesh_channels(groups: Sequence[tuple[str, DriverData]], rest: Mapping[str, NDArray[np.float64]] | None = None
                  ) -> list[tuple[str, Expr]]:
    """(shape key name, value expression) of every channel of one mesh's groups, in group
    then channel order (``weights.group_weights``, then ``channels.channel_weights``).

    rest: each driver joint's bind local rotation in the asset (x, y, z, w), where Blender's
    bones rest; missing joints are taken to rest at the groups' stored bind rotations."""
    rest = rest or {}
    by_name = dict(groups)
    x = {g: pose_coordinates(data, rest) for g, data in groups}
    raw = {g: rbf_outputs(data, x[g], f"psd:{g}") for g, data in groups}
    out: list[tuple[str, Expr]] = []
    for g, data in groups:
        w = list(raw[g])
        for gate, part in zip(data.gate_groups, gate_slices(by_name, data), strict=True):
            directions = np.asarray(data.gate_directions)[:, part]
            w = [mul(ws, Named(f"psd:{g}:a{s}:{gate}", gate_activation(raw[gate], x[gate], directions[s], f"psd:{gate}")))
                 for s, ws in enumerate(w)]
        w = [Named(f"psd:{g}:w{s}", ws) for s, ws in enumerate(apply_options(data, w, f"psd:{g}"))]
        if len(data.channels):
            out += [(name, channel_weight(w[int(col)], float(scale)))
                    for name, col, scale in zip(data.channels, data.channel_columns, data.channel_scales, strict=True)]
        else:
            out += list(zip(channel_names(data), w, strict=True))
    return out


def compile_mesh(groups: Sequence[tuple[str, DriverData]], rest: Mapping[str, NDArray[np.float64]] | None = None
                 ) -> DriverGraph:
    """One mesh's drivers: ``mesh_channels`` laid out within Blender's expression limit."""
    return lay_out(mesh_channels(groups, rest))
