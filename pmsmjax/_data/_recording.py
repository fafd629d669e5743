"""Recorded drive data: the file format read and written by `pmsmjax plant` and `replay`.

One format for data from a simulation, another tool or a real drive (docs/conventions.md,
"Recorded drive data"), stored either as NPZ (one named array each) or as CSV (one row per
sample, a header row with the names, 2-vectors split into `_a`/`_b` columns such as
`u_ab_a`, `u_ab_b`):

| name | unit | shape | meaning |
|---|---|---|---|
| `t` | s | (N,) | sampling instants t_k, uniform spacing T_s |
| `u_ab` | V | (N, 2) | stator voltage applied over [t_k, t_{k+1}) (after any delay) |
| `i_ab` | A | (N, 2) | stator current sampled at t_k |
| `theta` | rad | (N,) | electrical rotor angle at t_k (optional) |
| `w_m` | rad/s | (N,) | electrical rotor speed at t_k (optional) |
| `tau_L` | N m | (N,) | load torque over [t_k, t_{k+1}) (optional) |
| `theta_hat` | rad | (N,) | estimated electrical angle at t_k (outputs of `replay`) |
| `w_hat` | rad/s | (N,) | estimated electrical speed at t_k (outputs of `replay`) |

Other names in a file are ignored. Which arrays must be present depends on the use:
`("t", "u_ab")` to drive the plant, `("t", "u_ab", "i_ab")` to replay an observer.
"""

from __future__ import annotations

import os
import zipfile

import equinox as eqx
import numpy as np

from .._files import save_npz


#: The span (s) of the centred difference that derives a speed from a logged angle
#: (`centred_speed`) where a log has no speed: convert's layout default, identify's.
SPEED_WINDOW = 0.002


#: Every array of the format with its unit and whether it is a 2-vector, in file order.
FIELDS: dict[str, tuple[str, bool]] = {
    "t": ("s", False),
    "u_ab": ("V", True),
    "i_ab": ("A", True),
    "theta": ("rad", False),
    "w_m": ("rad/s", False),
    "tau_L": ("N m", False),
    "theta_hat": ("rad", False),
    "w_hat": ("rad/s", False),
}

#: Largest relative deviation of a sample spacing from the mean spacing T_s.
T_RTOL = 1e-6
#: Largest recording `load_recording` reads by default (bytes): 1 GiB, about 16 M samples
#: of the full set of arrays; pass `max_bytes` to read larger files.
MAX_RECORDING_BYTES = 2 ** 30

_EXTENSIONS = (".npz", ".csv")


def _where(source) -> str:
    return f"{source}: " if source else ""


def _check_array(name: str, a, n: int | None, source) -> np.ndarray:
    unit, vector = FIELDS[name]
    where = _where(source)
    a = np.asarray(a)
    if a.dtype.kind not in "biuf":
        raise ValueError(
            f"{where}`{name}` ({unit}) must be a real numeric array; got dtype {a.dtype}."
        )
    a = a.astype(float)
    n_txt = "N" if n is None else str(n)
    expected = f"({n_txt}, 2)" if vector else f"({n_txt},)"
    ok = a.ndim == (2 if vector else 1) and (not vector or a.shape[1] == 2)
    if not ok:
        kind = "a 2-vector per sample" if vector else "a scalar per sample"
        raise ValueError(
            f"{where}`{name}` ({unit}) must have shape {expected} ({kind}); got shape "
            f"{a.shape}."
        )
    if n is not None and a.shape[0] != n:
        raise ValueError(
            f"{where}`{name}` ({unit}) must have shape {expected}, the same number of "
            f"samples as `t`; got shape {a.shape}."
        )
    bad = ~np.isfinite(a)
    if np.any(bad):
        k = int(np.argwhere(bad)[0][0])
        raise ValueError(
            f"{where}`{name}` ({unit}) must be finite; sample {k} is "
            f"{np.array2string(a[k])} ({int(np.sum(np.any(bad.reshape(a.shape[0], -1), 1)))}"
            f" non-finite samples in all)."
        )
    return a


