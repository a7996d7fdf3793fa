"""Every simulator kernel's docstring says which State / StepScratch fields it reads and writes.

Each ``@wp.kernel`` of ``cpsim.kernels`` carries two docstring lines

    Reads: a, b, c, scratch.present
    Writes: x, y

naming the fields of its State parameters (bare for the parameter called ``state``, prefixed
for another one, e.g. ``dst.alive``; ``dst.*`` is every State field; ``-`` is none) and of
its :class:`cpsim.state.StepScratch` parameter (always prefixed: ``scratch.idm_accel``;
``scratch.*`` is every scratch field). The Model and Params structs are read-only inputs and
are not listed; a kernel taking any other struct fails here until this test knows it. This
test derives both sets from the source (``ast`` of the kernel and, through calls, of the
``@wp.func`` helpers it reaches, followed to any depth and resolved by name in the caller's
module) and asserts they equal the docstring's, so a new read or write fails here until the
docstring says so.

What counts, for a State or StepScratch parameter ``s`` (or a helper parameter bound to
``s`` or to one of its fields):

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
from cpsim.state import State, scratch_field_names, state_field_names

ALL_FIELDS = frozenset(state_field_names())
SCRATCH_FIELDS = frozenset(scratch_field_names())
#: The structs whose fields a docstring lists (annotation name -> fields), and the read-only ones.
LISTED_STRUCTS = {"State": ALL_FIELDS, "StepScratch": SCRATCH_FIELDS}
READ_ONLY_STRUCTS = {"ModelArrays", "Params"}


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


def _listed_struct(node: ast.expr | None) -> str | None:
    """The name of a listed struct (State, StepScratch) a parameter is annotated with, else None."""
    return node.id if isinstance(node, ast.Name) and node.id in LISTED_STRUCTS else None


def _struct_binding(kind: str, prefix: str) -> str:
    """The binding of a name that is a ``kind`` struct whose fields are reported as ``prefix + field``."""
    return f"{kind}:{prefix}"


def _helper_of(target) -> object | None:
    """The Python function of a ``@wp.func`` (anything with a plain-function ``func``)."""
    func = getattr(target, "func", None)
    return func if inspect.isfunction(func) and not isinstance(target, wp.Kernel) else None


def analyse(func, bindings: dict[str, str], out: Access, seen: set | None = None) -> Access:
    """Add to ``out`` the State fields ``func`` reads / writes.

    ``bindings``: local name -> ``"Kind:prefix."`` (the name is a State or StepScratch struct,
    ``Kind``, whose fields are reported as ``prefix + field``; see :func:`_struct_binding`) or
    ``"=label"`` (the name is the array of field ``label``)."""
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
                kind, prefix = b.split(":", 1)
                assert node.attr in LISTED_STRUCTS[kind], f"{func.__name__}: no {kind} field {node.attr!r}"
                return prefix + node.attr
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
                f"{func.__name__}: struct {node.id!r} used in a way the contract test cannot follow")
    return out


def kernel_bindings(kernel) -> dict[str, str]:
    """Parameter name -> struct binding for the kernel's State / StepScratch parameters (fields
    of the parameter ``state`` are reported bare, those of any other parameter prefixed)."""
    tree = _parse(kernel.func)
    out = {}
    for a in tree.args.args:
        kind = _listed_struct(a.annotation)
        if kind is not None:
            prefix = "" if a.arg == "state" and kind == "State" else a.arg + "."
            out[a.arg] = _struct_binding(kind, prefix)
    return out


def kernel_access(kernel) -> Access:
    """The State / StepScratch fields a kernel reads and writes (see the module docstring)."""
    return analyse(kernel.func, kernel_bindings(kernel), Access())


# ----------------------------------------------------------------------------- docstrings
_LINE = re.compile(r"^\s*(Reads|Writes):(.*)$")


def documented(kernel, func=None, required: tuple[str, ...] = ("Reads", "Writes")) -> Access:
    """The ``Reads:`` / ``Writes:`` lists of a kernel's docstring (a list may continue on
    the following more-indented lines); with ``func``, those of ``func``'s docstring (a
    launcher of the kernel: its names resolve against the kernel's parameters)."""
    func = kernel.func if func is None else func
    doc = inspect.getdoc(func) or ""
    lists: dict[str, list[str]] = {}
    current = None
    for line in doc.splitlines():
        m = _LINE.match(line)
        if m:
            current = m.group(1)
            assert current not in lists, f"{func.__name__}: two {current}: lines"
            lists[current] = [m.group(2)]
        elif current is not None and line.startswith((" ", "\t")) and line.strip():
            lists[current].append(line)
        else:
            current = None
    missing = set(required) - set(lists)
    assert not missing, f"{func.__name__}: docstring lacks the {sorted(missing)} line(s)"
    kinds = dict(b.split(":", 1)[::-1] for b in kernel_bindings(kernel).values())  # prefix -> kind
    out = Access()
    for kind, parts in lists.items():
        names = [n for n in re.split(r"[\s,]+", " ".join(parts)) if n]
        target = out.reads if kind == "Reads" else out.writes
        if names == ["-"]:
            continue
        for n in names:
            if n.endswith("*"):
                struct = kinds.get(n[:-1])
                assert struct is not None, f"{func.__name__}: {n!r} names no State / StepScratch parameter"
                target.update(n[:-1] + f for f in LISTED_STRUCTS[struct])
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
def test_every_struct_parameter_is_listed_or_read_only(kernel):
    """A kernel's struct parameters are State / StepScratch (whose fields the docstring lists;
    the scratch one is called ``scratch``) or the read-only Model / Params: a new struct fails
    here until this test knows whether its fields must be listed."""
    name = kernel.func.__name__
    for arg in _parse(kernel.func).args.args:
        ann = arg.annotation
        if not isinstance(ann, ast.Name):
            continue
        if isinstance(kernel.func.__globals__.get(ann.id), type(State)):
            assert ann.id in LISTED_STRUCTS or ann.id in READ_ONLY_STRUCTS, f"{name}: unknown struct {ann.id}"
        if ann.id == "StepScratch":
            assert arg.arg == "scratch", f"{name}: the StepScratch parameter is called {arg.arg!r}"


