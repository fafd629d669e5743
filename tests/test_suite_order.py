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
        if prefix.startswith(conftest.NOTEBOOK_TEST):
            stem = prefix[len(conftest.NOTEBOOK_TEST):]
            assert len(list((ROOT / "notebooks").glob(stem + "*.ipynb"))) == 1, prefix
        else:
            assert rest == "", prefix  # a whole module
    # every notebook is ordered (each is a unit of work of its own)
    stems = [p[len(conftest.NOTEBOOK_TEST):] for p in conftest.LONGEST_FIRST
             if p.startswith(conftest.NOTEBOOK_TEST)]
    for nb in (ROOT / "notebooks").glob("*.ipynb"):
        assert any(nb.name.startswith(stem) for stem in stems), nb.name
