"""MkDocs hooks of the documentation site (mkdocs.yml: `hooks:`).

- Every notebook in `notebooks/` becomes a page under "Notebooks" (in file-name order),
  so a new notebook appears on the site without editing mkdocs.yml; mkdocs-jupyter
  renders it (executed at build time unless `PMSMJAX_DOCS_EXECUTE=false`).
- `BENCHMARKS.md`, `CITATION.cff` and the README are read from the repository root by
  the pages that include them (pymdownx.snippets), so they exist once.
- An API page's `<!-- module docstring: pmsmjax.X.Y -->` line becomes the docstring of
  the module that defines the public object `pmsmjax.X.Y` (see `_module_docstrings`).
- The command-line reference in `cli.md` is written from the argparse parsers at build
  time (`pmsmjax.cli._reference`), so it cannot drift from the commands.
- `firmware.md` (the firmware page) joins the navigation after "Comparing observers"
  when it exists and mkdocs.yml does not list it yet.
- Formulas are rendered at build time: every LaTeX formula of a page (Markdown `\\( \\)`,
  `$ $`, `$$ $$` through pymdownx.arithmatex, docstrings through mkdocstrings, notebook
  markdown cells' `$ $` and `$$ $$`) becomes MathML (latex2mathml), which browsers draw
  without any script; the notebook pages' MathJax and Mermaid loaders (both from a CDN)
  are removed, so the site loads nothing from outside. A formula latex2mathml cannot
  convert is a warning, which fails the strict build.
"""

from __future__ import annotations

import html
import logging
import pathlib
import re

from mkdocs.structure.files import File, Files


ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
log = logging.getLogger("mkdocs.hooks.pmsmjax")


def _notebooks() -> list[pathlib.Path]:
    return sorted(NOTEBOOKS.glob("*.ipynb"))


def _title(path: pathlib.Path) -> str:
    stem = path.stem
    number, _, rest = stem.partition("_")
    words = rest.replace("_", " ") if number.isdigit() else stem.replace("_", " ")
    return f"{number} {words}" if number.isdigit() else words


def _in_nav(nav, page: str) -> bool:
    for item in nav:
        value = next(iter(item.values())) if isinstance(item, dict) else item
        if value == page or (isinstance(value, list) and _in_nav(value, page)):
            return True
    return False


def on_config(config, **kwargs):
    nav = config.get("nav")
    if nav is not None and (ROOT / "docs" / "firmware.md").is_file() \
            and not _in_nav(nav, "firmware.md"):
        at = next((i + 1 for i, item in enumerate(nav) if isinstance(item, dict)
                   and "comparison.md" in item.values()), len(nav))
        nav.insert(at, {"Firmware": "firmware.md"})
    if nav is not None:
        entries = [{_title(p): f"notebooks/{p.name}"} for p in _notebooks()]
        for item in nav:
            if isinstance(item, dict) and "Notebooks" in item:
                item["Notebooks"] = list(item["Notebooks"] or []) + entries
                break
        else:
            nav.append({"Notebooks": entries})
    return config


def on_files(files, config, **kwargs):
    # hooks run after the plugins: mkdocs-jupyter wraps the notebooks added here itself
    added = Files([File(f"notebooks/{p.name}", str(ROOT), config["site_dir"],
                        config["use_directory_urls"]) for p in _notebooks()])
    for f in config.plugins["mkdocs-jupyter"].on_files(added, config):
        files.append(f)
    return files


def _import_root():
    import sys

    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))


# `<!-- module docstring: pmsmjax.observers.RotorFluxObserver -->` in an API page: the
# notes of the module that defines that public object (model, notation, equations). The
# module is found at build time, so the page names public objects only and a private
# module may move.
_MODULE_DOC = re.compile(r"^<!-- module docstring: ([\w.]+) -->$", re.M)


def resolve(path: str):
    """The object named by a dotted path (`pmsmjax.observers.ESOObserver`; None where an
    attribute is missing): the longest importable module prefix, then attributes."""
    import importlib

    _import_root()
    parts = path.split(".")
    for n in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:n]))
        except ImportError:
            continue
        for attr in parts[n:]:
            obj = getattr(obj, attr, None)
        return obj
    raise ImportError(path)


def _defining_module(public: str) -> str:
    return resolve(public).__module__


def _module_docstrings(markdown: str) -> str:
    return _MODULE_DOC.sub(lambda m: f"::: {_defining_module(m.group(1))}\n"
                                     "    options:\n      show_root_heading: false\n"
                                     "      show_root_toc_entry: false\n"
                                     "      members: false\n", markdown)


