"""`pmsmjax.identify` fitting a saturation model (`fit=["saturation"]`, `pmsmjax identify
--fit saturation`): the flux-linkage plant of the fit against the package's plant, the
recovery of `ipm3k5_saturation` from a noisy closed-loop recording of the `ipm3k5_sat`
preset (a FluxMap plant: the recording and the fit share no magnetic code), the named
excitation warning on a recording that excites only i_q, and the command's files.

The recordings: sensored current control at 0.3 p.u. speed, free rotor, i_q stepping
through +-0.25..1 i_max with alternating sign, i_d stepping to -0.3, -0.9, -0.6, -0.15
i_max (or held at 0), 0.02 A current noise, 0.15 s at 10 kHz. One recording length and
one starting drive throughout, so every fit runs the same compiled programs."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tomllib

import pmsmjax as pj
from pmsmjax._data import _identify_saturation as isat
from pmsmjax._data._identify_motion import cut as _cut, simulate_segments as _simulate_segments
from pmsmjax.cli.__main__ import main as cli_main


T_REC = 0.15
NOISE = 0.005
MAX_STEPS = 40
TRUE = pj.ipm3k5_saturation()


def _recording(only_q: bool, key: int) -> pj.RecordedData:
    d = pj.preset("ipm3k5_sat")
    i_m, T = float(d.i_max), T_REC
    amps = [0.25, 0.5, 0.75, 1.0, 0.9, 0.6, 0.35, 0.8, 1.0]
    i_q = pj.Profile.steps(list(np.linspace(0, T, 11)[1:-1]),
                           [a * i_m * (-1) ** k for k, a in enumerate(amps, 1)],
                           initial=0.5 * i_m)
    # i_d held at zero with the same four steps (to zero): the same profile shape, so
    # both recordings run one compiled simulation
    i_d = pj.Profile.steps([0.15 * T, 0.35 * T, 0.55 * T, 0.75 * T],
                           np.array([-0.3, -0.9, -0.6, -0.15]) * (0.0 if only_q else i_m),
                           initial=0.0)
    tr = pj.simulate(d, pj.FOC.from_drive(d), pj.SensoredObserver(),
                     pj.Scenario(t_end=T, i_q_ref=i_q, i_d_ref=i_d), T_s=1e-4,
                     w_m0=0.3 * float(d.w_rated), sensing=pj.Sensing(noise_std=NOISE),
                     key=jax.random.PRNGKey(key))
    return pj.RecordedData.from_trajectory(tr)


@pytest.fixture(scope="module")
def start(tmp_path_factory):
    """The unsaturated drive a user would start from, 30 % off in its constants, through
    a motor file (as the command line reads it)."""
    d = pj.preset("morawiec_ipm3k5")
    m = d.motor
    d = pj.replace_params(d, L_d=1.3 * float(m.L_d), L_q=0.7 * float(m.L_q),
                          psi_f=0.9 * float(m.psi_f))
    path = tmp_path_factory.mktemp("start") / "start.toml"
    pj.save_motor_file(d, path)
    return path, pj.load_motor_file(path)


def test_flux_plant_equals_the_package_plant():
    """The fit's flux-state plant (`flux_rates`, explicit current) against `PMSM` with
    `magnetic=AlgebraicSaturation` (current state, Newton inversion every evaluation):
    the same trajectory over 20 ms of a rich voltage at speed (currents to 10 A), with
    dead time and load, the rotor's motion integrated or taken from the recording, up to
    their RK4 errors: the difference shrinks at fourth order
    with the step (measured 3.6e-8 A at two and 2.0e-9 A at four RK4 steps per 0.1 ms)."""
    d = pj.replace_params(pj.preset("morawiec_ipm3k5"), u_dt=3.0)
    d = isat.set_magnetic(d, TRUE)
    n, T_s = 200, 1e-4
    t = np.arange(n) * T_s
    u_dq = np.stack([-70 + 40 * np.sin(2 * np.pi * 170 * t),
                     125 + 40 * np.cos(2 * np.pi * 230 * t)], -1)
    th = 150.0 * t
    u_ab = np.stack([np.cos(th) * u_dq[:, 0] - np.sin(th) * u_dq[:, 1],
                     np.sin(th) * u_dq[:, 0] + np.cos(th) * u_dq[:, 1]], -1)
    rec = pj.RecordedData(t=t, u_ab=u_ab, i_ab=np.tile([-3.0, 6.0], (n, 1)), theta=th,
                          w_m=np.full(n, 150.0), tau_L=np.full(n, 5.0))
    seg = _cut(rec, n - 1)
    plant = pj.PMSM(d.motor, d.mechanics, d.inverter)
    # each pair of runs as one compiled program (run op by op, each run's start and
    # steps compiled as many small programs)
    both = jax.jit(lambda seg, k, measured: (_simulate_segments(plant, seg, k, measured),
                                             isat.simulate_segments(plant, TRUE, seg, k,
                                                                    measured)),
                   static_argnums=(1, 2))
    for measured in (False, True):  # the rotor integrated, or moving as recorded
        errs = []
        for k in (2, 4):
            (i_ref, w_ref), (i_flux, w_flux) = jax.tree_util.tree_map(
                np.asarray, both(seg, k, measured))
            errs.append(max(np.abs(i_flux - i_ref).max(), np.abs(w_flux - w_ref).max()))
        assert np.abs(i_ref).max() > 8.0  # a real excursion
        assert errs[1] < 6e-9 and errs[0] / errs[1] > 12, (measured, errs)


@pytest.fixture(scope="module")
def fitted(start):
    rec = _recording(only_q=False, key=1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = pj.identify(start[1], rec, ["saturation"], max_steps=MAX_STEPS)
    return rec, res, caught


def _flux_error(model, info):
    i_d, i_q = isat.grid(info, 11)
    cur = jnp.stack(jnp.meshgrid(jnp.asarray(i_d), jnp.asarray(i_q), indexing="ij"), -1)
    return np.abs(np.asarray(model.flux_dq(cur)) - np.asarray(TRUE.flux_dq(cur))).max()


#: Measured relative errors of the coefficients (0.005 A noise, 0.15 s, key 1).
MEASURED = dict(a_d0=8.3e-5, a_dd=3.5e-4, a_q0=1.1e-5, a_qq=1.8e-3, a_dq=7.2e-5,
                i_f=5.0e-5)


def test_recovers_the_saturation_model(fitted):
    """From a start 30 % off in L_d, L_q, psi_f with assumed saturation terms (a_qq 39x,
    a_dq 0.39x the truth), every coefficient within three times its measured error
    (`MEASURED`: a_qq, the q axis's self-saturation, trades against the cross term a_dq
    and is the least determined), and the flux over the recorded currents.

    Each shooting segment's start is fitted too, so no noisy sample enters the model as
    a state (when the segments started from the measured current, the flux started off
    by about L_q(0) x the noise, and the fit was 1.9e-4 V s off at 0.005 A, 7.9e-4 V s at
    0.02 A). Measured now: the flux over the recorded currents 1.2e-5 V s off at 0.005 A
    (4.9e-5 V s at 0.02 A), within its reported 1-sigma uncertainty (1.7e-5 V s); every
    coefficient within 0.3 of its standard deviation. The flux must be within three of
    its reported standard deviations. The deployed constants are the fitted model's
    small-current values, within 1 % of the truth's."""
    rec, res, caught = fitted
    assert not [w for w in caught if issubclass(w.category, pj.ExcitationWarning)]
    for n, lim in MEASURED.items():
        err = res.parameters[n]["value"] / float(getattr(TRUE, n)) - 1
        assert abs(err) < 3 * lim, (n, err, res.parameters[n])
        assert res.parameters[n]["std"] > 0
    info = res.saturation["currents"]
    assert info["coverage_d"] > 0.9 and info["coverage_q"] > 0.9
    flux_std = res.saturation["flux_std"]
    assert _flux_error(res.saturation["model"], info) < 3 * max(flux_std["psi_d_std_Vs"],
                                                                flux_std["psi_q_std_Vs"])
    assert 0 < res.saturation["flux_std"]["relative_to_psi_f"] < 1e-4
    assert res.drive.three_phase_motor.magnetic is res.saturation["model"]
    for got, true in zip(pj.constant_model(res.saturation["model"]), pj.constant_model(TRUE)):
        m = res.drive.three_phase_motor
        assert abs(got / true - 1) < 0.01
    m = res.drive.three_phase_motor
    assert (float(m.L_d), float(m.L_q), float(m.psi_f)) == pj.constant_model(
        res.saturation["model"])


