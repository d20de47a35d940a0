"""Vectorised evaluation of weight expressions: filter images with one or many expression trees at once.

For every pixel p and every offset q - p in the (2r+1)^2 window (Davletaliyev 2016, Eq. 2.10):

    out_p = sum_q w(p, q) c_q / sum_q w(p, q),      w(p, q) = the expression's value at (p, q)

As in `src.models.filters.cross_bilateral`, the loop runs over the window offsets, not the pixels: per
offset each operator is one whole-image tensor op, and only sum_q w c_q and sum_q w are kept, so memory is
O(N * H * W * (channels + expression size)) whatever the radius. Borders use replicate padding for the
features and the colour; the pixel coordinates of q are the virtual ones (p + offset), so the spatial
distance of a border offset is the offset itself, as in the cross-bilateral baseline.

Inputs (`features`): a dict from terminal name to a tensor on the colour's device,
    vector terminals    (N, C, H, W), C = 1 or 3; the first argument of a vector operator is read at the
                        centre p, the second at the neighbour q
    scalar variables    (N, 1, H, W) (or anything broadcastable to it): the value at the centre p
`pixel` is built here (row, column, 0) and needs no entry. Only the terminals a tree uses must be present.

Many trees at once (`filter_images(trees, ...)`): they share the padded features and, per offset, every
common sub-expression (nodes are keyed by their prefix text, so distance2(normal, normal) is computed once
per offset for all trees); sub-expressions without a vector operator (constants, variables) do not depend on
the offset and are computed once.

Validity (the thesis's "undefined operation", Sec. 3.2.3): an expression is invalid for an image when its
filtered colour or its weight sum is not finite anywhere, or its weight sum is exactly 0 at some pixel (the
filtering equation is undefined there). NaN/Inf weights always end up there: NaN and Inf propagate through
the sums. `FilterResult.valid` holds the flags; the search gives an invalid expression the worst fitness,
`GPFilter` refuses to return its output. Negative weights are allowed (Mitchell's lobes).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from deap import gp

from src.gp.grammar import BINARY, UNARY, VECTOR_OPS, VECTORS
from src.gp.text import ExpressionError

#: Vector operators on two `pixel` terminals, as functions of the offset (dy, dx) alone.
_PIXEL_OPS = {
    "distance2": lambda dy, dx: (dy * dy + dx * dx) ** 0.5,
    "distance1": lambda dy, dx: abs(dy) + abs(dx),
    "distanceMax": lambda dy, dx: max(abs(dy), abs(dx)),
}


@dataclass(frozen=True)
class _Node:
    key: str  # prefix text of the subtree: equal subtrees share one node
    kind: str  # "const" | "var" | "unary" | "binary" | "vector"
    name: str  # operator or terminal name
    children: tuple[str, ...]  # keys (for "vector": the two terminal names)
    value: float = 0.0  # for "const"
    varying: bool = False  # depends on the offset (contains a vector operator)


class Plan:
    """The trees' sub-expressions in one dependency order, common ones merged (module docstring)."""

    def __init__(self, trees: Sequence[gp.PrimitiveTree]) -> None:
        self.nodes: dict[str, _Node] = {}
        self.roots = [self._add(tree, 0)[0] for tree in trees]
        self.static = [k for k, n in self.nodes.items() if not n.varying]
        self.varying = [k for k, n in self.nodes.items() if n.varying]
        self.vectors = sorted({c for n in self.nodes.values() if n.kind == "vector" for c in n.children})
        self.variables = sorted({n.name for n in self.nodes.values() if n.kind == "var"})
        # Last position (in self.varying) where each varying value is read, so it can be freed then.
        self.last_use: dict[str, int] = {}
        for i, key in enumerate(self.varying):
            for child in self.nodes[key].children:
                if self.nodes[key].kind != "vector" and self.nodes[child].varying:
                    self.last_use[child] = i

    def _add(self, tree: gp.PrimitiveTree, i: int) -> tuple[str, int]:
        """Add the subtree at tree[i]; (its key, index after it)."""
        node = tree[i]
        end = tree.searchSubtree(i).stop
        key = str(gp.PrimitiveTree(tree[i:end]))
        if key in self.nodes:
            return key, end
        if isinstance(node, gp.Terminal):
            if node.ret is not float:
                raise ExpressionError(f"{key}: a vector terminal outside a vector operator")
            if isinstance(node.value, str) and node.value != "pi":
                self.nodes[key] = _Node(key, "var", node.value, ())
            else:
                value = torch.pi if node.value == "pi" else float(node.value)
                self.nodes[key] = _Node(key, "const", key, (), value)
            return key, end
        if node.name in VECTOR_OPS:
            a, b = tree[i + 1], tree[i + 2]
            for t in (a, b):
                if not (isinstance(t, gp.Terminal) and t.value in VECTORS):
                    raise ExpressionError(f"{key}: {node.name} takes two vector terminals")
            self.nodes[key] = _Node(key, "vector", node.name, (a.value, b.value), varying=True)
            return key, end
        children, j = [], i + 1
        for _ in range(node.arity):
            child, j = self._add(tree, j)
            children.append(child)
        kind = "unary" if node.name in UNARY else "binary"
        if node.name not in UNARY and node.name not in BINARY:
            raise ExpressionError(f"{key}: unknown operator {node.name!r}")
        varying = any(self.nodes[c].varying for c in children)
        self.nodes[key] = _Node(key, kind, node.name, tuple(children), varying=varying)
        return key, end


