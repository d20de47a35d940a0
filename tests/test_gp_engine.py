"""The GP filter-expression engine (src/gp, issue 18; Davletaliyev 2016): kernels, operators, parsing and
printing, vectorised evaluation against a per-pixel loop, batching, memory, invalid expressions, the
published expressions, the bilateral seed against the cross-bilateral baseline, and GPFilter."""

import math
import random
import weakref
from pathlib import Path

import numpy as np
import pytest
import torch
from deap import gp
from omegaconf import OmegaConf
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

from src.errors import ConfigError
from src.gp import grammar
from src.gp.evaluate import filter_images, required_terminals, window_weights
from src.gp.features import normalize_feature, sobel_gradient
from src.gp.grammar import PSET, gen_full, gen_grow, gen_half_and_half
from src.gp.published import EXPR1, EXPR2, EXPR3, PUBLISHED, bilateral_expression
from src.gp.text import ExpressionError, compact, parse, to_infix
from src.models.filters.cross_bilateral import cross_bilateral, guide_features
from src.models.filters.gp_filter import GPFilter
from src.models.instantiate import build_method
from tests.conftest import CONF_DIR, compose_config, one_line_error

CONF_MODEL = Path(CONF_DIR) / "model"

# ---------------------------------------------------------------------------------------------------------
# Plain-Python reference kernels (thesis formulas, written independently of the torch versions)

B = C = 1 / 3


def mitchell_ref(x):
    a = abs(x)
    if a < 1:
        return ((12 - 9 * B - 6 * C) * a**3 + (-18 + 12 * B + 6 * C) * a**2 + (6 - 2 * B)) / 6
    if a < 2:
        return ((-B - 6 * C) * a**3 + (6 * B + 30 * C) * a**2 + (-12 * B - 48 * C) * a + (8 * B + 24 * C)) / 6
    return 0.0


def sinc_ref(x):
    if x == 0:
        return 1.0
    if abs(x) <= 1:
        return math.sin(math.pi * x) * math.sin(3 * math.pi * x) / (math.pi**2 * x * x)
    return 0.0


def epanechnikov_ref(x):
    return 2 / math.pi * (1 - x * x) if abs(x) < 1 else 0.0


def biweight_ref(x):
    return 15 / 16 * (1 - x * x) ** 2 if abs(x) <= 1 else 0.0


def tricube_ref(x):
    return (1 - abs(x) ** 3) ** 3 if abs(x) < 1 else 0.0


def safe_div_ref(a, b):
    return 1.0 if abs(b) <= grammar.SAFE_DIV_EPS else a / b


SCALAR = {
    "neg": lambda x: -x,
    "sin": math.sin,
    "cos": math.cos,
    "tan": math.tan,
    "exp": math.exp,
    "asin": math.asin,
    "acos": math.acos,
    "atan": math.atan,
    "sqrt": math.sqrt,
    "mitchell": mitchell_ref,
    "sinc": sinc_ref,
    "epanechnikov": epanechnikov_ref,
    "biweight": biweight_ref,
    "tricube": tricube_ref,
    "mul": lambda a, b: a * b,
    "sub": lambda a, b: a - b,
    "add": lambda a, b: a + b,
    "div": safe_div_ref,
    "pow": lambda a, b: a**b,
}
VECTOR = {
    "dot": lambda a, b: float(np.sum(a * b)),
    "distance2": lambda a, b: float(np.sqrt(np.sum((a - b) ** 2))),
    "distance1": lambda a, b: float(np.sum(np.abs(a - b))),
    "distanceMax": lambda a, b: float(np.max(np.abs(a - b))),
}


pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py


def t(values, dtype=torch.float64):
    return torch.tensor(values, dtype=dtype)


# ---------------------------------------------------------------------------------------------------------
# Kernels and operators


@pytest.mark.parametrize(
    ("name", "points"),
    [
        ("mitchell", {0: 8 / 9, 1: 1 / 18, -1: 1 / 18, 1.5: -5 / 144, 2: 0, -2.5: 0, 10: 0}),
        ("sinc", {0: 1, 0.5: -4 / math.pi**2, -0.5: -4 / math.pi**2, 1 / 3: 0, 1: 0, 1.5: 0, -7: 0}),
        ("epanechnikov", {0: 2 / math.pi, 0.5: 1.5 / math.pi, -0.5: 1.5 / math.pi, 1: 0, -1: 0, 3: 0}),
        ("biweight", {0: 15 / 16, 0.5: 15 / 16 * 0.5625, -0.5: 15 / 16 * 0.5625, 1: 0, 1.2: 0}),
        ("tricube", {0: 1, 0.5: 0.875**3, -0.5: 0.875**3, 1: 0, -1.01: 0}),
    ],
)
def test_kernels_closed_form_values_and_support(name, points):
    fn = grammar.UNARY[name]
    xs = list(points)
    got = fn(t(xs)).tolist()
    np.testing.assert_allclose(got, [points[x] for x in xs], atol=1e-12)
    dense = np.linspace(-3, 3, 601)  # symmetric, and equal to the reference everywhere (incl. support ends)
    np.testing.assert_allclose(fn(t(dense)).numpy(), [SCALAR[name](x) for x in dense], atol=1e-12)
    # An undefined argument stays undefined; a huge one is outside every support.
    out = fn(t([math.nan, math.inf, -math.inf]))
    assert math.isnan(out[0]) and out[1] == 0 and out[2] == 0


