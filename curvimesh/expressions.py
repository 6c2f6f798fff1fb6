"""Safe parsing of user expressions into sympy (SPEC §2, "Expressions").

Metric files hold expressions as text, possibly written by someone untrusted.
They are parsed with :func:`ast.parse` and walked against a whitelist; nothing
is ever handed to ``eval``, ``exec`` or ``sympy.sympify`` (which evaluates).

Grammar (Python syntax)::

    expr := number | NAME | pi | (expr) | +expr | -expr
          | expr (+ | - | * | / | **) expr
          | FUNCTION(expr, ...) | diff(expr, x) | diff(expr, y)

``number`` is an int or float literal (scientific notation included), ``NAME``
a key of the ``names`` mapping given by the caller (coordinates, parameters,
earlier definitions) and ``FUNCTION`` one of :data:`FUNCTIONS`. Everything else
(attribute access, subscripts, lambdas, strings, comprehensions, comparisons,
boolean operators, keyword arguments, ``//``, ``%``, bit operators, complex
literals, ...) is rejected with a one-line :class:`ExpressionError` that quotes
the offending piece of text, before anything is evaluated.

Safety bounds, so that no input can hang the parser or exhaust memory:

- text of at most :data:`MAX_LENGTH` characters; an AST of at most
  :data:`MAX_NODES` nodes nested at most :data:`MAX_DEPTH` expressions deep;
- every constant sub-expression is also evaluated in double precision, and one
  that overflows or has no real value (``1/0``, ``log(0)``, ``sqrt(-1)``,
  ``9**9**9**9``, ``1e400``) is rejected at once, so sympy never sees towers of
  huge numbers;
- exact rational arithmetic is kept small: integer literals above
  :data:`MAX_INTEGER` become floats, a power is computed exactly only when its
  exponent is a rational ``p/q`` with ``|p|, q <= MAX_EXPONENT`` and the
  result has at most about :data:`MAX_EXACT_BITS` bits (otherwise a constant
  power becomes a Float and the exponent of a symbolic base becomes a Float:
  ``(x + 1)**100000`` is kept as ``(x + 1)**100000.0``, never expanded);
- ``min``/``max`` of symbolic arguments are built as a balanced tree of binary,
  unevaluated ``Min``/``Max`` (sympy's n-ary simplification is quadratic);
- ``diff`` may differentiate at most :data:`MAX_DIFF_WORK` sympy nodes in one
  expression (the cost of a derivative grows quickly with its operand);
- building an expression may take at most :data:`TIME_LIMIT` seconds of CPU (sympy's
  automatic simplification can take minutes on crafted input);
- the result has at most :data:`MAX_SIZE` sympy nodes, nested at most
  :data:`MAX_TREE_DEPTH` deep (sympy's printers and lambdify recurse), once the
  definitions in ``names`` are substituted; no node built on the way holds
  ``zoo``, ``oo``, ``nan``, ``I`` or a Float beyond the double range (a constant
  that underflows becomes its double value).
"""

from __future__ import annotations

import ast
import ctypes
import difflib
import math
import operator
import sys
import threading
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import NamedTuple

import sympy
from sympy.printing.pycode import PythonCodePrinter

from curvimesh.errors import ExpressionError

__all__ = [
    "CONSTANTS",
    "FUNCTIONS",
    "MAX_DEPTH",
    "MAX_DIFF_WORK",
    "MAX_EXACT_BITS",
    "MAX_EXPONENT",
    "MAX_INTEGER",
    "MAX_LENGTH",
    "MAX_NODES",
    "MAX_SIZE",
    "MAX_TREE_DEPTH",
    "RESERVED",
    "TIME_LIMIT",
    "Builtin",
    "ScalarPrinter",
    "expression_symbols",
    "parse_expression",
    "scalar_function",
    "smooth_minmax",
]

MAX_LENGTH = 2000
"""Longest accepted expression text, in characters."""
MAX_DEPTH = 50
"""Deepest accepted nesting of AST expression nodes (``x + 1`` has depth 2)."""
MAX_NODES = 2000
"""Most AST nodes (of any kind) in one expression."""
MAX_SIZE = 20_000
"""Most nodes of the resulting sympy tree, definitions substituted."""
MAX_TREE_DEPTH = 100
"""Deepest nesting of the resulting sympy tree, definitions substituted."""
MAX_DIFF_WORK = 1000
"""Most sympy nodes differentiated, summed over the ``diff`` calls of one expression."""
MAX_INTEGER = 10**6
"""Larger integer literals become sympy Floats."""
MAX_EXPONENT = 64
"""Largest numerator or denominator of an exponent that is kept exact."""
MAX_EXACT_BITS = 2048
"""Largest exact rational (in bits of numerator or denominator) a power may create."""
TIME_LIMIT = 1.0
"""Default bound on the seconds of CPU time spent building one expression (wall-clock
seconds where the platform cannot read a thread's CPU clock; see :class:`_TimeLimit`)."""

_QUOTE_LENGTH = 60


# -- the whitelist -------------------------------------------------------------