def _apply(node: _Node, values: Mapping[str, torch.Tensor]) -> torch.Tensor:
    if node.kind == "unary":
        return UNARY[node.name](values[node.children[0]])
    return BINARY[node.name](values[node.children[0]], values[node.children[1]])


@dataclass
class FilterResult:
    """Per tree k: `color[k]` (N, C, H, W) the filtered colour, `valid[k]` (N,) whether it is defined."""

    color: list[torch.Tensor]
    valid: list[torch.Tensor]


def required_terminals(trees: Sequence[gp.PrimitiveTree]) -> set[str]:
    """The feature terminals (vector terminals but `pixel`, scalar variables) the trees read."""
    plan = Plan(trees)
    return (set(plan.vectors) - {"pixel"}) | set(plan.variables)


def _pixel_grid(n: int, h: int, w: int, like: torch.Tensor) -> torch.Tensor:
    rows = torch.arange(h, dtype=like.dtype, device=like.device).view(1, 1, h, 1).expand(n, 1, h, w)
    cols = torch.arange(w, dtype=like.dtype, device=like.device).view(1, 1, 1, w).expand(n, 1, h, w)
    return torch.cat([rows, cols, torch.zeros_like(rows)], dim=1)


class _Inputs:
    """The features one call reads: centre values, replicate-padded copies for the neighbour views."""

    def __init__(self, plan: Plan, features: Mapping[str, torch.Tensor], like: torch.Tensor, radius: int):
        n, _, h, w = like.shape
        self.h, self.w, self.radius = h, w, radius
        missing = sorted(
            name for name in (set(plan.vectors) - {"pixel"}) | set(plan.variables) if name not in features
        )
        if missing:
            raise ExpressionError(f"no feature {missing[0]!r} given ({len(missing)} missing: {missing})")
        self.centre: dict[str, torch.Tensor] = {}
        self.padded: dict[str, torch.Tensor] = {}
        for name in plan.vectors:
            x = _pixel_grid(n, h, w, like) if name == "pixel" else features[name].to(like)
            if x.ndim != 4 or x.shape[0] != n or x.shape[2:] != (h, w) or x.shape[1] not in (1, 3):
                raise ExpressionError(
                    f"feature {name!r}: shape {tuple(x.shape)}, expected ({n}, 1|3, {h}, {w})"
                )
            self.centre[name] = x
            if name != "pixel":
                self.padded[name] = F.pad(x, (radius,) * 4, mode="replicate")
        self.variables = {name: features[name].to(like) for name in plan.variables}

    def neighbour(self, name: str, dy: int, dx: int) -> torch.Tensor:
        """Feature `name` at q = p + (dy, dx), for every p."""
        if name == "pixel":
            offset = torch.tensor([dy, dx, 0], dtype=self.centre[name].dtype, device=self.centre[name].device)
            return self.centre[name] + offset.view(1, 3, 1, 1)
        r = self.radius
        return self.padded[name][:, :, r + dy : r + dy + self.h, r + dx : r + dx + self.w]


