"""Tests of the whitelist expression parser (curvimesh.expressions)."""

from __future__ import annotations

import math
import time

import pytest
import sympy
from hypothesis import given, settings
from hypothesis import strategies as st

from curvimesh.errors import ExpressionError, InputError
from curvimesh.expressions import (
    CONSTANTS,
    FUNCTIONS,
    MAX_DEPTH,
    MAX_DIFF_WORK,
    MAX_LENGTH,
    MAX_SIZE,
    MAX_TREE_DEPTH,
    RESERVED,
    expression_symbols,
    parse_expression,
)

X, Y = sympy.symbols("x y", real=True)
NAMES = {
    "x": X,
    "y": Y,
    "eps": sympy.Float(0.01),
    "k": sympy.Integer(3),
    "r": sympy.sqrt(X**2 + Y**2),
    "for": sympy.Integer(2),  # a parameter whose name is close to 'foo'
}
# Points with x, y of both signs, and points in the positive quadrant.
POINTS = [(0.3, 0.7), (-1.2, 0.4), (2.5, -0.9), (-0.6, -1.7)]
POSITIVE = [(0.3, 0.7), (1.9, 0.4), (2.5, 3.1)]


def value_at(expr: sympy.Expr, x: float, y: float) -> float:
    """The value of ``expr`` at (x, y), by sympy's own arbitrary-precision evaluation."""
    return float(expr.evalf(30, subs={X: x, Y: y}))


R = math.hypot

ALLOWED = [
    # literals, names, pi, unary and binary operators
    ("x", lambda x, y: x),
    ("3", lambda x, y: 3.0),
    ("2.5", lambda x, y: 2.5),
    ("1.5e-3 * x", lambda x, y: 1.5e-3 * x),
    ("2E2 + y", lambda x, y: 200.0 + y),
    ("-x", lambda x, y: -x),
    ("+y", lambda x, y: y),
    ("- -x", lambda x, y: x),
    ("x + y", lambda x, y: x + y),
    ("x - 2*y", lambda x, y: x - 2 * y),
    ("x * y / 3", lambda x, y: x * y / 3),
    ("(x + 1) * (y - 2)", lambda x, y: (x + 1) * (y - 2)),
    ("x**2", lambda x, y: x**2),
    ("x**-2", lambda x, y: x**-2),
    ("-x**2", lambda x, y: -(x**2)),
    ("2**x", lambda x, y: 2**x),
    ("2**3**2", lambda x, y: 2**9),
    ("(x**2 + y**2)**(1/2)", lambda x, y: R(x, y)),
    ("pi * x", lambda x, y: math.pi * x),
    ("eps * r + k", lambda x, y: 0.01 * R(x, y) + 3),
    # every function
    ("sqrt(x**2 + y**2)", lambda x, y: R(x, y)),
    ("exp(x) - exp(-y)", lambda x, y: math.exp(x) - math.exp(-y)),
    ("log(x**2 + 1)", lambda x, y: math.log(x**2 + 1)),
    ("sin(x) + cos(y) + tan(x*y)", lambda x, y: math.sin(x) + math.cos(y) + math.tan(x * y)),
    ("asin(x/3) + acos(y/2)", lambda x, y: math.asin(x / 3) + math.acos(y / 2)),
    ("atan(x) + atan2(y, x)", lambda x, y: math.atan(x) + math.atan2(y, x)),
    ("sinh(x) * cosh(y) - tanh(x)", lambda x, y: math.sinh(x) * math.cosh(y) - math.tanh(x)),
    ("abs(x - y)", lambda x, y: abs(x - y)),
    ("min(x, y)", lambda x, y: min(x, y)),
    ("min(x, y, 0)", lambda x, y: min(x, y, 0)),
    ("max(x, y, 0.5)", lambda x, y: max(x, y, 0.5)),
    ("max(min(x, y), -x, y**2)", lambda x, y: max(min(x, y), -x, y**2)),
    # diff of expressions and of definitions
    ("diff(x**3 * y, x)", lambda x, y: 3 * x**2 * y),
    ("diff(sin(x*y), y)", lambda x, y: x * math.cos(x * y)),
    ("diff(r, x)", lambda x, y: x / R(x, y)),
    ("diff(diff(x**2 * y**2, x), y)", lambda x, y: 4 * x * y),
    ("diff(eps, x) + 1", lambda x, y: 1.0),
    ("diff(atan2(y, x), x)", lambda x, y: -y / (x**2 + y**2)),
]

