"""Unit conversion expressions (``pos_to_device``, ``vel_from_device`` ...).

ros_canopen evaluates these with muParser. This module is a small
hand-written recursive-descent parser instead of Python's eval because the
text comes from a parameter server anyone on the ROS network can write: it
must never be able to run code. It knows only numbers, the variables
``pos``, ``vel``, ``eff``, ``objXXXX`` / ``objXXXXsubYY`` (hex, like
ros_canopen's object strings), the constant ``pi``, the operators
``+ - * / ^`` and parentheses, and the functions in FUNCTIONS. Anything else
is refused at compile time, which the driver does at start.

The parsed expression is turned once into a tree of Python closures, so the
10 ms cycle only calls functions: no text is looked at after start.

Grammar (``^`` binds tighter than unary minus and is right-associative, so
``-2^2`` is -4 and ``2^3^2`` is 512)::

    expr    := term (("+" | "-") term)*
    term    := unary (("*" | "/") unary)*
    unary   := ("+" | "-") unary | power
    power   := primary ("^" unary)?
    primary := NUMBER | "pi" | VARIABLE | FUNCTION "(" expr ("," expr)* ")"
             | "(" expr ")"
"""
from __future__ import annotations

import math
import re
import weakref
from typing import Callable, Dict, List, Mapping, Optional, Tuple

from .objects import ObjectKey

__all__ = [
    "UnitExpressionError",
    "Expression",
    "compile_expression",
    "object_variable_name",
    "FUNCTIONS",
    "MAX_LENGTH",
]

MAX_LENGTH = 1000  # characters; real conversions are a few dozen
_MAX_DEPTH = 64    # nesting; keeps hostile input from exhausting the stack

Env = Mapping[str, float]
_Node = Callable[[Env], float]


class UnitExpressionError(ValueError):
    """An expression that is not valid; the message says where and why."""


def _rint(x: float) -> float:
    # C rint() rounds half to even in the default rounding mode, like round().
    return float(round(x))


def _norm(val: float, lo: float, hi: float) -> float:
    """Wrap val into [lo, hi), e.g. an angle into [-pi, pi)."""
    span = hi - lo
    if not span > 0:
        return math.nan
    return lo + math.fmod(math.fmod(val - lo, span) + span, span)


def _smooth(val: float, old: float, alpha: float) -> float:
    """Exponential smoothing: alpha*val + (1-alpha)*old (old NaN -> val)."""
    if math.isnan(old):
        return val
    return alpha * val + (1.0 - alpha) * old


def _avg(*vals: float) -> float:
    return math.fsum(vals) / len(vals)


# name -> (function, minimum arguments, maximum arguments or None)
FUNCTIONS: Dict[str, Tuple[Callable[..., float], int, Optional[int]]] = {
    "rint": (_rint, 1, 1),
    "abs": (abs, 1, 1),
    "sin": (math.sin, 1, 1),
    "cos": (math.cos, 1, 1),
    "tan": (math.tan, 1, 1),
    "sqrt": (math.sqrt, 1, 1),
    "deg2rad": (math.radians, 1, 1),
    "rad2deg": (math.degrees, 1, 1),
    "min": (lambda *vals: min(vals), 1, None),
    "max": (lambda *vals: max(vals), 1, None),
    "avg": (_avg, 1, None),
    "norm": (_norm, 3, 3),
    "smooth": (_smooth, 3, 3),
}
_PLAIN_VARIABLES = ("pos", "vel", "eff")
_OBJ_RE = re.compile(r"^obj([0-9a-f]{4})(?:sub([0-9a-f]{1,2}))?$", re.IGNORECASE)
_TOKEN_RE = re.compile(r"""
    (?P<ws>\s+)
  | (?P<num>(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?)
  | (?P<name>[A-Za-z_][A-Za-z0-9_]*)
  | (?P<op>[-+*/^(),])
""", re.VERBOSE)


def object_variable_name(key: ObjectKey) -> str:
    """The canonical variable name of an object: ``obj6064``, ``obj6099sub02``."""
    if key.subindex:
        return "obj%04Xsub%02X" % (key.index, key.subindex)
    return "obj%04X" % key.index


# What a compiled function may raise; evaluate() turns each into NaN.
EVALUATION_ERRORS = (ArithmeticError, ValueError, TypeError)