def _vector_value(node: _Node, inputs: _Inputs, dy: int, dx: int) -> torch.Tensor:
    a, b = node.children
    if a == b == "pixel" and node.name in _PIXEL_OPS:
        ref = inputs.centre["pixel"]
        return torch.tensor(float(_PIXEL_OPS[node.name](dy, dx)), dtype=ref.dtype, device=ref.device)
    return VECTOR_OPS[node.name](inputs.centre[a], inputs.neighbour(b, dy, dx))


def _offset_values(plan: Plan, inputs: _Inputs, static: Mapping[str, torch.Tensor], dy: int, dx: int):
    """Yield (root index, weight) of every tree for one offset; varying values are freed after last use."""
    values = dict(static)
    pending = {}  # root keys per position, so shared roots are yielded once each tree
    for k, root in enumerate(plan.roots):
        pending.setdefault(root, []).append(k)
    for root, ks in pending.items():
        if not plan.nodes[root].varying:
            for k in ks:
                yield k, values[root]
    for i, key in enumerate(plan.varying):
        node = plan.nodes[key]
        values[key] = _vector_value(node, inputs, dy, dx) if node.kind == "vector" else _apply(node, values)
        for k in pending.get(key, ()):
            yield k, values[key]
        for child in dict.fromkeys(node.children) if node.kind != "vector" else ():  # x * x: once
            if plan.last_use.get(child) == i and child not in pending:
                del values[child]
        if key not in pending and key not in plan.last_use:
            del values[key]


def _static_values(plan: Plan, inputs: _Inputs, like: torch.Tensor) -> dict[str, torch.Tensor]:
    values: dict[str, torch.Tensor] = {}
    for key in plan.static:
        node = plan.nodes[key]
        if node.kind == "const":
            values[key] = torch.tensor(node.value, dtype=like.dtype, device=like.device)
        elif node.kind == "var":
            values[key] = inputs.variables[node.name]
        else:
            values[key] = _apply(node, values)
    return values


def _offsets(radius: int):
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            yield dy, dx


@torch.no_grad()
def filter_images(
    trees: Sequence[gp.PrimitiveTree],
    features: Mapping[str, torch.Tensor],
    color: torch.Tensor,
    radius: int,
) -> FilterResult:
    """Filter `color` (N, C, H, W) with each tree's weights over a (2r+1)^2 window (module docstring).

    Computed in the colour's dtype and on its device; features are moved there."""
    if int(radius) != radius or radius < 0:
        raise ValueError(f"radius must be an integer >= 0, got {radius!r}")
    radius = int(radius)
    plan = Plan(trees)
    n, c, h, w = color.shape
    inputs = _Inputs(plan, features, color, radius)
    static = _static_values(plan, inputs, color)
    color_pad = F.pad(color, (radius,) * 4, mode="replicate")
    acc = [torch.zeros_like(color) for _ in trees]
    wsum = [torch.zeros((n, 1, h, w), dtype=color.dtype, device=color.device) for _ in trees]
    for dy, dx in _offsets(radius):
        shifted = color_pad[:, :, radius + dy : radius + dy + h, radius + dx : radius + dx + w]
        for k, weight in _offset_values(plan, inputs, static, dy, dx):
            acc[k].add_(weight * shifted)
            wsum[k].add_(weight)
    colors, valid = [], []
    for a, s in zip(acc, wsum, strict=True):
        out = a / s
        ok = torch.isfinite(out).flatten(1).all(1) & torch.isfinite(s).flatten(1).all(1)
        valid.append(ok & (s != 0).flatten(1).all(1))
        colors.append(out)
    return FilterResult(colors, valid)


@torch.no_grad()
def window_weights(
    tree: gp.PrimitiveTree, features: Mapping[str, torch.Tensor], like: torch.Tensor, radius: int
) -> torch.Tensor:
    """Every weight w(p, q) of one tree: (N, (2r+1)^2, H, W), offsets in row-major order (dy, then dx,
    from -r). O((2r+1)^2 H W) memory: for inspection and tests, not for filtering."""
    plan = Plan([tree])
    inputs = _Inputs(plan, features, like, radius)
    static = _static_values(plan, inputs, like)
    n, _, h, w = like.shape
    out = []
    for dy, dx in _offsets(radius):
        for _, weight in _offset_values(plan, inputs, static, dy, dx):
            out.append(weight.expand(n, 1, h, w).clone())
    return torch.cat(out, dim=1)