def test_mitchell_is_continuous_at_its_knots():
    k = grammar.mitchell(t([1 - 1e-9, 1 + 1e-9, 2 - 1e-9]))
    assert abs(k[0] - k[1]) < 1e-7 and abs(k[2]) < 1e-7


def test_vector_operators_compare_centre_and_neighbour_over_channels():
    a = t([1.0, -2.0, 3.0]).view(1, 3, 1, 1)
    b = t([0.5, 1.0, 1.0]).view(1, 3, 1, 1)
    assert grammar.dot(a, b).item() == pytest.approx(0.5 - 2 + 3)
    assert grammar.distance2(a, b).item() == pytest.approx(math.sqrt(0.25 + 9 + 4))
    assert grammar.distance1(a, b).item() == pytest.approx(0.5 + 3 + 2)
    assert grammar.distance_max(a, b).item() == pytest.approx(3)
    one = t([2.0]).view(1, 1, 1, 1)  # a 1-channel feature broadcasts against a 3-channel one
    assert grammar.distance1(one, b).item() == pytest.approx(1.5 + 1 + 1)
    assert grammar.distance2(a, b).shape == (1, 1, 1, 1)


def test_safe_division_and_nan_propagation():
    a, b = t([3.0, 1.0, 2.0, math.nan, 1.0]), t([2.0, 0.0, 1e-13, 0.0, math.nan])
    out = grammar.safe_div(a, b)
    assert out[:3].tolist() == [1.5, 1.0, 1.0]
    assert math.isnan(out[3]) and math.isnan(out[4])
    p = grammar.power(t([math.nan, 1.0, -8.0, 0.0]), t([0.0, math.nan, 1 / 3, 2.0]))
    assert math.isnan(p[0]) and math.isnan(p[1]) and math.isnan(p[2]) and p[3] == 0


# ---------------------------------------------------------------------------------------------------------
# Grammar, generation, parsing and printing


def test_grammar_matches_the_thesis_figure():
    names = {p.name for prims in PSET.primitives.values() for p in prims}
    assert names == set(grammar.UNARY) | set(grammar.BINARY) | set(grammar.VECTOR_OPS)
    assert len(grammar.UNARY) == 14 and len(grammar.BINARY) == 5 and len(grammar.VECTOR_OPS) == 4
    vectors = {term.name for term in PSET.terminals[grammar.Vector]}
    assert vectors == set(grammar.GRAMMAR_VECTORS) | {"color", "pixel"} and len(grammar.GRAMMAR_VECTORS) == 12
    scalars = {term.name for term in PSET.terminals[float]}
    constants = {"0.1", "0.2", "0.3", "0.3333", "1.0", "2.0", "3.0", "pi", "5.0", "7.0", "11.0", "13.0"}
    assert scalars == constants | set(grammar.VARIABLES) | {"colorVariance"}  # Sec. 3.2.1.2, not Fig. 3.2


def test_deap_typed_generation_bug_and_its_workaround():
    # DEAP issues #219 / #579: a type with terminals but no primitives (Vector) breaks gp.genFull.
    random.seed(0)
    failures = 0
    for _ in range(30):
        try:
            gp.genFull(PSET, 3, 3)
        except IndexError:
            failures += 1
    assert failures > 0
    for seed in range(150):
        random.seed(seed)
        for gen in (gen_full, gen_grow, gen_half_and_half):
            tree = gp.PrimitiveTree(gen(PSET, 1, 4))
            assert parse(str(tree)) == tree and parse(to_infix(tree)) == tree  # well typed, round trips
    random.seed(1)
    tree = gp.PrimitiveTree(gen_full(PSET, 3, 3))
    assert tree.height >= 3  # full trees still reach the drawn depth where the types allow


ROUND_TRIP = [
    EXPR1,
    EXPR2,
    EXPR3,
    bilateral_expression(5.0, 0.5, 0.3, 0.1, 0.05),
    "-0.5",
    "neg(0.5)",
    "neg(-0.5)",
    "-pi * 2",
    "(-2.5) ** 2.0",
    "-2.5 ** 2.0",
    "2.0 ** 3.0 ** 2.0",
    "(2.0 ** 3.0) ** 2.0",
    "1.0 - (2.0 - 3.0)",
    "1.0 - 2.0 - 3.0",
    "1.0 / (2.0 * 3.0)",
    "-(-nVariance)",
    "2.0 ** -dot(normal, texture)",
    "1e-05 + 0.1 + 0.30000000000000004 + 123456.789",
    "mul(exp(neg(distance2(normal, normal))), 0.05)",
]


@pytest.mark.parametrize("text", ROUND_TRIP)
def test_print_parse_round_trip(text):
    tree = parse(text)
    assert parse(to_infix(tree)) == tree
    assert parse(str(tree)) == tree
    assert gp.PrimitiveTree.from_string(str(tree), PSET) == tree  # DEAP's own parser agrees
    assert to_infix(parse(to_infix(tree))) == to_infix(tree)


def test_parse_reads_infix_and_prefix_alike_and_keeps_constants():
    assert parse("exp(-distance2(normal, normal)) * 0.5") == parse(
        "mul(exp(neg(distance2(normal, normal))), 0.5)"
    )
    assert parse("2") == parse("2.0")
    assert str(parse("-0.5")) == "-0.5" and str(parse("neg(0.5)")) == "neg(0.5)"
    assert parse("0.1")[0] is PSET.mapping["0.1"]  # the grammar's own constant
    assert parse("0.05")[0].value == 0.05