def test_warns_on_a_recording_that_excites_only_i_q(start, fitted):
    """i_d held at zero (it moves by -1.5..0.8 A in the i_q steps' transients: 14 % of
    the range): an `ExcitationWarning` names the d axis, the range recorded and the
    range needed, and the coefficients it leaves undetermined, and only it (the q axis
    is covered); the fit's standard deviations name a_dd as weakly determined, its
    relative standard deviation 24 times that of the recording with i_d steps
    (measured: 2.3 % against 0.094 %)."""
    rec = _recording(only_q=True, key=2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = pj.identify(start[1], rec, ["saturation"], max_steps=MAX_STEPS)
    msgs = [str(w.message) for w in caught if issubclass(w.category, pj.ExcitationWarning)]
    assert len(msgs) == 1, msgs
    i_max = float(start[1].i_max)
    assert "d-axis" in msgs[0] and "a_dd" in msgs[0] and f"{-i_max:.3g}..0 A" in msgs[0]
    assert "q-axis" not in msgs[0]
    assert res.saturation["currents"]["coverage_d"] < 0.2
    assert res.saturation["currents"]["coverage_q"] > 0.9
    weak = [m for m in res.warnings if "weakly determined" in m]
    assert any(m.startswith("a_dd") for m in weak), res.warnings
    rel = [r.parameters["a_dd"]["std"] / r.parameters["a_dd"]["value"]
           for r in (res, fitted[1])]
    assert rel[0] > 8 * rel[1], rel


def test_cli_writes_saturation_table_and_flux_map(fitted, start, tmp_path):
    """`pmsmjax identify --fit saturation`: identified.toml with a `[saturation]` table
    (model = "algebraic" and exactly the keys a_d0 .. i_f, S, T, U, V, equal to the
    Python fit of the same recording), its constants the model's small-current values,
    and flux_map.csv (header i_d,i_q,psi_d,psi_q) over the recorded currents equal to
    the fitted model there."""
    rec, res, _ = fitted
    pj.save_recording(tmp_path / "rec.npz", rec)
    out = tmp_path / "out"
    rc = cli_main(["identify", "--motor-file", str(start[0]), "--data",
                   str(tmp_path / "rec.npz"), "--fit", "saturation", "--max-steps",
                   str(MAX_STEPS), "--no-plot", "--out", str(out)])
    assert rc == 0
    text = (out / "identified.toml").read_text()
    sat = tomllib.loads(text)["saturation"]
    assert list(sat) == ["model", "a_d0", "a_dd", "a_q0", "a_qq", "a_dq", "i_f",
                         "S", "T", "U", "V"]
    assert sat["model"] == "algebraic"
    model = res.saturation["model"]
    for k in list(sat)[1:]:
        assert sat[k] == pytest.approx(float(getattr(model, k)), rel=1e-9), k
    # the whole file is a motor file of the saturated machine; its constants are the
    # model's small-current values
    drive = pj.load_motor_file(out / "identified.toml")
    m = drive.three_phase_motor
    assert isinstance(m.magnetic, pj.AlgebraicSaturation)
    for k in list(sat)[1:]:
        assert float(getattr(m.magnetic, k)) == pytest.approx(sat[k], rel=1e-12), k
    assert (float(m.L_d), float(m.L_q), float(m.psi_f)) == pytest.approx(
        pj.constant_model(model), rel=1e-9)
    lines = (out / "flux_map.csv").read_text().splitlines()
    assert lines[0] == "i_d,i_q,psi_d,psi_q"
    rows = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    info = res.saturation["currents"]
    assert rows.shape == (21 * 21, 4)
    assert rows[:, 0].min() == pytest.approx(info["i_d_A"][0])
    assert rows[:, 1].max() == pytest.approx(info["i_q_A"][1])
    psi = np.asarray(model.flux_dq(jnp.asarray(rows[:, :2])))
    np.testing.assert_allclose(rows[:, 2:], psi, rtol=0, atol=1e-9)


def test_bad_saturation_fits_are_named(start):
    """Each wrong request names the argument, the value and what is allowed, before any
    fit runs."""
    d = start[1]
    n = 50
    rec = pj.RecordedData(t=np.arange(n) * 1e-4, u_ab=np.zeros((n, 2)),
                          i_ab=np.zeros((n, 2)), theta=np.zeros(n))
    cases = [
        (dict(fit=["saturation", "L_q"]), "L_q"),
        (dict(fit=["saturation"], min_coverage=1.5), "min_coverage"),
        (dict(fit=["saturation"], exponents=(4, 2, 2)), "exponents"),
        (dict(fit=["saturation"], saturation=d.motor), "saturation"),
        (dict(fit=["saturatoin"]), "saturatoin"),
    ]
    for kwargs, word in cases:
        with pytest.raises(pj.IdentifyError, match=word):
            pj.identify(d, rec, **kwargs)
    harm = pj.preset("morawiec_ipm3k5", trapezoid=0.02)
    with pytest.raises(pj.IdentifyError, match="harmonics"):
        pj.identify(harm, rec, ["saturation"])