def _check_time(t: np.ndarray, source, rtol: float) -> None:
    where = _where(source)
    n = t.shape[0]
    if n < 2:
        raise ValueError(f"{where}`t` (s) needs at least 2 samples; got {n}.")
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.argmax(dt <= 0))
        raise ValueError(
            f"{where}`t` (s) must be strictly increasing; t[{k + 1}] = {float(t[k + 1])!r} is "
            f"not after t[{k}] = {float(t[k])!r}."
        )
    T_s = float(np.median(dt))
    dev = np.abs(dt - T_s)
    if np.any(dev > rtol * T_s):
        k = int(np.argmax(dev))
        raise ValueError(
            f"{where}`t` (s) must be uniformly spaced (relative tolerance {rtol:g}); the "
            f"typical spacing is T_s = {T_s!r} s but t[{k + 1}] - t[{k}] = {float(dt[k])!r} s."
        )


class RecordedData(eqx.Module):
    """Recorded drive data: sampled voltages, currents and (optionally) rotor states.

    Arrays are stored as NumPy float64 arrays; all have the same number of samples N >= 2
    and `t` is strictly increasing with uniform spacing (see the module docstring).
    Construction validates shapes, finiteness and the time axis and raises `ValueError`
    naming the array (and `source`, the file it came from, if given).

    **Arguments:**

    - `t`: sampling instants t_k (s), shape (N,).
    - `u_ab`: stator voltage over [t_k, t_{k+1}) (V, stationary frame, (N, 2)): the one
      the inverter applied, or, for a drive's own log, the one its controller commanded
      (then replay with `inverter=` / `--voltage commanded`).
    - `i_ab`: stator current sampled at t_k (A, stationary frame, (N, 2)).
    - `theta`: electrical rotor angle at t_k (rad, (N,)); optional.
    - `w_m`: electrical rotor speed at t_k (rad/s, (N,)); optional.
    - `tau_L`: load torque over [t_k, t_{k+1}) (N m, (N,)); optional.
    - `theta_hat`, `w_hat`: observer estimates at t_k (rad, rad/s, (N,)); optional.
    - `source`: where the data came from (a file name), used in error messages only.
    - `t_rtol`: tolerance on the uniformity of `t` (relative to T_s), default 1e-6.
    """

    t: np.ndarray
    u_ab: np.ndarray | None
    i_ab: np.ndarray | None
    theta: np.ndarray | None
    w_m: np.ndarray | None
    tau_L: np.ndarray | None
    theta_hat: np.ndarray | None
    w_hat: np.ndarray | None
    source: str = eqx.field(static=True, default="")

    def __init__(self, t, u_ab=None, i_ab=None, theta=None, w_m=None, tau_L=None,
                 theta_hat=None, w_hat=None, *, source="", t_rtol: float = T_RTOL):
        source = "" if source is None else str(source)
        if t is None:
            raise ValueError(f"{_where(source)}`t` (s) is required.")
        t = _check_array("t", t, None, source)
        _check_time(t, source, t_rtol)
        n = t.shape[0]
        values = dict(u_ab=u_ab, i_ab=i_ab, theta=theta, w_m=w_m, tau_L=tau_L,
                      theta_hat=theta_hat, w_hat=w_hat)
        self.t = t
        for name, value in values.items():
            setattr(self, name, None if value is None else _check_array(name, value, n,
                                                                         source))
        self.source = source

    @property
    def n(self) -> int:
        """Number of samples N."""
        return int(self.t.shape[0])

    @property
    def T_s(self) -> float:
        """Sampling period (s): the mean spacing of `t`."""
        return float((self.t[-1] - self.t[0]) / (self.n - 1))

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the arrays present, in the order of `FIELDS`."""
        return tuple(k for k in FIELDS if getattr(self, k) is not None)

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays present as a `{name: array}` dict."""
        return {k: getattr(self, k) for k in self.names}

    def require(self, names) -> RecordedData:
        """Raise `ValueError` unless every array in `names` is present; return `self`."""
        names = _check_names(names)
        missing = [k for k in names if getattr(self, k) is None]
        if missing:
            present = ", ".join(self.names)
            raise ValueError(
                f"{_where(self.source)}required array(s) missing: "
                + ", ".join(f"`{k}` ({FIELDS[k][0]})" for k in missing)
                + f"; the data has {present}."
            )
        return self

    @classmethod
    def from_trajectory(cls, traj, *, measured: bool = True, estimates: bool = False,
                        encoder_quantum: float = 0.0, speed_window: float = SPEED_WINDOW,
                        voltage_noise_std: float = 0.0, key=None) -> RecordedData:
        """The recorded-data view of one `Trajectory` from `simulate`.

        **Arguments:**

        - `traj`: an unbatched `Trajectory`.
        - `measured`: if `True` (default), `i_ab` is the current the controller measured
          (`Trajectory.i_meas_ab`, with the sensor noise and quantisation of `Sensing`),
          as a drive would log it; otherwise the true current `Trajectory.i_ab`.
        - `estimates`: also store `theta_hat`, `w_hat`.
        - `encoder_quantum`: the logged angle's resolution (rad, electrical; an encoder of
          N counts per mechanical revolution on n_p pole pairs: 2 pi n_p / N); 0 (default)
          logs the true angle and speed. Above 0 the angle is the quantised one and the
          speed is derived from it as `pmsmjax convert` derives it from an encoder
          column (`centred_speed` over `speed_window` s).
        - `voltage_noise_std`: white Gaussian noise (V) on each logged voltage component,
          as a voltage measurement adds it; needs `key` (a `jax.random` key) when > 0.

        `u_ab` is the voltage commanded over each period (after any computational delay;
        the plant's own when the inverter is ideal, `drive.inverter.u_dt` unset), `theta` the
        true angle (wrapped to (-pi, pi]) and `w_m`, `tau_L` the true speed and load.
        """
        if np.ndim(traj.t) != 1:
            raise ValueError(
                "`RecordedData.from_trajectory` needs one run; index a batched Trajectory "
                "first, e.g. `jax.tree_util.tree_map(lambda x: x[0], traj)`."
            )
        for name, v, unit in (("encoder_quantum", encoder_quantum, "rad"),
                              ("speed_window", speed_window, "s"),
                              ("voltage_noise_std", voltage_noise_std, "V")):
            if not (np.isfinite(v) and v >= 0) or (name == "speed_window" and v == 0):
                raise ValueError(f"`RecordedData.from_trajectory({name}=...)` ({unit}) must "
                                 f"be finite and {'> 0' if name == 'speed_window' else '>= 0'}"
                                 f"; got {v!r}.")
        extra = dict(theta_hat=traj.theta_hat, w_hat=traj.w_hat) if estimates else {}
        t, theta, w_m, u_ab = (np.asarray(a, float) for a in (traj.t, traj.theta, traj.w_m,
                                                               traj.u_ab))
        if encoder_quantum > 0:
            counts = np.round(np.unwrap(theta) / encoder_quantum) * encoder_quantum
            theta = np.angle(np.exp(1j * counts))
            w_m = centred_speed(counts, t, speed_window)
        if voltage_noise_std > 0:
            if key is None:
                raise ValueError("`RecordedData.from_trajectory(voltage_noise_std=...)` > 0 "
                                 "needs `key` (jax.random.PRNGKey).")
            import jax

            u_ab = u_ab + voltage_noise_std * np.asarray(jax.random.normal(key, u_ab.shape))
        return cls(t=t, u_ab=u_ab, i_ab=traj.i_meas_ab if measured else traj.i_ab,
                   theta=theta, w_m=w_m, tau_L=traj.tau_L, **extra)