def test_compact_text_rounds_constants_for_display_and_the_exact_text_keeps_them():
    noisy = "exp(-(distance2(depth, depth) * 0.020000000000000004)) * biweight((-0.30000000000000004) * 1.5)"
    assert to_infix(parse(noisy)) == noisy  # what is logged reads back to the same tree
    assert compact(noisy) == "exp(-(distance2(depth, depth) * 0.02)) * biweight((-0.3) * 1.5)"
    assert compact("neg(0.123456789) * 1e-07", digits=3) == "neg(0.123) * 1e-07"
    assert compact("distance2(normal, 1.0) +") == "distance2(normal, 1.0) +"  # not an expression: as it is


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("normal + 1.0", "a vector where a scalar is expected"),
        ("distance2(normal, 1.0)", "a scalar where a vector is expected"),
        ("log(2.0)", "'log' is not an operator"),
        ("sin(1.0, 2.0)", "sin takes 1 argument"),
        ("albedo", "'albedo' is not a terminal"),
        ("1.0 +", "cannot parse"),
        ("1.0 % 2.0", "not an expression of the grammar"),
        ("normal", "a vector where a scalar is expected"),
    ],
)
def test_parse_errors_name_the_offending_part(text, needle):
    with pytest.raises(ExpressionError, match=needle):
        parse(text)


# ---------------------------------------------------------------------------------------------------------
# Evaluation


def random_features(n, h, w, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)

    def u(c, lo=0.0, hi=1.0):
        return lo + (hi - lo) * torch.rand(n, c, h, w, generator=g, dtype=dtype)

    normal = torch.nn.functional.normalize(u(3, -1, 1), dim=1)
    feats = {
        "color": u(3, 0, 2),
        "normal": normal,
        "texture": u(3),
        "secondaryTexture": u(3),
        "worldPosition": u(3),
        "depth": u(1),
        "directIllumination": u(1),
    }
    for name, base in grammar.GRADIENT_OF.items():
        feats[name] = sobel_gradient(feats[base])
    for name in grammar.VARIABLES:
        feats[name] = u(1, 0, 0.1)
    return feats


def brute_force(tree, feats, color, radius):
    """Per-pixel, per-offset evaluation of the tree with plain floats (replicate borders for features and
    colour, virtual pixel coordinates), then the normalised weighted sum."""
    n, c, h, w = color.shape
    f = {k: v.numpy() for k, v in feats.items()}
    col = color.numpy()
    out = np.zeros((n, c, h, w))

    def vec(name, b, y, x, virtual):
        if name == "pixel":
            return np.array([virtual[0], virtual[1], 0.0])
        return f[name][b, :, y, x]

    def ev(i, b, p, q, qv):
        node = tree[i]
        if isinstance(node, gp.Terminal):
            if node.value == "pi":
                return math.pi, i + 1
            if isinstance(node.value, str):
                return float(f[node.value][b, 0, p[0], p[1]]), i + 1
            return float(node.value), i + 1
        if node.name in VECTOR:
            a, bb = tree[i + 1].value, tree[i + 2].value
            return VECTOR[node.name](vec(a, b, *p, p), vec(bb, b, *q, qv)), i + 3
        args, j = [], i + 1
        for _ in range(node.arity):
            v, j = ev(j, b, p, q, qv)
            args.append(v)
        return SCALAR[node.name](*args), j

    for b in range(n):
        for y in range(h):
            for x in range(w):
                acc, total = np.zeros(c), 0.0
                for dy in range(-radius, radius + 1):
                    for dx in range(-radius, radius + 1):
                        qy, qx = min(max(y + dy, 0), h - 1), min(max(x + dx, 0), w - 1)
                        wgt, _ = ev(0, b, (y, x), (qy, qx), (y + dy, x + dx))
                        acc += wgt * col[b, :, qy, qx]
                        total += wgt
                out[b, :, y, x] = acc / total
    return out


MIXED = [
    EXPR1,
    EXPR2,
    EXPR3,
    bilateral_expression(1.5, 0.5, 0.3, 0.2, 0.1),
    "exp(-dot(normal, texture) * nVariance) + sqrt(distance1(pixel, pixel)) + 0.1 * texVariance",
    "epanechnikov(distanceMax(depth, texture) / 3.0) + tricube(distance2(wpGradient, wpGradient)) + 0.2",
    "exp(mitchell(distance2(secondaryTexture, secondaryTexture) * 3.0) - dot(pixel, pixel) / 100.0)",
    "pow(1.0 + atan(distance1(dovGradient, diGradient)), cos(diVariance)) + 0.0 * secTexVariance",
    # pixel against another feature: its coordinates (row, column, 0) at p, or the virtual ones at q
    "exp(-distance2(texture, pixel) / 4.0) + distance1(pixel, depth) * 0.1 + dot(normal, pixel) ** 2.0",
]


@pytest.mark.parametrize("text", MIXED)
def test_vectorised_evaluation_equals_a_per_pixel_loop(text):
    tree = parse(text)
    feats = random_features(2, 4, 5, seed=3)
    color = feats["color"]
    result = filter_images([tree], feats, color, radius=2)
    assert result.valid[0].tolist() == [True, True]
    np.testing.assert_allclose(
        result.color[0].numpy(), brute_force(tree, feats, color, 2), rtol=1e-9, atol=1e-12
    )


