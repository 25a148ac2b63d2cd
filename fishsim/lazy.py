"""Package namespaces that import their submodules on first use (PEP 562).

A package ``__init__`` that re-exports its torch-heavy submodules imports torch for anyone who
imports one light submodule of it, e.g. a config dataclass that ``fishsim.config`` assembles for
a command's ``--help``. With ``__getattr__, __all__ = exports(__name__, {...})`` the package's
names stay the same (``from fishsim.solid import SolidModel``) and each submodule is imported
when one of its names is first asked for.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib import import_module
from typing import Any


def exports(package: str, names: dict[str, tuple[str, ...]]) -> tuple[Callable[[str], Any], list[str]]:
    """The module ``__getattr__`` and ``__all__`` of ``package``, which re-exports ``names``
    ({submodule: its names}). Other names raise AttributeError, so ``from package import
    submodule`` still imports the submodule."""
    where = {name: module for module, exported in names.items() for name in exported}

    def __getattr__(name: str) -> Any:
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(import_module(f"{package}.{where[name]}"), name)

    return __getattr__, sorted(where)