def _real(function: Callable[..., float]) -> Callable[..., float]:
    """Wrap a float function: overflow gives inf, a domain error nan, never an exception."""

    def wrapped(*args: float) -> float:
        try:
            return float(function(*args))
        except OverflowError:
            return math.inf
        except (ValueError, ZeroDivisionError):
            return math.nan

    return wrapped


def _log(a: float) -> float:
    return -math.inf if a == 0 else math.log(a)


def _atan2(y: float, x: float) -> float:
    # sympy.atan2(0, 0) is nan; agree with it rather than with math.atan2.
    return math.nan if x == 0 and y == 0 else math.atan2(y, x)


def _divide(a: float, b: float) -> float:
    if b == 0:
        return math.nan if a == 0 else math.inf
    return a / b


def _power(a: float, b: float) -> float:
    if a == 0 and b < 0:
        return math.inf
    return math.pow(a, b)


_real_power = _real(_power)
_real_float = _real(float)


def _extremum(cls: type[sympy.Min] | type[sympy.Max]) -> Callable[..., sympy.Expr]:
    """A balanced tree of binary, unevaluated Min/Max.

    Evaluated n-ary Min/Max compare their arguments pairwise (quadratic, and each
    comparison may query assumptions); binary ones cost nothing, differentiate
    to two Heaviside terms, and a balanced tree keeps the nesting shallow.
    """

    def build(*args: sympy.Expr) -> sympy.Expr:
        level = list(args)
        while len(level) > 1:
            odd = level[-1:] if len(level) % 2 else []
            pairs = range(0, len(level) - 1, 2)
            level = [cls(level[i], level[i + 1], evaluate=False) for i in pairs] + odd
        return level[0]

    return build


@dataclass(frozen=True)
class Builtin:
    """A whitelisted function: how many arguments it takes, and its two forms.

    ``symbolic`` builds the sympy expression; ``numeric`` computes its value in
    double precision when every argument is constant, returning inf on overflow
    and nan where there is no real value (it never raises). Both are None for
    ``diff``, which the parser handles itself.
    """

    name: str
    min_args: int
    max_args: int | None
    symbolic: Callable[..., sympy.Expr] | None
    numeric: Callable[..., float] | None

    @property
    def arity(self) -> str:
        """The number of arguments in words, for error messages."""
        if self.max_args is None:
            return f"at least {self.min_args} arguments"
        return f"{self.min_args} argument" + ("s" if self.min_args != 1 else "")


def _builtins() -> dict[str, Builtin]:
    unary = {
        "sqrt": (sympy.sqrt, math.sqrt),
        "exp": (sympy.exp, math.exp),
        "log": (sympy.log, _log),
        "sin": (sympy.sin, math.sin),
        "cos": (sympy.cos, math.cos),
        "tan": (sympy.tan, math.tan),
        "asin": (sympy.asin, math.asin),
        "acos": (sympy.acos, math.acos),
        "atan": (sympy.atan, math.atan),
    }
    table = {name: Builtin(name, 1, 1, sym, _real(num)) for name, (sym, num) in unary.items()}
    table["atan2"] = Builtin("atan2", 2, 2, sympy.atan2, _real(_atan2))
    for name, sym, num in [
        ("sinh", sympy.sinh, math.sinh),
        ("cosh", sympy.cosh, math.cosh),
        ("tanh", sympy.tanh, math.tanh),
        ("abs", sympy.Abs, abs),
    ]:
        table[name] = Builtin(name, 1, 1, sym, _real(num))
    table["min"] = Builtin("min", 2, None, _extremum(sympy.Min), _real(min))
    table["max"] = Builtin("max", 2, None, _extremum(sympy.Max), _real(max))
    table["diff"] = Builtin("diff", 2, 2, None, None)
    return table


FUNCTIONS: Mapping[str, Builtin] = MappingProxyType(_builtins())
"""The functions an expression may call, by name."""

CONSTANTS: Mapping[str, sympy.Expr] = MappingProxyType({"pi": sympy.pi})
"""The named constants an expression may use (a key of ``names`` takes precedence)."""

RESERVED: frozenset[str] = frozenset(FUNCTIONS) | frozenset(CONSTANTS)
"""Names a metric file should not give to a parameter or definition."""

_BINARY: dict[type[ast.operator], tuple[Callable[..., sympy.Expr], Callable[..., float]]] = {
    ast.Add: (operator.add, operator.add),
    ast.Sub: (operator.sub, operator.sub),
    ast.Mult: (operator.mul, operator.mul),
    ast.Div: (operator.truediv, _divide),
}

_OPERATOR_SYMBOLS: dict[type[ast.AST], str] = {
    ast.FloorDiv: "//",
    ast.Mod: "%",
    ast.MatMult: "@",
    ast.LShift: "<<",
    ast.RShift: ">>",
    ast.BitOr: "|",
    ast.BitXor: "^",
    ast.BitAnd: "&",
    ast.Not: "not",
    ast.Invert: "~",
}

