"""Expressions as text: DEAP's prefix form, a readable infix form, and one parser for both.

    prefix  str(tree), DEAP's own form: mul(exp(neg(distance2(normal, normal))), 0.5)
    infix   `to_infix`, Python syntax: exp(-distance2(normal, normal)) * 0.5

Both are Python expressions (a prefix call `mul(a, b)` is a call, `a * b` an operator), so `parse` reads
either, or a mix, with Python's `ast`: + - * / ** and unary minus are add sub mul div pow neg; every other
operator is a call by its grammar name; names are terminals; numbers are constants (an integer is a float;
"-0.5" is the constant -0.5, while neg applied to a constant prints as `neg(0.5)` so that the two stay
apart). Types are checked (a vector terminal only as an argument of a vector operator), and
`parse(to_infix(t)) == t` and `parse(str(t)) == t` for every tree t, constants included (floats print with
`repr`, which round-trips).
"""

from __future__ import annotations

import ast
import math

from deap import gp

from src.gp.grammar import BINARY, BINARY_SYMBOLS, PSET, UNARY, Vector

#: Infix precedence of each form (higher binds tighter), as in Python.
_PREC = {"add": 1, "sub": 1, "mul": 2, "div": 2, "neg": 3, "pow": 4}
_ATOM = 5
_BINOPS = {ast.Add: "add", ast.Sub: "sub", ast.Mult: "mul", ast.Div: "div", ast.Pow: "pow"}


class ExpressionError(ValueError):
    """An expression's text does not parse, or is not well typed, under the grammar."""


def _type_name(t: type) -> str:
    return "vector" if t is Vector else "scalar"


def constant(value: float, pset: gp.PrimitiveSetTyped = PSET) -> gp.Terminal:
    """The terminal of a numeric constant: the grammar's own (Fig. 3.2) when it is one, else a new one."""
    value = float(value)
    if not math.isfinite(value):
        raise ExpressionError(f"constant {value!r} is not finite")
    own = pset.mapping.get(repr(value))
    if isinstance(own, gp.Terminal) and own.value == value:
        return own
    return gp.Terminal(value, False, float)


def parse(text: str, pset: gp.PrimitiveSetTyped = PSET) -> gp.PrimitiveTree:
    """The tree of an expression in prefix or infix form (module docstring); ExpressionError if it is
    malformed or ill-typed, naming the offending part."""
    try:
        body = ast.parse(text.strip(), mode="eval").body
    except SyntaxError as err:
        raise ExpressionError(f"cannot parse {text!r}: {err.msg}") from None
    nodes: list = []
    _convert(body, float, pset, nodes)
    return gp.PrimitiveTree(nodes)


def _convert(node: ast.AST, want: type, pset: gp.PrimitiveSetTyped, out: list) -> None:
    """Append the prefix nodes of `node`, which must have type `want`."""
    where = ast.unparse(node)
    if (
        isinstance(node, ast.Constant)
        and isinstance(node.value, int | float)
        and not isinstance(node.value, bool)
    ):
        prim = constant(node.value, pset)
        args: list[ast.AST] = []
    elif (
        isinstance(node, ast.UnaryOp)
        and isinstance(node.op, ast.USub)
        and isinstance(node.operand, ast.Constant)
        and isinstance(node.operand.value, int | float)
    ):
        prim, args = constant(-node.operand.value, pset), []
    elif isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        if isinstance(node.op, ast.UAdd):
            _convert(node.operand, want, pset, out)
            return
        prim, args = pset.mapping["neg"], [node.operand]
    elif isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
        prim, args = pset.mapping[_BINOPS[type(node.op)]], [node.left, node.right]
    elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and not node.keywords:
        prim = pset.mapping.get(node.func.id)
        if not isinstance(prim, gp.Primitive):
            raise ExpressionError(f"{where}: {node.func.id!r} is not an operator of the grammar")
        args = list(node.args)
        if len(args) != prim.arity:
            raise ExpressionError(f"{where}: {prim.name} takes {prim.arity} argument(s), got {len(args)}")
    elif isinstance(node, ast.Name):
        prim = pset.mapping.get(node.id)
        if not isinstance(prim, gp.Terminal):
            raise ExpressionError(f"{where}: {node.id!r} is not a terminal of the grammar")
        args = []
    else:
        raise ExpressionError(f"{where}: not an expression of the grammar")
    if prim.ret is not want:
        raise ExpressionError(f"{where}: a {_type_name(prim.ret)} where a {_type_name(want)} is expected")
    out.append(prim)
    for arg, arg_type in zip(args, getattr(prim, "args", ()), strict=True):
        _convert(arg, arg_type, pset, out)


def to_prefix(tree: gp.PrimitiveTree) -> str:
    """DEAP's prefix form (str(tree))."""
    return str(tree)


def to_infix(tree: gp.PrimitiveTree, digits: int | None = None) -> str:
    """Readable infix form (Python syntax, minimal parentheses); `parse` reads it back to an equal tree.
    `digits`: constants to that many significant digits instead (for display: 0.02, not the
    0.020000000000000004 a mutation can make; what is logged keeps every digit)."""
    text, _ = _infix(tree, 0, digits)
    return text


def compact(text: str, digits: int = 6) -> str:
    """An expression's text as a page shows it: infix with constants to `digits` significant digits (its
    text unchanged when it does not parse, e.g. an older grammar's)."""
    try:
        return to_infix(parse(text), digits)
    except ExpressionError:
        return text


def _is_number(node) -> bool:
    """Whether a node is a numeric constant (named terminals, pi included, hold their name as value)."""
    return isinstance(node, gp.Terminal) and not isinstance(node.value, str)


def _wrap(text: str, prec: int, minimum: int) -> str:
    return text if prec >= minimum else f"({text})"


def _number(node: gp.Terminal, digits: int | None) -> str:
    return node.format() if digits is None or not _is_number(node) else f"{node.value:.{digits}g}"


def _infix(tree: gp.PrimitiveTree, i: int, digits: int | None = None) -> tuple[str, int]:
    """(infix text, precedence) of the subtree rooted at tree[i]; `digits`: see `to_infix`."""
    node = tree[i]
    if isinstance(node, gp.Terminal):
        if _is_number(node) and node.value < 0:
            return f"({_number(node, digits)})", _ATOM  # "(-0.5)": a constant, not neg(0.5)
        return _number(node, digits), _ATOM
    children, j = [], i + 1
    for _ in range(node.arity):
        end = tree.searchSubtree(j).stop
        children.append((j, end))
        j = end
    if node.name in BINARY:
        (la, _), (ra, _) = children
        left, lp = _infix(tree, la, digits)
        right, rp = _infix(tree, ra, digits)
        prec = _PREC[node.name]
        if node.name == "pow":  # right-associative; a ** -b is valid Python
            left, right = _wrap(left, lp, _ATOM), _wrap(right, rp, _PREC["neg"])
        else:
            left, right = _wrap(left, lp, prec), _wrap(right, rp, prec + 1)
        return f"{left} {BINARY_SYMBOLS[node.name]} {right}", prec
    if node.name == "neg":
        child = tree[children[0][0]]
        if _is_number(child):
            return f"neg({_number(child, digits)})", _ATOM  # keep neg(0.5) apart from the constant -0.5
        operand, op_prec = _infix(tree, children[0][0], digits)
        return f"-{_wrap(operand, op_prec, _PREC['pow'])}", _PREC["neg"]
    assert node.name in UNARY or node.arity == 2
    args = ", ".join(_infix(tree, a, digits)[0] for a, _ in children)
    return f"{node.name}({args})", _ATOM
