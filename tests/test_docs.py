"""The documentation site builds in strict mode (a broken link or reference fails), and
the pages that are written from the code are up to date.

The build here sets `PMSMJAX_DOCS_EXECUTE=false` (read by mkdocs.yml), so mkdocs-jupyter
renders the notebooks without executing them: tests/test_notebooks.py executes every
notebook already, and `make docs` builds the site with them executed.
"""

import html
import html.parser
import os
import pathlib
import re
import shutil
import subprocess
import sys

import pytest

import pmsmjax as pj


ROOT = pathlib.Path(__file__).parents[1]
DOCS = ROOT / "docs"


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The site, built once for the tests of this module (strict, notebooks not executed)."""
    site = tmp_path_factory.mktemp("docs") / "site"
    env = dict(os.environ, PMSMJAX_DOCS_EXECUTE="false", NO_MKDOCS_2_WARNING="1")
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d",
                           str(site)], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    return site


@pytest.mark.timeout(600)
def test_docs_build_strict(site):
    # every notebook is a page (the hook adds them without editing mkdocs.yml), with
    # admonitions and the API reference rendered
    for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
        assert (site / "notebooks" / f"{nb.stem}.html").stat().st_size > 0, nb.name
    api = (site / "api" / "pmsmjax.html").read_text()
    assert "Simulate one closed-loop run" in api
    assert 'class="admonition tip"' in (site / "getting-started.html").read_text()
    assert not (ROOT / ".cache").exists()  # the build writes nothing into the repository


class _Text(html.parser.HTMLParser):
    """The text a reader sees as prose: outside code, scripts, styles and formulas."""

    SKIP = {"code", "pre", "script", "style", "math", "svg", "textarea", "title"}
    VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta",
            "source", "track", "wbr"}

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.depth, self.parts = 0, []

    def handle_starttag(self, tag, attrs):
        # a notebook code cell's source, kept as text for its copy button, is code too
        copy_text = "clipboard-copy-txt" in (dict(attrs).get("class") or "")
        if tag not in self.VOID and (self.depth or tag in self.SKIP or copy_text):
            self.depth += 1

    def handle_startendtag(self, tag, attrs):
        pass

    def handle_endtag(self, tag):
        self.depth -= self.depth > 0

    def handle_data(self, data):
        if not self.depth:
            self.parts.append(data)


def _prose(page: pathlib.Path) -> str:
    parser = _Text()
    parser.feed(page.read_text(encoding="utf-8"))
    return " ".join(parser.parts)


# LaTeX left as text: a delimiter, a `$\cmd`, `$$`, a `$x$` (`$D = $` too: arithmatex
# takes no space before a closing dollar) or a backslash command
_RAW_LATEX = re.compile(r"\\[()\[\]]|\$\$|\$\\|\\[a-zA-Z]{2,}|\$\S[^$\n]{0,60}\$")
# a resource the browser would fetch from another host (a link to read is fine)
_EXTERNAL = re.compile(
    r"<(?:script|img|iframe|source|audio|video|embed|input)\b[^>]*\bsrc\s*=\s*[\"']?"
    r"(?:https?:)?//|<link\b[^>]*\bhref\s*=\s*[\"']?(?:https?:)?//"
    r"|\bimport\s*\(?\s*[\"'](?:https?:)?//|@import\s+(?:url\()?[\"']?(?:https?:)?//"
    r"|url\(\s*[\"']?(?:https?:)?//", re.I)


@pytest.mark.timeout(600)
def test_formulas_are_rendered_and_nothing_loads_from_outside(site):
    """Every formula (Markdown pages, docstrings in the API reference, notebook markdown)
    is MathML in the built HTML, no LaTeX is left in the prose, and no page or stylesheet
    fetches anything from another host (no CDN: the site reads offline)."""
    raw, external = [], []
    for page in sorted(site.rglob("*.html")):
        name = str(page.relative_to(site))
        text = _prose(page)
        raw += [f"{name}: ...{text[max(0, m.start() - 30):m.end() + 30]!r}"
                for m in _RAW_LATEX.finditer(text)]
        source = page.read_text(encoding="utf-8")
        external += [f"{name}: {m.group(0)[:120]}" for m in _EXTERNAL.finditer(source)]
        # a command the converter did not know stays as text inside the formula
        raw += [f"{name}: {m.group(0)}" for m in re.finditer(r"<m\w+[^>]*>\\[a-zA-Z]+<",
                                                             source)]
    for sheet in sorted(site.rglob("*.css")):
        external += [f"{sheet.relative_to(site)}: {m.group(0)}"
                     for m in _EXTERNAL.finditer(sheet.read_text(encoding="utf-8"))]
    assert not raw, "LaTeX left as text:\n" + "\n".join(raw[:20])
    assert not external, "fetched from outside:\n" + "\n".join(external[:20])
    # each source of formulas renders: a Markdown page, docstrings, a notebook
    for page, least in (("firmware.html", 50), ("api/observers.html", 50),
                        ("notebooks/02_eso_observers.html", 10)):
        assert (site / page).read_text().count("<math") >= least, page
    assert 'display="block"' in (site / "api" / "observers.html").read_text()


def _hooks():
    """The site's MkDocs hooks (docs/_hooks.py) as a module."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("docs_hooks", DOCS / "_hooks.py")
    hooks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hooks)
    return hooks


