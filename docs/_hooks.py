"""MkDocs hooks of the documentation site (mkdocs.yml: `hooks:`).

- Every notebook in `notebooks/` becomes a page under "Notebooks" (in file-name order),
  so a new notebook appears on the site without editing mkdocs.yml; mkdocs-jupyter
  renders it (executed at build time unless `PMSMJAX_DOCS_EXECUTE=false`).
- `BENCHMARKS.md`, `CITATION.cff` and the README are read from the repository root by
  the pages that include them (pymdownx.snippets), so they exist once.
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


def on_config(config, **kwargs):
    nav = config.get("nav")
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
