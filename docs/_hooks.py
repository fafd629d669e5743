"""MkDocs hooks of the documentation site (mkdocs.yml: `hooks:`).

- Every notebook in `notebooks/` becomes a page under "Notebooks" (in file-name order),
  so a new notebook appears on the site without editing mkdocs.yml; mkdocs-jupyter
  renders it (executed at build time unless `PMSMJAX_DOCS_EXECUTE=false`).
- `BENCHMARKS.md`, `CITATION.cff` and the README are read from the repository root by
  the pages that include them (pymdownx.snippets), so they exist once.
- The command-line reference in `cli.md` is written from the argparse parsers at build
  time (`pmsmjax.cli._reference`), so it cannot drift from the commands.
- `firmware.md` (the firmware page) joins the navigation after "Comparing observers"
  when it exists and mkdocs.yml does not list it yet.
"""

from __future__ import annotations

import pathlib

from mkdocs.structure.files import File, Files


ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"


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


def on_page_markdown(markdown, page, config, files, **kwargs):
    if page.file.src_uri == "cli.md":
        import sys

        if str(ROOT) not in sys.path:
            sys.path.insert(0, str(ROOT))
        from pmsmjax.cli._reference import MARKER, reference_markdown

        if MARKER not in markdown:
            raise ValueError(f"cli.md must hold the marker {MARKER}")
        markdown = markdown.replace(MARKER, reference_markdown())
    return markdown