def test_batched_evaluation_equals_one_at_a_time():
    trees = [parse(x) for x in MIXED] + [
        parse(MIXED[0]),
        parse("distance2(normal, normal) + 1.0"),
        parse("2.0"),
    ]
    feats = random_features(1, 6, 7, seed=5, dtype=torch.float32)
    color = feats["color"]
    together = filter_images(trees, feats, color, radius=1)
    for k, tree in enumerate(trees):
        alone = filter_images([tree], feats, color, radius=1)
        torch.testing.assert_close(together.color[k], alone.color[0], rtol=0, atol=0)
        assert together.valid[k].tolist() == alone.valid[0].tolist()


def test_constant_weight_is_a_box_filter():
    feats = random_features(1, 5, 6, seed=1)
    out = filter_images([parse("2.0")], feats, feats["color"], radius=1).color[0]
    ref = brute_force(parse("1.0"), feats, feats["color"], 1)
    np.testing.assert_allclose(out.numpy(), ref, rtol=1e-12)


class _Allocations(TorchDispatchMode):
    """Largest tensor and peak total bytes of live (non-view) tensors created under the mode."""

    def __init__(self):
        super().__init__()
        self.refs, self.peak, self.largest = {}, 0, 0  # storage address -> weakref (in-place ops return self)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        self.refs = {k: r for k, r in self.refs.items() if r() is not None}
        for x in tree_flatten(out)[0]:
            if isinstance(x, torch.Tensor) and not x._is_view():
                self.refs.setdefault(x.untyped_storage().data_ptr(), weakref.ref(x))
                self.largest = max(self.largest, x.numel())
        self.peak = max(self.peak, sum(r().nbytes for r in self.refs.values() if r() is not None))
        return out


def test_memory_does_not_grow_with_the_window():
    feats = random_features(1, 24, 24, seed=2, dtype=torch.float32)
    trees = [parse(EXPR3)]
    peaks = {}
    for radius in (1, 4):
        with _Allocations() as mode:
            filter_images(trees, feats, feats["color"], radius)
        peaks[radius] = mode.peak
        assert mode.largest <= 3 * (24 + 2 * radius) ** 2  # one padded 3-channel frame at most
    # (2r+1)^2 grows 9x from r = 1 to r = 4; only the padded borders of the features may grow the peak.
    assert peaks[4] < 1.7 * peaks[1], peaks


def test_undefined_expressions_are_flagged_invalid():
    feats = random_features(2, 5, 5, seed=4, dtype=torch.float32)
    flat = dict(feats, depth=torch.cat([torch.full_like(feats["depth"][:1], 0.5), feats["depth"][1:]]))
    cases = {
        "sqrt(neg(1.0))": [False, False],  # NaN everywhere
        "asin(2.0 + distance2(normal, normal))": [False, False],
        "sqrt(distance2(depth, depth) - 0.2)": [False, False],  # negative where depths are close
        "exp(exp(exp(10.0 + distance2(normal, normal))))": [False, False],  # overflow to inf
        "biweight(sqrt(neg(distance2(texture, texture)) - 1.0))": [False, False],  # NaN through a kernel
        "pow(0.0, neg(distance2(normal, normal)))": [False, False],  # 0^-x = inf at the centre
        "distance2(depth, depth)": [False, True],  # zero weight sum on the constant-depth image
        "exp(-distance2(depth, depth))": [True, True],
        "div(1.0, distance2(depth, depth))": [True, True],  # safe division: defined
    }
    for text, expected in cases.items():
        result = filter_images([parse(text)], flat, flat["color"], radius=1)
        assert result.valid[0].tolist() == expected, text


def test_negative_weights_are_defined_unless_their_sum_is_zero():
    """Negative weights are allowed (module docstring: Mitchell's lobes); only a zero or non-finite sum is
    undefined. Weights 7 at the centre and -2 at its 8 neighbours sum to -9: defined, and the output is
    the hand-computed (7 c - 2 sum of neighbours) / -9; weights 8 and -1 sum to exactly 0: undefined."""
    feats = random_features(2, 5, 5, seed=6, dtype=torch.float64)
    color = feats["color"]
    padded = torch.nn.functional.pad(color, (1,) * 4, mode="replicate")
    around = sum(padded[:, :, 1 + dy : 6 + dy, 1 + dx : 6 + dx] for dy, dx in _NEIGHBOURS)
    lobes = filter_images([parse("7.0 - 9.0 * distanceMax(pixel, pixel)")], feats, color, radius=1)
    assert lobes.valid[0].tolist() == [True, True]
    torch.testing.assert_close(lobes.color[0], (7 * color - 2 * around) / -9)
    negative = filter_images([parse("neg(1.0)")], feats, color, radius=1)  # all negative: the box filter
    assert negative.valid[0].tolist() == [True, True]
    torch.testing.assert_close(negative.color[0], (color + around) / 9)
    zero = filter_images([parse("8.0 - 9.0 * distanceMax(pixel, pixel)")], feats, color, radius=1)
    assert zero.valid[0].tolist() == [False, False]


_NEIGHBOURS = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]


def test_intermediate_values_are_freed_after_their_last_use():
    """Per offset, a varying value is freed once the last node reading it has run: twelve nested sines
    above a distance hold no more memory at their peak than two (without the freeing, ten more planes)."""
    feats = random_features(1, 16, 16, seed=6, dtype=torch.float32)
    plane = 16 * 16 * 4  # bytes of one (1, 1, 16, 16) float32 value
    peaks = {}
    for depth in (2, 12):
        text = "sin(" * depth + "distance2(normal, normal)" + ")" * depth
        with _Allocations() as mode:
            filter_images([parse(text)], feats, feats["color"], radius=1)
        peaks[depth] = mode.peak
    assert peaks[12] - peaks[2] < 2 * plane, (peaks, plane)