POSITIVE_ONLY = [
    ("x**2.5 + y**(1/3)", lambda x, y: x**2.5 + y ** (1 / 3)),
    ("x**y", lambda x, y: x**y),
    ("log(x) - log(y)", lambda x, y: math.log(x) - math.log(y)),
]


@pytest.mark.parametrize(("text", "oracle"), ALLOWED, ids=[t for t, _ in ALLOWED])
def test_allowed_constructs_have_the_right_value(text, oracle):
    expr = parse_expression(text, NAMES)
    assert isinstance(expr, sympy.Expr)
    for x, y in POINTS:
        assert value_at(expr, x, y) == pytest.approx(oracle(x, y), rel=1e-12, abs=1e-12)


@pytest.mark.parametrize(("text", "oracle"), POSITIVE_ONLY, ids=[t for t, _ in POSITIVE_ONLY])
def test_real_powers_and_logs_in_the_positive_quadrant(text, oracle):
    expr = parse_expression(text, NAMES)
    for x, y in POSITIVE:
        assert value_at(expr, x, y) == pytest.approx(oracle(x, y), rel=1e-12)


def test_numbers_are_exact_where_small():
    assert parse_expression("1/3", {}) == sympy.Rational(1, 3)
    assert parse_expression("2**(1/2)", {}) == sympy.sqrt(2)
    assert parse_expression("10**7", {}) == sympy.Integer(10**7)
    assert parse_expression("0x10 + 1_000", {}) == 1016
    assert parse_expression("1000000", {}) == sympy.Integer(10**6)
    # a larger literal becomes a Float, of the same value
    big = parse_expression("123456789012", {})
    assert isinstance(big, sympy.Float)
    assert float(big) == 123456789012.0


def test_yaml_numbers_are_accepted_directly():
    assert parse_expression(2, {}) == 2
    assert parse_expression(0.25, {}) == sympy.Float(0.25)
    assert parse_expression(-7, NAMES) == -7


@pytest.mark.parametrize("value", [True, False, None, [1, 2], {"a": 1}, b"x"])
def test_other_python_values_are_rejected(value):
    with pytest.raises(ExpressionError, match="expected an expression"):
        parse_expression(value, NAMES)


def test_expression_error_is_an_input_error():
    assert issubclass(ExpressionError, InputError)


def test_the_whitelist_is_the_documented_one():
    assert set(FUNCTIONS) == {
        *"sqrt exp log sin cos tan asin acos atan atan2 sinh cosh tanh abs min max".split(),
        "diff",
    }
    assert set(CONSTANTS) == {"pi"}
    assert RESERVED == set(FUNCTIONS) | {"pi"}


def test_atan2_takes_y_then_x_in_every_quadrant():
    expr = parse_expression("atan2(y, x)", NAMES)
    assert expr == sympy.atan2(Y, X)
    for x, y in [(1, 1), (-1, 1), (-1, -1), (1, -1), (-1, 0.0)]:
        assert value_at(expr, x, y) == pytest.approx(math.atan2(y, x), rel=1e-14)


def test_min_and_max():
    assert isinstance(parse_expression("max(x, y)", NAMES), sympy.Max)
    assert isinstance(parse_expression("min(x, y, 1)", NAMES), sympy.Min)
    # constant arguments: the extreme one, exactly
    assert parse_expression("max(1, 3, 2)", {}) == 3
    assert parse_expression("min(pi, 3, 4)", {}) == 3
    assert parse_expression("max(pi, 3)", {}) == sympy.pi
    # the derivative picks the branch
    slope = parse_expression("diff(max(x, 2*y), x)", NAMES)
    assert value_at(slope, 1.0, 0.0) == 1.0
    assert value_at(slope, 0.0, 1.0) == 0.0


def test_abs():
    assert parse_expression("abs(-x)", NAMES) == sympy.Abs(X)
    assert parse_expression("abs(-2)", {}) == 2
    slope = parse_expression("diff(abs(x), x)", NAMES)
    assert value_at(slope, 0.5, 0.0) == 1.0
    assert value_at(slope, -0.5, 0.0) == -1.0


