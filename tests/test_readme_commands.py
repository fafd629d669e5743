"""Every command line the README and the your-own-drive guide show runs, on small
settings, in the order they show them (one scratch folder per page, so the quick start
runs as written and the guide end to end: motor file -> simulate -> replay -> analyse ->
tune -> deploy).

Command lines are read from the README's ```sh blocks, so lines added later are picked
up without touching this file:

- `pmsmjax ...` and `python -m tuning ...` (also spelled `.venv/bin/...`) run in-process
  with `SMALL` options appended (shorter runs, no plots);
- `ls FILE...` checks that the files exist;
- `make ...` (tested by tests/test_main_job.py and the suite itself), `source ...`, and
  installs (`pip`, `jupyter`) are skipped; `pmsmjax identify` (it needs a commissioning
  log) is parsed only;
- anything else fails: add a rule here.

The command lines of every other page of docs/ are parsed (every option must exist;
`pmsmjax tune`/`compare` with the tuner's parsers).
"""

import json
import pathlib
import re
import shlex

import pytest

from pmsmjax.cli.__main__ import build_parser, main as pmsmjax_main
from tuning.__main__ import build_parser as tuning_parser, main as tuning_main


ROOT = pathlib.Path(__file__).parents[1]

#: Options appended per command for a short run (only options the line does not give).
#: simulate: the README's own length (its line gives --t-end 0.5), so that the guide's
#: runs reuse the quick start's compiled program (a new length is a new program).
#: tuning: training runs as long as the validation runs (0.25 s in --quick) and one
#: validation speed (6 runs, as many as the training and held-out sets): the three sets
#: run the same compiled programs (measured: the guide's `tune` 28.7 -> 25.1 s CPU).
SMALL = {
    "simulate": ["--t-end", "0.5", "--no-plot"],
    "replay": ["--no-plot"],
    "plant": ["--no-plot"],
    "feasibility": ["--no-plot"],
    "certify": ["--quick"],
    "tuning": ["--quick", "--budget", "12", "--peers", "cmaes", "--t-end", "0.25",
               "--val-speeds", "0.4", "--no-plot", "--no-progress"],
}
SMALL["tune"] = SMALL["tuning"]
#: The pages whose command lines run (the others are parsed).
RUN = (ROOT / "README.md", ROOT / "docs" / "your-own-drive.md")
SKIP = ("make", "source", "pip", "jupyter", "cd", "export")
#: Commands that need inputs the pages do not produce (identify: the drive's commissioning
#: log): parsed, not run (tests/test_identify.py runs the command).
PARSE_ONLY = ("identify",)


