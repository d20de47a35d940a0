"""The grammar of filter weight expressions (Davletaliyev 2016, Sec. 3.2.1 and Fig. 3.2) as a DEAP strongly
typed primitive set, with the torch implementation of every operator.

An expression computes the weight w(p, q) that the centre pixel p gives its neighbour q in the filtering
equation out_p = sum_q w(p, q) c_q / sum_q w(p, q) (Davletaliyev 2016, Eq. 2.10). Two types:

    float   a scalar per (p, q): every operator's result, the scalar variables and the constants
    Vector  a feature buffer; only the vector operators take it, so a vector never reaches an arithmetic
            operator (strongly typed GP, Sec. 3.2.1 and Ch. 5: "closure does not hold in strict sense")

Operators (Fig. 3.2):

    unary   neg sin cos tan exp asin acos atan sqrt, and the kernels mitchell sinc epanechnikov biweight
            tricube (Sec. 3.2.2; formulas in their docstrings below)
    binary  mul sub add div (safe division, `safe_div`) pow
    vector  dot distance2 distance1 distanceMax: vectorOp(a, b) compares feature a at the *centre* pixel p
            with feature b at the *neighbour* q (the thesis writes ||f_i - f_j|| with i the filtered pixel);
            a and b are usually the same feature, but the grammar allows any two (the thesis normalises the
            features "to ensure the interchangeability between features", Sec. 3.3.2); a 1-channel feature
            broadcasts against a 3-channel one.

Terminals:

    Vector  worldPosition normal texture secondaryTexture depth directIllumination and the Sobel gradients
            wpGradient nGradient texGradient secTexGradient dovGradient diGradient (Fig. 3.2; "dov" is the
            depth: the grammar's name, kept), plus two that Fig. 3.2 omits but the published expressions
            (Eq. 4.1-4.8) and the bilateral seed of the population (Sec. 3.2.5) use: `color` (the noisy
            colour c) and `pixel` (the pixel coordinates (row, column, 0), so that ||p_i - p_j|| is the
            spatial distance in pixels).
    float   the per-pixel sample variances wpVariance nVariance texVariance secTexVariance dovVariance
            diVariance of the centre pixel p (Fig. 3.2, "Scalar Variables"), colorVariance (the noisy
            colour's, which Sec. 3.2.1.2 calls one of the most valuable components but Fig. 3.2 omits;
            batch key `color_var`), and the constants
            0.1 0.2 0.3 0.3333 1.0 2.0 3.0 pi 5.0 7.0 11.0 13.0 (Fig. 3.2); a parsed expression may hold any
            other numeric constant (a seed's sigma, the 0.05 of Eq. 4.5).

Undefined values: an operation outside its domain (sqrt or pow of a negative base, asin/acos outside
[-1, 1], overflow) gives NaN or Inf, which every operator here propagates (the kernels too, although their
`where`s would otherwise map NaN to 0); `src.gp.evaluate` then flags the expression invalid, which the search
turns into the worst fitness (Davletaliyev 2016, Sec. 3.2.3: "the fitness value is set ... to a very big
number"). Only division is protected, as in the thesis (Sec. 3.2.1).

DEAP's typed tree generation (`gp.genFull`, `genGrow`, `genHalfAndHalf`) fails on this grammar: `Vector` has
terminals but no primitive returning it, and `gp.generate` raises IndexError whenever it wants an inner node
of such a type above the tree's drawn height (DEAP issues #219 and #579). `generate` below is DEAP's function
with the one fix: a type with no primitive takes a terminal (and a type with no terminal a primitive), so
vector leaves may sit above the drawn height; `gen_full`, `gen_grow` and `gen_half_and_half` use it.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable

import torch
from deap import gp

SAFE_DIV_EPS = 1e-12
"""`safe_div(a, b)` returns 1 where |b| <= this (Koza's protected division, DEAP's `protectedDiv`)."""

MITCHELL_B = MITCHELL_C = 1.0 / 3.0
"""Mitchell-Netravali parameters, the thesis's default (Sec. 3.2.2)."""

SINC_TAU = 3.0
"""The sinc kernel's tuning parameter tau (Sec. 3.2.2, default 3.0)."""


class Vector:
    """DEAP type of the feature-buffer terminals (never instantiated: the evaluator reads the buffers)."""