def test_diff():
    assert parse_expression("diff(x**2*y, x)", NAMES) == 2 * X * Y
    assert parse_expression("diff(x**2*y, y)", NAMES) == X**2
    assert parse_expression("diff(k, x)", NAMES) == 0
    # a definition is differentiated as the expression it stands for
    assert parse_expression("diff(r, y)", NAMES) == Y / sympy.sqrt(X**2 + Y**2)
    # without 'x' among the names nothing depends on x
    assert parse_expression("diff(y**2, x)", {"y": Y}) == 0


def test_pi_and_names_and_symbols():
    assert parse_expression("pi", {}) == sympy.pi
    assert expression_symbols(parse_expression("eps*x + k", NAMES)) == {"x"}
    assert expression_symbols(parse_expression("r", NAMES)) == {"x", "y"}
    assert expression_symbols(parse_expression("2*pi", NAMES)) == set()


def test_whitespace_and_parenthesised_newlines_are_fine():
    assert parse_expression("  x + 1  ", NAMES) == X + 1
    assert parse_expression("(x +\n 1)", NAMES) == X + 1


# -- rejection -------------------------------------------------------------------

# (hostile text, a piece the one-line message must contain)
HOSTILE = [
    ("__import__('os').system('ls')", "attribute access is not allowed"),
    ("__import__('os')", "function '__import__' is not allowed"),
    ("().__class__.__bases__[0]", "'().__class__.__bases__[0]'"),
    ("x.real", "attribute access is not allowed: 'x.real'"),
    ("x.__class__", "'x.__class__'"),
    ("lambda: 1", "lambda expressions are not allowed: 'lambda: 1'"),
    ("[x for x in y]", "comprehensions are not allowed: '[x for x in y]'"),
    ("(x for x in y)", "comprehensions are not allowed"),
    ("'a'", "strings are not allowed: \"'a'\""),
    ("b'a'", "bytes are not allowed"),
    ('f"{x}"', "f-strings are not allowed"),
    ("x if y else 1", "conditional expressions are not allowed: 'x if y else 1'"),
    ("x < y", "comparisons are not allowed: 'x < y'"),
    ("x and y", "boolean operators (and, or) are not allowed: 'x and y'"),
    ("not x", "operator 'not' is not allowed: 'not x'"),
    ("open('f')", "function 'open' is not allowed"),
    ("eval('1')", "function 'eval' is not allowed (allowed: sqrt, exp"),
    ("exec('x')", "function 'exec' is not allowed"),
    ("getattr(x, 'real')", "function 'getattr' is not allowed"),
    ("x[0]", "subscripts are not allowed: 'x[0]'"),
    ("x[1:2]", "subscripts are not allowed"),
    ("[x, y]", "lists are not allowed"),
    ("(x, y)", "tuples are not allowed"),
    ("{x: 1}", "dicts are not allowed"),
    ("{x}", "sets are not allowed"),
    ("9**9**9**9", "'9**9**9' is not finite"),
    ("10**1000000", "'10**1000000' is not finite"),
    ("(" * 1000 + "x" + ")" * 1000, "too long"),
    ("(" * 300 + "x" + ")" * 300, "syntax error at column"),
    ("-" * 1999 + "x", "nested too deeply"),
    ("x" + "+x" * 60, "nested too deeply"),
    ("1j", "complex numbers are not allowed: '1j'"),
    ("x + 2j", "'2j'"),
    ("x // y", "operator '//' is not allowed: 'x // y'"),
    ("x % 2", "operator '%' is not allowed: 'x % 2'"),
    ("x @ y", "operator '@' is not allowed"),
    ("x ^ 2", "use ** for powers"),
    ("x << 2", "operator '<<' is not allowed"),
    ("x | y", "operator '|' is not allowed"),
    ("~x", "operator '~' is not allowed"),
    ("a := 1", "syntax error at column 3"),
    ("(x := 1)", "assignment expressions (:=) are not allowed: 'x := 1'"),
    ("...", "'...'"),
    ("None", "the constant None is not allowed"),
    ("True", "the constant True is not allowed"),
    ("sin(x=1)", "keyword arguments are not allowed: 'x=1'"),
    ("max(*x)", "starred arguments are not allowed: '*x'"),
    ("x(1)", "'x' is not a function: 'x(1)'"),
    ("(x + 1)(2)", "only the allowed functions can be called: '(x + 1)(2)'"),
    ("sqrt.__call__(x)", "attribute access is not allowed: 'sqrt.__call__'"),
    ("__builtins__", "unknown name '__builtins__'"),
    ("__debug__", "unknown name '__debug__'"),
    ("foo", "unknown name 'foo'"),
    ("sin", "function 'sin' must be called"),
    ("sin(x, y)", "sin() takes 1 argument (2 given): 'sin(x, y)'"),
    ("log(x, 2)", "log() takes 1 argument (2 given)"),
    ("atan2(y)", "atan2() takes 2 arguments (1 given)"),
    ("max(x)", "max() takes at least 2 arguments (1 given)"),
    ("diff(x**2, z)", "diff() takes an expression and x or y: 'diff(x**2, z)'"),
    ("diff(x**2, 2*x)", "diff() takes an expression and x or y"),
    ("diff(x**2)", "diff() takes an expression and x or y"),
    ("", "expression is empty"),
    ("x +", "syntax error at the end: invalid syntax in 'x +'"),
    ("sin(x", "syntax error at column 4: '(' was never closed in 'sin(x'"),
    ("x\0", "syntax error"),
    ("await x", "await is not allowed"),
    ("x\n+ 1", "syntax error at line 2"),
]