def command_lines(path: pathlib.Path) -> list[list[str]]:
    """The command lines of the ```sh blocks of `path` (comments and line continuations
    handled), as argument lists."""
    out = []
    for block in re.findall(r"```(?:sh|bash)\n(.*?)```", path.read_text(), flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            argv = shlex.split(line, comments=True)
            if argv:
                out.append(argv)
    return out


def _program(argv):
    """("pmsmjax" | "tuning" | "ls" | "skip", rest of the arguments)."""
    exe = pathlib.PurePath(argv[0]).name
    if exe == "pmsmjax":
        return "pmsmjax", argv[1:]
    if exe.startswith("python") and argv[1:3] == ["-m", "tuning"]:
        return "tuning", argv[3:]
    if exe.startswith("python") and argv[1:3] == ["-m", "pmsmjax"]:
        return "pmsmjax", argv[3:]
    if exe == "ls":
        return "ls", argv[1:]
    if exe in SKIP:
        return "skip", argv
    raise AssertionError(f"README command line {' '.join(argv)!r}: no rule in "
                         f"tests/test_readme_commands.py")


def _small(cmd: str, args: list[str]) -> list[str]:
    extra = SMALL.get(cmd, [])
    out, i = [], 0
    while i < len(extra):  # append an option (and its value) only if not given
        opt = extra[i]
        has_value = i + 1 < len(extra) and not extra[i + 1].startswith("--")
        if opt not in args:
            out += extra[i:i + 1 + has_value]
        i += 1 + has_value
    return args + out


def _run_page(page: pathlib.Path, folder: pathlib.Path, monkeypatch, capsys) -> list[str]:
    folder.mkdir()
    (folder / "docs").symlink_to(ROOT / "docs")  # the pages' paths are the repository's
    monkeypatch.chdir(folder)
    ran = []
    for argv in command_lines(page):
        prog, args = _program(argv)
        if prog == "skip":
            continue
        if prog == "ls":
            for f in args:
                assert (folder / f).is_file(), f"{page.name}: `ls {f}`: no such file"
            continue
        if prog == "pmsmjax" and args[:1] and args[0] in PARSE_ONLY:
            build_parser().parse_args(args)
            continue
        if prog == "tuning":
            rc = tuning_main(_small("tuning", args))
        else:
            rc = pmsmjax_main(_small(args[0], args) if args else args)
        out = capsys.readouterr()
        assert rc == 0, f"{page.name}: command line {' '.join(argv)!r} -> exit {rc}\n" \
                        f"{out.out[-2000:]}\n{out.err[-2000:]}"
        ran.append(" ".join(argv))
    return ran


@pytest.mark.timeout(900)
def test_readme_command_lines_run(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MPLBACKEND", "Agg")
    readme, guide = (_run_page(page, tmp_path / page.stem, monkeypatch, capsys)
                     for page in RUN)
    # the quick start: a sensorless run, a replay of its recording, the analysis; and
    # what the README says they show
    assert [r.split()[1] for r in readme] == ["simulate", "replay", "equilibria"]
    stats = json.loads((tmp_path / "README" / "replay" / "stats.json").read_text())
    assert abs(stats["theta_err_mean_deg"]) < 0.1  # "0.06 deg mean after settling"
    eq_line = shlex.split(readme[2])[1:]
    for i_q, designed, others in (("0.5", 3.4, [118]), ("0", 0.0, None)):
        assert pmsmjax_main([*eq_line, "--i-q", i_q, "--json"]) == 0
        report = json.loads(capsys.readouterr().out)
        eqs = report["equilibria"]
        d = [e for e in eqs if e["designed"]]
        assert len(d) == 1 and d[0]["stable"] and round(d[0]["theta_deg"], 1) == designed
        if others is not None:  # "an unstable one at 118 deg"
            assert [round(e["theta_deg"]) for e in eqs if not e["designed"]] == others
            assert not any(e["stable"] for e in eqs if not e["designed"])
    # the your-own-drive guide is there and ran end to end: from a logger's CSV to the C
    # of the tuned design with the drive's dead-time compensation
    assert any("--motor-file" in r and "tune" in r for r in guide)
    assert any("--design" in r and "replay" in r for r in guide)
    assert any(r.split()[1] == "convert" for r in guide)
    assert guide[-1].split()[1] == "export-c"
    header = (tmp_path / "your-own-drive" / "firmware" / "pmsm_observer.h").read_text()
    assert "#define PMSM_OBS_DEAD_TIME_COMPENSATION 1" in header


def test_docs_command_lines_parse():
    """The command lines of every page of docs/ name existing options."""
    from pmsmjax.cli._tuning import tuning_module

    pages = sorted((ROOT / "docs").glob("*.md"))
    parsed = 0
    for page in pages:
        for argv in command_lines(page):
            try:
                prog, args = _program(argv)
            except AssertionError:
                continue  # not a pmsmjax command (a shell line, a script)
            if prog == "pmsmjax" and args and args[0] in ("tune", "compare"):
                parser, args = tuning_module(args[0]).build_parser(), args[1:]
            elif prog == "pmsmjax":
                parser = build_parser()
            elif prog == "tuning" and args[:1] == ["compare"]:
                parser, args = tuning_module("compare").build_parser(), args[1:]
            elif prog == "tuning":
                parser = tuning_parser()
            else:
                continue
            try:
                parser.parse_args(args)
            except SystemExit as e:  # `--help`
                assert e.code == 0, f"{page.name}: {' '.join(argv)!r}"
            parsed += 1
    assert parsed >= 10


def test_quick_start_benchmark_times_the_readme_commands():
    """benchmarks/commands/startup.py --readme times the README's quick start as written."""
    from benchmarks.commands import startup as bench

    readme = [argv for argv in command_lines(ROOT / "README.md")
              if _program(argv)[0] == "pmsmjax"]
    timed = [[a.replace("{tmp}/", "") for a in cmd]
             for cmd in bench.README_QUICK_START.values()]
    assert [argv[1:] for argv in readme] == timed