def test_scratch_is_apart_from_the_state():
    """StepScratch shares no field name with State (a bare docstring name is a State field)."""
    assert not (ALL_FIELDS & SCRATCH_FIELDS)
    assert {"present", "idm_accel"} <= SCRATCH_FIELDS


#: The kernels of a step in launch order (``Simulator._record_step_launches``; on CPU the
#: per-world variants of the events / observation kernels).
STEP_ORDER = [("idm_kernel",), ("dynamics_kernel",), ("prepare_kernel",), ("events_kernel", "events_world_kernel"),
              ("finish_kernel",), ("observation_kernel", "observation_world_kernel")]


def test_every_scratch_read_of_a_step_follows_its_write_in_the_same_step():
    """Scratch is never carried between steps: each scratch field a step kernel reads is
    written by an earlier kernel of the same step, and neither reset nor the world copies
    (snapshot / restore) touch scratch."""
    by_name = {k.func.__name__: k for k in KERNELS}
    written: set[str] = set()
    for stage in STEP_ORDER:
        stage_writes: set[str] = set()
        for name in stage:
            got = kernel_access(by_name[name])
            reads = {f for f in got.reads if f.startswith("scratch.")}
            assert reads <= written, f"{name}: reads scratch {sorted(reads - written)} no earlier kernel writes"
            stage_writes |= {f for f in got.writes if f.startswith("scratch.")}
        written |= stage_writes
    assert written == {"scratch." + f for f in SCRATCH_FIELDS}
    for name in ("reset_kernel", "copy_worlds_kernel"):
        assert not any(b.startswith("StepScratch:") for b in kernel_bindings(by_name[name]).values()), name


@pytest.mark.parametrize("kernel", KERNELS, ids=[k.func.__name__ for k in KERNELS])
def test_docstring_lists_the_state_fields_the_kernel_reads_and_writes(kernel):
    got, doc = kernel_access(kernel), documented(kernel)
    name = kernel.func.__name__
    assert got.writes == doc.writes, (
        f"{name}: Writes: undocumented {sorted(got.writes - doc.writes)}, not written {sorted(doc.writes - got.writes)}")
    assert got.reads == doc.reads, (
        f"{name}: Reads: undocumented {sorted(got.reads - doc.reads)}, not read {sorted(doc.reads - got.reads)}")


# ----------------------------------------------------------------------------- launchers
def simulator_launchers() -> list:
    """The ``launch_*`` functions of ``cpsim.kernels`` (marked by ``cpsim.kernels.common.launcher``)."""
    found = []
    for info in pkgutil.iter_modules(cpsim.kernels.__path__):
        module = importlib.import_module(f"cpsim.kernels.{info.name}")
        for obj in vars(module).values():
            if inspect.isfunction(obj) and hasattr(obj, "kernels") and obj.__module__ == module.__name__:
                found.append(obj)
    return sorted(found, key=lambda f: f.__qualname__)


LAUNCHERS = simulator_launchers()


def _is_array_annotation(node: ast.expr | None) -> bool:
    """``wp.array(...)``, ``wp.array2d(...)``, ...: an array parameter of a kernel."""
    return isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr.startswith("array")


def written_array_parameters(kernel) -> set[str]:
    """The kernel's array parameters it writes (directly or through helpers)."""
    tree = _parse(kernel.func)
    bindings = kernel_bindings(kernel)
    bindings.update({a.arg: "=@" + a.arg for a in tree.args.args if _is_array_annotation(a.annotation)})
    got = analyse(kernel.func, bindings, Access())
    return {w[1:] for w in got.writes if w.startswith("@")}