@pytest.mark.parametrize(("text", "fragment"), HOSTILE, ids=[t[:40] for t, _ in HOSTILE])
def test_hostile_input_is_rejected_with_a_one_line_message(text, fragment):
    with pytest.raises(ExpressionError) as info:
        parse_expression(text, NAMES)
    message = str(info.value)
    assert "\n" not in message
    assert fragment in message
    assert len(message) < 300


NOT_FINITE = [
    ("1/0", "'1/0' is not finite"),
    ("0/0", "'0/0' is not a finite real number"),
    ("x/0", "'x/0' is not finite"),
    ("1/(x - x)", "'1/(x - x)' is not finite"),
    ("log(0)", "'log(0)' is not finite"),
    ("1e400", "'1e400' is not finite"),
    ("x * 1e308 * 1e308", "is not finite"),
    ("exp(1000)", "'exp(1000)' is not finite"),
    ("x + cosh(800)", "'cosh(800)' is not finite"),
    ("exp(1000 * (x - x + 1))", "is not finite"),
    ("0**-1", "is not finite"),
    ("((2*x)**64)**64", "is not finite"),
    ("sqrt(-1)", "'sqrt(-1)' is not a finite real number"),
    ("asin(2)", "is not a finite real number"),
    ("(-8)**(1/3)", "is not a finite real number"),
    ("atan2(0, 0)", "is not a finite real number"),
    ("1" * 400, "is not finite"),
]


@pytest.mark.parametrize(("text", "fragment"), NOT_FINITE, ids=[t[:40] for t, _ in NOT_FINITE])
def test_constants_that_are_not_finite_and_real_are_rejected(text, fragment):
    with pytest.raises(ExpressionError, match="not") as info:
        parse_expression(text, NAMES)
    assert fragment in str(info.value)


@pytest.mark.parametrize("value", [math.inf, -math.inf, math.nan, 10**400])
def test_yaml_numbers_that_are_not_finite_are_rejected(value):
    with pytest.raises(ExpressionError, match=r"is not (finite|a finite real number)"):
        parse_expression(value, NAMES)


def test_did_you_mean():
    with pytest.raises(ExpressionError, match=r"function 'sqtr' .*did you mean 'sqrt'\?"):
        parse_expression("sqtr(x)", NAMES)
    with pytest.raises(ExpressionError, match=r"unknown name 'xx' \(did you mean 'x'\?\)"):
        parse_expression("xx + 1", NAMES)
    with pytest.raises(ExpressionError, match=r"unknown name 'foo' \(did you mean 'for'\?\)"):
        parse_expression("foo", NAMES)
    # nothing close: the known names are listed instead
    with pytest.raises(ExpressionError, match=r"unknown name 'zeta' \(known names: eps, "):
        parse_expression("zeta", NAMES)