def centred_speed(theta: np.ndarray, t: np.ndarray, window: float) -> np.ndarray:
    """The unwrapped angle's centred difference over `window` seconds (a shorter span at
    the ends): no delay, and an encoder's quantum divided by the span instead of one
    period (rad/s)."""
    n = t.size
    h = max(1, int(round(0.5 * window / (t[1] - t[0]))))
    k = np.arange(n)
    hi, lo = np.minimum(k + h, n - 1), np.maximum(k - h, 0)
    return (theta[hi] - theta[lo]) / (t[hi] - t[lo])


def _check_names(names) -> tuple[str, ...]:
    if isinstance(names, str):
        names = (names,)
    names = tuple(names)
    unknown = [k for k in names if k not in FIELDS]
    if unknown:
        raise ValueError(
            f"Unknown recorded-data name(s) {', '.join(map(repr, unknown))}; known names are "
            f"{', '.join(FIELDS)}."
        )
    return names


def _extension(path) -> str:
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext not in _EXTENSIONS:
        raise ValueError(
            f"{path}: unknown file extension {ext or '(none)'!r}; recorded drive data must be "
            f"'.npz' (NumPy archive) or '.csv' (comma-separated, header row)."
        )
    return ext


def _read_npz(path) -> dict[str, np.ndarray]:
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic[:2] != b"PK":  # every zip archive (and so every NPZ file) starts with "PK"
        raise ValueError(
            f"{path}: not an NPZ archive (expected a zip file of .npy arrays as written by "
            f"numpy.savez)."
        )
    try:
        archive = np.load(path, allow_pickle=False)
    except (FileNotFoundError, IsADirectoryError, PermissionError):
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"{path}: not a readable NPZ archive ({e}).") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise ValueError(
            f"{path}: holds a single array, not an NPZ archive of named arrays "
            f"({', '.join(FIELDS)})."
        )
    out = {}
    with archive:
        for name in archive.files:
            if name not in FIELDS:
                continue
            try:
                out[name] = archive[name]
            except ValueError as e:  # e.g. object arrays with allow_pickle=False
                raise ValueError(f"{path}: cannot read array `{name}` ({e}).") from None
    return out


