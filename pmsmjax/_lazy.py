"""Lazy exports of a package: the names imported in its `if TYPE_CHECKING:` block are
loaded on first access (module `__getattr__`), so that `import pmsmjax` does not import
what a command does not use (diffrax and optimistix for the simulator and the Lyapunov
certificates: about a quarter of a second). Documentation tools and type checkers read
the same block as ordinary imports; the public API is unchanged (`pmsmjax.simulate` works
as before, `dir(pmsmjax)` lists it)."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path


def lazy_exports(package: str, init_file: str, namespace: dict, after_load=None):
    """`(__getattr__, __dir__)` for the package `package` whose `__init__` is `init_file`
    and whose globals are `namespace`: every name imported inside its `if TYPE_CHECKING:`
    block is loaded from its module when first asked for, then kept in `namespace`;
    `after_load()`, if given, runs after each such load."""
    tree = ast.parse(Path(init_file).read_text(encoding="utf-8"))
    table: dict[str, tuple[str, str | None]] = {}
    for node in tree.body:
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) \
                and node.test.id == "TYPE_CHECKING":
            for imp in node.body:
                if not isinstance(imp, ast.ImportFrom):
                    raise TypeError(f"{package}: only `from  import` in the TYPE_CHECKING "
                                    "block")
                mod = "." * imp.level + (imp.module or "")
                for a in imp.names:
                    name = a.asname or a.name
                    # `from . import sub`: the sub-package itself
                    table[name] = (mod + a.name, None) if imp.module is None else (mod, a.name)

    def __getattr__(name: str):
        spec = table.get(name)
        if spec is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        mod = importlib.import_module(spec[0], package)
        value = mod if spec[1] is None else getattr(mod, spec[1])
        namespace[name] = value
        if after_load is not None:
            after_load()
        return value

    def __dir__():
        return sorted(set(namespace) | set(table))

    return __getattr__, __dir__