def _keep_nan(x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """k, with NaN wherever the argument x is NaN (the comparisons in the piecewise kernels are False
    for NaN, which would silently turn an undefined argument into a defined weight)."""
    return torch.where(torch.isnan(x), x, k)


def mitchell(x: torch.Tensor) -> torch.Tensor:
    """Mitchell-Netravali (BC-spline) kernel, B = C = 1/3 (Davletaliyev 2016, Eq. 3.1):

        k(x) = 1/6 * ( (12 - 9B - 6C)|x|^3 + (-18 + 12B + 6C)|x|^2 + (6 - 2B) )            |x| < 1
               1/6 * ( (-B - 6C)|x|^3 + (6B + 30C)|x|^2 + (-12B - 48C)|x| + (8B + 24C) )   1 <= |x| < 2
               0                                                                             otherwise

    Support (-2, 2); continuous (both pieces agree at |x| = 1, the second is 0 at |x| = 2); k(0) = 8/9 and
    k is negative for 4/3 < |x| < 2 with B = C = 1/3 (the negative lobes of the BC-spline).
    """
    b, c = MITCHELL_B, MITCHELL_C
    a = x.abs()
    a2, a3 = a * a, a * a * a
    inner = ((12 - 9 * b - 6 * c) * a3 + (-18 + 12 * b + 6 * c) * a2 + (6 - 2 * b)) / 6
    outer = ((-b - 6 * c) * a3 + (6 * b + 30 * c) * a2 + (-12 * b - 48 * c) * a + (8 * b + 24 * c)) / 6
    k = torch.where(a < 1, inner, torch.where(a < 2, outer, torch.zeros_like(a)))
    return _keep_nan(x, k)


def sinc(x: torch.Tensor) -> torch.Tensor:
    """The thesis's sinc kernel with tau = 3 (Davletaliyev 2016, Sec. 3.2.2), as printed:

        k(x) = 1                                       x = 0
               sin(pi x) sin(tau pi x) / (pi^2 x^2)    0 < |x| <= 1
               0                                       |x| > 1

    Support [-1, 1]. As printed it is discontinuous at 0 (the limit x -> 0 is tau = 3, k(0) is 1) and it is
    0 at |x| = 1/3, 2/3, 1; we transcribe it literally, since the published expressions were evolved with it.
    """
    zero = x == 0
    safe = torch.where(zero, torch.ones_like(x), x)
    value = torch.sin(math.pi * safe) * torch.sin(SINC_TAU * math.pi * safe) / (math.pi**2 * safe * safe)
    k = torch.where(zero, torch.ones_like(x), torch.where(x.abs() <= 1, value, torch.zeros_like(x)))
    return _keep_nan(x, k)


def epanechnikov(x: torch.Tensor) -> torch.Tensor:
    """Epanechnikov kernel (Davletaliyev 2016, Sec. 3.2.2): k(x) = 2/pi (1 - |x|^2) for |x| < 1, else 0.

    Support (-1, 1); 2/pi is the thesis's constant (the normalisation of the 2-D kernel). Written as
    2/pi max(1 - x^2, 0), which is the same function and keeps NaN (clamp propagates it)."""
    return (2.0 / math.pi) * (1.0 - x * x).clamp(min=0.0)


def biweight(x: torch.Tensor) -> torch.Tensor:
    """Biweight kernel (Davletaliyev 2016, Eq. 3.2): k(x) = 15/16 (1 - |x|^2)^2 for |x| <= 1, else 0.

    Support [-1, 1] (0 at the boundary either way); k(0) = 15/16."""
    return (15.0 / 16.0) * (1.0 - x * x).clamp(min=0.0).square()


def tricube(x: torch.Tensor) -> torch.Tensor:
    """Tricube kernel (Davletaliyev 2016, Eq. 3.3): k(x) = (1 - |x|^3)^3 for |x| < 1, else 0.

    Support (-1, 1); k(0) = 1 (the thesis omits the usual 70/81 normalisation)."""
    a = x.abs()
    return (1.0 - a * a * a).clamp(min=0.0).pow(3)


def safe_div(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a / b, and 1 where |b| <= SAFE_DIV_EPS (protected division, Sec. 3.2.1: "safe division function to
    avoid division by zero"); NaN in a or b still propagates (a * 0 + 1 is NaN for a NaN)."""
    small = b.abs() <= SAFE_DIV_EPS
    return torch.where(small, a * 0.0 + 1.0, a / torch.where(small, torch.ones_like(b), b))


def power(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a ** b (Sec. 3.2.1: "first parameter as a base and the second parameter as the exponent"); NaN for a
    negative base with a non-integer exponent, and NaN whenever a or b is NaN (IEEE pow(NaN, 0) = 1 and
    pow(1, NaN) = 1 would hide an undefined argument)."""
    result = torch.pow(a, b)
    return torch.where(torch.isnan(a) | torch.isnan(b), a + b, result)


def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """sum_i a_i b_i over channels (dim 1, kept)."""
    return (a * b).sum(dim=1, keepdim=True)


def distance2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Euclidean distance sqrt(sum_i (a_i - b_i)^2) (Sec. 3.2.1)."""
    return (a - b).square().sum(dim=1, keepdim=True).sqrt()


def distance1(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Manhattan distance sum_i |a_i - b_i| (Sec. 3.2.1)."""
    return (a - b).abs().sum(dim=1, keepdim=True)


def distance_max(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Chebyshev distance max_i |a_i - b_i| (Sec. 3.2.1; amax propagates NaN)."""
    return (a - b).abs().amax(dim=1, keepdim=True)


UNARY: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "neg": torch.neg,
    "sin": torch.sin,
    "cos": torch.cos,
    "tan": torch.tan,
    "exp": torch.exp,
    "asin": torch.asin,
    "acos": torch.acos,
    "atan": torch.atan,
    "sqrt": torch.sqrt,
    "mitchell": mitchell,
    "sinc": sinc,
    "epanechnikov": epanechnikov,
    "biweight": biweight,
    "tricube": tricube,
}
KERNELS = ("mitchell", "sinc", "epanechnikov", "biweight", "tricube")
BINARY: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {
    "mul": torch.mul,
    "sub": torch.sub,
    "add": torch.add,
    "div": safe_div,
    "pow": power,
}
#: Infix symbols of the binary operators (Python syntax, what `src.gp.text` prints and parses).
BINARY_SYMBOLS = {"add": "+", "sub": "-", "mul": "*", "div": "/", "pow": "**"}
VECTOR_OPS: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {
    "dot": dot,
    "distance2": distance2,
    "distance1": distance1,
    "distanceMax": distance_max,
}

#: Fig. 3.2's vector terminals, in its order.
GRAMMAR_VECTORS = (
    "worldPosition",
    "normal",
    "texture",
    "secondaryTexture",
    "depth",
    "directIllumination",
    "wpGradient",
    "nGradient",
    "texGradient",
    "secTexGradient",
    "dovGradient",
    "diGradient",
)
#: Vector terminals beyond Fig. 3.2 that the published expressions and the bilateral seed use.
EXTRA_VECTORS = ("color", "pixel")
VECTORS = GRAMMAR_VECTORS + EXTRA_VECTORS
#: Fig. 3.2's scalar variables (per-pixel sample variances of the centre pixel).
VARIABLES = ("wpVariance", "nVariance", "texVariance", "secTexVariance", "dovVariance", "diVariance")
#: Scalar variables beyond Fig. 3.2: the noisy colour's per-pixel sample variance, which the thesis calls
#: "one of the most valuable components for error estimation" (Sec. 3.2.1.2, "Scalar Variables") but
#: leaves out of its grammar. The search draws it only with `task.search.color_variance: true`.
EXTRA_VARIABLES = ("colorVariance",)
ALL_VARIABLES = VARIABLES + EXTRA_VARIABLES
#: Fig. 3.2's constants; pi is the terminal named "pi".
CONSTANTS = (0.1, 0.2, 0.3, 0.3333, 1.0, 2.0, 3.0, math.pi, 5.0, 7.0, 11.0, 13.0)
#: Gradient terminal -> the feature it is the Sobel gradient of.
GRADIENT_OF = {
    "wpGradient": "worldPosition",
    "nGradient": "normal",
    "texGradient": "texture",
    "secTexGradient": "secondaryTexture",
    "dovGradient": "depth",
    "diGradient": "directIllumination",
}


def make_pset() -> gp.PrimitiveSetTyped:
    """The thesis's grammar (Fig. 3.2, plus `color` and `pixel`) as a DEAP typed primitive set returning a
    float. The primitives carry the torch functions; `src.gp.evaluate` looks them up by name."""
    pset = gp.PrimitiveSetTyped("weight", [], float)
    for name, fn in UNARY.items():
        pset.addPrimitive(fn, [float], float, name=name)
    for name, fn in BINARY.items():
        pset.addPrimitive(fn, [float, float], float, name=name)
    for name, fn in VECTOR_OPS.items():
        pset.addPrimitive(fn, [Vector, Vector], float, name=name)
    for name in VECTORS:
        pset.addTerminal(name, Vector, name=name)
    for name in ALL_VARIABLES:
        pset.addTerminal(name, float, name=name)
    for value in CONSTANTS:
        if value == math.pi:
            pset.addTerminal(math.pi, float, name="pi")
        else:
            pset.addTerminal(value, float)
    return pset


PSET = make_pset()


def generate(pset, min_: int, max_: int, condition, type_=None) -> list:
    """`deap.gp.generate` with the fix for types that have terminals but no primitives (or the reverse),
    DEAP issues #219 / #579: such a type takes what it has, whatever the depth (module docstring)."""
    if type_ is None:
        type_ = pset.ret
    expr = []
    height = random.randint(min_, max_)
    stack = [(0, type_)]
    while stack:
        depth, type_ = stack.pop()
        primitives, terminals = pset.primitives[type_], pset.terminals[type_]
        if (condition(height, depth) and terminals) or not primitives:
            term = random.choice(terminals)
            if type(term) is gp.MetaEphemeral:
                term = term()
            expr.append(term)
        else:
            prim = random.choice(primitives)
            expr.append(prim)
            for arg in reversed(prim.args):
                stack.append((depth + 1, arg))
    return expr


def gen_full(pset, min_: int, max_: int, type_=None) -> list:
    """`deap.gp.genFull` through the fixed `generate`."""
    return generate(pset, min_, max_, lambda height, depth: depth == height, type_)


def gen_grow(pset, min_: int, max_: int, type_=None) -> list:
    """`deap.gp.genGrow` through the fixed `generate`."""

    def condition(height: int, depth: int) -> bool:
        return depth == height or (depth >= min_ and random.random() < pset.terminalRatio)

    return generate(pset, min_, max_, condition, type_)


def gen_half_and_half(pset, min_: int, max_: int, type_=None) -> list:
    """`deap.gp.genHalfAndHalf` through the fixed `generate`."""
    return random.choice((gen_grow, gen_full))(pset, min_, max_, type_)
