"""The code's structure, read from its own imports: rooms that hold one idea stay that way.

Module-level imports only (an import inside a function is a deliberate late binding, such
as an observer's analysis hook, and runs after every module has loaded).
"""

import ast
from pathlib import Path

import pytest


ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pmsmjax", "tuning")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(p.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = p
    return out


MODULES = _modules()


def _is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def _top_level_imports(name: str) -> set[str]:
    """The project modules `name` imports at module level (its `if TYPE_CHECKING:` block
    left out: those names load lazily)."""
    tree = ast.parse(MODULES[name].read_text(encoding="utf-8"))
    base = name.split(".") if _is_package(name) else name.split(".")[:-1]
    found = set()

    def add(target: str):
        # `from pkg import sub` may name a submodule, else the package itself
        while target and target not in MODULES:
            target = target.rpartition(".")[0]
        if target and target != name:
            found.add(target)

    def visit(body):
        for node in body:
            if isinstance(node, ast.If) and isinstance(node.test, ast.Name) \
                    and node.test.id == "TYPE_CHECKING":
                continue
            if isinstance(node, ast.Import):
                for a in node.names:
                    add(a.name)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    mod = ".".join(base[: len(base) - node.level + 1] + (
                        [node.module] if node.module else []))
                else:
                    mod = node.module or ""
                for a in node.names:
                    add(f"{mod}.{a.name}")
            elif isinstance(node, ast.If | ast.Try):
                visit(node.body)
                visit(getattr(node, "orelse", []))

    visit(tree.body)
    return found


def test_the_module_level_imports_have_no_cycle():
    graph = {m: _top_level_imports(m) for m in MODULES}
    # a package's __init__ importing its own submodules is how it re-exports them
    graph = {m: {d for d in deps if not d.startswith(m + ".")} for m, deps in graph.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycle = stack[stack.index(d):] + [d]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_the_library_core_never_imports_the_tuner_or_matplotlib():
    """`tuning` imports `pmsmjax`, never the reverse; plotting stays out of the core (the
    figures live in `pmsmjax.plotting` and next to their papers; the command line, which
    writes them, loads them on demand)."""
    for m in MODULES:
        if not m.startswith("pmsmjax"):
            continue
        tops = {n.split(".")[0] for n in _absolute_imports(MODULES[m])}
        assert "tuning" not in tops, m
        if not (m.startswith(("pmsmjax.plotting", "pmsmjax.cli")) or m.endswith("_plots")):
            assert "matplotlib" not in tops, m


def _absolute_imports(path: Path) -> set[str]:
    """Every absolute module name `path` imports, anywhere in it."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names.add(node.module)
    return names


def test_rooms_stay_small():
    """The package root holds at most 12 modules; no module is over 800 lines and at most
    three are over 600 (one idea that needs the room)."""
    root = [p for p in (ROOT / "pmsmjax").glob("*.py")]
    assert len(root) <= 12, sorted(p.name for p in root)
    sizes = {m: len(p.read_text(encoding="utf-8").splitlines()) for m, p in MODULES.items()}
    assert max(sizes.values()) <= 800, max(sizes, key=sizes.get)
    assert sum(n > 600 for n in sizes.values()) <= 3, sorted(
        m for m, n in sizes.items() if n > 600)


def test_the_cycle_check_sees_a_cycle(tmp_path, monkeypatch):
    """The cycle test can fail: two modules that import each other at module level."""
    (tmp_path / "a.py").write_text("from ._cycle_b import x\n")
    (tmp_path / "b.py").write_text("import pmsmjax._cycle_a\nx = 1\n")
    monkeypatch.setitem(MODULES, "pmsmjax._cycle_a", tmp_path / "a.py")
    monkeypatch.setitem(MODULES, "pmsmjax._cycle_b", tmp_path / "b.py")
    assert _top_level_imports("pmsmjax._cycle_a") == {"pmsmjax._cycle_b"}
    with pytest.raises(pytest.fail.Exception, match="import cycle"):
        test_the_module_level_imports_have_no_cycle()


def _project_imports(path: Path):
    """Every `from pmsmjax... import name` / `from tuning... import name` in `path`, at any
    depth (inside functions too: the benchmarks import late), and in string constants
    that are Python code (the scripts the benchmarks run in child processes), as
    (module, name)."""
    yield from _imports_in(ast.parse(path.read_text(encoding="utf-8")))


def _imports_in(tree):
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and not node.level and node.module \
                and node.module.split(".")[0] in PACKAGES:
            for a in node.names:
                yield node.module, a.name
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) \
                and "import " in node.value and "\n" in node.value:
            try:
                inner = ast.parse(node.value)
            except SyntaxError:  # prose, or a template that is not Python as it stands
                continue
            yield from _imports_in(inner)


def _resolves(module: str, name: str) -> bool:
    import importlib

    try:
        m = importlib.import_module(module)
    except ImportError:
        return False
    if name == "*" or hasattr(m, name):
        return True
    try:
        importlib.import_module(f"{module}.{name}")
    except ImportError:
        return False
    return True


def test_the_scripts_import_what_exists():
    """Every name the benchmarks, the tuner and the docs' scripts import from the library
    exists there, late imports inside functions included (a moved private module broke
    the benchmarks' JSON output unnoticed: `pmsmjax._data._files`)."""
    files = [p for d in ("benchmarks", "tuning", "docs") for p in sorted((ROOT / d).rglob("*.py"))]
    assert len(files) > 30
    missing = [(str(p.relative_to(ROOT)), m, n) for p in files for m, n in _project_imports(p)
               if not _resolves(m, n)]
    assert not missing, missing


def test_the_import_check_sees_a_missing_name(tmp_path):
    script = tmp_path / "s.py"
    child = 'CHILD = """\nimport sys\nfrom pmsmjax.cli._options import drive_from_args\n"""\n'
    script.write_text("def f():\n    from pmsmjax._data._files import json_text\n" + child)
    assert [(m, n) for m, n in _project_imports(script) if not _resolves(m, n)] == [
        ("pmsmjax._data._files", "json_text"), ("pmsmjax.cli._options", "drive_from_args")]
