"""The package host/learn as a whole: no function in it runs over MAX_LINES lines or
takes more than MAX_PARAMS parameters (issue 31: training is a config handed to a
trainer in small steps, not one long function of 23 parameters)."""
from __future__ import annotations

import ast

from tests import REPO_ROOT

MAX_LINES = 80
MAX_PARAMS = 8
#: the functions that still break a limit, each with why it is left: an entry that
#: no longer breaks one must be removed (the test says so), and none may be added
KNOWN = {
    "host/learn/cnn.py:FrameCNN.__init__": "an estimator's hyperparameters, as keywords "
                                           "(scikit-learn's get_params convention)",
}


def _params(fn: ast.FunctionDef) -> int:
    a = fn.args
    n = (len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + (a.vararg is not None)
         + (a.kwarg is not None))
    first = (a.posonlyargs + a.args)[:1]
    return n - (1 if first and first[0].arg in ("self", "cls") else 0)


def _own_lines(fn: ast.FunctionDef) -> int:
    """Lines of the function's body without its docstring and without the functions
    and classes defined inside it (each of those is measured on its own)."""
    body = fn.body
    if (body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)):
        body = body[1:]
    if not body:
        return 0
    lines = set(range(body[0].lineno, fn.end_lineno + 1))
    for node in ast.walk(fn):
        if node is not fn and isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef,
                                                ast.ClassDef)):
            lines -= set(range(node.lineno, node.end_lineno + 1))
    return len(lines)


def _functions(tree: ast.Module, prefix: str = ""):
    """(qualified name, node) of every function, methods and nested ones included."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield prefix + node.name, node
            yield from _functions(node, prefix + node.name + ".")
        elif isinstance(node, ast.ClassDef):
            yield from _functions(node, prefix + node.name + ".")


def too_big(source: str) -> dict[str, str]:
    """{function: what it breaks} for the functions of ``source`` over a limit."""
    out = {}
    for name, fn in _functions(ast.parse(source)):
        n, lines = _params(fn), _own_lines(fn)
        broken = ([f"{n} parameters > {MAX_PARAMS}"] if n > MAX_PARAMS else []) + \
                 ([f"{lines} lines > {MAX_LINES}"] if lines > MAX_LINES else [])
        if broken:
            out[name] = ", ".join(broken)
    return out


def test_the_walk_finds_a_long_function_and_one_of_many_parameters():
    long = "def f(a):\n    '''doc'''\n" + "    a += 1\n" * (MAX_LINES + 1)
    many = "class C:\n    def g(self, " + ", ".join(f"p{i}" for i in range(MAX_PARAMS)) + \
           ", *rest):\n        pass\n"
    nested = "def h():\n" + "    def inner():\n" + "        x = 1\n" * (MAX_LINES + 1)
    found = too_big(long + many + nested)
    assert found == {"f": f"{MAX_LINES + 1} lines > {MAX_LINES}",
                     "C.g": f"{MAX_PARAMS + 1} parameters > {MAX_PARAMS}",
                     "h.inner": f"{MAX_LINES + 1} lines > {MAX_LINES}"}
    ok = "def k(self, a, b, c, d, e, f, g, h):\n    '''doc\n\n    more'''\n    return a\n"
    assert too_big(ok) == {}


def test_no_function_in_host_learn_is_too_long_or_takes_too_many_parameters():
    found = {}
    for path in sorted((REPO_ROOT / "host" / "learn").glob("*.py")):
        rel = path.relative_to(REPO_ROOT).as_posix()
        for name, why in too_big(path.read_text()).items():
            found[f"{rel}:{name}"] = why
    new = {k: v for k, v in found.items() if k not in KNOWN}
    assert new == {}, f"functions over the limits of host/learn: {new}"
    fixed = sorted(set(KNOWN) - set(found))
    assert fixed == [], f"within the limits now, remove from KNOWN: {fixed}"


def test_train_model_is_a_config_handed_to_a_trainer_of_one_table():
    from host.learn.tasks import MODELS, TASK_MODELS
    from host.learn.train import TRAINERS, train_model
    assert set(TRAINERS) == set(MODELS) and "cnn" in MODELS
    assert {m for ms in TASK_MODELS.values() for m in ms} <= set(MODELS)
    src = ast.parse((REPO_ROOT / "host" / "learn" / "train.py").read_text())
    fn = next(f for n, f in _functions(src) if n == "train_model")
    assert _params(fn) <= 7 and _own_lines(fn) <= 5
    assert callable(train_model)