def test_limits_are_enforced_at_their_bounds():
    at_limit = "x" + " " * (MAX_LENGTH - 1)
    assert parse_expression(at_limit, NAMES) == X
    deep = "-" * (MAX_DEPTH - 1) + "x"
    assert parse_expression(deep, NAMES) == -X
    with pytest.raises(ExpressionError, match="nested too deeply"):
        parse_expression("-" + deep, NAMES)


def test_huge_powers_of_symbols_stay_unexpanded():
    expr = parse_expression("(x + 1)**100000", NAMES)
    assert expr == (X + 1) ** sympy.Float(100000)
    assert parse_expression("(x + 1)**64", NAMES) == (X + 1) ** 64
    # a power the size of a double is kept exact; a larger one becomes a Float
    assert parse_expression("2**64", {}) == 2**64
    assert isinstance(parse_expression("3**100", {}), sympy.Float)


def test_differentiation_is_bounded():
    product = sympy.Mul(*[sympy.sin(i * X + Y) for i in range(1, 300)])
    with pytest.raises(ExpressionError, match="too much to differentiate"):
        parse_expression("diff(p, x)", {"x": X, "y": Y, "p": product})
    small = sympy.Mul(*[sympy.sin(i * X + Y) for i in range(1, 8)])
    repeated = " + ".join(["diff(p, x)"] * 40)
    with pytest.raises(ExpressionError, match=f"more than {MAX_DIFF_WORK} nodes"):
        parse_expression(repeated, {"x": X, "y": Y, "p": small})


def test_definitions_that_blow_up_when_substituted_are_rejected():
    # Each definition uses the previous one twice: a shared tree of exponential size.
    names = {"x": X, "d": X}
    for _ in range(30):
        names["d"] = names["d"] * (names["d"] + 1)
    with pytest.raises(ExpressionError, match=f"more than {MAX_SIZE} nodes"):
        parse_expression("d + x", names)
    # The same through the parser: some definition in the chain is refused.
    names = {"x": X, "d": X + 1}
    with pytest.raises(ExpressionError, match=f"more than {MAX_SIZE} nodes"):
        for _ in range(30):
            names["d"] = parse_expression("d * (d + x)", names)


def test_deeply_nested_definitions_are_rejected():
    names = {"x": X, "d": X}
    with pytest.raises(ExpressionError, match=f"more than {MAX_TREE_DEPTH} levels"):
        for _ in range(10):
            names["d"] = parse_expression("sin(" * 20 + "d" + ")" * 20, names)


def test_many_min_max_arguments_nest_shallowly():
    text = "max(" + ", ".join(f"x*{i} + y" for i in range(1, 130)) + ")"
    expr = parse_expression(text, NAMES)
    # a balanced tree of binary Max: depth about log2(129)
    depth, level = 0, [expr]
    while any(isinstance(e, sympy.Max) for e in level):
        depth += 1
        level = [a for e in level if isinstance(e, sympy.Max) for a in e.args]
    assert depth == 8
    assert value_at(expr, 0.5, 0.25) == pytest.approx(129 * 0.5 + 0.25)


def test_names_must_be_sympy_values():
    with pytest.raises(TypeError):
        parse_expression("x", {"x": "x"})


# Inputs a hostile person might write to hang the parser or exhaust memory; some
# are valid and must come back fast, the others must be rejected fast.
HEAVY = [
    *(text for text, _ in HOSTILE),
    *(text for text, _ in NOT_FINITE),
    "(x+1)**100000",
    "x**(2**20)",
    "((x**64)**64)**64",
    "(((2*x)**64)**64)**64",
    "((((2**64)**64)**64)**64)**64",
    "((1000001/1000000)**64)**64",
    "max(" + ", ".join(f"x*{i}+y" for i in range(1, 200)) + ")",
    "min(" + ", ".join(f"sin({i}*x)" for i in range(1, 150)) + ")",
    "diff(" * 24 + "exp(x*sin(x))" + ", x)" * 24,
    "diff(" * 45 + "x**50" + ", x)" * 45,
    "exp(exp(exp(exp(exp(x)))))",
    "sin(" * 49 + "x" + ")" * 49,
    "x**x**x**x**x**x**x**x**x**x**x**x**x**x**x**x",
    "*".join(["(x + y + 1)"] * 150),
    "2**0.5**" + "**".join(["2"] * 40),
    "1e308 * 10",
    "1e-320 ** -2",
    "x * 1e-300 / 1e-300 / 1e-300",
    "(1e-300 * y)**1000000 + cosh(tanh(y))",
    # sympy's assumption queries on this took 11 s before the time limit
    "sin(-(sinh(diff(diff(diff(min(-eps, asin((64 ** y)), diff(r, y), (pi * pi)), y), x), y))"
    " / -7.5e3))",
]


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # a lost shot
def test_no_input_hangs():
    durations = []
    for text in HEAVY:
        start = time.perf_counter()
        try:
            result = parse_expression(text, NAMES)
        except ExpressionError as error:
            assert "\n" not in str(error)
        else:
            assert isinstance(result, sympy.Expr)
        durations.append(time.perf_counter() - start)
    # The time limit is 1 s of CPU; a hang would be minutes. Generous for loaded machines.
    assert max(durations) < 3.0


