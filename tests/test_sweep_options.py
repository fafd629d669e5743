"""The shared sweep options of the command line (`pmsmjax.cli._sweep_options`): parsing,
defaults, and an error naming the option for every inconsistent combination."""

import argparse
import os

import pytest

from pmsmjax.cli import CLIError
from pmsmjax.cli._sweep_options import (
    DEFAULT_CHUNK_SIZE,
    SweepSettings,
    add_sweep_options,
    init_distributed,
    sweep_settings,
)


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise CLIError(message)


def parse(*argv, out="results"):
    p = _Parser(prog="cmd")
    p.add_argument("--out", default=out)
    add_sweep_options(p)
    return p.parse_args(list(argv))


def settings(*argv, **kw):
    return sweep_settings(parse(*argv, **kw))


def test_defaults_one_process():
    s = settings()
    assert s == SweepSettings(chunk_size=DEFAULT_CHUNK_SIZE, batch_size=None,
                              sweep_dir=os.path.join("results", "sweep"), resume=True)
    assert not s.distributed
    assert s.run_sweep_kwargs() == dict(out_dir=os.path.join("results", "sweep"),
                                        chunk_size=DEFAULT_CHUNK_SIZE, batch_size=None,
                                        resume=True, progress=True)
    assert init_distributed(s) is s  # nothing to start


def test_all_options(tmp_path):
    s = settings("--chunk-size", "512", "--batch-size", "64", "--sweep-dir", str(tmp_path),
                 "--restart", "--coordinator", "node0:1234", "--num-processes", "4",
                 "--process-id", "3")
    assert (s.chunk_size, s.batch_size, s.sweep_dir, s.resume) == (512, 64, str(tmp_path),
                                                                   False)
    assert (s.coordinator, s.num_processes, s.process_id) == ("node0:1234", 4, 3)
    assert s.distributed
    assert s.run_sweep_kwargs(progress=False)["progress"] is False
    # `auto`: jax.distributed finds the missing settings in the cluster's environment
    s = settings("--coordinator", "auto")
    assert s.distributed and (s.num_processes, s.process_id) == (None, None)
    assert settings("--coordinator", "[::1]:80", "--num-processes", "1",
                    "--process-id", "0").coordinator == "[::1]:80"
    # the default sweep folder follows --out, or the caller's folder
    assert settings(out="elsewhere").sweep_dir == os.path.join("elsewhere", "sweep")
    assert sweep_settings(parse(out=None), out="job").sweep_dir == os.path.join("job", "sweep")


@pytest.mark.parametrize("argv, words", [
    (["--chunk-size", "0"], ["--chunk-size", ">= 1"]),
    (["--chunk-size", "1.5"], ["--chunk-size", "not an integer"]),
    (["--batch-size", "-2"], ["--batch-size", ">= 1"]),
    (["--chunk-size", "100", "--batch-size", "200"],
     ["--batch-size 200 with --chunk-size 100", "batch size <= chunk size"]),
    (["--num-processes", "2"], ["--num-processes 2", "needs --coordinator"]),
    (["--process-id", "1"], ["--process-id 1", "needs --coordinator"]),
    (["--num-processes", "2", "--process-id", "1"],
     ["--num-processes 2 and --process-id 1", "--coordinator"]),
    (["--num-processes", "0", "--coordinator", "h:1"], ["--num-processes", ">= 1"]),
    (["--process-id", "-1"], ["--process-id", ">= 0"]),
    (["--coordinator", "localhost:1234"],
     ["--coordinator localhost:1234 needs --num-processes P and --process-id I"]),
    (["--coordinator", "localhost:1234", "--num-processes", "2"],
     ["--coordinator localhost:1234 needs --process-id I", "auto"]),
    (["--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"],
     ["--process-id 2 with --num-processes 2", "0 <= process id <= 1"]),
    (["--coordinator", "localhost", "--num-processes", "2", "--process-id", "0"],
     ["--coordinator 'localhost'", "HOST:PORT", "auto"]),
    (["--coordinator", "h:99999", "--num-processes", "2", "--process-id", "0"],
     ["--coordinator 'h:99999'", "1 to 65535"]),
    (["--coordinator", ":1234", "--num-processes", "2", "--process-id", "0"],
     ["--coordinator ':1234'", "HOST:PORT"]),
])
def test_inconsistent_options_name_the_option(argv, words):
    with pytest.raises(CLIError) as e:
        settings(*argv)
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_sweep_dir_checks(tmp_path):
    f = tmp_path / "file"
    f.write_text("")
    with pytest.raises(CLIError, match="--sweep-dir .* not a directory"):
        settings("--sweep-dir", str(f))
    with pytest.raises(CLIError, match=r"--sweep-dir: needed .*--out"):
        settings(out=None)


def test_distributed_must_start_before_any_computation():
    import jax

    jax.devices()  # the backend runs: jax.distributed cannot start any more
    s = settings("--coordinator", "localhost:1", "--num-processes", "1", "--process-id", "0")
    with pytest.raises(CLIError, match="--coordinator localhost:1: jax.distributed must "
                                       "start before any JAX computation"):
        init_distributed(s)
