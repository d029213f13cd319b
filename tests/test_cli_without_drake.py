"""The CLI on a machine without Drake (e.g. a GPU box for training): `bench --model`, `train` and `export`
need only torch, every subcommand's --help works, and a command that needs Drake says so in one line.

Each check runs in a fresh interpreter whose import system refuses `pydrake` (and its submodules) as if
it were not installed."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

_NO_DRAKE = textwrap.dedent(
    """
    import importlib.abc
    import sys


    class _NoDrake(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name == "pydrake" or name.startswith("pydrake."):
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None


    sys.meta_path.insert(0, _NoDrake())
    """
)


def _run_without_drake(code: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _NO_DRAKE + textwrap.dedent(code)],
                          capture_output=True, text=True, timeout=timeout)


def test_the_finder_really_hides_drake():
    result = _run_without_drake("import pydrake.math")
    assert result.returncode != 0 and "No module named 'pydrake" in result.stderr


def test_bench_model_runs_without_drake():
    result = _run_without_drake(
        """
        from trivla_drake.cli import main

        rc = main(["bench", "--model", "--preset", "tiny", "--json"])
        assert not any(name.split(".")[0] == "pydrake" for name in sys.modules)
        sys.exit(rc)
        """
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["preset"] == "tiny" and report["precision"] == "float32" and report["skipped"] is False
    assert set(report["latency_ms"]) == {"system1", "system2", "system3", "full"}
    assert report["params_millions"]["total"] > 0
    assert [row["systems"] for row in report["ablations"]] == ["1", "1+3", "1+2+3"]


def test_every_subcommand_help_and_train_export_parsing_work_without_drake():
    result = _run_without_drake(
        """
        import argparse
        import contextlib
        import io

        from trivla_drake.cli import build_parser, main

        parser = build_parser()
        (subcommands,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        names = sorted(subcommands.choices)
        assert {"sim", "demo", "collect", "evaluate", "train", "export", "soup", "tables", "bench"} <= set(names)
        assert "probe" not in names  # the probes are at git tag research-archive
        for argv in [["--help"]] + [[name, "--help"] for name in names]:
            out = io.StringIO()
            try:
                with contextlib.redirect_stdout(out):
                    main(argv)
            except SystemExit as exit:
                assert exit.code == 0, (argv, exit.code)
            else:
                raise AssertionError(f"{argv}: no SystemExit")
            assert "usage: trivla-drake" in out.getvalue(), argv
        train = parser.parse_args(["train", "--stage", "policy", "--data", "d", "--out", "o"])
        export = parser.parse_args(["export", "ckpt", "--out", "o"])
        assert (train.command, train.stage, export.command, export.checkpoint) == ("train", "policy", "export", "ckpt")
        assert not any(name.split(".")[0] == "pydrake" for name in sys.modules)
        print(",".join(names))
        """
    )
    assert result.returncode == 0, result.stderr
    assert "bench" in result.stdout.split(",")


def test_a_drake_command_says_it_needs_drake():
    result = _run_without_drake(
        """
        from trivla_drake.cli import main

        sys.exit(main(["sim", "--seconds", "0.1"]))
        """
    )
    assert result.returncode == 2, result.stderr
    assert "trivla-drake sim: error:" in result.stderr and "needs Drake" in result.stderr, result.stderr
    assert "Traceback" not in result.stderr


def test_scenario_errors_are_caught_as_value_errors():
    """main() no longer names ScenarioError (that would import Drake): it must stay a ValueError."""
    pytest.importorskip("pydrake")
    from trivla_drake.station.scenario import ScenarioError

    assert issubclass(ScenarioError, ValueError)
