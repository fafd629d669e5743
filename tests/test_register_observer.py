"""`pmsmjax.observers.register_observer`: an observer class of one's own becomes a name
for `make_observer`, `observer_names`, `observer_class` and the command line's
`--observer NAME`.

The observer registered here is a minimal one written in this file: it reads the encoder
and reports the angle shifted by a design parameter `offset` (rad), with the encoder
angle as an extra output. Its angle error theta - theta_hat is therefore `offset` at
every sample, in closed form; that is what the closed-loop run through the command line
is checked against (and the extra against the trajectory's own rotor angle). Bad
registrations raise `ValueError` naming what is wrong. A fixture restores the registry
after every test, so the other tests see the built-in observers only.
"""

import json
import math
from typing import ClassVar

import jax.numpy as jnp
import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax.cli.__main__ import main
from pmsmjax.observers import (
    AbstractObserver,
    ErrorCoordinates,
    Estimate,
    _registry,
    make_observer,
    observer_class,
    observer_names,
    register_observer,
)

from .helpers import motor_numbers, read_npz


DRIVE = pj.preset("zhang750")


class OffsetEncoder(AbstractObserver):
    """The encoder angle less `offset` (rad); the encoder speed."""

    motor: pj.PMSMParams
    offset: float = 0.1
    coordinates: ClassVar[ErrorCoordinates] = ErrorCoordinates(("theta",), ("rad",), 0)
    design_units: ClassVar[dict] = {"offset": "rad, the angle subtracted from the encoder's"}
    extras: ClassVar[dict] = {"theta_enc": "rad, the encoder angle"}

    def init(self, theta0=0.0, w0=0.0):
        del theta0, w0
        return ()

    def step(self, state, meas, T_s):
        del T_s
        th = jnp.arctan2(jnp.sin(meas.theta - self.offset), jnp.cos(meas.theta - self.offset))
        return state, Estimate(theta_hat=th, w_hat=meas.w_m,
                               extras={"theta_enc": meas.theta})

    @classmethod
    def from_drive(cls, drive, *, motor=None, **design):
        obs = cls(motor=drive.three_phase_motor if motor is None else motor)
        return obs.with_design(**design) if design else obs

    def design_parameters(self):
        return {"offset": self.offset}

    def with_design(self, **values):
        self._check_design_names(values)
        return self._replace(**values)

    # the angle error is the constant offset: d(theta - theta_hat)/dt = w - w = 0
    def error_rhs(self, x, op, plant):
        return jnp.zeros_like(x)

    def error_scale(self, op, plant):
        return jnp.ones(1)

    def error_state(self, state, truth, plant):
        return jnp.array([self.offset])

    def observer_state(self, x, truth, plant):
        return ()


@pytest.fixture
def registry():
    """The registry as it was, restored after the test."""
    saved = dict(_registry._REGISTRY)
    yield
    _registry._REGISTRY.clear()
    _registry._REGISTRY.update(saved)
    assert observer_names() == tuple(saved)


def test_registered_class_is_available_by_name(registry):
    before = observer_names()
    assert "offset-encoder" not in before
    assert register_observer("Offset-Encoder", OffsetEncoder) is OffsetEncoder
    # names are lower case, appended in registration order
    assert observer_names() == before + ("offset-encoder",)
    assert observer_class("OFFSET-ENCODER") is OffsetEncoder
    obs = make_observer("offset-encoder", DRIVE, offset=0.25)
    assert isinstance(obs, OffsetEncoder) and obs.offset == 0.25
    assert motor_numbers(obs.motor) == motor_numbers(DRIVE.motor)
    m_hat = pj.replace_params(DRIVE, L_q=3e-3).motor
    assert motor_numbers(make_observer("offset-encoder", DRIVE, motor=m_hat).motor) == \
        motor_numbers(m_hat)
    with pytest.raises(ValueError, match="unknown design parameter.*gain"):
        make_observer("offset-encoder", DRIVE, gain=1.0)
    # an unknown name lists the registered ones, the new one included
    with pytest.raises(ValueError, match="offset-encoder"):
        make_observer("no-such-observer", DRIVE)


def test_decorator_and_re_registration(registry):
    @register_observer("deco-encoder")
    class DecoEncoder(OffsetEncoder):
        pass

    assert observer_class("deco-encoder") is DecoEncoder
    # documented: registering a name again replaces the class, the name stays once
    register_observer("deco-encoder", OffsetEncoder)
    assert observer_class("deco-encoder") is OffsetEncoder
    assert observer_names().count("deco-encoder") == 1


@pytest.mark.parametrize("bad", [object, OffsetEncoder(motor=DRIVE.motor), print,
                                 "OffsetEncoder", pj.PMSMParams])
def test_registering_a_non_observer_is_refused(registry, bad):
    before = observer_names()
    with pytest.raises(ValueError, match="needs an `AbstractObserver` subclass"):
        register_observer("bad-one", bad)
    with pytest.raises(ValueError, match="'bad-one'"):
        register_observer("bad-one")(bad)
    assert observer_names() == before  # nothing half-registered


def test_command_line_runs_a_registered_observer(registry, tmp_path, capsys):
    register_observer("offset-encoder", OffsetEncoder)
    offset = 0.2
    assert main(["simulate", "--observer", "offset-encoder", "--gain", f"offset={offset}",
                 "--startup", "none", "--scenario", "ramp", "--t-end", "0.05",
                 "--no-plot", "--out", str(tmp_path)]) == 0
    assert "observer offset-encoder, offset = 0.2" in capsys.readouterr().out
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["observer"] == "offset-encoder"
    assert summary["observer_details"]["class"] == "OffsetEncoder"
    assert summary["observer_details"]["design"]["offset"] == offset
    traj = read_npz(tmp_path / "trajectory.npz")
    assert traj["t"].shape == (400,)  # 0.05 s at the default 125 us
    # the closed-form angle error: theta - (theta - offset), wrapped, at every sample
    np.testing.assert_allclose(traj["theta_err"], offset, rtol=0, atol=1e-12)
    np.testing.assert_allclose(traj["theta_hat"],
                               np.angle(np.exp(1j * (traj["theta"] - offset))),
                               rtol=0, atol=1e-12)
    # the extra arrives under its name: the encoder angle, i.e. the rotor angle
    np.testing.assert_allclose(np.angle(np.exp(1j * (traj["theta_enc"] - traj["theta"]))),
                               0.0, rtol=0, atol=1e-12)
    # the summary's angle-error statistics: both the constant offset in degrees
    assert summary["angle_error_deg"]["rms"] == pytest.approx(math.degrees(offset),
                                                              rel=1e-9)
    assert summary["angle_error_deg"]["max_abs"] == pytest.approx(math.degrees(offset),
                                                                  rel=1e-9)
    # the drive moved (the frame offset only costs torque, cos 0.2 = 0.98)
    assert traj["w_m"][-1] > 0.5 * traj["w_m_ref"][-1] > 0

    # a design parameter it does not have: exit status 2, the message names it
    assert main(["simulate", "--observer", "offset-encoder", "--gain", "w2=300",
                 "--no-plot", "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err
    assert "--gain w2=300" in err and "offset-encoder" in err and "offset" in err


def test_command_line_without_the_registration(registry, tmp_path, capsys):
    """The command line reads the registry when it runs: unregistered, the name is an
    invalid choice (exit status 2, the name in the message)."""
    assert "offset-encoder" not in observer_names()
    assert main(["simulate", "--observer", "offset-encoder", "--no-plot", "--out",
                 str(tmp_path)]) == 2
    assert "invalid choice: 'offset-encoder'" in capsys.readouterr().err
