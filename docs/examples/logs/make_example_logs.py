"""Write the two example logger CSVs of docs/your-own-drive.md (step 4) and their layouts.

One simulated run of the 750 W drive (the zhang750 preset with a 3 V inverter dead time,
as a drive on a dyno: speed held at 0.3 p.u., q current 0.3 of the current limit, current
noise 0.02 A, a 4096-count encoder), logged as two loggers would:

- `logger_a.csv`: `;`-separated, time in ms, phases a and b in A, duty cycles a, b, c in
  percent (min-max common mode) with the DC-bus voltage (311 V with a 100 Hz ripple), the
  mechanical encoder angle in degrees with a 12.3 deg mounting offset.
- `logger_b.csv`: time in us, three phase currents as 12-bit converter counts (zero at
  2048, 0.01 A per count), the alpha-beta voltage references the firmware computed (one
  sample before they apply), encoder counts counting against the phase sequence, rpm.

It also writes the guide's figure of logger a's conversion (docs/figures/convert_logger_a.png,
the figure `pmsmjax convert` writes). Run from the repository root:
`python docs/examples/logs/make_example_logs.py`.
"""

import math
import pathlib

import jax
import numpy as np

import pmsmjax as pj


HERE = pathlib.Path(__file__).parent
T_S = 125e-6
OFFSET_MECH_DEG = 12.3


def inverse_clarke(x_ab):
    a = x_ab[:, 0]
    b = -0.5 * x_ab[:, 0] + math.sqrt(3) / 2 * x_ab[:, 1]
    return np.stack([a, b, -a - b], axis=1)


def write(path, columns, delimiter, digits):
    names = list(columns)
    rows = np.stack([np.asarray(columns[n], float) for n in names], axis=1)
    with open(path, "w") as f:
        f.write(delimiter.join(names) + "\n")
        for r in rows:
            f.write(delimiter.join(f"{v:.{d}f}" for v, d in zip(r, digits)) + "\n")


def main():
    drive = pj.replace_params(pj.preset("zhang750"), u_dt=3.0)
    n_p, w = float(drive.motor.n_p), 0.3 * float(drive.w_rated)
    sc = pj.Scenario(t_end=0.2, i_d_ref=pj.Profile.constant(0.0),
                     i_q_ref=pj.Profile.constant(0.3 * float(drive.i_max)),
                     w_m_imposed=pj.Profile.constant(w))
    lsb = 2 * math.pi / 4096 * n_p
    run = pj.simulate(drive, pj.FOC.from_drive(drive), pj.SensoredObserver(), sc, T_s=T_S,
                      w_m0=w, sensing=pj.Sensing(noise_std=0.02, encoder_quantum=lsb),
                      key=jax.random.PRNGKey(7))
    t = np.asarray(run.t)
    u_ab, i_ab = np.asarray(run.u_ab), np.asarray(run.i_meas_ab)
    theta = np.unwrap(np.asarray(run.theta))
    theta_enc = np.round(theta / lsb) * lsb  # what a 4096-count encoder reads
    # logger a
    u_dc = 311.0 + 3.0 * np.sin(2 * np.pi * 100 * t)
    v = inverse_clarke(u_ab)
    v = v - 0.5 * (v.max(axis=1, keepdims=True) + v.min(axis=1, keepdims=True)) \
        + 0.5 * u_dc[:, None]
    i3 = inverse_clarke(i_ab)
    write(HERE / "logger_a.csv",
          {"time_ms": 1e3 * t, "ia": i3[:, 0], "ib": i3[:, 1],
           "da": 100 * v[:, 0] / u_dc, "db": 100 * v[:, 1] / u_dc, "dc": 100 * v[:, 2] / u_dc,
           "vbus": u_dc,
           "enc_deg": np.degrees(theta_enc / n_p) % 360 + OFFSET_MECH_DEG},
          ";", (3, 4, 4, 5, 5, 5, 2, 4))
    # logger b
    counts = np.clip(np.round(2048 + inverse_clarke(i_ab) / 0.01), 0, 4095)
    u_log = np.vstack([u_ab[1:], u_ab[-1:]])  # row k: the voltage applied from t_{k+1}
    enc = np.round(-theta_enc / n_p / (2 * np.pi) * 4096) % 4096
    write(HERE / "logger_b.csv",
          {"t_us": 1e6 * t, "adc_a": counts[:, 0], "adc_b": counts[:, 1],
           "adc_c": counts[:, 2], "v_alpha": u_log[:, 0], "v_beta": u_log[:, 1],
           "enc": enc, "rpm": np.asarray(run.w_m) / n_p * 60 / (2 * np.pi)},
          ",", (1, 0, 0, 0, 3, 3, 0, 2))
    # the guide's figure: what `pmsmjax convert` shows of logger a
    from pmsmjax.plotting import plot_recording

    res = pj.convert_log(HERE / "logger_a.csv", pj.load_log_layout(HERE / "logger_a.toml"),
                         drive=pj.preset("zhang750"))
    plot_recording(res.data, title="logger_a.csv converted", t_window=0.1).savefig(
        HERE.parents[1] / "figures" / "convert_logger_a.png", dpi=80)


if __name__ == "__main__":
    main()
