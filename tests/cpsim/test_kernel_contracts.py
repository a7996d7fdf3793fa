"""Every simulator kernel's docstring says which State fields it reads and writes.

Each ``@wp.kernel`` of ``cpsim.kernels`` carries two docstring lines

    Reads: a, b, c
    Writes: x, y

naming the fields of its State parameter (bare for the parameter called ``state``, prefixed
for another one, e.g. ``dst.alive``; ``dst.*`` is every State field; ``-`` is none). The
Model and Params structs are read-only inputs and are not listed. This test derives both
sets from the source (``ast`` of the kernel and, through calls, of the ``@wp.func`` helpers
it reaches, followed to any depth and resolved by name in the caller's module) and asserts
they equal the docstring's, so a new read or write fails here until the docstring says so.

What counts, for a State parameter ``s`` (or a helper parameter bound to ``s`` or to one
of its fields):

* write: ``s.f[...] = v``, ``s.f[...] += v`` (also a read), ``wp.atomic_*(s.f, ...)``
  (also a read), a helper writing the array ``s.f`` was passed as;
* read: any other use of ``s.f``, except ``s.f.shape`` (layout, not data).
"""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
import re
import textwrap
from dataclasses import dataclass, field

import pytest
import warp as wp

import cpsim.kernels
from cpsim.state import state_field_names

ALL_FIELDS = frozenset(state_field_names())


# ----------------------------------------------------------------------------- analysis
@dataclass
class Access:
    reads: set[str] = field(default_factory=set)
    writes: set[str] = field(default_factory=set)


def _parse(func) -> ast.FunctionDef:
    tree = ast.parse(textwrap.dedent(inspect.getsource(func)))
    node = tree.body[0]
    assert isinstance(node, ast.FunctionDef), func
    return node


def _is_state_annotation(node: ast.expr | None) -> bool:
    return isinstance(node, ast.Name) and node.id == "State"


def _helper_of(target) -> object | None:
    """The Python function of a ``@wp.func`` (anything with a plain-function ``func``)."""
    func = getattr(target, "func", None)
    return func if inspect.isfunction(func) and not isinstance(target, wp.Kernel) else None


def analyse(func, bindings: dict[str, str], out: Access, seen: set | None = None) -> Access:
    """Add to ``out`` the State fields ``func`` reads / writes.

    ``bindings``: local name -> ``"prefix."`` (the name is a State struct whose fields are
    reported as ``prefix + field``) or ``"=label"`` (the name is the array of field
    ``label``)."""
    seen = set() if seen is None else seen
    key = (func, tuple(sorted(bindings.items())))
    if key in seen:
        return out
    seen.add(key)
    tree = _parse(func)
    env = func.__globals__
    bound = dict(bindings)
    parent = {id(c): p for p in ast.walk(tree) for c in ast.iter_child_nodes(p)}

    def label_of(node: ast.expr) -> str | None:
        """The field label of an expression that is a whole State field array, else None."""
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            b = bound.get(node.value.id)
            if b is not None and not b.startswith("="):
                assert node.attr in ALL_FIELDS, f"{func.__name__}: no State field {node.attr!r}"
                return b + node.attr
        if isinstance(node, ast.Name):
            b = bound.get(node.id)
            if b is not None and b.startswith("="):
                return b[1:]
        return None

    def struct_of(node: ast.expr) -> str | None:
        if isinstance(node, ast.Name):
            b = bound.get(node.id)
            if b is not None and not b.startswith("="):
                return b
        return None

    # local aliases of whole fields (``arr = state.alive``), flow-insensitive
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            lab = label_of(node.value)
            if lab is not None:
                bound[node.targets[0].id] = "=" + lab

    handled: set[int] = set()  # ids of nodes already accounted for

    for node in ast.walk(tree):
        if isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Store):
            lab = label_of(node.value)
            if lab is not None:
                out.writes.add(lab)
                handled.add(id(node.value))
        elif isinstance(node, ast.AugAssign) and isinstance(node.target, ast.Subscript):
            lab = label_of(node.target.value)
            if lab is not None:
                out.reads.add(lab)  # the Store above records the write
        elif isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name) \
                and label_of(node.value) is not None:
            handled.add(id(node.value))  # an alias, not a read
        elif isinstance(node, ast.Attribute) and node.attr == "shape" and label_of(node.value) is not None:
            handled.add(id(node.value))  # layout, not data
        elif isinstance(node, ast.Call):
            callee = node.func
            if isinstance(callee, ast.Attribute) and isinstance(callee.value, ast.Name) \
                    and callee.value.id == "wp" and callee.attr.startswith("atomic_") and node.args:
                lab = label_of(node.args[0])
                if lab is not None:
                    out.reads.add(lab)
                    out.writes.add(lab)
                    handled.add(id(node.args[0]))
                continue
            target = env.get(callee.id) if isinstance(callee, ast.Name) else None
            passes = [(i, a) for i, a in enumerate(node.args) if label_of(a) is not None or struct_of(a) is not None]
            passes += [(k.arg, k.value) for k in node.keywords
                       if label_of(k.value) is not None or struct_of(k.value) is not None]
            if not passes:
                continue
            helper = _helper_of(target)
            assert helper is not None, (
                f"{func.__name__}: State data passed to {ast.unparse(callee)}, which is no @wp.func of "
                f"this module's namespace: teach tests/cpsim/test_kernel_contracts.py about it")
            params = list(inspect.signature(helper).parameters)
            sub: dict[str, str] = {}
            for where, arg in passes:
                name = params[where] if isinstance(where, int) else where
                lab = label_of(arg)
                sub[name] = "=" + lab if lab is not None else struct_of(arg)
                handled.add(id(arg))
            analyse(helper, sub, out, seen)

    for node in ast.walk(tree):
        if id(node) in handled or not isinstance(getattr(node, "ctx", None), ast.Load):
            continue
        lab = label_of(node)
        if lab is not None:
            out.reads.add(lab)
        elif struct_of(node) is not None and isinstance(node, ast.Name):
            # the struct itself used other than through a field or a helper call
            assert isinstance(parent.get(id(node)), ast.Attribute), (
                f"{func.__name__}: State struct {node.id!r} used in a way the contract test cannot follow")
    return out


