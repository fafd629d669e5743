"""`pmsmjax.plotting`: figures for one run, a vmapped batch and a plant trace."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from matplotlib.figure import Figure

import pmsmjax as pj
from pmsmjax.plotting import plot_plant_trace, plot_trajectory


T_S = 125e-6


@pytest.fixture(scope="module")
def setup():
    drive = pj.preset("zhang750")
    foc = pj.FOC.from_drive(drive)
    scenario = pj.Scenario(t_end=0.02, w_m_ref=pj.Profile.ramp(0.0, 0.02, 0.0, 100.0))
    return drive, foc, scenario


def test_plot_one_run(setup, tmp_path):
    drive, foc, scenario = setup
    traj = pj.simulate(drive, foc, pj.SensoredObserver(), scenario, T_s=T_S)
    fig = plot_trajectory(traj, drive, title="one run")
    assert isinstance(fig, Figure)
    assert len(fig.axes) == 5
    assert fig.axes[-1].get_xlabel() == "time (s)"
    assert [ax.get_ylabel() for ax in fig.axes] == [
        "speed (p.u.)", "torque (p.u.)", "current (p.u.)", "voltage (p.u.)",
        "angle error (deg)"]
    # speed is drawn in p.u. of the rated speed
    line = fig.axes[0].get_lines()[1]
    np.testing.assert_allclose(line.get_ydata(), np.asarray(traj.w_m) / drive.w_rated)
    fig.savefig(tmp_path / "one.png")
    # drawing into the same figure overlays instead of adding axes
    n_lines = len(fig.axes[0].get_lines())
    assert plot_trajectory(traj, drive, fig=fig) is fig
    assert len(fig.axes) == 5 and len(fig.axes[0].get_lines()) == 2 * n_lines


def test_plot_batch(setup, tmp_path):
    drive, foc, scenario = setup
    Js = jnp.array([0.5, 1.0, 2.0]) * drive.mechanics.J

    @jax.vmap
    def run(J):
        d = eqx.tree_at(lambda d: d.mechanics.J, drive, J)
        return pj.simulate(d, foc, pj.SensoredObserver(), scenario, T_s=T_S, throw=False)

    batch = run(Js)
    fig = plot_trajectory(batch, drive, labels=[f"J = {float(J):.2e}" for J in Js])
    speed_lines = [ln for ln in fig.axes[0].get_lines() if ln.get_label().startswith("J =")]
    assert len(speed_lines) == 3
    fig.savefig(tmp_path / "batch.png")
    with pytest.raises(ValueError, match="one label per run"):
        plot_trajectory(batch, drive, labels=["a"])
    with pytest.raises(ValueError, match=r"single \(unbatched\) `Drive`"):
        plot_trajectory(batch, eqx.tree_at(lambda d: d.w_rated, drive, jnp.ones(3)))


def test_plot_plant_trace(tmp_path):
    drive = pj.preset("zhang750")
    n = 200
    t = np.arange(n) * T_S
    data = pj.RecordedData(t=t, u_ab=np.tile([5.0, 0.0], (n, 1)), theta=np.zeros(n))
    trace = pj.run_plant(drive, data.t, data.u_ab, n_substeps=1)
    fig = plot_plant_trace(trace, drive, data=data)
    assert len(fig.axes) == 6  # voltage, i_ab, i_dq, speed, torque, angle difference
    fig.savefig(tmp_path / "plant.png")
    assert len(plot_plant_trace(trace, drive).axes) == 4