def on_page_markdown(markdown, page, config, files, **kwargs):
    if page.file.src_uri.startswith("api/"):
        markdown = _module_docstrings(markdown)
    if page.file.src_uri == "cli.md":
        _import_root()
        from pmsmjax.cli._reference import MARKER, reference_markdown

        if MARKER not in markdown:
            raise ValueError(f"cli.md must hold the marker {MARKER}")
        markdown = markdown.replace(MARKER, reference_markdown())
    return markdown


# ---------------------------------------------------------------------------------------
# Formulas: LaTeX -> MathML at build time (no script, no CDN).
# ---------------------------------------------------------------------------------------

# elements whose text is never mathematics: code, scripts, styles, formulas already drawn
# (everything inside one of them is skipped)
_SKIP = {"code", "pre", "script", "style", "math", "svg", "textarea", "kbd", "samp",
         "title"}
_TAG = re.compile(r"<!--.*?-->|<(/?)([a-zA-Z][\w:-]*)((?:[^>\"']|\"[^\"]*\"|'[^']*')*)>",
                  re.S)
# a notebook code cell's source kept as text for the copy button
_COPY_TEXT = "clipboard-copy-txt"
_VOID = {"area", "base", "br", "col", "embed", "hr", "img", "input", "link", "meta",
         "source", "track", "wbr"}
# display first (`$$` before `$`); `\( \)`, `\[ \]` are arithmatex's output
_DISPLAY = re.compile(r"\\\[(.+?)\\\]|\$\$(.+?)\$\$", re.S)
_INLINE = re.compile(r"\\\((.+?)\\\)", re.S)
# a notebook's `$x$`: no space just inside the dollars
_DOLLAR = re.compile(r"(?<![\\$])\$(?=\S)([^$]+?)(?<=\S)\$", re.S)
# the notebook template's loaders: an empty MathJax script, its configuration, and a
# module that imports Mermaid from a CDN when a cell holds a diagram
_NB_LOADERS = [
    re.compile(r"<!-- Load mathjax -->\s*<script[^>]*>\s*</script>", re.S),
    re.compile(r"<!-- MathJax configuration -->.*?<!-- End of mathjax configuration -->",
               re.S),
    re.compile(r"<script type=\"module\">(?:(?!</script>).)*?mermaid(?:(?!</script>).)*?"
               r"</script>", re.S),
]


# standard LaTeX operator names latex2mathml does not know, as the operators they are
_OPERATORS = re.compile(r"\\(arg)(?![a-zA-Z])")
# a command latex2mathml passed through as text (`<mi>\foo</mi>`): not rendered
_UNKNOWN = re.compile(r">\\[a-zA-Z]+<")


def _mathml(latex: str, display: bool, where: str) -> str | None:
    from latex2mathml.converter import convert

    tex = _OPERATORS.sub(r"\\operatorname{\1}", html.unescape(latex).strip())
    try:
        out = convert(tex, display="block" if display else "inline")
    except Exception as e:  # noqa: BLE001 - any failure: report the formula, keep its text
        log.warning("%s: formula not converted to MathML (%s): %s", where, e, latex)
        return None
    if _UNKNOWN.search(out):
        log.warning("%s: formula with a command latex2mathml does not know: %s", where, latex)
    return out


def _render_text(text: str, dollars: bool, where: str) -> str:
    def sub(display):
        def one(m):
            latex = next(g for g in m.groups() if g is not None)
            out = _mathml(latex, display, where)
            return m.group(0) if out is None else out
        return one

    text = _DISPLAY.sub(sub(True), text)
    text = _INLINE.sub(sub(False), text)
    if dollars:
        text = _DOLLAR.sub(sub(False), text)
    return text


def render_math(page_html: str, dollars: bool = False, where: str = "") -> str:
    """`page_html` with every formula in its text (outside code, scripts, styles) as
    MathML; `dollars`: `$...$` is a formula too (notebook markdown)."""
    out, pos, skip = [], 0, []
    for m in _TAG.finditer(page_html):
        text = page_html[pos:m.start()]
        out.append(text if skip or not text.strip() else _render_text(text, dollars, where))
        out.append(m.group(0))
        pos = m.end()
        closing, name = m.group(1), (m.group(2) or "").lower()
        if not name or name in _VOID or m.group(0).endswith("/>"):
            continue
        if closing:
            if skip:
                skip.pop()
        elif skip or name in _SKIP or _COPY_TEXT in (m.group(3) or ""):
            skip.append(name)
    tail = page_html[pos:]
    out.append(tail if skip else _render_text(tail, dollars, where))
    return "".join(out)


def on_post_page(html_text, page, config, **kwargs):
    # the whole page: a notebook's headings are in its table of contents too
    notebook = page.file.src_uri.endswith(".ipynb")
    if notebook:
        for pattern in _NB_LOADERS:
            html_text = pattern.sub("", html_text)
    return render_math(html_text, dollars=notebook, where=page.file.src_uri)
