"""The scene format's expressions, read by the harness itself (not by mbfg).

The reference generators evaluate a load's value — `kp*(w*t - theta) - kd*rate(theta)`,
`F0*(1 - (3/(5 - x(S)))^1.4)` — with this translator, so that a load mbfg turns into
generalized forces wrongly cannot pass its check by being read the same way twice. It
implements the grammar of docs/scene-format.md, section 2, as a recursive descent into
Python closures over IEEE float arithmetic (numpy's, so that 1/0 is inf and sqrt(-1) NaN
as in the Rust f64 mbfg computes with); nothing is handed to `eval`.

    e = parse("kp*(w*t - theta) - kd*rate(theta)")
    e.names                         # {'kp', 'w', 't', 'theta', 'rate(theta)'}
    e({"kp": 2, "w": 1, "t": 0.5, "theta": 0.1, "rate(theta)": 0.0})

A state quantity `rate(c)`, `x(P)`, `y(P)`, `vx(P)`, `vy(P)`, `angle(B)`, `omega(B)` is a
name of its own, looked up whole. `harness/tests/test_expressions.py` checks the
translator against mbfg's evaluator on the fuzz corpus and on every expression of the
repository's scenes.
"""
from __future__ import annotations

import math
from typing import Callable, Mapping

import numpy as np

# The size limits of the format: longer, larger or deeper texts are refused.
MAX_LEN = 100_000
MAX_NODES = 10_000
MAX_DEPTH = 100

STATE_ACCESSORS = ("rate", "x", "y", "vx", "vy", "angle", "omega")


class ExpressionError(ValueError):
    """A malformed expression, an undefined name, or a non-finite value."""


def _sign(a):
    return np.float64(1.0) if a > 0 else np.float64(-1.0) if a < 0 else a


def _fmin(a, b):
    # IEEE minNum: a NaN argument loses (as Rust's f64::min).
    return np.fmin(a, b)


FUNCTIONS: dict[str, tuple[int, Callable]] = {
    "sqrt": (1, np.sqrt), "sin": (1, np.sin), "cos": (1, np.cos), "tan": (1, np.tan),
    "asin": (1, np.arcsin), "acos": (1, np.arccos), "atan": (1, np.arctan),
    "atan2": (2, np.arctan2), "exp": (1, np.exp), "log": (1, np.log), "ln": (1, np.log),
    "abs": (1, np.abs), "min": (2, _fmin), "max": (2, np.fmax), "pow": (2, np.power),
    "sinh": (1, np.sinh), "cosh": (1, np.cosh), "tanh": (1, np.tanh), "sign": (1, _sign),
}

_OPS = {"+": np.add, "-": np.subtract, "*": np.multiply, "/": np.divide}

Env = Mapping[str, float]


class Expression:
    """A parsed expression: call it with the values of its names."""

    def __init__(self, text: str, fn: Callable[[Env], float], names: set[str]):
        self.text = text
        self._fn = fn
        self.names = names

    @property
    def state_names(self) -> set[str]:
        """The names that are not parameters or the time (anything with a '(')."""
        return {n for n in self.names if "(" in n}

    def raw(self, env: Env) -> float:
        """The value, finite or not."""
        with np.errstate(all="ignore"):
            return float(self._fn(env))

    def __call__(self, env: Env) -> float:
        v = self.raw(env)
        if not math.isfinite(v):
            raise ExpressionError(f"{self.text!r} evaluates to a non-finite number ({v})")
        return v

    def __repr__(self) -> str:
        return f"Expression({self.text!r})"


def parse(text: str) -> Expression:
    if not isinstance(text, str):
        raise ExpressionError(f"an expression must be text, not {type(text).__name__}")
    if len(text.encode()) > MAX_LEN:
        raise ExpressionError(f"expression too long: {len(text.encode())} bytes")
    p = _Parser(text)
    fn = p.expr()
    p.skip_ws()
    if p.pos < len(text):
        raise p.error(f"unexpected {text[p.pos]!r}")
    return Expression(text, fn, p.names)


def value(x, env: Env) -> float:
    """A number of the scene: a YAML number as it is, a text as an expression."""
    if isinstance(x, bool):
        raise ExpressionError(f"expected a number, not the boolean {x}")
    if isinstance(x, (int, float)):
        v = float(x)
        if not math.isfinite(v):
            raise ExpressionError(f"{x} is not finite")
        return v
    return parse(str(x))(env)


def _var(name: str) -> Callable[[Env], float]:
    def look(env: Env) -> float:
        try:
            return np.float64(env[name])
        except KeyError:
            if name == "pi":
                return np.float64(math.pi)
            raise ExpressionError(f"undefined name {name!r}") from None
    return look