_MEASURE = """<!doctype html><html><head><meta charset="utf-8"></head><body>
<iframe id="f" src="PAGE" style="width:1280px;height:900px"></iframe><pre id="r">-</pre>
<script>
document.getElementById("f").addEventListener("load", () => {
  const d = document.getElementById("f").contentDocument, w = d.defaultView;
  const maths = [...d.querySelectorAll("math")], fracs = [...d.querySelectorAll("mfrac")];
  const box = e => e.getBoundingClientRect();
  document.getElementById("r").textContent = JSON.stringify({
    math: maths.length,
    mathml: maths.filter(m => m instanceof w.MathMLElement).length,
    sized: maths.filter(m => box(m).width > 0 && box(m).height > 0).length,
    mfrac: fracs.length,
    stacked: fracs.filter(f => f.children.length == 2 &&
      box(f.children[0]).bottom <= box(f.children[1]).top + 1).length});
});
</script></body></html>"""


@pytest.mark.timeout(600)
@pytest.mark.skipif(shutil.which("chromium") is None, reason="no chromium (apt-get install "
                    "chromium); the static checks above always run")
def test_formulas_render_in_chromium(site, tmp_path):
    """In a real browser (headless Chromium) the formulas of the observers' API page are
    MathML elements with a size, and every fraction is laid out as a fraction (numerator
    above denominator), so the browser renders them, with no script. The step to look at
    the pages by eye is in getting-started.md ("Looking at it in a browser")."""
    import json

    page = tmp_path / "measure.html"
    page.write_text(_MEASURE.replace("PAGE", (site / "api" / "observers.html").as_uri()))
    proc = subprocess.run(
        ["chromium", "--headless", "--no-sandbox", "--disable-gpu",
         "--allow-file-access-from-files", f"--user-data-dir={tmp_path / 'profile'}",
         "--virtual-time-budget=10000", "--dump-dom", page.as_uri()],
        capture_output=True, text=True, timeout=300)
    m = re.search(r'<pre id="r">([^<]*)</pre>', proc.stdout)
    assert m and m.group(1) != "-", proc.stdout[-2000:] + proc.stderr[-2000:]
    n = json.loads(html.unescape(m.group(1)))
    assert n["math"] >= 100 and n["mathml"] == n["math"] and n["sized"] == n["math"], n
    assert n["mfrac"] >= 10 and n["stacked"] == n["mfrac"], n


def test_math_hook_leaves_code_alone():
    """The hook converts formulas in prose and keeps code, and `$...$` only where asked
    (notebook markdown)."""
    hooks = _hooks()
    page = (r'<p>angle \(\hat\theta &lt; \pi\)</p><pre><code>x = "\(a\)"</code></pre>'
            r"<p>cost $5 and $x_1$</p>")
    out = hooks.render_math(page)
    assert out.count("<math") == 1 and r'"\(a\)"' in out and "$x_1$" in out
    assert "&lt;" in out or "&#x0003C;" in out  # the formula's "<" is still escaped
    out = hooks.render_math(page, dollars=True)
    assert out.count("<math") == 2 and "cost $5 and" in out


# The packages whose public names the API reference documents, and their pages.
_API = {
    "pmsmjax": "pmsmjax", "pmsmjax.observers": "observers", "pmsmjax.analysis": "analysis",
    "pmsmjax.firmware": "firmware", "pmsmjax.runtime": "runtime",
    "pmsmjax.plotting": "plotting", "pmsmjax.papers": "papers", "tuning": "tuning",
    "tuning.report": "tuning", "tuning.compare": "tuning",
}


def public_names(package: str) -> list[str]:
    """A package's public names: `__all__` where it has one, else what its `__init__`
    re-exports (`from .x import Y as Y`, or a name imported from inside the project that
    the `__init__` does not use itself, as a linter's unused-import rule sees it; the
    `if TYPE_CHECKING:` block of the lazy exports included) and the functions, classes and
    constants it defines; never a name with a leading underscore."""
    import ast
    import importlib

    module = importlib.import_module(package)
    if hasattr(module, "__all__"):
        return sorted(module.__all__)
    tree = ast.parse(pathlib.Path(module.__file__).read_text(encoding="utf-8"))
    used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    names = set()

    def visit(body):
        for node in body:
            if isinstance(node, ast.If):
                visit(node.body)
            elif isinstance(node, ast.ImportFrom) and (
                    node.level or (node.module or "").split(".")[0] in ("pmsmjax", "tuning")):
                names.update(a.asname or a.name for a in node.names
                             if a.asname == a.name or (a.asname or a.name) not in used)
            elif isinstance(node, ast.FunctionDef | ast.ClassDef):
                names.add(node.name)
            elif isinstance(node, ast.Assign):
                names.update(t.id for t in node.targets if isinstance(t, ast.Name))
            elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                names.add(node.target.id)

    visit(tree.body)
    return sorted(n for n in names if not n.startswith("_"))


