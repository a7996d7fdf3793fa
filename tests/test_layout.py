"""The package layout: no import cycles, every moved module still importable under its old
path (shipped checkpoints and user code pickle or import class paths), and every shipped
checkpoint loads and acts."""

from __future__ import annotations

import importlib
import re

import numpy as np
import pytest

from tests.import_cycles import ROOT, cycles, graph

_BASELINES = {"spiced": ("spiced", "reference"), "cl4ad": ("cl4ad", "curriculum"), "dapo": ("dapo",),
              "vineppo": ("vineppo",), "plannerrft": ("plannerrft", "policies"), "craft": ("craft", "proxy")}

#: old module path -> where it lives now (the old path is the same module)
MOVED_MODULES = {
    "cpalgo.common.continuations": "cpalgo.baselines.continuations",
    "cpalgo.common.baseline_registry": "cpalgo.baselines.registry",
    **{f"cpalgo.{pkg}.{mod}": f"cpalgo.baselines.{pkg}.{mod}" for pkg, mods in _BASELINES.items() for mod in mods},
    "cpalgo.pretrain": "cpalgo.anchor.imitation",
    "cpalgo.teacher_ppo": "cpalgo.anchor.teacher_ppo",
    "cpalgo.compress": "cpalgo.anchor.compress",
    "cpalgo.selfplay_eval": "cpalgo.anchor.outcomes",
}
#: old package path -> new package (the old one forwards its names)
MOVED_PACKAGES = {f"cpalgo.{pkg}": f"cpalgo.baselines.{pkg}" for pkg in _BASELINES}
#: new packages whose lazy names must all resolve
PACKAGES = ("cpalgo.baselines", "cpalgo.traffic", "cpalgo.anchor")
#: old module path -> new module: the old one re-exports the public names of the new one
REEXPORTS = {
    "cpalgo.bc": "cpalgo.traffic.bc",
}


def test_no_import_cycles():
    found = cycles(graph(ROOT))
    assert len(found) == 0, f"import cycles (run python tests/import_cycles.py): {found}"


#: Writers that still replace files by themselves (outside the layout's reach).
KNOWN_OWN_WRITERS = {"cpsim/bench.py"}


def test_one_atomic_writer():
    """Files and folders are replaced atomically by :mod:`cpsim.atomic` only; everything
    else writes through it."""
    pattern = re.compile(r"\bos\.(replace|rename)\(|\bmk[sd]temp\(")
    own = {str(p.relative_to(ROOT)) for pkg in ("cpalgo", "cpsim") for p in (ROOT / pkg).rglob("*.py")
           if pattern.search(p.read_text())}
    assert own - KNOWN_OWN_WRITERS == {"cpsim/atomic.py"}


@pytest.mark.parametrize("old", sorted(MOVED_MODULES))
def test_moved_module_keeps_its_old_path(old):
    assert importlib.import_module(old) is importlib.import_module(MOVED_MODULES[old])


@pytest.mark.parametrize("old", sorted(MOVED_PACKAGES))
def test_moved_package_forwards_its_names(old):
    before, after = importlib.import_module(old), importlib.import_module(MOVED_PACKAGES[old])
    assert after.__all__
    for name in after.__all__:
        assert getattr(before, name) is getattr(after, name), name


@pytest.mark.parametrize("package", PACKAGES)
def test_new_packages_resolve_every_name(package):
    pkg = importlib.import_module(package)
    for name in getattr(pkg, "__all__", ()):
        assert getattr(pkg, name) is not None, name


@pytest.mark.parametrize("old", sorted(REEXPORTS))
def test_reexport_shim_has_every_public_name(old):
    before, after = importlib.import_module(old), importlib.import_module(REEXPORTS[old])
    public = [n for n in vars(after) if not n.startswith("_")]
    assert public
    for name in public:
        assert getattr(before, name) is getattr(after, name), name


def test_methods_registry_still_lists_the_six_baselines():
    from cpalgo.methods import get_method, method_names

    names = method_names()
    for name in ("spiced", "cl4ad", "dapo", "vineppo", "plannerrft", "craft"):
        assert name in names
        assert get_method(name).resolve().__module__ == f"cpalgo.baselines.{name}.{name}"


def _shipped_checkpoints() -> list[str]:
    from cpalgo.recipes import shipped_names

    return [n for n in shipped_names() if n.endswith((".zip", ".pt"))]


def test_the_shipped_checkpoints_are_found():
    assert {"anchor.zip", "anchor_imitation.zip", "anchor_fast.zip", "bc_traffic.pt"} <= set(_shipped_checkpoints())


@pytest.mark.parametrize("name", _shipped_checkpoints())
def test_every_shipped_checkpoint_loads_and_acts(name):
    """Each shipped model loads with the loader the commands use (the class paths it
    pickled still import) and maps an observation to a valid action."""
    pytest.importorskip("torch")
    from cpalgo.evaluate.runner import load_model
    from cpalgo.recipes import shipped_path

    model = load_model(shipped_path(name), "checkpoint")
    if name.endswith(".pt"):
        obs_size, num_actions = model.obs_size, model.num_actions
    else:
        obs_size, num_actions = model.observation_space.shape[0], model.action_space.n
    actions, _ = model.predict(np.zeros((3, obs_size), np.float32), None, np.ones(3, bool), deterministic=True)
    actions = np.asarray(actions).reshape(-1)
    assert actions.shape == (3,) and np.all((actions >= 0) & (actions < num_actions))
