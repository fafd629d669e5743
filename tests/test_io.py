"""Recorded drive data: round trips through NPZ and CSV, and every malformed-file case."""

import re

import numpy as np
import pytest

import pmsmjax as pj


N = 50
T_S = 125e-6


def full_data(rng=None):
    rng = np.random.default_rng(0) if rng is None else rng
    return pj.RecordedData(
        t=np.arange(N) * T_S,
        u_ab=rng.normal(size=(N, 2)) * 100.0,
        i_ab=rng.normal(size=(N, 2)),
        theta=rng.uniform(-np.pi, np.pi, size=N),
        w_m=rng.normal(size=N) * 500.0,
        tau_L=rng.normal(size=N),
        theta_hat=rng.uniform(-np.pi, np.pi, size=N),
        w_hat=rng.normal(size=N) * 500.0,
    )


def write_csv(path, header, rows):
    lines = [",".join(header)] + [",".join(str(v) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def plant_columns(n=N, t=None):
    """Header and rows of a minimal valid plant-input CSV (t, u_ab)."""
    t = np.arange(n) * T_S if t is None else t
    return ["t", "u_ab_a", "u_ab_b"], [[repr(float(tk)), 1.0, -1.0] for tk in t]


def raises(path, *fragments):
    """pytest.raises for a ValueError whose message names the file and every fragment."""
    pattern = re.escape(str(path)) + ".*" + ".*".join(re.escape(f) for f in fragments)
    return pytest.raises(ValueError, match=pattern)


# --- round trips ---------------------------------------------------------------------

@pytest.mark.parametrize("ext", [".npz", ".csv", ".NPZ", ".Csv"])
def test_round_trip_all_arrays(tmp_path, ext):
    data = full_data()
    path = tmp_path / f"rec{ext}"
    pj.save_recording(path, data)
    back = pj.load_recording(path, require=tuple(data.names))
    assert back.names == data.names == ("t", "u_ab", "i_ab", "theta", "w_m", "tau_L",
                                        "theta_hat", "w_hat")
    for name in data.names:
        # 17 significant digits in CSV: the round trip is exact in float64
        np.testing.assert_array_equal(getattr(back, name), getattr(data, name))
    assert back.source == str(path)
    assert back.n == N
    assert back.T_s == pytest.approx(T_S, rel=1e-12)


@pytest.mark.parametrize("ext", [".npz", ".csv"])
def test_round_trip_optional_arrays_absent(tmp_path, ext):
    full = full_data()
    data = pj.RecordedData(t=full.t, u_ab=full.u_ab)
    path = tmp_path / f"plant_in{ext}"
    pj.save_recording(path, data)
    back = pj.load_recording(path, require=("t", "u_ab"))
    assert back.names == ("t", "u_ab")
    assert back.i_ab is None and back.theta is None and back.tau_L is None
    np.testing.assert_array_equal(back.u_ab, data.u_ab)


def test_csv_layout_and_comments(tmp_path):
    data = full_data()
    path = tmp_path / "rec.csv"
    pj.save_recording(path, pj.RecordedData(t=data.t, u_ab=data.u_ab, w_m=data.w_m))
    lines = path.read_text().splitlines()
    assert lines[0] == "t,u_ab_a,u_ab_b,w_m"
    assert len(lines) == N + 1
    # Comment lines, blank lines, spaces around names, extra columns and another column
    # order are all accepted.
    header, rows = plant_columns()
    text = "# logged by some tool\n\n" + " , ".join(["extra"] + header[::-1]) + "\n"
    text += "\n".join(",".join(["7"] + [str(v) for v in r[::-1]]) for r in rows) + "\n"
    other = tmp_path / "other.csv"
    other.write_text(text)
    back = pj.load_recording(other, require=("t", "u_ab"))
    assert back.names == ("t", "u_ab")
    np.testing.assert_array_equal(back.u_ab, np.tile([1.0, -1.0], (N, 1)))


def test_npz_ignores_unknown_arrays(tmp_path):
    path = tmp_path / "rec.npz"
    np.savez(path, t=np.arange(3) * T_S, u_ab=np.zeros((3, 2)), comment=np.arange(5))
    assert pj.load_recording(path, require=("t", "u_ab")).names == ("t", "u_ab")


def test_time_tolerance(tmp_path):
    t = np.arange(N) * T_S
    jitter = np.zeros(N)
    jitter[10] = 1e-8 * T_S  # well inside the 1e-6 relative tolerance
    pj.RecordedData(t=t + jitter, u_ab=np.zeros((N, 2)))
    jitter[10] = 1e-5 * T_S
    with pytest.raises(ValueError, match="uniformly spaced"):
        pj.RecordedData(t=t + jitter, u_ab=np.zeros((N, 2)))
    # a looser tolerance can be asked for
    pj.RecordedData(t=t + jitter, u_ab=np.zeros((N, 2)), t_rtol=1e-4)


# --- malformed files: each raises ValueError naming the file and the problem ----------

def test_missing_required_array(tmp_path):
    path = tmp_path / "rec.npz"
    np.savez(path, t=np.arange(N) * T_S, u_ab=np.zeros((N, 2)))
    pj.load_recording(path, require=("t", "u_ab"))  # fine for the plant
    with raises(path, "required array(s) missing", "`i_ab` (A)"):
        pj.load_recording(path, require=("t", "u_ab", "i_ab"))  # not for replay
    with raises(path, "missing", "`i_ab` (A)"):
        pj.load_recording(path)  # default: t, u_ab, i_ab
    np.savez(path, u_ab=np.zeros((N, 2)))
    with raises(path, "missing", "`t` (s)"):
        pj.load_recording(path, require=("u_ab",))  # t is always required


def test_missing_array_csv(tmp_path):
    path = write_csv(tmp_path / "rec.csv", ["t", "i_ab_a", "i_ab_b"],
                     [[k * T_S, 0, 0] for k in range(N)])
    with raises(path, "missing", "`u_ab` (V)", "u_ab_a"):
        pj.load_recording(path, require=("t", "u_ab"))


def test_csv_vector_half_missing(tmp_path):
    path = write_csv(tmp_path / "rec.csv", ["t", "u_ab_a"], [[k * T_S, 0] for k in range(N)])
    with raises(path, "`u_ab_b` is missing"):
        pj.load_recording(path, require=("t", "u_ab"))


def test_csv_vector_not_split(tmp_path):
    path = write_csv(tmp_path / "rec.csv", ["t", "u_ab"], [[k * T_S, 0] for k in range(N)])
    with raises(path, "`u_ab` must be split", "`u_ab_a` and `u_ab_b`"):
        pj.load_recording(path, require=("t", "u_ab"))


@pytest.mark.parametrize(
    "arrays, fragments",
    [
        (dict(u_ab=np.zeros((N, 3))), ("`u_ab` (V)", "shape (50, 2)", "got shape (50, 3)")),
        (dict(u_ab=np.zeros(N)), ("`u_ab` (V)", "shape (50, 2)", "got shape (50,)")),
        (dict(u_ab=np.zeros((2, N))), ("`u_ab` (V)", "shape (50, 2)", "got shape (2, 50)")),
        (dict(u_ab=np.zeros((N, 2)), w_m=np.zeros((N, 2))), ("`w_m`", "shape (50,)")),
        (dict(u_ab=np.zeros((N - 1, 2))), ("`u_ab`", "same number of samples as `t`")),
        (dict(u_ab=np.zeros((N, 2)), tau_L=np.zeros(N + 1)), ("`tau_L` (N m)", "(50,)")),
    ],
)
def test_wrong_shape(tmp_path, arrays, fragments):
    path = tmp_path / "rec.npz"
    np.savez(path, t=np.arange(N) * T_S, **arrays)
    with raises(path, *fragments):
        pj.load_recording(path, require=("t",))


def test_wrong_shape_of_t(tmp_path):
    path = tmp_path / "rec.npz"
    np.savez(path, t=(np.arange(N) * T_S)[:, None], u_ab=np.zeros((N, 2)))
    with raises(path, "`t` (s)", "shape (N,)", "got shape (50, 1)"):
        pj.load_recording(path, require=("t", "u_ab"))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_npz(tmp_path, bad):
    path = tmp_path / "rec.npz"
    i_ab = np.zeros((N, 2))
    i_ab[7, 1] = bad
    np.savez(path, t=np.arange(N) * T_S, u_ab=np.zeros((N, 2)), i_ab=i_ab)
    with raises(path, "`i_ab` (A)", "must be finite", "sample 7"):
        pj.load_recording(path)


def test_non_finite_csv(tmp_path):
    header, rows = plant_columns()
    rows[3][2] = "nan"
    path = write_csv(tmp_path / "rec.csv", header, rows)
    with raises(path, "`u_ab` (V)", "must be finite", "sample 3"):
        pj.load_recording(path, require=("t", "u_ab"))


def test_non_finite_time(tmp_path):
    path = tmp_path / "rec.npz"
    t = np.arange(N) * T_S
    t[4] = np.nan
    np.savez(path, t=t, u_ab=np.zeros((N, 2)))
    with raises(path, "`t` (s)", "must be finite"):
        pj.load_recording(path, require=("t", "u_ab"))


@pytest.mark.parametrize("n", [0, 1])
def test_too_few_samples(tmp_path, n):
    header, rows = plant_columns(n)
    path = write_csv(tmp_path / "rec.csv", header, rows)
    with raises(path, "`t` (s)", "at least 2 samples", f"got {n}"):
        pj.load_recording(path, require=("t", "u_ab"))


@pytest.mark.parametrize("ext", [".npz", ".csv"])
def test_non_increasing_time(tmp_path, ext):
    t = np.arange(N) * T_S
    t[[20, 21]] = t[[21, 20]]
    data_path = tmp_path / f"rec{ext}"
    if ext == ".npz":
        np.savez(data_path, t=t, u_ab=np.zeros((N, 2)))
    else:
        write_csv(data_path, *plant_columns(t=t))
    with raises(data_path, "`t` (s)", "strictly increasing", "t[21]", "t[20]"):
        pj.load_recording(data_path, require=("t", "u_ab"))


def test_repeated_time(tmp_path):
    t = np.arange(N) * T_S
    t[5] = t[4]
    path = write_csv(tmp_path / "rec.csv", *plant_columns(t=t))
    with raises(path, "strictly increasing"):
        pj.load_recording(path, require=("t", "u_ab"))


def test_non_uniform_time(tmp_path):
    t = np.arange(N) * T_S
    t[30:] += 0.5 * T_S  # one long gap: a dropped half sample
    path = tmp_path / "rec.npz"
    np.savez(path, t=t, u_ab=np.zeros((N, 2)))
    with raises(path, "`t` (s)", "uniformly spaced", "t[30] - t[29]"):
        pj.load_recording(path, require=("t", "u_ab"))


@pytest.mark.parametrize("name", ["rec.txt", "rec.npy", "rec"])
def test_unknown_extension(tmp_path, name):
    path = tmp_path / name
    path.write_text("t\n0\n1\n")
    with raises(path, "unknown file extension", "'.npz'", "'.csv'"):
        pj.load_recording(path)
    with raises(path, "unknown file extension"):
        pj.save_recording(path, full_data())


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        pj.load_recording(tmp_path / "nothing.npz")


def test_not_an_npz_archive(tmp_path):
    path = tmp_path / "rec.npz"
    path.write_text("t,u_ab_a,u_ab_b\n0,0,0\n")
    with raises(path, "not an NPZ archive"):
        pj.load_recording(path)
    with open(path, "wb") as f:  # a single .npy array under an .npz name
        np.save(f, np.zeros(3))
    with raises(path, "not an NPZ archive"):
        pj.load_recording(path)


def test_npz_non_numeric(tmp_path):
    path = tmp_path / "rec.npz"
    np.savez(path, t=np.array(["a", "b", "c"]), u_ab=np.zeros((3, 2)))
    with raises(path, "`t` (s)", "real numeric", "dtype"):
        pj.load_recording(path, require=("t", "u_ab"))


def test_csv_not_numbers(tmp_path):
    header, rows = plant_columns()
    rows[2][1] = "abc"
    path = write_csv(tmp_path / "rec.csv", header, rows)
    with raises(path, "cannot parse the CSV data as numbers", "line 4", "`u_ab_a`", "'abc'"):
        pj.load_recording(path, require=("t", "u_ab"))


def test_csv_ragged_rows(tmp_path):
    header, rows = plant_columns()
    rows[4] = rows[4][:2]
    path = write_csv(tmp_path / "rec.csv", header, rows)
    with raises(path, "line 6 has 2 fields", "header names 3 columns"):
        pj.load_recording(path, require=("t", "u_ab"))


def test_csv_header_problems(tmp_path):
    empty = tmp_path / "empty.csv"
    empty.write_text("# only a comment\n\n")
    with raises(empty, "empty"):
        pj.load_recording(empty)
    dup = write_csv(tmp_path / "dup.csv", ["t", "t", "u_ab_a", "u_ab_b"], [[0, 0, 0, 0]])
    with raises(dup, "duplicate CSV column", "t"):
        pj.load_recording(dup)
    blank = write_csv(tmp_path / "blank.csv", ["t", "", "u_ab_b"], [[0, 0, 0]])
    with raises(blank, "empty column name"):
        pj.load_recording(blank)


def test_unknown_required_name(tmp_path):
    path = tmp_path / "rec.npz"
    pj.save_recording(path, full_data())
    with pytest.raises(ValueError, match="Unknown recorded-data name.*'u_dq'"):
        pj.load_recording(path, require=("t", "u_dq"))


def test_constructor_and_require_messages():
    t = np.arange(N) * T_S
    with pytest.raises(ValueError, match=r"^x\.csv: `u_ab` \(V\) must have shape"):
        pj.RecordedData(t=t, u_ab=np.zeros((N, 3)), source="x.csv")
    data = pj.RecordedData(t=t, u_ab=np.zeros((N, 2)))
    assert data.require(("t", "u_ab")) is data
    with pytest.raises(ValueError, match="missing: `i_ab` \\(A\\), `w_m` \\(rad/s\\)"):
        data.require(("i_ab", "w_m"))
    with pytest.raises(ValueError, match="must be a `RecordedData`"):
        pj.save_recording("x.npz", {"t": t})


def test_npz_files_read_as_np_savez_writes_them(tmp_path):
    """`save_npz` (every `.npz` the package writes) against NumPy's own `np.savez`: the
    same members, dtypes, shapes and bytes, for arrays written from their own memory
    (large, C-contiguous) and as NumPy writes them (small, strided, Fortran-ordered,
    0-d, empty, structured, strings), to a path, an open file and an open zip."""
    import zipfile

    from pmsmjax._files import _NPZ_DIRECT_BYTES, save_npz

    rng = np.random.default_rng(1)
    big = _NPZ_DIRECT_BYTES // 8 + 3
    arrays = {
        "f8": rng.normal(size=big), "f4_2d": rng.normal(size=(big // 4, 4)).astype(np.float32),
        "i8": rng.integers(-100, 100, size=big).astype(np.int8),
        "b": rng.normal(size=_NPZ_DIRECT_BYTES + 1) > 0,
        "c16": rng.normal(size=big) + 1j * rng.normal(size=big),
        "u_big": np.array(["ab", "c\u00e9"] * (_NPZ_DIRECT_BYTES // 8)),
        "strided": rng.normal(size=2 * big)[::2], "fortran": np.asfortranarray(
            rng.normal(size=(300, 300))), "scalar": np.float64(2.5), "zero_d": np.array(7),
        "empty": np.zeros((0, 3)), "text": np.str_("observer"),
        "rec": np.zeros(3, dtype=[("a", "<f8"), ("b", "<i4")]),
        "big_endian": rng.normal(size=big).astype(">f8"),
    }
    np.savez(tmp_path / "ref.npz", **arrays)
    save_npz(tmp_path / "path.npz", arrays)
    with open(tmp_path / "file.npz", "wb") as f:
        save_npz(f, arrays)
    with zipfile.ZipFile(tmp_path / "zip.npz", "w", zipfile.ZIP_STORED, allowZip64=True) as z:
        save_npz(None, arrays, zip_file=z)
    with np.load(tmp_path / "ref.npz", allow_pickle=False) as ref:
        want = {k: ref[k] for k in ref.files}
    for name in ("path", "file", "zip"):
        with np.load(tmp_path / f"{name}.npz", allow_pickle=False) as got:
            assert got.files == list(want), name
            for k, a in want.items():
                b = got[k]
                assert (b.dtype, b.shape) == (a.dtype, a.shape), (name, k)
                assert b.tobytes() == a.tobytes(), (name, k)
    with pytest.raises(ValueError, match="'obj' holds Python objects"):
        save_npz(tmp_path / "obj.npz", {"obj": np.array([{}, None], dtype=object)})