def test_features_are_computed_in_the_colours_dtype():
    """Features and variables are converted to the colour's dtype: float32 buffers under a float64 colour
    give exactly the float64 result (computed in float32, the weights would differ at ~1e-7)."""
    feats = random_features(1, 6, 7, seed=8, dtype=torch.float32)
    tree = parse("exp(-distance2(normal, normal) / 0.3 - nVariance / 0.7) + 0.1")
    color = feats["color"].double()
    f64 = {k: v.double() for k, v in feats.items()}
    got = filter_images([tree], feats, color, radius=1).color[0]
    want = filter_images([tree], f64, color, radius=1).color[0]
    assert got.dtype == torch.float64
    torch.testing.assert_close(got, want, rtol=0, atol=0)


@pytest.mark.parametrize(
    "shape",
    [(1, 3, 5, 6), (2, 3, 6, 6), (2, 3, 5, 7), (2, 2, 5, 6), (3, 5, 6)],
    ids=["batch", "height", "width", "channels", "ndim"],
)
def test_a_feature_of_the_wrong_shape_is_named(shape):
    feats = random_features(2, 5, 6)
    feats["normal"] = torch.rand(shape, dtype=torch.float64)
    with pytest.raises(ExpressionError, match=r"feature 'normal': shape"):
        filter_images([parse("exp(-distance2(normal, normal))")], feats, feats["color"], 1)