_FORBIDDEN: dict[type[ast.AST], str] = {
    ast.Attribute: "attribute access is not allowed",
    ast.Subscript: "subscripts are not allowed",
    ast.Slice: "slices are not allowed",
    ast.Lambda: "lambda expressions are not allowed",
    ast.ListComp: "comprehensions are not allowed",
    ast.SetComp: "comprehensions are not allowed",
    ast.DictComp: "comprehensions are not allowed",
    ast.GeneratorExp: "comprehensions are not allowed",
    ast.List: "lists are not allowed",
    ast.Tuple: "tuples are not allowed",
    ast.Set: "sets are not allowed",
    ast.Dict: "dicts are not allowed",
    ast.JoinedStr: "f-strings are not allowed",
    ast.FormattedValue: "f-strings are not allowed",
    ast.Compare: "comparisons are not allowed",
    ast.BoolOp: "boolean operators (and, or) are not allowed",
    ast.IfExp: "conditional expressions are not allowed",
    ast.NamedExpr: "assignment expressions (:=) are not allowed",
    ast.Starred: "starred arguments are not allowed",
    ast.Await: "await is not allowed",
    ast.Yield: "yield is not allowed",
    ast.YieldFrom: "yield is not allowed",
}


# -- public API ----------------------------------------------------------------


def parse_expression(
    text: str | int | float,
    names: Mapping[str, sympy.Expr],
    *,
    time_limit: float | None = TIME_LIMIT,
) -> sympy.Expr:
    """Parse an expression of a metric file into a sympy expression.

    ``text`` is the expression as written (a number read from YAML is accepted
    as is; a bool is not). ``names`` maps each identifier the expression may
    use to its sympy value: the coordinates ``x``, ``y`` as real Symbols,
    parameters as numbers, earlier definitions as expressions; its keys take
    precedence over :data:`CONSTANTS`. ``diff(E, x)`` differentiates with
    respect to ``names["x"]`` (a fresh real Symbol ``x`` if that is not a Symbol).
    ``time_limit`` bounds the seconds spent building the expression (None: no
    bound; see :data:`TIME_LIMIT`).

    Returns a sympy expression in the symbols that come through ``names``.
    Raises :class:`ExpressionError` with a one-line message (without file or
    key, which the caller adds) for anything outside the grammar or the safety
    bounds of this module, and for a result that is not finite or not real.

    >>> import sympy
    >>> x, y = sympy.symbols("x y", real=True)
    >>> parse_expression("sqrt(x**2 + y**2) + 2*pi", {"x": x, "y": y})
    sqrt(x**2 + y**2) + 2*pi
    >>> parse_expression("diff(x**3 * y, x)", {"x": x, "y": y})
    3*x**2*y
    >>> parse_expression("x.__class__", {"x": x})
    Traceback (most recent call last):
    ...
    curvimesh.errors.ExpressionError: attribute access is not allowed: 'x.__class__'
    """
    if isinstance(text, bool) or not isinstance(text, (str, int, float)):
        got = repr(text) if text is None or isinstance(text, bool) else type(text).__name__
        raise ExpressionError(f"expected an expression (text or a number), got {got}")
    for key, value in names.items():
        if isinstance(value, bool) or not isinstance(value, (sympy.Expr, int, float)):
            raise TypeError(f"names[{key!r}] is a {type(value).__name__}, not a sympy Expr")
    if isinstance(text, int) and text.bit_length() > 4 * MAX_LENGTH:
        raise ExpressionError(f"integer with {text.bit_length()} bits is too long")
    source = text.strip() if isinstance(text, str) else repr(text)
    parser = _Parser(source, names)
    tree = None
    if isinstance(text, str):
        tree = _parse(source)
        _check_shape(tree)
        parser.check(tree.body)
    try:
        with _TimeLimit(time_limit):
            if tree is None:
                result = parser.number(text, None)  # type: ignore[arg-type]  # int or float
            else:
                result = parser.build(tree.body)
            parser.check_result(result.expr)
    except ExpressionError:
        raise
    except _OutOfTime:
        raise ExpressionError(
            f"expression takes too long to build (more than {time_limit} s): {_quote(source)}"
        ) from None
    except RecursionError:
        raise ExpressionError(f"expression is nested too deeply: {_quote(source)}") from None
    except Exception as exc:  # sympy raises assorted types on odd input; report one line
        reason = _one_line(f"{type(exc).__name__}: {exc}")
        raise ExpressionError(f"cannot evaluate {_quote(source)}: {reason}") from exc
    return result.expr


def split_list_hint(items: object) -> str:
    """A hint for a YAML flow list whose items are pieces of expressions: YAML splits
    ``[min(a, b), c]`` at every comma, into ``'min(a'``, ``'b)'`` and ``c``. The hint
    (with a leading ``"; "``) when an item's parentheses do not balance, else ``""``."""
    if not isinstance(items, list):
        return ""
    for item in items:
        if isinstance(item, str) and item.count("(") != item.count(")"):
            return (
                "; YAML splits a [...] list at every comma: quote an expression with a comma,"
                " as 'min(a, b)'"
            )
    return ""