def kernel_access(kernel) -> Access:
    """The State fields a kernel reads and writes (see the module docstring)."""
    tree = _parse(kernel.func)
    bindings = {a.arg: ("" if a.arg == "state" else a.arg + ".")
                for a in tree.args.args if _is_state_annotation(a.annotation)}
    return analyse(kernel.func, bindings, Access())


# ----------------------------------------------------------------------------- docstrings
_LINE = re.compile(r"^\s*(Reads|Writes):(.*)$")


def documented(kernel) -> Access:
    """The ``Reads:`` / ``Writes:`` lists of a kernel's docstring (a list may continue on
    the following more-indented lines)."""
    doc = inspect.getdoc(kernel.func) or ""
    lists: dict[str, list[str]] = {}
    current = None
    for line in doc.splitlines():
        m = _LINE.match(line)
        if m:
            current = m.group(1)
            assert current not in lists, f"{kernel.func.__name__}: two {current}: lines"
            lists[current] = [m.group(2)]
        elif current is not None and line.startswith((" ", "\t")) and line.strip():
            lists[current].append(line)
        else:
            current = None
    missing = {"Reads", "Writes"} - set(lists)
    assert not missing, f"{kernel.func.__name__}: docstring lacks the {sorted(missing)} line(s)"
    out = Access()
    for kind, parts in lists.items():
        names = [n for n in re.split(r"[\s,]+", " ".join(parts)) if n]
        target = out.reads if kind == "Reads" else out.writes
        if names == ["-"]:
            continue
        for n in names:
            if n.endswith("*"):
                target.update(n[:-1] + f for f in ALL_FIELDS)
            else:
                target.add(n)
    return out


def simulator_kernels() -> list:
    found = []
    for info in pkgutil.iter_modules(cpsim.kernels.__path__):
        module = importlib.import_module(f"cpsim.kernels.{info.name}")
        for obj in vars(module).values():
            if isinstance(obj, wp.Kernel) and obj.func.__module__ == module.__name__:
                found.append(obj)
    return sorted(found, key=lambda k: k.func.__qualname__)


KERNELS = simulator_kernels()


def test_every_simulator_kernel_is_checked():
    names = {k.func.__name__ for k in KERNELS}
    assert {"dynamics_kernel", "events_kernel", "events_world_kernel", "reset_kernel", "copy_worlds_kernel",
            "observation_kernel", "finish_kernel", "idm_kernel"} <= names, names


@pytest.mark.parametrize("kernel", KERNELS, ids=[k.func.__name__ for k in KERNELS])
def test_docstring_lists_the_state_fields_the_kernel_reads_and_writes(kernel):
    got, doc = kernel_access(kernel), documented(kernel)
    name = kernel.func.__name__
    assert got.writes == doc.writes, (
        f"{name}: Writes: undocumented {sorted(got.writes - doc.writes)}, not written {sorted(doc.writes - got.writes)}")
    assert got.reads == doc.reads, (
        f"{name}: Reads: undocumented {sorted(got.reads - doc.reads)}, not read {sorted(doc.reads - got.reads)}")


# ----------------------------------------------------------------------------- the analysis itself
class _FakeFunction:
    """A stand-in @wp.func for the self-test (the analysis uses only ``func``)."""

    def __init__(self, func):
        self.func = func


def _helper(arr, s, w: int):
    arr[w, 0] = s.pos[w, 0]
    s.goal[w, 0] = s.goal[w, 0]


def _kernel(state, w: int):
    state.alive[w, 0] = True
    state.jerk[w, 0] += 1.0
    wp.atomic_add(state.steps_alive, w, 0, 1)
    n = state.speed.shape[1]
    alias = state.finished
    alias[w, 0] = n > 0
    helper(state.reward, state, w)  # noqa: F821 (resolved from the globals below)


def test_the_analysis_finds_direct_augmented_atomic_aliased_and_helper_accesses():
    _kernel.__globals__["helper"] = _FakeFunction(_helper)
    try:
        got = analyse(_kernel, {"state": ""}, Access())
    finally:
        del _kernel.__globals__["helper"]
    assert got.writes == {"alive", "jerk", "steps_alive", "finished", "reward", "goal"}
    assert got.reads == {"jerk", "steps_alive", "pos", "goal"}  # not speed: .shape only