def test_the_time_limit_interrupts_sympy():
    with pytest.raises(ExpressionError, match=r"takes too long to build \(more than 0.05 s\)"):
        parse_expression(HEAVY[-1], NAMES, time_limit=0.05)


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the lost shot
def test_the_time_limit_is_not_lost_in_a_finalizer():
    from curvimesh import expressions

    class Slow:
        def __del__(self):  # the limit's first shot lands here, where Python ignores it
            end = time.perf_counter() + 0.3
            while time.perf_counter() < end:
                pass

    start = time.perf_counter()
    with pytest.raises(expressions._OutOfTime), expressions._TimeLimit(0.05):
        Slow()  # collected at once
        while time.perf_counter() - start < 3.0:
            pass
    assert time.perf_counter() - start < 1.0


@pytest.mark.skipif(not hasattr(time, "pthread_getcpuclockid"), reason="no thread CPU clock")
def test_the_time_limit_counts_cpu_time_not_waiting():
    """A thread that waits (for the CPU on a loaded machine, or here asleep) spends no
    CPU time: 0.4 s of sleep inside a limit of 0.1 s is not interrupted, while work is
    (once its CPU time reaches the limit, long before the loop's 3 s)."""
    from curvimesh import expressions

    with expressions._TimeLimit(0.1):
        time.sleep(0.4)
    start = time.perf_counter()
    with pytest.raises(expressions._OutOfTime), expressions._TimeLimit(0.1):
        while time.perf_counter() - start < 3.0:
            pass


def _busy(seconds: float) -> int:
    """Bytecode for ``seconds`` of wall clock, where a stray interruption would land."""
    end, loops = time.perf_counter() + seconds, 0
    while time.perf_counter() < end:
        loops += 1
    return loops


def test_a_time_limit_whose_opener_has_returned_stops_shooting():
    """A block whose exit never ran (a shot can carry the exception past it) must not
    interrupt what the thread runs after the frame that opened it has returned."""
    from curvimesh import expressions

    def open_and_return():
        limit = expressions._TimeLimit(0.02)
        limit.__enter__()  # the exit is never called
        return limit

    limit = open_and_return()
    assert _busy(0.5) > 0  # the limit is up after 0.02 s of CPU; no shot may land
    assert limit.timer.join(1.0) is None and not limit.timer.is_alive()
    assert not limit.fired


def test_a_time_limit_gives_up_after_its_last_shot(monkeypatch):
    from curvimesh import expressions

    monkeypatch.setattr(expressions, "MAX_SHOTS", 3)
    shots = 0
    limit = expressions._TimeLimit(0.02)
    limit.__enter__()
    end = time.perf_counter() + 2.0
    while time.perf_counter() < end:  # a block that swallows every shot
        try:
            _busy(end - time.perf_counter())
        except expressions._OutOfTime:
            shots += 1
    limit.__exit__(None, None, None)
    assert shots == 3
    assert not limit.timer.is_alive()


def test_a_time_limit_running_out_at_the_end_leaves_nothing_behind():
    # Limits about as long as the work: the interruption is due just as the work
    # ends. Either way nothing may be raised once parse_expression has returned.
    outcomes = set()
    for i in range(300):
        try:
            parse_expression("diff(r, x)*sin(x) + max(x, y)", NAMES, time_limit=(i % 30) * 2e-4)
            outcomes.add("parsed")
        except ExpressionError:
            outcomes.add("rejected")
        total = 0
        for j in range(2000):  # bytecode during which a stray interruption would land
            total += j
        assert total == 1999000
    assert "parsed" in outcomes


