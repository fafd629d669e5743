"""pyproject.toml's `dependencies` and the code agree: every declared dependency is
imported by the packages the wheel ships (pmsmjax, tuning), and every third-party module
they import is declared (or comes with one that is)."""

import ast
import re
import sys
from pathlib import Path


try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib


ROOT = Path(__file__).parents[1]
PACKAGES = ("pmsmjax", "tuning")
#: distribution name -> import name, where the two differ (e.g. "pyyaml": "yaml")
IMPORT_NAMES: dict[str, str] = {}
#: modules imported without a declaration of their own: each comes with a declared one
COMES_WITH = {"jaxlib": "jax"}


def _declared() -> set[str]:
    """Import names of the distributions in `[project] dependencies`."""
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    names = set()
    for spec in deps["project"]["dependencies"]:
        dist = re.match(r"[A-Za-z0-9][A-Za-z0-9._-]*", spec).group(0).lower()
        names.add(IMPORT_NAMES.get(dist, dist.replace("-", "_").replace(".", "_")))
    return names


def _imported() -> dict[str, set[str]]:
    """Top-level modules the packages import (absolute imports, and the names given to
    `importlib.util.find_spec` / `importlib.import_module`), each with its importers."""
    found: dict[str, set[str]] = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            where = str(path.relative_to(ROOT))
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                elif (isinstance(node, ast.Call) and getattr(node.func, "attr", None)
                      in ("find_spec", "import_module") and node.args
                      and isinstance(node.args[0], ast.Constant)
                      and isinstance(node.args[0].value, str)
                      and not node.args[0].value.startswith(".")):
                    names = [node.args[0].value]
                for name in names:
                    found.setdefault(name.split(".")[0], set()).add(where)
    return found


def test_every_declared_dependency_is_imported():
    unused = sorted(_declared() - set(_imported()))
    assert not unused, (f"pyproject.toml declares {unused}, which nothing in "
                        f"{'/, '.join(PACKAGES)}/ imports: use them or drop them")


def test_every_imported_module_is_declared():
    declared = _declared()
    missing = {m: sorted(w)[:3] for m, w in _imported().items()
               if m not in sys.stdlib_module_names and m not in PACKAGES
               and m not in declared and COMES_WITH.get(m) not in declared}
    assert not missing, f"imported but not in pyproject.toml's dependencies: {missing}"