def launched_arguments(launcher) -> tuple[list[str], list[str]]:
    """The names a launcher passes as ``inputs`` and ``outputs`` (its one call of
    ``cpsim.kernels.common.launch(kernel, kernels, dim, inputs, outputs=None, ...)``)."""
    calls = [n for n in ast.walk(_parse(launcher)) if isinstance(n, ast.Call)
             and isinstance(n.func, ast.Name) and n.func.id == "launch"]
    assert len(calls) == 1, f"{launcher.__name__}: expected one launch(...) call"
    call = calls[0]

    def names(node: ast.expr | None) -> list[str]:
        if node is None:
            return []
        assert isinstance(node, ast.List), f"{launcher.__name__}: inputs / outputs must be list literals"
        out = []
        for e in node.elts:
            if isinstance(e, ast.Call) and isinstance(e.func, ast.Name) and e.func.id in ("int", "float"):
                e = e.args[0]  # a scalar converted for Warp
            assert isinstance(e, ast.Name), f"{launcher.__name__}: pass parameters by name, got {ast.unparse(e)}"
            out.append(e.id)
        return out

    outputs = call.args[4] if len(call.args) > 4 else next((k.value for k in call.keywords if k.arg == "outputs"), None)
    return names(call.args[3]), names(outputs)


def test_every_kernel_has_one_launcher_beside_it():
    for kernel in KERNELS:
        owners = [f.__name__ for f in LAUNCHERS if any(k is kernel for k in f.kernels)]
        assert len(owners) == 1, f"{kernel.func.__name__}: launchers {owners}"
    for f in LAUNCHERS:
        for kernel in f.kernels:
            assert kernel.func.__module__ == f.__module__, f"{f.__name__}: {kernel.func.__name__} lives elsewhere"


@pytest.mark.parametrize("launcher", LAUNCHERS, ids=[f.__name__ for f in LAUNCHERS])
def test_launcher_passes_the_kernel_parameters_in_order_and_the_written_arrays_as_outputs(launcher):
    """inputs + outputs are the kernel's parameters in order; outputs are exactly the array
    parameters the kernel writes; the launcher's ``Writes:`` line equals the kernel's."""
    inputs, outputs = launched_arguments(launcher)
    own = list(inspect.signature(launcher).parameters)
    assert set(inputs + outputs) <= set(own), f"{launcher.__name__}: passes names it does not take"
    for kernel in launcher.kernels:
        name = kernel.func.__name__
        assert inputs + outputs == list(inspect.signature(kernel.func).parameters), name
        assert set(outputs) == written_array_parameters(kernel), name
        assert documented(kernel, launcher, ("Writes",)).writes == documented(kernel).writes, (
            f"{launcher.__name__}: its Writes: line differs from {name}'s")


def test_written_arrays_are_found():
    by_name = {k.func.__name__: k for k in KERNELS}
    assert written_array_parameters(by_name["prepare_kernel"]) == {
        "trig", "prev_trig", "present_idx", "tracked_idx", "roster_n", "radius"}
    assert written_array_parameters(by_name["observation_kernel"]) == {"obs", "sel_idx", "sel_d2", "obs_clear",
                                                                       "filled"}
    assert written_array_parameters(by_name["events_kernel"]) == set()


def test_simulator_launches_kernels_only_through_launchers():
    import cpsim.model
    import cpsim.simulator

    for module in (cpsim.simulator, cpsim.model):
        assert "wp.launch(" not in inspect.getsource(module), module.__name__


# ----------------------------------------------------------------------------- the analysis itself
class _FakeFunction:
    """A stand-in @wp.func for the self-test (the analysis uses only ``func``)."""

    def __init__(self, func):
        self.func = func


def _helper(arr, s, w: int):
    arr[w, 0] = s.pos[w, 0]
    s.goal[w, 0] = s.goal[w, 0]


def _scratch_helper(sc, w: int):
    sc.idm_accel[w, 0] = float(sc.present[w, 1])


def _kernel(state, scratch, w: int):
    state.alive[w, 0] = True
    state.jerk[w, 0] += 1.0
    wp.atomic_add(state.steps_alive, w, 0, 1)
    n = state.speed.shape[1] + scratch.present.shape[1]
    alias = state.finished
    alias[w, 0] = n > 0
    helper(state.reward, state, w)  # noqa: F821 (resolved from the globals below)
    if scratch.present[w, 0]:
        scratch_helper(scratch, w)  # noqa: F821


def test_the_analysis_finds_direct_augmented_atomic_aliased_and_helper_accesses():
    _kernel.__globals__["helper"] = _FakeFunction(_helper)
    _kernel.__globals__["scratch_helper"] = _FakeFunction(_scratch_helper)
    try:
        got = analyse(_kernel, {"state": _struct_binding("State", ""),
                                "scratch": _struct_binding("StepScratch", "scratch.")}, Access())
    finally:
        del _kernel.__globals__["helper"], _kernel.__globals__["scratch_helper"]
    assert got.writes == {"alive", "jerk", "steps_alive", "finished", "reward", "goal", "scratch.idm_accel"}
    # not speed: .shape only
    assert got.reads == {"jerk", "steps_alive", "pos", "goal", "scratch.present"}


def test_the_analysis_rejects_a_field_of_the_wrong_struct():
    def bad(state, scratch, w: int):
        scratch.alive[w, 0] = state.present[w, 0]

    with pytest.raises(AssertionError, match="no StepScratch field 'alive'"):
        analyse(bad, {"state": _struct_binding("State", ""),
                      "scratch": _struct_binding("StepScratch", "scratch.")}, Access())
