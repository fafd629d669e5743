"""Every defect a real recorded-data file can have gives a clear error naming the file and
the field, through the API (`pmsmjax.load_recording`) and the command line (`pmsmjax
replay` / `pmsmjax plant`, exit status 2, one line, no traceback), and a failed command
leaves nothing half-written in its `--out` folder."""

import pickle

import numpy as np
import pytest

import pmsmjax as pj
from pmsmjax.cli.__main__ import main


N = 50


def _good(n=N):
    t = np.arange(n) * 1e-4
    return dict(t=t, u_ab=np.stack([np.cos(t), np.sin(t)], -1),
                i_ab=np.stack([np.sin(t), np.cos(t)], -1), theta=t.copy(), w_m=np.ones(n))


def _csv(path, cols: dict, rows=None):
    names = list(cols)
    n = len(next(iter(cols.values())))
    lines = [",".join(names)]
    for k in range(n):
        lines.append(",".join(str(cols[c][k]) for c in names))
    if rows is not None:
        lines = rows(lines)
    path.write_text("\n".join(lines) + "\n")
    return path


def _csv_cols(d):
    cols = {"t": d["t"]}
    for name in ("u_ab", "i_ab"):
        cols[f"{name}_a"], cols[f"{name}_b"] = d[name][:, 0], d[name][:, 1]
    return cols


def _npz(path, **arrays):
    np.savez(path, **arrays)
    return path


def _defects(tmp_path):
    """(file, regex the message must match) for every defect class."""
    g = _good()
    nan_u = g["u_ab"].copy()
    nan_u[7, 1] = np.nan
    inf_i = g["i_ab"].copy()
    inf_i[3, 0] = np.inf
    t_nonuni = g["t"].copy()
    t_nonuni[10:] += 3e-5
    t_dec = g["t"][::-1].copy()
    cases = {
        "nan": (_npz(tmp_path / "nan.npz", **{**g, "u_ab": nan_u}), r"u_ab.*(finite|NaN)"),
        "inf": (_npz(tmp_path / "inf.npz", **{**g, "i_ab": inf_i}), r"i_ab.*(finite|inf)"),
        "non-uniform t": (_npz(tmp_path / "nonuni.npz", **{**g, "t": t_nonuni}),
                          r"`t`.*uniform"),
        "decreasing t": (_npz(tmp_path / "dec.npz", **{**g, "t": t_dec}), r"`t`.*increasing"),
        "lengths": (_npz(tmp_path / "len.npz", **{**g, "i_ab": g["i_ab"][:-3]}),
                    r"i_ab.*(shape|samples|length)"),
        "one sample": (_npz(tmp_path / "one.npz", **{k: v[:1] for k, v in g.items()}),
                       r"`t`.*at least 2"),
        "shape": (_npz(tmp_path / "shape.npz", **{**g, "u_ab": g["u_ab"].T}),
                  r"u_ab.*shape"),
        "missing array": (_npz(tmp_path / "miss.npz", t=g["t"], u_ab=g["u_ab"]),
                          r"required array.*i_ab"),
        "missing CSV column": (_csv(tmp_path / "miss.csv", {
            k: v for k, v in _csv_cols(g).items() if k != "i_ab_b"}),
            r"i_ab_b.*missing"),
        "text in CSV": (_csv(tmp_path / "text.csv", _csv_cols(g),
                             rows=lambda ls: ls[:5] + [ls[5].replace(ls[5].split(",")[2],
                                                                     "abc")] + ls[6:]),
                        r"line 6, column `u_ab_b` holds 'abc'"),
        "ragged CSV": (_csv(tmp_path / "ragged.csv", _csv_cols(g),
                            rows=lambda ls: ls[:9] + [ls[9] + ",1.0"] + ls[10:]),
                       r"line 10 has 6 fields but the header names 5"),
        "pickled object array": (tmp_path / "obj.npz", r"cannot read array `u_ab`"),
        "not an archive": (tmp_path / "pickle.npz", r"not an NPZ archive"),
        "unknown extension": (tmp_path / "data.txt", r"extension"),
        "empty CSV": (tmp_path / "empty.csv", r"empty"),
    }
    obj = np.empty((N, 2), dtype=object)
    obj[:] = 1.0
    np.savez(tmp_path / "obj.npz", **{**g, "u_ab": obj})
    (tmp_path / "pickle.npz").write_bytes(pickle.dumps(g))
    (tmp_path / "data.txt").write_text("t,u_ab_a\n0,1\n")
    (tmp_path / "empty.csv").write_text("")
    return cases


def test_every_defect_gives_a_named_error_through_the_api(tmp_path):
    for name, (path, msg) in _defects(tmp_path).items():
        with pytest.raises(ValueError, match=msg) as e:
            pj.load_recording(path)
        assert str(path) in str(e.value), name


def test_extra_columns_and_arrays_are_ignored(tmp_path):
    g = _good()
    cols = {**_csv_cols(g), "u_dc": np.full(N, 300.0), "temperature": np.full(N, 40.0)}
    rec = pj.load_recording(_csv(tmp_path / "extra.csv", cols))
    np.testing.assert_array_equal(rec.i_ab, g["i_ab"])
    rec = pj.load_recording(_npz(tmp_path / "extra.npz", **g, u_dc=np.full(N, 300.0)))
    np.testing.assert_array_equal(rec.u_ab, g["u_ab"])


def test_a_huge_file_is_refused_before_it_is_read(tmp_path):
    path = _npz(tmp_path / "big.npz", **_good(20000))
    with pytest.raises(ValueError, match=r"big\.npz: the file is .* above the limit"):
        pj.load_recording(path, max_bytes=100_000)
    assert pj.load_recording(path).n == 20000  # below the default limit of 1 GiB


@pytest.mark.parametrize("command", ["replay", "plant"])
def test_every_defect_through_the_command_line(tmp_path, capsys, command):
    for name, (path, msg) in _defects(tmp_path).items():
        if command == "plant" and name in ("missing array", "missing CSV column"):
            continue  # the plant needs no current
        out = tmp_path / f"out-{command}-{name.replace(' ', '_')}"
        assert main([command, "--data", str(path), "--out", str(out)]) == 2, name
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"pmsmjax {command}: error: ") and "\n" not in err, (name, err)
        assert "Traceback" not in err
        assert not out.exists(), name  # nothing created for a run that failed


def test_a_failed_command_leaves_nothing_half_written(tmp_path, capsys, monkeypatch):
    # a failure after some outputs were written (here: the figure cannot be saved)
    g = _good(400)
    data = _npz(tmp_path / "rec.npz", **g)
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("a file of the user's")
    import matplotlib.figure

    def broken(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", broken)
    assert main(["replay", "--data", str(data), "--out", str(out)]) == 2
    assert "disk full" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    # and without the failure the same command writes its files
    monkeypatch.undo()
    assert main(["replay", "--data", str(data), "--out", str(out), "--no-plot"]) == 0
    assert {"replay.npz", "stats.json", "keep.txt"} <= {p.name for p in out.iterdir()}