class Expression:
    """A compiled expression. Call ``evaluate(env)`` with the variables.

    ``variables`` are the canonical names the expression reads (``pos``,
    ``obj6064``, ``obj6099sub02``...), ``objects`` the ObjectKeys behind the
    ``obj`` ones: the driver maps or reads these. Evaluation never raises: a
    domain error (sqrt(-1), 1/0, overflow) gives NaN, which the driver
    refuses to put on the bus. ``raw`` is the compiled function itself, for
    the driver's cycle, which calls it inline: it may raise
    EVALUATION_ERRORS, and its result is a number to pass through float().
    """

    __slots__ = ("text", "variables", "objects", "_fn", "constant", "raw")

    def __init__(self, text: str, fn: _Node, variables: Tuple[str, ...],
                 objects: Tuple[ObjectKey, ...], constant: bool) -> None:
        self.text = text
        self._fn = self.raw = fn
        self.variables = variables
        self.objects = objects
        self.constant = constant

    def evaluate(self, env: Env) -> float:
        try:
            return float(self._fn(env))
        except EVALUATION_ERRORS:
            return math.nan

    __call__ = evaluate

    def uses(self, name: str) -> bool:
        return name in self.variables

    def __repr__(self) -> str:
        return "Expression(%r)" % self.text


class _Parser:
    def __init__(self, text: str) -> None:
        self.text = text
        self.tokens: List[Tuple[str, str, int]] = []
        self.pos = 0
        self.depth = 0
        self.variables: Dict[str, ObjectKey] = {}
        self.plain: List[str] = []
        self._tokenize()

    def _error(self, msg: str, at: Optional[int] = None) -> UnitExpressionError:
        if at is None:
            at = self.tokens[self.pos][2] if self.pos < len(self.tokens) else len(self.text)
        return UnitExpressionError("%s at character %d of %r" % (msg, at + 1, self.text))

    def _tokenize(self) -> None:
        i = 0
        text = self.text
        while i < len(text):
            m = _TOKEN_RE.match(text, i)
            if not m:
                raise self._error("unexpected character %r" % text[i], i)
            kind = m.lastgroup
            if kind != "ws":
                self.tokens.append((kind, m.group(kind), i))
            i = m.end()

    # -- helpers ---------------------------------------------------------
    def _peek(self) -> Optional[Tuple[str, str, int]]:
        return self.tokens[self.pos] if self.pos < len(self.tokens) else None

    def _accept(self, op: str) -> bool:
        tok = self._peek()
        if tok is not None and tok[0] == "op" and tok[1] == op:
            self.pos += 1
            return True
        return False

    def _expect(self, op: str) -> None:
        if not self._accept(op):
            tok = self._peek()
            found = "end of expression" if tok is None else repr(tok[1])
            raise self._error("expected %r, found %s" % (op, found))

    def _enter(self) -> None:
        self.depth += 1
        if self.depth > _MAX_DEPTH:
            raise self._error("expression nested too deeply")

    # -- grammar ---------------------------------------------------------
    def parse(self) -> Tuple[_Node, bool]:
        if not self.tokens:
            raise UnitExpressionError("empty expression")
        node = self._expr()
        if self.pos != len(self.tokens):
            raise self._error("unexpected %r" % self.tokens[self.pos][1])
        return node

    def _expr(self) -> Tuple[_Node, bool]:
        self._enter()
        left = self._term()
        while True:
            if self._accept("+"):
                left = _binary(left, self._term(), _add)
            elif self._accept("-"):
                left = _binary(left, self._term(), _sub)
            else:
                break
        self.depth -= 1
        return left

    def _term(self) -> Tuple[_Node, bool]:
        left = self._unary()
        while True:
            if self._accept("*"):
                left = _binary(left, self._unary(), _mul)
            elif self._accept("/"):
                left = _binary(left, self._unary(), _div)
            else:
                break
        return left

    def _unary(self) -> Tuple[_Node, bool]:
        self._enter()
        if self._accept("-"):
            fn, const = self._unary()
            result = _fold(lambda env: -fn(env), const)
        elif self._accept("+"):
            result = self._unary()
        else:
            result = self._power()
        self.depth -= 1
        return result

    def _power(self) -> Tuple[_Node, bool]:
        base = self._primary()
        if self._accept("^"):
            return _binary(base, self._unary(), _pow)
        return base

    def _primary(self) -> Tuple[_Node, bool]:
        tok = self._peek()
        if tok is None:
            raise self._error("expression ends too early")
        kind, text, _ = tok
        if kind == "num":
            self.pos += 1
            value = float(text)
            return (lambda env: value), True
        if kind == "op" and text == "(":
            self.pos += 1
            inner = self._expr()
            self._expect(")")
            return inner
        if kind == "name":
            self.pos += 1
            if text in FUNCTIONS:
                return self._call(text)
            if text == "pi":
                if self._accept("("):  # pi() as some write it
                    self._expect(")")
                return (lambda env: math.pi), True
            return self._variable(text)
        raise self._error("unexpected %r" % text)

    def _call(self, name: str) -> Tuple[_Node, bool]:
        fn, lo, hi = FUNCTIONS[name]
        self._expect("(")
        args = [self._expr()]
        while self._accept(","):
            args.append(self._expr())
        self._expect(")")
        if len(args) < lo or (hi is not None and len(args) > hi):
            want = str(lo) if lo == hi else ("%d or more" % lo if hi is None else "%d..%d" % (lo, hi))
            raise self._error("%s() takes %s argument(s), got %d" % (name, want, len(args)))
        fns = tuple(a[0] for a in args)
        const = all(a[1] for a in args)
        if len(fns) == 1:
            (a0,) = fns
            if fn is _rint and not const:  # _rint inline: every position command is rint(...)
                return (lambda env: float(round(a0(env)))), False
            return _fold(lambda env: fn(a0(env)), const)
        if len(fns) == 3:
            a0, a1, a2 = fns
            return _fold(lambda env: fn(a0(env), a1(env), a2(env)), const)
        return _fold(lambda env: fn(*[a(env) for a in fns]), const)

    def _variable(self, name: str) -> Tuple[_Node, bool]:
        if name in _PLAIN_VARIABLES:
            if name not in self.plain:
                self.plain.append(name)
            canonical = name
        else:
            m = _OBJ_RE.match(name)
            if not m:
                raise self._error(
                    "unknown name %r (variables: pos, vel, eff, objXXXX, objXXXXsubYY; functions: %s, pi)"
                    % (name, ", ".join(sorted(FUNCTIONS))), self.tokens[self.pos - 1][2])
            key = ObjectKey(int(m.group(1), 16), int(m.group(2), 16) if m.group(2) else 0)
            canonical = object_variable_name(key)
            self.variables[canonical] = key

        def node(env: Env) -> float:
            return env[canonical]
        _VARIABLE_NODES[node] = canonical  # lets _binary read the variable itself
        return node, False