def expression_symbols(expr: sympy.Expr) -> set[str]:
    """The names of the free symbols of ``expr``.

    >>> x, y = sympy.symbols("x y", real=True)
    >>> sorted(expression_symbols(parse_expression("x*exp(y) + 1", {"x": x, "y": y})))
    ['x', 'y']
    """
    return {symbol.name for symbol in expr.free_symbols}


# -- text and tree -------------------------------------------------------------


def _one_line(message: str) -> str:
    return " ".join(message.split())


def _quote(segment: str) -> str:
    """``segment`` on one line, truncated, in quotes."""
    segment = _one_line(segment)
    if len(segment) > _QUOTE_LENGTH:
        segment = segment[: _QUOTE_LENGTH - 3] + "..."
    return repr(segment)


def _parse(text: str) -> ast.Expression:
    if len(text) > MAX_LENGTH:
        raise ExpressionError(
            f"expression is too long ({len(text)} characters, at most {MAX_LENGTH})"
        )
    if not text:
        raise ExpressionError("expression is empty")
    try:
        with warnings.catch_warnings():
            # Invalid escapes in strings and the like warn; the text is rejected anyway.
            warnings.simplefilter("ignore")
            return ast.parse(text, mode="eval")
    except SyntaxError as exc:
        where = ""
        if exc.offset is not None:
            # Python reports an error at the end of the text at column 0.
            where = f" at column {exc.offset}" if exc.offset > 0 else " at the end"
            if exc.lineno is not None and exc.lineno > 1 and exc.offset > 0:
                where = f" at line {exc.lineno}, column {exc.offset}"
        reason = _one_line(exc.msg or "invalid syntax")
        raise ExpressionError(f"syntax error{where}: {reason} in {_quote(text)}") from None
    except ValueError as exc:  # a null character, on some Python versions
        raise ExpressionError(f"syntax error: {_one_line(str(exc))}") from None
    except (RecursionError, MemoryError):
        raise ExpressionError(f"expression is nested too deeply: {_quote(text)}") from None


def _check_shape(tree: ast.Expression) -> None:
    """Bound the number of AST nodes and the nesting depth of expressions."""
    count = 0
    stack: list[tuple[ast.AST, int]] = [(tree.body, 1)]
    while stack:
        node, depth = stack.pop()
        count += 1
        if count > MAX_NODES:
            raise ExpressionError(f"expression is too large (more than {MAX_NODES} syntax nodes)")
        if depth > MAX_DEPTH:
            raise ExpressionError(f"expression is nested too deeply (more than {MAX_DEPTH} levels)")
        for child in ast.iter_child_nodes(node):
            stack.append((child, depth + isinstance(child, ast.expr)))


# -- the time limit --------------------------------------------------------------


class _OutOfTime(BaseException):
    """Raised inside sympy when the time limit is reached.

    A BaseException, so that sympy's own ``except Exception`` clauses let it through.
    """


class _TimeLimit:
    """Interrupt the code run inside after ``seconds`` of its CPU time with :class:`_OutOfTime`.

    Some simplifications sympy makes while an expression is built (assumption
    queries that end in polynomial gcds, for instance) take minutes on crafted
    input, and no bound on the text prevents it. A timer thread raises
    :class:`_OutOfTime` asynchronously in this thread once the time is up
    (CPython's ``PyThreadState_SetAsyncExc``); this costs nothing until then,
    unlike a profile hook. Python ignores an exception raised inside a finalizer
    or a garbage collector callback (it prints it as unraisable), so the timer
    sends it again every :data:`REFIRE` seconds until the work ends (once lost
    so under a test suite's collector callback, the limit let 3.2 s of sympy
    run). An exception still pending when the work is done is cleared, under a
    lock, before leaving, so none escapes to the caller.

    The shots stop, whatever happens to the block, once the frame that opened it
    is no longer on the thread's stack, or after :data:`MAX_SHOTS`: a shot that
    lands before the block's exit has marked it done can carry the exception
    past that exit, and a timer that kept shooting would then interrupt whatever
    the thread runs next, for ever.

    The time counted is the CPU time of this thread (its POSIX CPU clock), so
    that a loaded machine does not trip the limit: the first expression of a
    process, 0.09 s of CPU in sympy's cold caches, took more than 1 s of wall
    clock beside three busy processes on two cores, and a valid metric file was
    refused. Where the clock cannot be read the wall clock counts; either way the
    work is interrupted after :data:`WALL_FACTOR` × ``seconds`` of wall clock.
    """

    def __init__(self, seconds: float | None) -> None:
        self.seconds = seconds
        self.lock = threading.Lock()
        self.ended = threading.Event()
        self.done = self.fired = False
        self.timer: threading.Timer | None = None

    def __enter__(self) -> None:
        if self.seconds is None:
            return
        self.ident = threading.get_ident()
        self.thread_id = ctypes.c_ulong(self.ident)
        self.opener = sys._getframe(1)  # the frame running the ``with`` statement
        self.cpu = _thread_cpu_clock()
        self.started = time.monotonic()
        self.spent_before = self.cpu() if self.cpu is not None else 0.0
        self.timer = threading.Timer(self.seconds, self._fire)
        self.timer.daemon = True
        self.timer.start()  # (a short limit can be up while start() waits for the thread)

    def __exit__(self, *exc: object) -> None:
        if self.timer is None:
            return
        while True:  # a shot may land here too, before ``done`` is set: again
            try:
                with self.lock:
                    self.done = True
                    if self.fired:  # raised already, or pending: clear it (NULL clears)
                        _set_async_exc(self.thread_id, None)
                break
            except _OutOfTime:
                continue
        self.ended.set()
        self.timer.cancel()
        self.opener = None

    def _fire(self) -> None:
        seconds, cpu = self.seconds, self.cpu
        assert seconds is not None
        while cpu is not None:  # until the thread has spent ``seconds`` of CPU time
            try:
                left = seconds - (cpu() - self.spent_before)
            except OSError:  # the thread has ended
                return
            if left <= 0 or time.monotonic() - self.started >= WALL_FACTOR * seconds:
                break
            if self.ended.wait(left):
                return
        for _ in range(MAX_SHOTS):
            with self.lock:
                if self.done or not self._open():
                    return
                self.fired = True
                _set_async_exc(self.thread_id, ctypes.py_object(_OutOfTime))
            if self.ended.wait(REFIRE):
                return

    def _open(self) -> bool:
        """Whether the frame that opened the block is still on its thread's stack."""
        frame = sys._current_frames().get(self.ident)
        while frame is not None:
            if frame is self.opener:
                return True
            frame = frame.f_back
        return False


