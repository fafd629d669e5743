"""The tuner's design space is read from the observer classes alone: a class's own tuning
coordinates map to its design and back, and no observer is special-cased by name."""

import math
import pathlib
import re

import pytest

import pmsmjax as pj
import tuning as tg
from pmsmjax.observers import make_observer, observer_class, observer_names


@pytest.mark.parametrize("name", observer_names())
def test_tuning_coordinates_map_to_the_design_and_back(name):
    cls = observer_class(name)
    drive = pj.preset(cls.paper_motor or "zhang750")
    design = make_observer(name, drive).design_parameters()
    own = {k: float(design[k]) for k in cls.tuning_replaces}
    coords = cls.tuning_from_design(own, drive)
    assert set(coords) == set(own) - set(cls.tuning_replaces) | set(cls.tuning_coordinates)
    back = cls.design_from_tuning(coords, drive)
    assert back.keys() == own.keys()
    assert all(math.isclose(back[k], own[k], rel_tol=1e-12) for k in own)
    for lo, hi, start, why in cls.tunable_bounds.values():
        assert 0 < lo < start < hi and why


def test_the_parallel_model_searches_its_tracking_filter_in_physical_terms():
    """stumper's tracking filter s^2 + v2 s + v1: bandwidth sqrt(v1), damping
    v2 / (2 sqrt(v1)); the paper's v1 = 16000 1/s^2, v2 = 253 1/s."""
    space = tg.DesignSpace(tg.TuningProblem.quick(observer="parallel-model"))
    c = {x.name: x for x in space.coordinates}
    assert math.isclose(c["w_tf"].paper, math.sqrt(16000.0), rel_tol=1e-12)
    assert math.isclose(c["zeta_tf"].paper, 253.0 / (2 * math.sqrt(16000.0)), rel_tol=1e-12)
    assert (c["w_tf"].kind, c["zeta_tf"].kind) == ("tracking", "damping")
    d = space.design(space.paper_point())
    assert math.isclose(float(d["v1"]), 16000.0, rel_tol=1e-12)
    assert math.isclose(float(d["v2"]), 253.0, rel_tol=1e-12)


def test_no_observer_is_named_in_the_design_space():
    src = (pathlib.Path(__file__).parents[1] / "tuning" / "design_space.py").read_text()
    code = re.sub(r'""".*?"""', "", src, flags=re.S)  # docstrings may cite papers
    for name in observer_names():
        assert f'"{name}"' not in code, name