def _fold(node: _Node, const: bool) -> Tuple[_Node, bool]:
    """Pre-compute constant sub-expressions once, at compile time."""
    if const:
        try:
            value = float(node({}))
        except (ArithmeticError, ValueError, TypeError):
            value = math.nan
        return (lambda env: value), True
    return node, False


def _add(a: float, b: float) -> float:
    return a + b


def _sub(a: float, b: float) -> float:
    return a - b


def _mul(a: float, b: float) -> float:
    return a * b


def _div(a: float, b: float) -> float:
    if b == 0.0:
        # muParser's IEEE behaviour: x/0 is +-inf (NaN for 0/0), never an exception.
        return math.nan if a == 0.0 or math.isnan(a) else math.copysign(math.inf, a) * math.copysign(1.0, b)
    return a / b


def _pow(a: float, b: float) -> float:
    return math.pow(a, b)


# variable node -> its name; weak, so nodes of expressions dropped go too
_VARIABLE_NODES: "weakref.WeakKeyDictionary[_Node, str]" = weakref.WeakKeyDictionary()


def _binary(left: Tuple[_Node, bool], right: Tuple[_Node, bool],
            op: Callable[[float, float], float]) -> Tuple[_Node, bool]:
    lf, lc = left
    rf, rc = right
    if lc and rc:
        return _fold(lambda env: op(lf(env), rf(env)), True)
    fast = _inline(lf, rf, rc, op)
    if fast is not None:
        return fast, False
    return (lambda env: op(lf(env), rf(env))), False