#: Seconds between the time limit's shots once it is up (see :class:`_TimeLimit`).
REFIRE = 0.05

#: Shots after which :class:`_TimeLimit` gives up on a block that never ends (5 s of
#: them at :data:`REFIRE`).
MAX_SHOTS = 100

#: Wall-clock seconds, in multiples of its CPU limit, after which :class:`_TimeLimit`
#: interrupts the work however little CPU time it had.
WALL_FACTOR = 30.0


def _thread_cpu_clock() -> Callable[[], float] | None:
    """The CPU seconds of the calling thread as a function another thread can call, or
    None where the platform has no per-thread CPU clock (``time.pthread_getcpuclockid``)."""
    try:
        clock_id = time.pthread_getcpuclockid(threading.get_ident())
        time.clock_gettime(clock_id)
    except (AttributeError, OSError):
        return None
    return lambda: time.clock_gettime(clock_id)


# (thread id as c_ulong, exception class as py_object, or None: NULL, which clears)
_set_async_exc = ctypes.pythonapi.PyThreadState_SetAsyncExc


# -- sympy trees -----------------------------------------------------------------


class _Value(NamedTuple):
    """A built sub-expression and, if it is constant, its value in double precision."""

    expr: sympy.Expr
    value: float | None


class _Facts(NamedTuple):
    """What :meth:`_Parser.facts` knows of a sympy tree."""

    size: int  # nodes of the tree (shared sub-trees counted each time), capped
    depth: int  # nesting depth of the tree
    symbolic: bool  # holds a Symbol
    bits: int  # largest bit length of the numerator or denominator of a Rational in it
    bad: str | None  # why the tree is not finite and real, if it is not


_UNDERFLOW = "holds a number too small for double precision"


def _atom_facts(atom: sympy.Basic) -> _Facts:
    if isinstance(atom, sympy.Symbol):
        return _Facts(1, 1, True, 0, None)
    if atom in (sympy.zoo, sympy.oo, -sympy.oo, sympy.nan):
        return _Facts(1, 1, False, 0, "is not finite")
    if atom is sympy.I:
        return _Facts(1, 1, False, 0, "is not real")
    bits = _rational_bits(atom) if atom.is_Rational else 0
    if atom.is_Number:
        value = float(atom)
        if not math.isfinite(value):
            return _Facts(1, 1, False, bits, "is not finite")
        # A Float beyond the double range, say 1e-300477121 from (1e-300*y)**1e6, is
        # cheap for mpmath but makes sympy build enormous rationals (it hangs).
        if atom.is_Float and value == 0 and not atom.is_zero:
            return _Facts(1, 1, False, bits, _UNDERFLOW)
    return _Facts(1, 1, False, bits, None)


def _rational_bits(expr: sympy.Expr) -> int:
    return max(abs(expr.p).bit_length(), expr.q.bit_length())


# -- the parser ----------------------------------------------------------------