def test_pi_is_the_constant_pi():
    """`pi` is a named terminal (its DEAP value is the string "pi"): a constant, not a feature to read."""
    like = torch.zeros(1, 3, 4, 5, dtype=torch.float64)
    weights = window_weights(parse("pi * distance1(pixel, pixel) + pi"), {}, like, radius=1)[0]
    expected = [math.pi * (abs(dy) + abs(dx)) + math.pi for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    np.testing.assert_allclose(weights[:, 2, 3].numpy(), expected, rtol=1e-15)
    assert required_terminals([parse("pi * 2.0")]) == set()


def test_ill_typed_trees_are_refused():
    """Trees built by hand past the typed grammar: a vector operator on a scalar, a vector terminal as a
    scalar."""
    feats = random_features(1, 3, 3)
    m = PSET.mapping
    on_scalar = gp.PrimitiveTree([m["distance2"], m["1.0"], m["normal"]])
    with pytest.raises(ExpressionError, match="distance2 takes two vector terminals"):
        filter_images([on_scalar], feats, feats["color"], 1)
    vector_as_scalar = gp.PrimitiveTree([m["mul"], m["normal"], m["1.0"]])
    with pytest.raises(ExpressionError, match="a vector terminal outside a vector operator"):
        filter_images([vector_as_scalar], feats, feats["color"], 1)


def test_missing_feature_is_named():
    feats = random_features(1, 3, 3)
    del feats["depth"]
    with pytest.raises(ExpressionError, match="'depth'"):
        filter_images([parse(EXPR1)], feats, feats["color"], 1)


# ---------------------------------------------------------------------------------------------------------
# The published expressions, by hand on a 3x3 image, radius 1 (centre pixel p = (1, 1), all 9 q)


def _norms(f, p, q):
    a, b = f[:, p[0], p[1]], f[:, q[0], q[1]]
    return {
        "L2": math.sqrt(sum((a - b) ** 2)),
        "L1": sum(abs(a - b)),
        "max": max(abs(a - b)),
        "dot": sum(a * b),
    }


def _hand(name, f, dy, dx):
    p, q = (1, 1), (1 + dy, 1 + dx)
    d, n, tex, col, di = (_norms(f[k], p, q) for k in ("depth", "normal", "texture", "color", "di"))
    p1, p2 = abs(dy) + abs(dx), math.sqrt(dy * dy + dx * dx)
    if name == "gp_expr1":  # Eq. 4.1
        first = math.exp(-(d["L2"] + n["L2"] + 2 * tex["dot"] + col["L2"] + tex["max"] + n["L1"]))
        return first * biweight_ref(-((di["L2"] ** 2) ** 2 * 2))
    wp = _norms(f["wp"], p, q)
    if name == "gp_expr2":  # Eq. 4.2-4.4
        wpg = _norms(f["wpg"], p, q)
        power = 2 + biweight_ref(math.sqrt(wpg["L2"] * p2 / (0.01 + wp["L1"])))
        a = (di["L1"] * di["max"]) ** power * math.cos(math.exp(-(n["L2"] ** 2) / 0.1**3)) + tex["dot"]
        return math.exp(-math.atan(col["dot"])) * math.exp(-(a * (p1 - math.atan(-n["L1"]))))
    # Eq. 4.5-4.8
    power1 = math.exp(biweight_ref(safe_div_ref(col["max"], 2**3 * sinc_ref(di["L2"]))))
    var_wp = f["wp_var"][0, 1, 1]
    power2 = math.exp(-(tex["max"] ** 2) / 0.01) * math.exp(tricube_ref(di["L2"]) * mitchell_ref(var_wp))
    num = p1 + 2 + math.exp(math.exp(sinc_ref(wp["L2"] ** 0.002)))
    den = 2 * math.asin(biweight_ref(((n["L2"] / 2) ** power1) ** power2))
    return math.exp(-wp["max"] / 0.05) * math.exp(-safe_div_ref(num, den))


@pytest.mark.parametrize("name", ["gp_expr1", "gp_expr2", "gp_expr3"])
def test_published_expression_weights_by_hand(name):
    rng = np.random.default_rng(7)
    normal = rng.normal(size=(3, 3, 3))
    f = {
        "depth": rng.uniform(0, 1, (1, 3, 3)),
        "normal": normal / np.linalg.norm(normal, axis=0),
        "texture": rng.uniform(0, 1, (3, 3, 3)),
        "color": rng.uniform(0, 0.5, (3, 3, 3)),
        "di": rng.uniform(0, 0.3, (1, 3, 3)),
        "wp": rng.uniform(0, 1, (3, 3, 3)) * 0.05,
        "wpg": rng.uniform(0, 1, (3, 3, 3)),
        "wp_var": rng.uniform(0, 2, (1, 3, 3)),
    }
    names = {"di": "directIllumination", "wp": "worldPosition", "wpg": "wpGradient", "wp_var": "wpVariance"}
    feats = {names.get(k, k): torch.from_numpy(v)[None] for k, v in f.items()}
    weights = window_weights(parse(PUBLISHED[name]), feats, feats["color"], radius=1)[0, :, 1, 1]
    expected = [_hand(name, f, dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    np.testing.assert_allclose(weights.numpy(), expected, rtol=1e-10)
    assert all(w > 0 for w in expected)


def test_published_expressions_need_these_features():
    need = {name: required_terminals([parse(text)]) for name, text in PUBLISHED.items()}
    assert need["gp_expr1"] == {"color", "depth", "directIllumination", "normal", "texture"}
    assert need["gp_expr2"] == {
        "color",
        "directIllumination",
        "normal",
        "texture",
        "worldPosition",
        "wpGradient",
    }
    assert need["gp_expr3"] == {
        "color",
        "directIllumination",
        "normal",
        "texture",
        "worldPosition",
        "wpVariance",
    }


# ---------------------------------------------------------------------------------------------------------
# The bilateral seed reproduces the cross-bilateral baseline


def test_bilateral_expression_reproduces_the_cross_bilateral_filter():
    g = torch.Generator().manual_seed(0)
    n, h, w = 2, 12, 15
    color = 3 * torch.rand(n, 3, h, w, generator=g)
    normal = torch.nn.functional.normalize(torch.randn(n, 3, h, w, generator=g), dim=1)
    albedo, depth = torch.rand(n, 3, h, w, generator=g), torch.rand(n, 1, h, w, generator=g)
    sigmas = {"spatial": 2.0, "color": 0.5, "normal": 0.3, "albedo": 0.2, "depth": 0.1}
    ref = cross_bilateral(color, guide_features(color, normal, albedo, depth, sigmas), 3, sigmas["spatial"])
    tree = parse(bilateral_expression(*sigmas.values()))
    feats = {"color": torch.log1p(color), "normal": normal, "texture": albedo, "depth": depth}
    out = filter_images([tree], feats, color, radius=3)
    assert out.valid[0].all()
    torch.testing.assert_close(out.color[0], ref, rtol=1e-5, atol=1e-5)
    assert bilateral_expression(2.0, math.inf, math.inf, math.inf, math.inf).count("distance2") == 1


# ---------------------------------------------------------------------------------------------------------
# Features: normalisation and gradients


def test_normalisation_of_one_and_three_dimensional_features():
    x = torch.tensor([[[[1.0, 4.0], [2.0, 0.5]]], [[[0.0, 0.0], [0.0, 0.0]]]])  # second image all zero
    torch.testing.assert_close(normalize_feature(x)[0], x[0] / 4)
    assert normalize_feature(x)[1].abs().sum() == 0
    v = torch.zeros(1, 3, 1, 2)
    v[0, :, 0, 0] = torch.tensor([3.0, 4.0, 0.0])  # length 5, the longest
    v[0, :, 0, 1] = torch.tensor([1.0, -2.0, 2.0])  # length 3
    out = normalize_feature(v)
    torch.testing.assert_close(out, v / 5)
    assert out.square().sum(1).sqrt().max() == pytest.approx(1.0)


def test_sobel_gradient_of_a_ramp():
    x = torch.arange(6.0).view(1, 1, 1, 6).expand(2, 3, 5, 6) * torch.tensor([1.0, 2.0, -1.0]).view(
        1, 3, 1, 1
    )
    g = sobel_gradient(x)
    assert g.shape == x.shape
    torch.testing.assert_close(
        g[..., 1:-1], 8 * torch.tensor([1.0, 2.0, 1.0]).view(1, 3, 1, 1).expand(2, 3, 5, 4)
    )
    torch.testing.assert_close(g[..., 0], 4 * torch.tensor([1.0, 2.0, 1.0]).view(1, 3, 1).expand(2, 3, 5))


# ---------------------------------------------------------------------------------------------------------
# GPFilter


def make_batch(n=1, h=9, w=11, seed=0, color=None):
    feats = random_features(n, h, w, seed=seed, dtype=torch.float32)
    batch = {
        "color": feats["color"] if color is None else color,
        "normal": feats["normal"],
        "albedo": feats["texture"],
        "depth": feats["depth"],
        "visibility": feats["directIllumination"],
        "position": feats["worldPosition"],
        "position_var": feats["wpVariance"],
    }
    return batch


@pytest.mark.parametrize("name", ["gp_expr1", "gp_expr2", "gp_expr3", "bilateral"])
def test_gp_filter_keeps_a_constant_image_whatever_the_features(name):
    text = PUBLISHED.get(name) or bilateral_expression(2.0, 0.5, 0.3, 0.1, 0.05)
    color = torch.full((2, 3, 9, 11), 0.7)
    out = GPFilter(text, radius=2)(make_batch(2, color=color))["color"]
    torch.testing.assert_close(out, color, rtol=0, atol=1e-6)


def test_gp_filter_reduces_noise_on_a_noisy_constant_image():
    g = torch.Generator().manual_seed(1)
    noisy = 0.5 + 0.1 * torch.randn(1, 3, 24, 24, generator=g)
    batch = make_batch(1, 24, 24, color=noisy)
    batch.update(normal=torch.ones(1, 3, 24, 24), albedo=torch.full((1, 3, 24, 24), 0.5))
    batch.update(depth=torch.full((1, 1, 24, 24), 0.3), visibility=torch.ones(1, 1, 24, 24))
    out = GPFilter(EXPR1, radius=3)(batch)["color"]
    assert (out - 0.5).square().mean() < 0.2 * (noisy - 0.5).square().mean()


def test_gp_filter_reads_visibility_from_the_network_inputs_and_names_missing_features():
    batch = make_batch(1)
    direct = GPFilter(EXPR1, radius=1)(batch)["color"]
    inputs = torch.cat([batch["color"], batch.pop("visibility"), torch.rand(1, 1, 9, 11)], dim=1)
    batch["diffuse_in"] = inputs
    via_inputs = GPFilter(EXPR1, radius=1, input_features=["color", "visibility", "normal.var"])(batch)[
        "color"
    ]
    torch.testing.assert_close(via_inputs, direct)
    with pytest.raises(ConfigError) as excinfo:
        GPFilter(EXPR1, radius=1, input_features=["color", "normal.var"])(batch)
    one_line_error(
        excinfo, "model.expression", "'directIllumination'", "'visibility'", "model.input_features"
    )
    batch = make_batch(1)
    del batch["position"]
    with pytest.raises(ConfigError) as excinfo:
        GPFilter(EXPR2, radius=1)(batch)
    one_line_error(excinfo, "model.expression", "'worldPosition'", "'position'")


def test_gp_filter_normalises_features_so_their_scale_does_not_matter():
    batch = make_batch(1, seed=3)
    scaled = dict(
        batch, depth=batch["depth"] * 10, albedo=batch["albedo"] * 2, visibility=batch["visibility"] * 3
    )
    out = GPFilter(EXPR1, radius=2)(batch)["color"]
    torch.testing.assert_close(GPFilter(EXPR1, radius=2)(scaled)["color"], out, rtol=1e-5, atol=1e-6)
    raw = GPFilter(EXPR1, radius=2, normalize=False)(scaled)["color"]
    assert not torch.allclose(raw, out, atol=1e-4)


def test_gp_filter_variances_scale_with_their_feature():
    batch = make_batch(1, seed=4)
    filt = GPFilter("exp(-distance2(worldPosition, worldPosition) - wpVariance)", radius=1)
    feats = filt.features(batch)
    s = batch["position"].square().sum(1).sqrt().max()
    torch.testing.assert_close(feats["wpVariance"], batch["position_var"] / s**2)
    torch.testing.assert_close(feats["worldPosition"], batch["position"] / s)


def test_gp_filter_config_errors_and_halo():
    with pytest.raises(ConfigError) as excinfo:
        GPFilter("exp(-normal)", radius=1)
    one_line_error(excinfo, "model.expression")
    with pytest.raises(ConfigError, match="model.radius"):
        GPFilter("1.0", radius=-1)
    assert GPFilter(EXPR1, radius=4).halo is None  # normalisation reads the whole image
    assert GPFilter(EXPR1, radius=4, normalize=False).halo == 4
    assert GPFilter(EXPR2, radius=4, normalize=False).halo == 5  # Sobel gradient: one more pixel


def test_gp_filter_output_is_nan_only_on_the_images_where_the_weights_are_undefined(caplog):
    batch = make_batch(2)
    batch["depth_var"] = torch.ones(2, 1, 9, 11)
    batch["depth_var"][1] = -1.0  # sqrt of a negative variance: NaN weights on image 1 only
    with caplog.at_level("WARNING"):
        out = GPFilter("sqrt(dovVariance)", radius=1, normalize=False)(batch)["color"]
    assert out[1].isnan().all()
    box = GPFilter("1.0", radius=1, normalize=False)({"color": batch["color"][:1]})["color"]
    torch.testing.assert_close(out[:1], box)  # a constant weight on image 0: the box filter
    assert "sqrt(dovVariance)" in caplog.text and "[1]" in caplog.text


def test_model_configs_build_the_published_filters():
    for name, text in PUBLISHED.items():
        cfg = OmegaConf.load(CONF_MODEL / f"{name}.yaml")
        assert cfg.expression == text and cfg._target_ == "src.models.filters.gp_filter.GPFilter"
    cfg = compose_config(["model=gp_expr1", "profile=smoke"]).model
    model = build_method(cfg)
    assert isinstance(model, GPFilter) and not model.learned and model.radius == 10
    assert parse(model.expression) == parse(EXPR1)
    assert model.input_channels is not None  # task.features reached it
    seed = build_method(compose_config(["model=gp_filter", "profile=smoke"]).model)
    assert parse(seed.expression) == parse(str(OmegaConf.load(CONF_MODEL / "gp_filter.yaml").expression))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_evaluation_equals_cpu():
    feats = random_features(1, 32, 32, seed=6, dtype=torch.float32)
    trees = [parse(x) for x in MIXED]
    cpu = filter_images(trees, feats, feats["color"], radius=3)
    gpu = filter_images(trees, {k: v.cuda() for k, v in feats.items()}, feats["color"].cuda(), radius=3)
    for a, b in zip(cpu.color, gpu.color, strict=True):
        assert b.device.type == "cuda"
        torch.testing.assert_close(b.cpu(), a, rtol=1e-4, atol=1e-5)


# Surviving mutants of src/gp/evaluate.py (bash scripts/mutation.sh gp_eval), all equivalent here:
# - `device=` dropped or None (_pixel_grid, _Inputs.neighbour, _static_values, _vector_value; 10 mutants):
#   the same on the CPU these tests run on (the CUDA test above is skipped without a GPU).
# - _pixel_grid `view(1, 1, h, 1)` -> `view(1, h, 1)` (and `view(1, 1, w)` for the columns): expand
#   broadcasts both to the same (n, 1, h, w); `dtype=` dropped or None for the rows or the columns: the
#   int64 one is promoted to the other's float dtype by `torch.cat`. _Inputs.neighbour's offset
#   `dtype=` dropped or None: int64 (dy, dx, 0) promotes with the float coordinates; `offset.view(3, 1, 1)`
#   broadcasts as (1, 3, 1, 1).
# - _vector_value's pixel fast path misspelt (`a == b == "XXpixelXX"`, "PIXEL"): the general path computes
#   the same distance between p and p + offset (the fast path only saves the work; pixel against another
#   feature is pinned above).
# - _Inputs `if name != "pixel"` misspelt: the pixel grid is padded too, and never read padded.
# - _offset_values `if node.kind != "vector"` -> `or True` or the kind misspelt: a vector node's children
#   are feature names, never keys of `last_use`, so nothing more is freed; `key not in pending and key not
#   in plan.last_use` -> `key in pending and ...`: the original branch never runs (every varying node but a
#   root is read by a later one, so it is in last_use), and the mutant frees a root after it was yielded
#   and used.
# - Plan._add: a `_Node`'s `key` None (the dict key is used, the field never read), a variable's or a
#   constant's `children` None or a constant's `name` None (static nodes: neither is read), `"binary"`
#   misspelt (`_apply` only tests `kind == "unary"`).


def _flat_features(n=1, h=24, w=24, wp_step=0.0, seed=0):
    """Constant guides (normal +z, texture and depth 0.5, visibility 1), noisy grey colour, and a world
    position that changes `wp_step` per pixel (0: constant)."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(
        torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij"
    )
    color = 0.5 + 0.05 * torch.randn(n, 3, h, w, generator=g)
    return {
        "color": color,
        "normal": torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand(n, 3, h, w).clone(),
        "texture": torch.full((n, 3, h, w), 0.5),
        "depth": torch.full((n, 1, h, w), 0.5),
        "worldPosition": torch.stack([xx * wp_step, yy * wp_step, torch.zeros_like(xx)])
        .expand(n, 3, h, w)
        .clone(),
        "directIllumination": torch.ones(n, 1, h, w),
        "wpGradient": torch.zeros(n, 3, h, w),
        "wpVariance": torch.zeros(n, 1, h, w),
    }


def _centre_over_4_neighbours(expression, features, radius=3):
    weights = window_weights(parse(expression), features, features["color"], radius)[0]
    h, w = weights.shape[-2:]
    grid = weights[:, h // 2, w // 2].view(2 * radius + 1, 2 * radius + 1)
    r = radius
    return float(grid[r, r] / ((grid[r - 1, r] + grid[r + 1, r] + grid[r, r - 1] + grid[r, r + 1]) / 4))


def test_expr3_gives_the_centre_about_one_percent_of_its_neighbours_weight_where_world_position_varies():
    """The property gp_expr3.yaml states: ||wp||^0.002 is ~1 for any neighbour, sinc(1) = 0, so e^(e^sinc)
    is e there and e^e at the centre; with a constant world position the centre weighs as much as (more
    than) its neighbours."""
    assert 0.005 < _centre_over_4_neighbours(EXPR3, _flat_features(wp_step=0.01)) < 0.02
    assert _centre_over_4_neighbours(EXPR3, _flat_features(wp_step=0.0)) > 1.0


def test_expr2_weighs_bright_neighbours_less_and_darkens_a_step():
    """The property gp_expr2.yaml states: exp(-atan(c_i . c_j)) is a dot product of the noisy colours, so
    on a 0.2 / 0.8 step with flat guides the output keeps less of the mean (0.98) than gp_expr1 (0.999)."""
    features = _flat_features(wp_step=0.01)
    n, _, h, w = features["color"].shape
    step = torch.full((n, 3, h, w), 0.2)
    step[..., w // 2 :] = 0.8
    step = step + 0.05 * torch.randn(n, 3, h, w, generator=torch.Generator().manual_seed(1))
    features["color"] = step
    out = filter_images([parse(EXPR2), parse(EXPR1)], features, step, 3).color
    energy2, energy1 = (float(o.mean() / step.mean()) for o in out)
    assert energy2 < 0.99 and energy1 > 0.995
