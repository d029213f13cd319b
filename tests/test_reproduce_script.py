"""scripts/reproduce_default_checkpoint.sh is the written record of how models/trivla_cpu was made: every
command in it, optional blocks included, must still parse with the CLI as it is now."""

import os
import shlex
import subprocess
import sys
from pathlib import Path

from trivla_drake.cli import build_parser

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "reproduce_default_checkpoint.sh"


def _dry_run(tmp_path: Path) -> list[list[str]]:
    """Run the script with `trivla-drake` replaced by a recorder; returns each call's arguments."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    calls = tmp_path / "calls.txt"
    recorder = bin_dir / "trivla-drake"
    recorder.write_text(f'#!/usr/bin/env bash\n{shlex.quote(sys.executable)} -c '
                        f'"import shlex, sys; print(shlex.join(sys.argv[1:]))" "$@" >> {shlex.quote(str(calls))}\n')
    recorder.chmod(0o755)
    work = tmp_path / "work"
    (work / "results").mkdir(parents=True)
    (work / "data").mkdir()
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "DATA": "data/sim",
           "STEPS": "1", "CLEAN": "1", "NOISE": "1", "GROUNDING": "1"}
    (work / "data" / "sim").mkdir()
    subprocess.run(["bash", str(SCRIPT)], cwd=work, env=env, check=True, capture_output=True, text=True)
    return [shlex.split(line) for line in calls.read_text().splitlines()]


def test_every_command_of_the_reproduce_script_parses(tmp_path):
    calls = _dry_run(tmp_path)
    parser = build_parser()
    for argv in calls:
        parser.parse_args(argv)  # exits (SystemExit) on an unknown flag or a bad value
    commands = [argv[0] for argv in calls]
    assert {"collect", "train", "export", "tables", "probe", "evaluate"} <= set(commands)


def test_the_shipped_checkpoint_is_the_export_of_the_9000_step_dart_run(tmp_path):
    calls = _dry_run(tmp_path)
    export = next(argv for argv in calls if argv[0] == "export" and argv[-1] == "models/trivla_cpu")
    run = export[1].removesuffix("/final")
    second = next(argv for argv in calls if argv[0] == "train" and argv[argv.index("--out") + 1] == run)
    first_run = second[second.index("--init") + 1].removesuffix("/final")
    first = next(argv for argv in calls if argv[0] == "train" and argv[argv.index("--out") + 1] == first_run)
    assert int(first[first.index("--steps") + 1]) + int(second[second.index("--steps") + 1]) == 9000
    data = second[second.index("--data") + 1]
    collect_dart = next(argv for argv in calls if argv[0] == "collect" and argv[argv.index("--out") + 1] == data)
    assert "--action-noise" in collect_dart and "--no-tcp-features" not in second


def test_a_fraction_run_continued_from_another_keeps_its_draw(tmp_path):
    """--seed also draws the --fraction subset: a continuation with another seed trains on other episodes."""
    def option(argv, name, default=None):
        return argv[argv.index(name) + 1] if name in argv else default

    runs = {option(argv, "--out"): argv for argv in _dry_run(tmp_path) if argv[0] == "train" and "--fraction" in argv}
    continued = [(argv, runs[option(argv, "--init").removesuffix("/final")]) for argv in runs.values()
                 if option(argv, "--init", "").removesuffix("/final") in runs]
    assert continued  # the 10%-data arm's second part
    for second, first in continued:
        assert option(second, "--fraction") == option(first, "--fraction")
        assert option(second, "--seed", "0") == option(first, "--seed", "0")
