"""The work order of the suite's two workers (tests/conftest.py) names modules and
notebooks that exist, so that a renamed one cannot silently fall back to the end."""

import pathlib

from . import conftest


ROOT = pathlib.Path(__file__).parents[1]


def test_the_work_order_names_existing_modules_and_notebooks():
    seen = set()
    for prefix in conftest.LONGEST_FIRST:
        assert prefix not in seen, prefix
        seen.add(prefix)
        path, _, rest = prefix.partition("::")
        assert (ROOT / path).is_file(), prefix
        if rest:
            assert rest.startswith("test_notebook_runs["), prefix
            stem = rest[len("test_notebook_runs["):]
            assert len(list((ROOT / "notebooks").glob(stem + "*.ipynb"))) == 1, prefix
    # every notebook is ordered (each is a unit of work of its own)
    for nb in (ROOT / "notebooks").glob("*.ipynb"):
        assert any(nb.name.startswith(p.split("[", 1)[1]) for p in conftest.LONGEST_FIRST
                   if "[" in p), nb.name