def test_public_names_rule():
    """The rule above finds what the packages export (and nothing of their plumbing)."""
    names = public_names("pmsmjax")
    assert {"simulate", "Drive", "ESOObserver", "analysis", "papers", "LOCK_DEG",
            "astype", "identify"} <= set(names)
    assert not {"lazy_exports", "jax", "importlib", "TYPE_CHECKING"} & set(names)
    assert {"LapackCall", "configure", "SAFE_FLAGS"} <= set(public_names("pmsmjax.runtime"))
    assert {"slowly_varying_certificate", "OperatingPoint"} <= set(
        public_names("pmsmjax.analysis"))
    for package in _API:
        module = __import__(package, fromlist=["_"])
        for name in public_names(package):
            assert hasattr(module, name), (package, name)


@pytest.mark.timeout(600)
def test_api_reference_lists_every_public_name(site):
    """Every public class, function and module of the packages in `_API` has an entry in
    the API reference (a heading with its public path, or, for a name that is also public
    elsewhere, e.g. `pmsmjax.ESOObserver`, a link from its package's page to that entry),
    and every public constant is named on its package's page: a new public name without
    a docs entry fails here."""
    import inspect
    import types

    pages = {p.stem: p.read_text(encoding="utf-8") for p in (site / "api").glob("*.html")}
    ids = {i for text in pages.values() for i in re.findall(r'\bid="([\w.]+)"', text)
           if "." in i and "._" not in i}

    resolve = _hooks().resolve
    missing = []
    for package, page in _API.items():
        module = resolve(package)
        text = pages[page]
        for name in public_names(package):
            obj, path = getattr(module, name), f"{package}.{name}"
            entry = isinstance(obj, types.ModuleType) or inspect.isclass(obj) \
                or inspect.isfunction(obj) or isinstance(obj, types.BuiltinFunctionType) \
                or callable(obj) and hasattr(obj, "__wrapped__")
            if not entry:  # a constant: an entry, or named on its package's page
                if not any(i.rsplit(".", 1)[-1] == name for i in ids) \
                        and f"<code>{name}</code>" not in text:
                    missing.append(f"{path} (constant, not named on api/{page}.md)")
                continue
            if path in ids:
                continue
            same = [i for i in ids if i.rsplit(".", 1)[-1] == name and resolve(i) is obj]
            if not any(f'href="#{i}"' in text or f'.html#{i}"' in text for i in same):
                missing.append(path + ("" if not same else f" (documented as {same[0]}, "
                                       f"but api/{page}.md does not link there)"))
    assert not missing, "public names without an API entry:\n" + "\n".join(missing)


def test_motor_file_page_lists_the_schema():
    text = (DOCS / "motor-file.md").read_text()
    for section, fields in pj.MOTOR_FILE_SCHEMA.items():
        assert (f"[{section}]" if section else "top level") in text, section
        for name, field in fields.items():
            assert f"| `{name}` | {field.unit or '-'} |" in text, (section, name)


@pytest.mark.parametrize("name", pj.PRESET_NAMES)
def test_example_motor_files_are_current(name):
    """docs/examples/NAME.toml is what `pmsmjax motor --export NAME` writes today (with a
    flux map: and NAME_flux_map.csv beside it)."""
    drive, csv = pj.preset(name), f"{name}_flux_map.csv"
    assert (DOCS / "examples" / f"{name}.toml").read_text() == pj.motor_file_text(drive, csv)
    if isinstance(drive.three_phase_motor.magnetic, pj.FluxMap):  # sampled by this machine's XLA
        fm, ref = pj.read_flux_map(DOCS / "examples" / csv), drive.three_phase_motor.magnetic
        for k in ("i_d", "i_q", "psi_d", "psi_q"):
            assert float(abs(getattr(fm, k) - getattr(ref, k)).max()) < 1e-12, k


# Patterns that point outside the repository: the design folder of the project's
# workspace, its conventions file, machine paths and references to the project's
# tickets (built by
# concatenation so that this file does not match itself).
_OUTSIDE = [
    re.compile("CONVEN" + "TIONS" + r"\.md"),
    re.compile(r"\.\./" + "shared"),
    re.compile("shared/" + "(design|papers)"),
    re.compile("/" + "work/"),
    re.compile(r"\bissue" + r"[ -]?(tracker|#?\d+)", re.I),
]
_TEXT = (".py", ".md", ".ipynb", ".toml", ".yml", ".yaml", ".cff", ".txt", ".cfg")