# -- fuzzing -----------------------------------------------------------------------

TOKENS = [
    *"xy0129.e+-*/()[],'\" _:<=j%@^~",
    "**",
    "//",
    "pi",
    "eps",
    "r",
    "sqrt",
    "sin",
    "max",
    "diff",
    "log",
    "atan2",
    "1e308",
    "__class__",
    "__import__",
    "lambda",
    "for",
    "in",
    "if",
    "not",
]

LEAVES = [
    *"xyr",
    "eps",
    "k",
    "pi",
    "0",
    "1",
    "2",
    "64",
    "0.5",
    "1e308",
    "1e-300",
    "1000000",
    "1000001",
    "xx",
    "'s'",
    "True",
    "None",
    "1j",
    "...",
]
BINARY = ["+", "-", "*", "/", "**", "//", "%", "<", "and", "@", "^"]
CALLS = [*FUNCTIONS, "foo", "eval"]


def _ast_strategy() -> st.SearchStrategy[str]:
    def extend(children: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
        return st.one_of(
            st.tuples(children, st.sampled_from(BINARY), children).map(
                lambda t: f"({t[0]} {t[1]} {t[2]})"
            ),
            st.tuples(st.sampled_from(["-", "+", "~", "not "]), children).map("".join),
            st.tuples(st.sampled_from(CALLS), st.lists(children, max_size=3)).map(
                lambda t: f"{t[0]}({', '.join(t[1])})"
            ),
            st.tuples(children, st.sampled_from(["x", "y", "z", "2"])).map(
                lambda t: f"diff({t[0]}, {t[1]})"
            ),
            children.map(lambda c: f"({c}).real"),
            children.map(lambda c: f"({c})[0]"),
        )

    return st.recursive(st.sampled_from(LEAVES), extend, max_leaves=30)


def _valid_ast_strategy() -> st.SearchStrategy[str]:
    """Texts inside the grammar (which may still overflow or have no real value)."""
    leaves = st.sampled_from([*"xyr", "eps", "k", "pi", "0", "1", "2", "0.5", "64", "1e308"])
    arities = {name: (f.min_args, f.max_args or 4) for name, f in FUNCTIONS.items()}
    del arities["diff"]

    def extend(children: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
        calls = st.sampled_from(sorted(arities)).flatmap(
            lambda name: st.lists(
                children, min_size=arities[name][0], max_size=arities[name][1]
            ).map(lambda args: f"{name}({', '.join(args)})")
        )
        return st.one_of(
            st.tuples(children, st.sampled_from(["+", "-", "*", "/", "**"]), children).map(
                lambda t: f"({t[0]} {t[1]} {t[2]})"
            ),
            children.map(lambda c: f"-{c}"),
            calls,
            st.tuples(children, st.sampled_from("xy")).map(lambda t: f"diff({t[0]}, {t[1]})"),
        )

    return st.recursive(leaves, extend, max_leaves=30)


def _parses_or_rejects(text: str) -> None:
    try:
        # A time limit well inside the deadline of hypothesis.
        result = parse_expression(text, NAMES, time_limit=0.5)
    except ExpressionError as error:
        assert "\n" not in str(error)
        return
    assert isinstance(result, sympy.Expr)
    assert not result.has(sympy.zoo, sympy.oo, -sympy.oo, sympy.nan)


@settings(deadline=2000, max_examples=300)
@given(st.lists(st.sampled_from(TOKENS), max_size=40).map("".join))
def test_random_token_strings_parse_or_are_rejected(text):
    _parses_or_rejects(text)


@settings(deadline=2000, max_examples=300)
@given(st.text(alphabet="xyer0129.+-*/()[],'\" _:<=j", max_size=60))
def test_random_character_strings_parse_or_are_rejected(text):
    _parses_or_rejects(text)


@settings(deadline=2000, max_examples=300)
@given(_ast_strategy())
def test_random_expression_trees_parse_or_are_rejected(text):
    _parses_or_rejects(text)


@settings(deadline=2000, max_examples=300)
@given(_valid_ast_strategy())
def test_random_valid_expressions_parse_or_are_rejected(text):
    _parses_or_rejects(text)