class _Parser:
    """Check an AST against the whitelist, then build its sympy expression."""

    def __init__(self, text: str, names: Mapping[str, sympy.Expr]) -> None:
        self.text = text
        self.names = names
        self.memo: dict[sympy.Basic, _Facts] = {}
        self.diff_work = 0

    # messages

    def quote(self, node: ast.AST | None) -> str:
        segment = None if node is None else ast.get_source_segment(self.text, node)
        return _quote(segment if segment is not None else self.text)

    def error(self, message: str, node: ast.AST) -> ExpressionError:
        return ExpressionError(f"{message}: {self.quote(node)}")

    def known_names(self) -> list[str]:
        return sorted(set(self.names) | set(CONSTANTS))

    # the whitelist, checked before anything is built

    def check(self, node: ast.AST) -> None:
        if isinstance(node, ast.BinOp):
            if type(node.op) not in _BINARY and not isinstance(node.op, ast.Pow):
                self.operator_error(node.op, node)
            self.check(node.left)
            self.check(node.right)
        elif isinstance(node, ast.UnaryOp):
            if not isinstance(node.op, (ast.UAdd, ast.USub)):
                self.operator_error(node.op, node)
            self.check(node.operand)
        elif isinstance(node, ast.Constant):
            self.check_constant(node)
        elif isinstance(node, ast.Name):
            self.check_name(node)
        elif isinstance(node, ast.Call):
            self.check_call(node)
        else:
            what = _FORBIDDEN.get(type(node), f"{type(node).__name__} is not allowed")
            raise self.error(what, node)

    def operator_error(self, op: ast.AST, node: ast.AST) -> None:
        symbol = _OPERATOR_SYMBOLS.get(type(op), type(op).__name__)
        hint = " (use ** for powers)" if symbol == "^" else ""
        raise self.error(f"operator '{symbol}' is not allowed{hint}", node)

    def check_constant(self, node: ast.Constant) -> None:
        value = node.value
        if isinstance(value, bool) or value is None:
            raise self.error(f"the constant {value} is not allowed", node)
        if isinstance(value, (int, float)):
            return
        if isinstance(value, str):
            raise self.error("strings are not allowed", node)
        if isinstance(value, bytes):
            raise self.error("bytes are not allowed", node)
        if isinstance(value, complex):
            raise self.error("complex numbers are not allowed", node)
        raise self.error(f"the constant {type(value).__name__} is not allowed", node)

    def check_name(self, node: ast.Name) -> None:
        name = node.id
        if name in self.names or name in CONSTANTS:
            return
        if name in FUNCTIONS:
            raise self.error(f"function '{name}' must be called, as in {name}(...)", node)
        candidates = [*self.known_names(), *FUNCTIONS]
        close = difflib.get_close_matches(name, candidates, n=1)
        if close:
            raise ExpressionError(f"unknown name {name!r} (did you mean {close[0]!r}?)")
        known = self.known_names()
        listed = ", ".join(known[:20]) + (", ..." if len(known) > 20 else "")
        raise ExpressionError(f"unknown name {name!r} (known names: {listed})")

    def check_call(self, node: ast.Call) -> None:
        func = node.func
        if not isinstance(func, ast.Name):
            self.check(func)  # attribute access, subscripts, lambdas, ... say what they are
            raise self.error("only the allowed functions can be called", node)
        name = func.id
        builtin = FUNCTIONS.get(name)
        if builtin is None:
            if name in self.names or name in CONSTANTS:
                raise self.error(f"{name!r} is not a function", node)
            close = difflib.get_close_matches(name, list(FUNCTIONS), n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ExpressionError(
                f"function {name!r} is not allowed ({hint}allowed: {', '.join(FUNCTIONS)})"
            )
        if node.keywords:
            raise self.error("keyword arguments are not allowed", node.keywords[0])
        for arg in node.args:
            if isinstance(arg, ast.Starred):
                raise self.error(_FORBIDDEN[ast.Starred], arg)
        if name == "diff":
            variable = node.args[1] if len(node.args) == 2 else None
            if not (isinstance(variable, ast.Name) and variable.id in ("x", "y")):
                raise self.error("diff() takes an expression and x or y", node)
            self.check(node.args[0])
            return
        count = len(node.args)
        if count < builtin.min_args or (builtin.max_args is not None and count > builtin.max_args):
            raise self.error(f"{name}() takes {builtin.arity} ({count} given)", node)
        for arg in node.args:
            self.check(arg)

    # facts about sympy trees, memoised over the shared sub-trees (a DAG)

    def facts(self, expr: sympy.Basic) -> _Facts:
        memo = self.memo
        stack = [expr]
        while stack:
            node = stack[-1]
            if node in memo:
                stack.pop()
                continue
            pending = [arg for arg in node.args if arg not in memo]
            if pending:
                stack.extend(pending)
                continue
            stack.pop()
            if not node.args:
                memo[node] = _atom_facts(node)
                continue
            parts = [memo[arg] for arg in node.args]
            memo[node] = _Facts(
                size=min(1 + sum(p.size for p in parts), MAX_SIZE + 1),
                depth=1 + max(p.depth for p in parts),
                symbolic=any(p.symbolic for p in parts),
                bits=max(p.bits for p in parts),
                bad=next((p.bad for p in parts if p.bad is not None), None),
            )
        return memo[expr]

    def check_result(self, expr: sympy.Expr) -> None:
        """The bounds on the whole expression, its names substituted."""
        facts = self.facts(expr)
        if facts.size > MAX_SIZE:
            raise ExpressionError(
                f"expression is too large once its names are substituted "
                f"(more than {MAX_SIZE} nodes): {self.quote(None)}"
            )
        if facts.depth > MAX_TREE_DEPTH:
            raise ExpressionError(
                f"expression is nested too deeply once its names are substituted "
                f"(more than {MAX_TREE_DEPTH} levels): {self.quote(None)}"
            )
        if facts.bad is not None:
            raise ExpressionError(f"{self.quote(None)} {facts.bad}")

    # building, bottom-up; every constant is checked as soon as it is made

    def build(self, node: ast.expr) -> _Value:
        if isinstance(node, ast.Constant):
            return self.number(node.value, node)
        if isinstance(node, ast.Name):
            return self.name(node)
        if isinstance(node, ast.UnaryOp):
            operand = self.build(node.operand)
            if isinstance(node.op, ast.UAdd):
                return operand
            value = None if operand.value is None else -operand.value
            return self.finish(-operand.expr, value, node)
        if isinstance(node, ast.BinOp):
            left, right = self.build(node.left), self.build(node.right)
            if isinstance(node.op, ast.Pow):
                return self.power(left, right, node)
            symbolic, numeric = _BINARY[type(node.op)]
            value = self.constant(numeric, [left, right], node)
            return self.finish(symbolic(left.expr, right.expr), value, node)
        if isinstance(node, ast.Call):
            return self.call(node)
        raise AssertionError(f"unchecked node {type(node).__name__}")  # pragma: no cover

    def constant(
        self, numeric: Callable[..., float], args: list[_Value], node: ast.AST
    ) -> float | None:
        """The value of a node whose arguments are all constant (checked), else None."""
        values = [arg.value for arg in args]
        if any(value is None for value in values):
            return None
        value = numeric(*values)
        self.check_finite(value, node)
        return value

    def check_finite(self, value: float, node: ast.AST | None) -> None:
        if math.isnan(value):
            raise ExpressionError(f"{self.quote(node)} is not a finite real number")
        if math.isinf(value):
            raise ExpressionError(f"{self.quote(node)} is not finite")

    def finish(self, expr: sympy.Expr, value: float | None, node: ast.AST | None) -> _Value:
        """Check each freshly built node, so that nothing bad is built upon.

        It must hold no infinity, nan, imaginary unit or number beyond the double
        range; a constant must have a finite real value, and stay a small number.
        """
        facts = self.facts(expr)
        if value is None and not facts.symbolic:
            # Symbols cancelled (x - x) or a derivative came out constant.
            try:
                value = float(expr)
            except (TypeError, ValueError, ArithmeticError):
                value = math.nan
            self.check_finite(value, node)
        if facts.bad is _UNDERFLOW and value is not None:
            expr = sympy.Float(value)  # a constant that underflows is its double value
        elif facts.bad is not None:
            raise ExpressionError(f"{self.quote(node)} {facts.bad}")
        if expr.is_Rational and _rational_bits(expr) > MAX_EXACT_BITS:
            expr = sympy.Float(value)
        return _Value(expr, value)

    def number(self, literal: int | float, node: ast.AST | None) -> _Value:
        value = _real_float(literal)
        self.check_finite(value, node)
        if isinstance(literal, int) and abs(literal) <= MAX_INTEGER:
            return _Value(sympy.Integer(literal), value)
        return _Value(sympy.Float(value), value)

    def name(self, node: ast.Name) -> _Value:
        if node.id not in self.names:
            return _Value(CONSTANTS[node.id], float(CONSTANTS[node.id]))
        expr = self.names[node.id]
        if isinstance(expr, int):
            expr = sympy.Integer(expr)
        elif isinstance(expr, float):
            expr = sympy.Float(expr)
        facts = self.facts(expr)
        if facts.size > MAX_SIZE or facts.depth > MAX_TREE_DEPTH:
            raise ExpressionError(
                f"{node.id!r} is too large (more than {MAX_SIZE} nodes or {MAX_TREE_DEPTH} levels)"
            )
        if facts.bad is not None:
            raise ExpressionError(f"{node.id!r} {facts.bad}")
        return self.finish(expr, None, node)

    def exact_power_is_cheap(self, base: sympy.Expr, exponent: sympy.Expr) -> bool:
        """Whether sympy may compute ``base**exponent`` without a huge exact number."""
        if not exponent.is_Rational:
            return True
        p, q = abs(exponent.p), exponent.q
        if p > MAX_EXPONENT or q > MAX_EXPONENT:
            return False
        return self.facts(base).bits * p <= MAX_EXACT_BITS

    def power(self, base: _Value, exponent: _Value, node: ast.BinOp) -> _Value:
        value = self.constant(_real_power, [base, exponent], node)
        cheap = self.exact_power_is_cheap(base.expr, exponent.expr)
        if value is not None:
            expr = base.expr**exponent.expr if cheap else sympy.Float(value)
        elif cheap:
            expr = base.expr**exponent.expr
        else:
            # (x + 1)**100000 stays a power (nothing expands it), with a Float exponent
            # so that sympy does not raise numeric coefficients of the base exactly.
            expr = base.expr ** sympy.Float(exponent.expr)
        return self.finish(expr, value, node)

    def call(self, node: ast.Call) -> _Value:
        assert isinstance(node.func, ast.Name)
        builtin = FUNCTIONS[node.func.id]
        if builtin.name == "diff":
            return self.derivative(node)
        assert builtin.symbolic is not None and builtin.numeric is not None
        args = [self.build(arg) for arg in node.args]
        value = self.constant(builtin.numeric, args, node)
        if value is not None and builtin.name in ("min", "max"):
            # Constant arguments: pick the extreme one instead of comparing symbolically.
            values = [arg.value for arg in args]
            return _Value(args[values.index(value)].expr, value)
        return self.finish(builtin.symbolic(*[arg.expr for arg in args]), value, node)

    def derivative(self, node: ast.Call) -> _Value:
        operand = self.build(node.args[0])
        if operand.value is not None:
            return _Value(sympy.Integer(0), 0.0)
        variable_name = node.args[1].id  # type: ignore[attr-defined]  # checked: a Name
        variable = self.names.get(variable_name)
        if not isinstance(variable, sympy.Symbol):
            variable = sympy.Symbol(variable_name, real=True)
        self.diff_work += self.facts(operand.expr).size
        if self.diff_work > MAX_DIFF_WORK:
            raise self.error(
                f"too much to differentiate (more than {MAX_DIFF_WORK} nodes in all)", node
            )
        return self.finish(sympy.diff(operand.expr, variable), None, node)


# -- code for other evaluators -----------------------------------------------------


def smooth_minmax(expr: sympy.Expr) -> sympy.Expr:
    """Min/Max rewritten as (a + b ∓ |a − b|)/2, folded left over their arguments.

    min(a, b) = (a + b − |a − b|)/2 and max(a, b) = (a + b + |a − b|)/2 exactly;
    in this form sympy differentiates plainly (d|u| = sign(u) du, where dMax
    gives a Heaviside) and lambdified numpy code broadcasts.

    >>> x, y = sympy.symbols("x y", real=True)
    >>> smooth_minmax(sympy.Max(x, y))
    x/2 + y/2 + Abs(x - y)/2
    """

    def fold(args: tuple, sign: int) -> sympy.Expr:
        acc = args[0]
        for other in args[1:]:
            acc = (acc + other + sign * sympy.Abs(acc - other)) / 2
        return acc

    return expr.replace(sympy.Min, lambda *a: fold(a, -1)).replace(sympy.Max, lambda *a: fold(a, 1))


class ScalarPrinter(PythonCodePrinter):
    """Python code of one point for :func:`curvimesh.kernels.compile_metric`.

    Bare names of ``math`` functions, ``abs`` and the kernels' ``sign``, and
    every float written exactly (its shortest repr), so that the compiled
    scalar code and the numpy code compute the same expressions.
    """

    def __init__(self) -> None:
        super().__init__({"fully_qualified_modules": False})

    def _print_Float(self, expr):
        return repr(float(expr))

    def _print_Abs(self, expr):
        return f"abs({self._print(expr.args[0])})"

    def _print_sign(self, expr):
        return f"sign({self._print(expr.args[0])})"

    def _print_Pow(self, expr, rational=False):
        # numba raises ZeroDivisionError for 0.0 ** (negative integer), whatever
        # the error model; 1 / 0.0 ** n is inf, as in numpy
        base, exp = expr.as_base_exp()
        if exp.is_number and exp.is_negative and exp != -sympy.S.Half:
            return f"(1/{self._print(sympy.Pow(base, -exp, evaluate=False))})"
        return super()._print_Pow(expr, rational=rational)

    def _print_not_supported(self, expr):
        raise ValueError(f"no scalar code for {type(expr).__name__}")


def scalar_function(name: str, exprs: Sequence[sympy.Expr]) -> str:
    """Source of ``def name(x, y)`` returning the expressions as floats (with cse).

    Min/Max are rewritten by :func:`smooth_minmax`, common subexpressions
    eliminated by :func:`sympy.cse`, and the code printed by :class:`ScalarPrinter`;
    ValueError if an expression has no scalar code.

    >>> x, y = sympy.symbols("x y", real=True)
    >>> print(scalar_function("f", [x * y, abs(x - y)]), end="")
    def f(x, y):
        return (float(x*y), float(abs(x - y)),)
    """
    printer = ScalarPrinter()
    subs, reduced = sympy.cse([smooth_minmax(sympy.sympify(e)) for e in exprs])
    lines = [f"def {name}(x, y):"]
    lines += [f"    {printer.doprint(s)} = {printer.doprint(e)}" for s, e in subs]
    values = ", ".join(f"float({printer.doprint(e)})" for e in reduced)
    lines.append(f"    return ({values},)")
    return "\n".join(lines) + "\n"