def _read_csv(path) -> dict[str, np.ndarray]:
    with open(path, encoding="utf-8-sig") as f:
        lines = f.read().splitlines()
    # The header is the first line that is neither empty nor a '#' comment.
    body_start = None
    for k, line in enumerate(lines):
        if line.strip() and not line.lstrip().startswith("#"):
            body_start = k + 1
            break
    if body_start is None:
        raise ValueError(f"{path}: the CSV file is empty (no header row).")
    header = [h.strip() for h in lines[body_start - 1].split(",")]
    if any(not h for h in header):
        raise ValueError(f"{path}: the CSV header row has an empty column name: "
                         f"{lines[body_start - 1]!r}.")
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise ValueError(f"{path}: duplicate CSV column(s) {', '.join(dup)}.")
    numbered = [(k + 1, ln) for k, ln in enumerate(lines) if k >= body_start
                and ln.strip() and not ln.lstrip().startswith("#")]
    if not numbered:
        values = np.zeros((0, len(header)))
    else:
        try:
            values = np.loadtxt([ln for _, ln in numbered], delimiter=",", dtype=float,
                                ndmin=2)
        except ValueError:
            _locate_csv_error(path, header, numbered)
            raise
        if values.shape[1] != len(header):
            _locate_csv_error(path, header, numbered)
    col = {h: values[:, j] for j, h in enumerate(header)}
    out = {}
    for name, (unit, vector) in FIELDS.items():
        if vector:
            a, b = f"{name}_a", f"{name}_b"
            if a in col and b in col:
                out[name] = np.stack([col[a], col[b]], axis=-1)
            elif a in col or b in col:
                have, miss = (a, b) if a in col else (b, a)
                raise ValueError(
                    f"{path}: CSV column `{miss}` is missing (`{name}` ({unit}) needs both "
                    f"`{a}` and `{b}`; found only `{have}`)."
                )
            elif name in col:
                raise ValueError(
                    f"{path}: CSV column `{name}` must be split into the two components "
                    f"`{a}` and `{b}`."
                )
        elif name in col:
            out[name] = col[name]
    return out