def _inline(lf: _Node, rf: _Node, rc: bool, op: Callable[[float, float], float]) -> Optional[_Node]:
    """The common shapes of unit conversions (a variable or a sub-expression
    with a constant: ``obj6064*2*pi/3200``) as one closure with the operator
    inline, instead of a call for each operand and one for the operator:
    conversions run for every axis every cycle. The arithmetic is the same
    (same operands, same order); _div keeps its own function unless the
    divisor is a constant other than 0."""
    if not rc or not (op is _add or op is _sub or op is _mul or (op is _div and rf({}) != 0.0)):
        return None
    c = rf({})  # a constant node reads nothing
    name = _VARIABLE_NODES.get(lf)
    if name is not None:
        if op is _mul or op is _div:
            return _scaling(name, ((op, c),))
        if op is _add:
            return lambda env: env[name] + c
        return lambda env: env[name] - c
    chain = _SCALINGS.get(lf)
    if chain is not None and (op is _mul or op is _div) and len(chain[1]) < 3:
        return _scaling(chain[0], chain[1] + ((op, c),))
    if op is _mul:
        return lambda env: lf(env) * c
    if op is _div:
        return lambda env: lf(env) / c
    if op is _add:
        return lambda env: lf(env) + c
    return lambda env: lf(env) - c


# scaling node -> (variable, ((_mul or _div, constant), ...)): lets _inline
# extend a chain; weak, as _VARIABLE_NODES
_SCALINGS: "weakref.WeakKeyDictionary[_Node, Tuple[str, Tuple[Tuple[Callable[[float, float], float], float], ...]]]" = \
    weakref.WeakKeyDictionary()


def _scaling(name: str, ops: Tuple[Tuple[Callable[[float, float], float], float], ...]) -> _Node:
    """A variable multiplied and divided by up to three constants (divisors
    not 0), left to right, as one closure: ``obj6064*2*pi/3200`` is one
    call instead of three. Python evaluates ``v * a / b`` as ``(v * a) / b``:
    the same operations in the same order as the nested closures."""
    m = tuple(op is _mul for op, _ in ops)
    cs = [c for _, c in ops]
    node: _Node
    if len(ops) == 1:
        (c1,) = cs
        node = (lambda env: env[name] * c1) if m[0] else (lambda env: env[name] / c1)
    elif len(ops) == 2:
        c1, c2 = cs
        node = {(True, True): lambda env: env[name] * c1 * c2,
                (True, False): lambda env: env[name] * c1 / c2,
                (False, True): lambda env: env[name] / c1 * c2,
                (False, False): lambda env: env[name] / c1 / c2}[m]
    else:
        c1, c2, c3 = cs
        node = {(True, True, True): lambda env: env[name] * c1 * c2 * c3,
                (True, True, False): lambda env: env[name] * c1 * c2 / c3,
                (True, False, True): lambda env: env[name] * c1 / c2 * c3,
                (True, False, False): lambda env: env[name] * c1 / c2 / c3,
                (False, True, True): lambda env: env[name] / c1 * c2 * c3,
                (False, True, False): lambda env: env[name] / c1 * c2 / c3,
                (False, False, True): lambda env: env[name] / c1 / c2 * c3,
                (False, False, False): lambda env: env[name] / c1 / c2 / c3}[m]
    _SCALINGS[node] = (name, ops)
    return node


def compile_expression(text: str) -> Expression:
    """Parse text once; raise UnitExpressionError saying what is wrong."""
    if not isinstance(text, str):
        if isinstance(text, (int, float)) and not isinstance(text, bool):
            text = repr(text)  # YAML gives eff_from_device: 0 as a number
        else:
            raise UnitExpressionError("expression must be a string, got %s" % type(text).__name__)
    if len(text) > MAX_LENGTH:
        raise UnitExpressionError("expression longer than %d characters" % MAX_LENGTH)
    parser = _Parser(text)
    fn, const = parser.parse()
    names = tuple(parser.plain) + tuple(parser.variables)
    expr = Expression(text, fn, names, tuple(parser.variables.values()), const)
    if not _finite_somewhere(expr):
        raise UnitExpressionError("%r gives NaN or infinity for every input: it can never convert a value" % text)
    return expr


# Inputs an expression is tried with at load: a conversion that is finite
# for none of them would refuse every command or publish only NaN.
_PROBES = (0.0, 1.0, -1.0, 0.5, -0.5, 2.0, 3.0, 1000.0, -1000.0, 1e6, -1e6, 0.001, 90.0)


def _finite_somewhere(expr: Expression) -> bool:
    names = expr.variables
    if not names:
        return math.isfinite(expr.evaluate({}))
    # every variable at every probe value would be len(_PROBES)**n points:
    # try the diagonal (all at one value) and each variable on its own
    for value in _PROBES:
        if math.isfinite(expr.evaluate({n: value for n in names})):
            return True
    for name in names:
        for value in _PROBES:
            for rest in (1.0, 0.0):
                env = {n: rest for n in names}
                env[name] = value
                if math.isfinite(expr.evaluate(env)):
                    return True
    return False
