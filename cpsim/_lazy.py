"""Lazy public names for packages: ``import cpsim`` must stay fast (no Warp compile, no
torch import), so heavy names are imported on first attribute access (PEP 562)."""

from __future__ import annotations

import importlib
from typing import Any, Callable, Mapping


def lazy_exports(package: str, table: Mapping[str, str], namespace: dict[str, Any]
                 ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """Module-level ``__getattr__`` and ``__dir__`` for ``package``.

    ``table`` maps a public name to the module defining it. A name that is itself a
    submodule (``"render": "cpsim.render"``) resolves to the module unless the module
    defines an attribute of that name. Resolved values are cached in ``namespace``.
    """

    def __getattr__(name: str) -> Any:
        module = table.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        mod = importlib.import_module(module)
        is_submodule = module.endswith("." + name) and not hasattr(mod, name)
        value = mod if is_submodule else getattr(mod, name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(table))

    return __getattr__, __dir__