def _locate_csv_error(path, header, numbered) -> None:
    """Raise a `ValueError` naming the first CSV line that is not `len(header)` numbers."""
    for lineno, line in numbered:
        fields = line.split(",")
        if len(fields) != len(header):
            raise ValueError(
                f"{path}: line {lineno} has {len(fields)} fields but the header names "
                f"{len(header)} columns ({', '.join(header)})."
            )
        for name, field in zip(header, fields):
            try:
                float(field)
            except ValueError:
                raise ValueError(
                    f"{path}: cannot parse the CSV data as numbers: line {lineno}, column "
                    f"`{name}` holds {field.strip()!r}."
                ) from None
    raise ValueError(f"{path}: cannot parse the CSV data as numbers.")


def load_recording(path, require=("t", "u_ab", "i_ab"), *, t_rtol: float = T_RTOL,
                   max_bytes: int = MAX_RECORDING_BYTES) -> RecordedData:
    """Read recorded drive data from an `.npz` or `.csv` file (see the module docstring).

    **Arguments:**

    - `path`: file name; the extension (`.npz` or `.csv`, any case) selects the format.
    - `require`: names of the arrays that must be present, e.g. `("t", "u_ab")` to drive
      the plant or `("t", "u_ab", "i_ab")` to replay an observer. `t` is always required.
    - `t_rtol`: tolerance on the uniformity of `t`, relative to T_s (default 1e-6).
    - `max_bytes`: refuse larger files (default `MAX_RECORDING_BYTES`, 1 GiB) instead of
      filling the memory.

    Arrays or CSV columns with other names are ignored (a drive's own extra signals, or
    an observer's outputs in `replay.npz`).

    **Returns:** a validated `RecordedData`.

    **Raises:** `FileNotFoundError` if the file does not exist; `ValueError` naming the file
    and the problem for an unknown extension, an unreadable file, a missing required array,
    a wrong shape, non-finite values, fewer than 2 samples or a time axis that is not
    strictly increasing and uniform.
    """
    require = _check_names(require)
    ext = _extension(path)
    size = os.path.getsize(path)  # FileNotFoundError for a missing file
    if size > max_bytes:
        raise ValueError(
            f"{path}: the file is {size / 2**20:.0f} MiB, above the limit of "
            f"{max_bytes / 2**20:.0f} MiB for recorded data (split the recording, or pass "
            f"`max_bytes` to pmsmjax.load_recording).")
    arrays = _read_npz(path) if ext == ".npz" else _read_csv(path)
    missing = [k for k in dict.fromkeys(("t",) + require) if k not in arrays]
    if missing:
        found = ", ".join(arrays) if arrays else "none of the known names"
        how = (" (CSV: 2-vectors as `_a`/`_b` columns, e.g. `u_ab_a`, `u_ab_b`)"
               if ext == ".csv" else "")
        raise ValueError(
            f"{path}: required array(s) missing: "
            + ", ".join(f"`{k}` ({FIELDS[k][0]})" for k in missing)
            + f"; the file has {found}{how}."
        )
    return RecordedData(**arrays, source=os.fspath(path), t_rtol=t_rtol)


def save_recording(path, data: RecordedData) -> None:
    """Write `data` to an `.npz` or `.csv` file (format chosen by the extension).

    Only the arrays present are written. CSV values are written with 17 significant
    digits, so a round trip through either format is exact.

    **Arguments:**

    - `path`: file name ending in `.npz` or `.csv`.
    - `data`: a `RecordedData`.
    """
    if not isinstance(data, RecordedData):
        raise ValueError(
            f"`save_recording(data=...)` must be a `RecordedData`; got {type(data).__name__}."
        )
    ext = _extension(path)
    arrays = data.arrays()
    if ext == ".npz":
        save_npz(path, arrays)
        return
    header, columns = [], []
    for name, a in arrays.items():
        if FIELDS[name][1]:
            header += [f"{name}_a", f"{name}_b"]
            columns += [a[:, 0], a[:, 1]]
        else:
            header.append(name)
            columns.append(a)
    np.savetxt(path, np.stack(columns, axis=-1), fmt="%.17g", delimiter=",",
               header=",".join(header), comments="")