class _Parser:
    def __init__(self, text: str):
        self.s = text
        self.pos = 0
        self.depth = 0
        self.nodes = 0
        self.names: set[str] = set()

    def error(self, msg: str) -> ExpressionError:
        return ExpressionError(f"malformed expression {self.s[:60]!r}: {msg} at character "
                               f"{self.pos + 1}")

    def count(self):
        self.nodes += 1
        if self.nodes > MAX_NODES:
            raise ExpressionError(f"expression too large: more than {MAX_NODES} nodes")

    def skip_ws(self):
        while self.pos < len(self.s) and self.s[self.pos].isspace():
            self.pos += 1

    def peek(self) -> str | None:
        self.skip_ws()
        return self.s[self.pos] if self.pos < len(self.s) else None

    def _level(self, ops: str, operand):
        first = operand()
        rest = []
        while (c := self.peek()) is not None and c in ops:
            self.pos += 1
            rest.append((_OPS[c], operand()))
            self.count()
        if not rest:
            return first

        def chain(env, first=first, rest=tuple(rest)):
            acc = first(env)
            for op, f in rest:
                acc = op(acc, f(env))
            return acc
        return chain

    def expr(self):
        return self._level("+-", self.term)

    def term(self):
        return self._level("*/", self.unary)

    def unary(self):
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise ExpressionError(f"expression nested too deeply: more than {MAX_DEPTH} levels")
        c = self.peek()
        if c == "-":
            self.pos += 1
            a = self.unary()
            self.count()
            out = lambda env, a=a: np.negative(a(env))  # noqa: E731
        elif c == "+":
            self.pos += 1
            out = self.unary()
        else:
            out = self.power()
        self.depth -= 1
        return out

    def power(self):
        base = self.atom()
        if self.peek() == "^":
            self.pos += 1
            exp = self.unary()          # right-associative, and 2^-1 is allowed
            self.count()
            return lambda env, b=base, e=exp: np.power(b(env), e(env))
        return base

    def _word(self) -> str:
        start = self.pos
        while self.pos < len(self.s) and (self.s[self.pos].isalnum() or self.s[self.pos] == "_"):
            self.pos += 1
        return self.s[start:self.pos]

    def atom(self):
        c = self.peek()
        if c is None:
            raise self.error("the expression ends too early")
        if c == "(":
            self.pos += 1
            inner = self.expr()
            if self.peek() != ")":
                raise self.error("missing ')'")
            self.pos += 1
            return inner
        if c.isdigit() and c.isascii() or c == ".":
            return self.number()
        if c.isalpha() or c == "_":
            name = self._word()
            if self.peek() == "(":
                if name in STATE_ACCESSORS:
                    return self.state_quantity(name)
                return self.call(name)
            self.names.add(name)
            self.count()
            return _var(name)
        raise self.error(f"unexpected {c!r}")

    def state_quantity(self, accessor: str):
        self.pos += 1
        self.skip_ws()
        arg = self._word()
        if not arg:
            raise self.error(f"{accessor}(…) takes a name")
        if self.peek() != ")":
            raise self.error(f"missing ')' after {accessor}({arg}")
        self.pos += 1
        name = f"{accessor}({arg})"
        self.names.add(name)
        self.count()
        return _var(name)

    def call(self, name: str):
        if name not in FUNCTIONS:
            raise self.error(f"unknown function {name!r}")
        arity, f = FUNCTIONS[name]
        self.pos += 1
        args = [self.expr()]
        while self.peek() == ",":
            self.pos += 1
            if len(args) == arity:
                raise self.error(f"{name} takes {arity} argument(s)")
            args.append(self.expr())
        if self.peek() != ")":
            raise self.error(f"missing ')' after the arguments of {name}")
        self.pos += 1
        if len(args) != arity:
            raise self.error(f"{name} takes {arity} argument(s), got {len(args)}")
        self.count()
        if arity == 1:
            (a,) = args
            return lambda env, f=f, a=a: f(a(env))
        a, b = args
        return lambda env, f=f, a=a, b=b: f(a(env), b(env))

    def number(self):
        start = self.pos
        s = self.s
        while self.pos < len(s) and (s[self.pos] in "0123456789."):
            self.pos += 1
        if self.pos < len(s) and s[self.pos] in "eE":
            k = self.pos + 1
            if k < len(s) and s[k] in "+-":
                k += 1
            if k < len(s) and s[k] in "0123456789":
                self.pos = k
                while self.pos < len(s) and s[self.pos] in "0123456789":
                    self.pos += 1
        text = s[start:self.pos]
        try:
            v = np.float64(float(text))
        except ValueError:
            self.pos = start
            raise self.error(f"malformed number {text!r}") from None
        self.count()
        return lambda env, v=v: v