def test_repository_is_self_contained():
    """No file, docstring, preset note or notebook refers to anything outside the
    repository (the workspace's design documents, machine paths, tickets)."""
    bad = []
    for base in ("pmsmjax", "tuning", "tests", "docs", "notebooks", "benchmarks"):
        for path in sorted((ROOT / base).rglob("*")):
            if path.suffix in _TEXT and path.is_file() and "__pycache__" not in path.parts:
                bad += _matches(path)
    for name in ("README.md", "BENCHMARKS.md", "mkdocs.yml", "CITATION.cff",
                 "pyproject.toml", "Makefile"):
        bad += _matches(ROOT / name)
    for name in pj.PRESET_NAMES:
        bad += [f"preset {name}: {p.pattern}" for p in _OUTSIDE
                if p.search(pj.preset(name).notes)]
    assert not bad, "\n".join(bad)


def _matches(path: pathlib.Path) -> list[str]:
    text = path.read_text(encoding="utf-8", errors="replace")
    return [f"{path.relative_to(ROOT)}: {m.group(0)!r}" for p in _OUTSIDE
            for m in p.finditer(text)]


def test_log_conversion_example_runs(tmp_path, monkeypatch):
    """The Python example of docs/your-own-drive.md, step 4, converts logger b's example
    log as the command line does (tests/test_convert.py checks the two example logs
    against each other)."""
    block, = re.findall(r"```python\n(.*?)```", (DOCS / "your-own-drive.md").read_text(),
                        flags=re.S)
    (tmp_path / "docs").symlink_to(DOCS)
    monkeypatch.chdir(tmp_path)
    exec(compile(block, "your-own-drive.md", "exec"), {})
    rec = pj.load_recording(tmp_path / "recording.npz",
                            require=("t", "u_ab", "i_ab", "theta", "w_m"))
    assert rec.n == 1599 and abs(rec.T_s - 125e-6) < 1e-12  # 1600 rows, one-sample delay


def test_cli_reference_is_written_from_the_parsers():
    """docs/cli.md holds the marker the docs hook replaces; the generated reference names
    every command and every option of every parser (tune and compare included)."""
    from pmsmjax.cli._reference import MARKER, _parsers, reference_markdown

    assert MARKER in (DOCS / "cli.md").read_text()
    text = reference_markdown()
    for name, parser in _parsers().items():
        assert f"## `pmsmjax {name}`" in text, name
        for action in parser._actions:
            for opt in action.option_strings:
                if opt.startswith("--") and opt != "--help":
                    assert f"`{opt}`" in text, (name, opt)


def _slug(heading: str) -> str:
    """The anchor Python-Markdown's toc extension gives a heading."""
    text = re.sub(r"[^\w\s-]", "", heading.strip().lower())
    return re.sub(r"[-\s]+", "-", text).strip("-")


def test_glossary_defines_the_terms_and_links_resolve():
    """Every term the README uses before explaining it has a glossary entry, and every
    link from the README or a docs page into the glossary names an existing entry."""
    glossary = (DOCS / "glossary.md").read_text()
    anchors = {_slug(h) for h in re.findall(r"^#+ (.+)$", glossary, flags=re.M)}
    for term in ("ESO", "LESO", "AFO", "p.u.", "Robust loss", "Feasibility",
                 "zhang2022 (38)/(25)", "Held-out", "Lost lock", "VSD", "Floquet",
                 "Closed-loop validation", "Verdict", "Gains table"):
        assert re.search(rf"^### .*{re.escape(term)}", glossary, flags=re.M), term
    pages = [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]
    links = 0
    for page in pages:
        for anchor in re.findall(r"glossary\.md#([\w-]+)", page.read_text()):
            assert anchor in anchors, (page.name, anchor)
            links += 1
    assert links >= 10


def test_readme_is_a_front_door():
    """At most 200 lines, and its links into the repository point at files that exist
    (docs/firmware.md comes with the C export)."""
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text):
        if "://" in target or target == "docs/firmware.md":
            continue
        assert (ROOT / target).exists(), target


def test_papers_page_states_the_rotor_flux_gamma_of_the_code():
    """docs/papers.md names the gamma that `RotorFluxObserver.from_drive` uses (the paper
    gives none)."""
    from pmsmjax.observers._rotor_flux import PAPER_GAINS_PU

    m = re.search(r"\$\\gamma\$ is not given with the paper's gains: ([0-9.]+) p\.u\.",
                  (DOCS / "papers.md").read_text())
    assert m and float(m.group(1)) == PAPER_GAINS_PU["gamma"]
