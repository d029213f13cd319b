"""scripts/reproduce_default_checkpoint.sh is the written record of how models/trivla_cpu was made: every
command in it, optional blocks included, must still parse with the CLI as it is now."""

import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from trivla_drake.cli import build_parser

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "reproduce_default_checkpoint.sh"


@pytest.fixture(scope="module")
def every_call(tmp_path_factory) -> list[list[str]]:
    """Each call of one dry run of the script, in order: `trivla-drake`'s arguments, and a results script's
    as ["python", script, ...] (run once: it records a few hundred calls)."""
    return _dry_run(tmp_path_factory.mktemp("reproduce"))


@pytest.fixture(scope="module")
def calls(every_call) -> list[list[str]]:
    """Each `trivla-drake` call of the dry run."""
    return [argv for argv in every_call if argv[0] != "python"]


def _dry_run(tmp_path: Path, skip: tuple[str, ...] = ()) -> list[list[str]]:
    """Run the script with `trivla-drake` and its Python replaced by recorders; returns each call's arguments.
    `skip` names optional steps' switches left unset."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    calls = tmp_path / "calls.txt"
    # a recorded collect or train call leaves its OUT folder (a train call OUT/summary.json), as a real one
    # does, for the steps that look for them
    record = ("import os, shlex, sys\n"
              "args = sys.argv[2:]\n"
              "print(sys.argv[1] + shlex.join(args))\n"
              "if args[:1] in (['collect'], ['train']) and '--out' in args:\n"
              "    out = args[args.index('--out') + 1]\n"
              "    os.makedirs(out, exist_ok=True)\n"
              "    if args[0] == 'train':\n"
              "        open(os.path.join(out, 'summary.json'), 'a').close()\n")
    (bin_dir / "record.py").write_text(record)
    for name, prefix in (("trivla-drake", ""), ("python-recorder", "python ")):
        recorder = bin_dir / name
        recorder.write_text(f'#!/usr/bin/env bash\n{shlex.quote(sys.executable)} {shlex.quote(str(bin_dir / "record.py"))} '
                            f'{shlex.quote(prefix)} "$@" >> {shlex.quote(str(calls))}\n')
        recorder.chmod(0o755)
    work = tmp_path / "work"
    (work / "results").mkdir(parents=True)
    (work / "data").mkdir()
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "DATA": "data/sim",
           "STEPS": "1", "CLEAN": "1", "NOISE": "1", "GROUNDING": "1",
           "DART_FOLLOW": "1", "DETOURS": "1", "TWISTS": "1", "MISSES": "1", "DRIFTS": "1",
           "CHUNKS": "1", "EMPHASIS": "1", "TAKEOVER": "1", "SUBGOALS": "1", "DIAGNOSE": "1", "CARRY": "1", "PHASE": "1", "PHASE_ALL": "1",
           "CONTROL": "1", "PHASE_LONGER": "1", "CONTROL_LONGER": "1", "PHASE_RESEED": "1", "PHASE_THIRD": "1",
           "FRESH_SEEDS": "1", "SOUP_FOLLOW": "1", "ANCHOR": "1", "SUBGOAL_TRUST": "1", "SYSTEM2_SCENES": "1", "CHAIN_STARTS": "1", "SHIPPED_FOLLOW": "1",
           "HOME_FIRST": "1", "WEAK_PRELUDES": "1", "MORE_SCENES": "1", "PRELUDE_RESET": "1", "CHAIN_LIFTS": "1",
           "STACKED_DEMOS": "1", "KEEP_NORM": "1", "PRELUDE_STACKED": "1", "STACKED_REFIT": "1",
           "STACKED_HOLD": "1", "GOAL_HOLD": "1", "DATA30": "1", "BIND_COUNTS": "1", "KEPT_GROUNDING": "1", "KEPT_UNION": "1",
           "PYTHON": str(bin_dir / "python-recorder")}
    env = {key: value for key, value in env.items() if key not in skip}
    (work / "data" / "sim").mkdir()
    (work / "data" / "sim-prelude").mkdir()  # step 22 copies what step 21 collected
    (work / "models" / "trivla_cpu").mkdir(parents=True)  # step 41 copies the soup it wrote
    subprocess.run(["bash", str(SCRIPT)], cwd=work, env=env, check=True, capture_output=True, text=True)
    return [shlex.split(line) for line in calls.read_text().splitlines()]


def option(argv: list[str], name: str, default: str | None = None) -> str | None:
    """The value after `name` in one recorded call (`default` where the call has no `name`)."""
    return argv[argv.index(name) + 1] if name in argv else default


def run_writing(calls: list[list[str]], out: str) -> list[str]:
    """The train or export call that writes `out`."""
    return next(argv for argv in calls if argv[0] in ("train", "export") and option(argv, "--out") == out)


def test_every_command_of_the_reproduce_script_parses(calls):
    parser = build_parser()
    for argv in calls:
        parser.parse_args(argv)  # exits (SystemExit) on an unknown flag or a bad value
    commands = [argv[0] for argv in calls]
    assert {"collect", "train", "export", "soup", "tables", "probe", "evaluate"} <= set(commands)


def test_the_shipped_checkpoint_is_the_grounded_recipe_on_the_9000_step_dart_run(calls):
    """models/trivla_cpu: a longer follow (weight average) <- follow <- bind (keeping the grounding) on step
    22's model with a System 2 trained afresh with the sub-cell dense loss <- the export of step 22's
    follow (weight average) on more chain-prelude demonstrations <- the export of
    follow on the chain-prelude demonstrations <- the export of follow (with the
    sub-goal offset) <- bind further on the DART demonstrations (keeping the grounding) <- bind <- joint
    (grounding, token positions) <- System 2 with the dense loss <- the export of the plain recipe's
    9000-step run on the DART demonstrations."""
    export = next(argv for argv in calls if argv[0] == "export" and option(argv, "--out") == "models/trivla_cpu")
    assert "--drop-unused-llm-layers" in export and "--trained-weights" not in export
    longer = run_writing(calls, export[1].removesuffix("/final"))
    sub4_follow = run_writing(calls, option(longer, "--init").removesuffix("/final"))
    sub4_bind = run_writing(calls, option(sub4_follow, "--init").removesuffix("/final"))
    assert [option(a, "--grounding-phase") for a in (longer, sub4_follow, sub4_bind)] == ["follow", "follow", "bind"]
    assert "--keep-grounding" in sub4_bind and "--system2-from" not in longer + sub4_follow
    assert all(float(option(a, "--ema-decay")) > 0 and "--subgoal-offset" in a for a in (longer, sub4_follow))
    assert int(option(longer, "--steps")) == 5000 and option(longer, "--data") == option(sub4_bind, "--data")
    vlm_sub4 = run_writing(calls, option(sub4_bind, "--system2-from").removesuffix("/final"))
    assert option(vlm_sub4, "--stage") == "vlm" and option(vlm_sub4, "--dense-subcells") == "4"
    assert "--init" not in vlm_sub4  # System 2 from scratch
    more_export = run_writing(calls, option(sub4_bind, "--init"))
    assert more_export[0] == "export" and "--drop-unused-llm-layers" in more_export
    assert "--trained-weights" not in more_export
    more = run_writing(calls, more_export[1].removesuffix("/final"))
    assert float(option(more, "--ema-decay")) > 0
    prelude_export = run_writing(calls, option(more, "--init"))
    assert prelude_export[0] == "export" and "--drop-unused-llm-layers" in prelude_export
    preludes = run_writing(calls, prelude_export[1].removesuffix("/final"))
    collect_more = [argv for argv in calls if argv[0] == "collect" and option(argv, "--out") == option(more, "--data")]
    assert [int(option(a, "--prelude-tasks", 0)) for a in collect_more] == [4, 0]
    curriculum_export = run_writing(calls, option(preludes, "--init"))
    assert curriculum_export[0] == "export" and "--drop-unused-llm-layers" in curriculum_export
    follow = run_writing(calls, curriculum_export[1].removesuffix("/final"))
    collect_preludes = [argv for argv in calls if argv[0] == "collect" and option(argv, "--out") == option(preludes, "--data")]
    assert [int(option(a, "--prelude-tasks", 0)) for a in collect_preludes] == [0, 4]
    assert option(preludes, "--grounding-phase") == "follow" and "--subgoal-offset" in preludes
    curriculum = run_writing(calls, option(follow, "--init").removesuffix("/final"))
    bind = run_writing(calls, option(curriculum, "--init").removesuffix("/final"))
    joint = run_writing(calls, option(bind, "--init").removesuffix("/final"))
    vlm = run_writing(calls, option(joint, "--init").removesuffix("/final"))
    assert [option(a, "--grounding-phase", "joint")
            for a in (follow, curriculum, bind, joint)] == ["follow", "bind", "bind", "joint"]
    assert "--keep-grounding" in curriculum and "--keep-grounding" not in bind
    dart = next(argv for argv in calls if argv[0] == "collect" and "--action-noise" in argv)
    assert option(curriculum, "--data") == option(dart, "--out") != option(bind, "--data")
    assert "--subgoal-offset" in follow and not any("--subgoal-offset" in a for a in (curriculum, bind, joint))
    assert not any("--grounding-reads-tcp" in a for a in (follow, curriculum, bind, joint))

    def follows_of(init):
        return [argv for argv in calls if argv[0] == "train" and "--init" in argv and option(argv, "--init") == init
                and "--grounding-phase" in argv and option(argv, "--grounding-phase") == "follow"]

    # step 12 (the grounded recipe) and step 14 (+ offset) follow step 12's bind run; step 15 differs
    # from step 14 only in its --init, step 14 from step 12 only in --subgoal-offset
    grounded, offset = sorted(follows_of(option(curriculum, "--init")), key=lambda a: "--subgoal-offset" in a)
    assert "--subgoal-offset" not in grounded and "--subgoal-offset" in offset
    keys = ("--steps", "--seed", "--data", "--lr", "--out", "--init")
    assert {k for k in keys if option(offset, k) != option(grounded, k)} == {"--out"}
    assert {k for k in keys if option(follow, k) != option(offset, k)} == {"--out", "--init"}
    assert {k for k in keys if option(preludes, k) != option(follow, k)} == {"--out", "--init", "--data"}
    assert {k for k in keys if option(more, k) != option(preludes, k)} == {"--out", "--init", "--data"}
    assert all("--vl-position-embedding" in a and float(option(a, "--grounding-weight")) > 0
               for a in (more, preludes, follow, curriculum, bind, joint))
    assert option(vlm, "--stage") == "vlm" and float(option(vlm, "--dense-weight")) > 0
    plain_export = run_writing(calls, option(vlm, "--init"))
    second = run_writing(calls, plain_export[1].removesuffix("/final"))
    first = run_writing(calls, option(second, "--init").removesuffix("/final"))
    assert int(option(first, "--steps")) + int(option(second, "--steps")) == 9000
    collect_dart = next(argv for argv in calls if argv[0] == "collect" and option(argv, "--out") == option(second, "--data"))
    assert "--action-noise" in collect_dart and "--no-tcp-features" not in second
    tables = next(argv for argv in calls if argv[0] == "tables" and option(argv, "--full") == "models/trivla_cpu")
    assert option(tables, "--out") == "results"


def test_a_fraction_run_continued_from_another_keeps_its_draw(calls):
    """--seed also draws the --fraction subset: a continuation with another seed trains on other episodes."""
    runs = {option(argv, "--out"): argv for argv in calls if argv[0] == "train" and "--fraction" in argv}
    continued = [(argv, runs[option(argv, "--init").removesuffix("/final")]) for argv in runs.values()
                 if option(argv, "--init", "").removesuffix("/final") in runs]
    assert continued  # the 10%-data arm's second part
    for second, first in continued:
        assert option(second, "--fraction") == option(first, "--fraction")
        assert option(second, "--seed", "0") == option(first, "--seed", "0")


def test_the_data_efficiency_arm_trains_a_fresh_system1_on_a_tenth_of_the_shipped_models_data(calls):
    """Step 30: the tables' 10% arm is an export <- follow <- bind (a fresh grounding) <- joint with a fresh
    System 1 on the shipped model's Systems 2 and 3, on 3 + 5 demonstrations per task (a tenth of the 30 + 50
    per task the shipped model's last runs trained on, in the same proportions)."""
    tables = next(argv for argv in calls if argv[0] == "tables" and "--data10" in argv
                  and option(argv, "--full") == "models/trivla_cpu")
    export = run_writing(calls, option(tables, "--data10"))
    follow = run_writing(calls, export[1].removesuffix("/final"))
    bind = run_writing(calls, option(follow, "--init").removesuffix("/final"))
    joint = run_writing(calls, option(bind, "--init").removesuffix("/final"))
    assert [option(a, "--grounding-phase", "joint")
            for a in (follow, bind, joint)] == ["follow", "bind", "joint"]
    assert "--fresh-system1" in joint and option(joint, "--init") == "models/trivla_cpu"
    assert "--keep-grounding" not in bind and not any("--fresh-system1" in a for a in (follow, bind))
    assert option(follow, "--data") == option(bind, "--data") == option(joint, "--data")

    collected = [argv for argv in calls if argv[0] == "collect" and option(argv, "--out") == option(joint, "--data")]
    # collect's --episodes-per-task counts the folder's episodes so far: 3 from the start posture, then up to 8
    # with a prelude (MORE_DATA has 30 and 50 per task: results/more_preludes_ema/)
    assert [(int(option(a, "--episodes-per-task")), "--prelude-tasks" in a) for a in collected] == [(3, False), (8, True)]


def test_the_carry_experiment_binds_the_shipped_grounding_on_stack_carries_then_follows(calls):
    """Step 32: export <- follow <- bind (keeping the shipped model's grounding, with --grounding-carry
    stack_block) on MORE_DATA, the data the shipped model's last runs trained on."""
    export = next(argv for argv in calls if argv[0] == "export" and option(argv, "--out", "").endswith("carry_export"))
    follow = run_writing(calls, export[1].removesuffix("/final"))
    bind = run_writing(calls, option(follow, "--init").removesuffix("/final"))
    assert [option(a, "--grounding-phase") for a in (follow, bind)] == ["follow", "bind"]
    assert option(bind, "--init") == "models/trivla_cpu" and "--keep-grounding" in bind
    assert option(bind, "--grounding-carry") == option(follow, "--grounding-carry") == "stack_block"
    shipped = run_writing(calls, "models/trivla_cpu")
    longer = run_writing(calls, shipped[1].removesuffix("/final"))
    assert option(bind, "--data") == option(follow, "--data") == option(longer, "--data")


@pytest.mark.parametrize("name, carrying", [
    ("held", "stack_block"),
    ("heldall", "stack_block,place_in_bowl,unstack_block,rotate_block_left,rotate_block_right"),
])
def test_the_phase_experiments_bind_only_a_held_block_readout_on_the_shipped_grounding_then_follow(calls, name, carrying):
    """Steps 33 and 34: export <- follow <- bind, the bind adding the held-block read-out to the shipped model's
    grounding and training only it (--bind-held-only) on the carrying frames of stack (of every task that
    releases a held block), on the shipped model's data."""
    export = next(argv for argv in calls if argv[0] == "export" and option(argv, "--out", "").endswith(f"/{name}_export"))
    follow = run_writing(calls, export[1].removesuffix("/final"))
    bind = run_writing(calls, option(follow, "--init").removesuffix("/final"))
    assert [option(a, "--grounding-phase") for a in (follow, bind)] == ["follow", "bind"]
    assert option(bind, "--init") == "models/trivla_cpu"
    assert {"--keep-grounding", "--grounding-reads-gripper", "--bind-held-only"} <= set(bind)
    assert option(bind, "--grounding-carry") == option(follow, "--grounding-carry") == carrying
    shipped = run_writing(calls, "models/trivla_cpu")
    longer = run_writing(calls, shipped[1].removesuffix("/final"))
    assert option(bind, "--data") == option(follow, "--data") == option(longer, "--data")


def test_the_follow_control_follows_the_shipped_model_as_step_34_followed_its_bind(calls):
    """Step 35: the control follows models/trivla_cpu with step 34's follow command but for --init, so the two
    differ only in the bind before."""
    export = next(argv for argv in calls if argv[0] == "export" and option(argv, "--out", "").endswith("/control_export"))
    control = run_writing(calls, export[1].removesuffix("/final"))
    heldall = next(argv for argv in calls if argv[0] == "train" and option(argv, "--out", "").endswith("/heldall_follow"))
    assert option(control, "--init") == "models/trivla_cpu"
    assert option(control, "--grounding-phase") == "follow"
    assert _without(control, "--init", "--out") == _without(heldall, "--init", "--out")
    assert _forty_chain_seeds(calls, option(export, "--out")) == ["1003", "1004"]


def _forty_chain_seeds(calls: list[list[str]], policy: str) -> list[str]:
    """The seeds of the 20-chain evaluations of `policy`."""
    return sorted(option(argv, "--seed") for argv in calls
                  if argv[0] == "evaluate" and option(argv, "--policy") == policy and option(argv, "--chains") == "20")


def step_57_start(argv_list: list[list[str]]) -> int:
    """The index of step 57's first call in `argv_list` (every_call or calls): its twelve evaluations of the shipped
    model come right before its first collect."""
    first_collect = next(i for i, a in enumerate(argv_list) if a[0] == "collect" and "data/sim-prelude-stacked" in a)
    return first_collect - 12


def step_58_start(argv_list: list[list[str]]) -> int:
    """The index of step 58's first call in `argv_list` (every_call or calls): its first evaluation with the
    stackfit model comes after the refit, which only every_call holds, so this looks for its diagnostics or the
    stackfit model's first evaluation, whichever comes first."""
    return next(i for i, a in enumerate(argv_list) if a[:2] == ["python", "results/stacked_subgoal/stacked_subgoal.py"]
                or (a[0] == "evaluate" and option(a, "--policy") == "runs/stackfit"))


def _without(argv: list[str], *names: str) -> list[str]:
    """One recorded call without the options `names` and their values."""
    drop = {i + k for i, a in enumerate(argv) if a in names for k in (0, 1)}
    return [a for i, a in enumerate(argv) if i not in drop]


@pytest.mark.parametrize("name", ["heldall", "control"])
def test_the_longer_follows_go_on_from_their_follow_with_another_seed(calls, name):
    """Steps 36 and 37: step 34's followed model and step 35's control followed 2500 steps more, each with its
    own follow command but --init and --seed, and the same command for both; each export runs the 40 chains."""
    export = next(argv for argv in calls if argv[0] == "export" and option(argv, "--out", "").endswith(f"/{name}2_export"))
    longer = run_writing(calls, export[1].removesuffix("/final"))
    first = next(argv for argv in calls if argv[0] == "train" and option(argv, "--out", "").endswith(f"/{name}_follow"))
    assert option(longer, "--init") == option(first, "--out") + "/final"
    assert option(longer, "--seed") == "4" != option(first, "--seed")
    assert _without(longer, "--init", "--out", "--seed") == _without(first, "--init", "--out", "--seed")
    assert _forty_chain_seeds(calls, option(export, "--out")) == ["1003", "1004"]


def test_the_reseeded_follow_is_step_36_with_another_seed_and_the_third_leg_goes_on_from_step_36(calls):
    """Step 38 repeats step 36's follow from the same start with seed 5, and nothing else changed; step 39 follows
    step 36's model with that same command. Both exports run the 40 chains."""
    def follow_of(name):
        export = next(argv for argv in calls if argv[0] == "export" and option(argv, "--out", "").endswith(f"/{name}_export"))
        assert _forty_chain_seeds(calls, option(export, "--out")) == ["1003", "1004"]
        return run_writing(calls, export[1].removesuffix("/final"))
    second, reseeded, third = follow_of("heldall2"), follow_of("heldall2b"), follow_of("heldall3")
    assert option(reseeded, "--init") == option(second, "--init")
    assert option(reseeded, "--seed") == "5" != option(second, "--seed")
    assert option(third, "--init") == option(second, "--out") + "/final"
    assert _without(reseeded, "--out", "--seed") == _without(second, "--out", "--seed")
    assert _without(third, "--init", "--out") == _without(reseeded, "--init", "--out")


def test_the_fresh_seeds_evaluate_step_29s_model_and_the_held_lineage_on_seeds_none_was_chosen_on(calls):
    """Step 40: seeds 1006-1011 for step 29's model (shipped until step 41's soup) and steps 36, 38 and 39, with the
    six-seed flags."""
    soup = next(i for i, argv in enumerate(calls) if argv[0] == "soup" and option(argv, "--out") == "models/trivla_cpu")
    for policy in ("models/trivla_cpu", "runs/heldall2_export", "runs/heldall2b_export", "runs/heldall3_export"):
        fresh = [argv for argv in calls[:soup] if argv[0] == "evaluate" and option(argv, "--policy") == policy
                 and int(option(argv, "--seed")) > 1005 and option(argv, "--chains") is None]
        assert sorted(option(argv, "--seed") for argv in fresh) == [str(seed) for seed in range(1006, 1012)]
        assert all(_without(argv, "--seed", "--policy") == _without(fresh[0], "--seed", "--policy") for argv in fresh)
        assert option(fresh[0], "--episodes") == "2" and "--prelude" not in fresh[0]


def refit_call(every_call: list[list[str]]) -> int:
    """The index in `every_call` of step 46's re-fit, which last writes models/trivla_cpu."""
    return next(i for i, argv in enumerate(every_call)
                if argv[:2] == ["python", "results/grounding_scenes/refit_grounding.py"])


def test_the_soup_is_the_held_lineages_three_follows_with_its_own_arms_and_tables(calls, every_call):
    """Step 41: models/trivla_cpu is written by the soup of steps 36 and 38 (one start, two seeds) and step 39
    (step 36 followed further), from the follows' final checkpoints; after it, until step 46 re-fits its grounding,
    come its twelve seeds (with the six seeds' flags; six more later), the 40 chains, its own ablation arms (trained
    from it), the tables with them and its grasp probe."""
    writes = [i for i, argv in enumerate(calls) if option(argv, "--out") == "models/trivla_cpu"]
    soup = calls[writes[-1]]
    assert soup[0] == "soup" and calls[writes[0]][0] == "export"  # step 29's model until then
    ingredients = soup[1:soup.index("--out")]
    follows = [run_writing(calls, path.removesuffix("/final")) for path in ingredients]
    assert [option(argv, "--out") for argv in follows] == ["runs/heldall2_follow", "runs/heldall2b_follow",
                                                           "runs/heldall3_follow"]
    assert option(follows[0], "--init") == option(follows[1], "--init") == "runs/heldall_follow/final"
    assert option(follows[2], "--init") == "runs/heldall2_follow/final"
    assert "--drop-unused-llm-layers" in soup
    soup_at = next(i for i, argv in enumerate(every_call) if argv == soup)
    after = [argv for argv in every_call[soup_at + 1:refit_call(every_call)] if argv[0] != "python"]
    six = next(argv for argv in calls if argv[0] == "evaluate" and option(argv, "--policy") == "runs/heldall2_export"
               and option(argv, "--chains") is None)
    runs = [argv for argv in after if argv[0] == "evaluate" and option(argv, "--policy") == "models/trivla_cpu"
            and option(argv, "--chains") is None and "--prelude" not in argv
            and option(argv, "--tasks") is None]  # step 43 evaluates its grasping tasks on 40 more episodes
    assert sorted(int(option(argv, "--seed")) for argv in runs) == list(range(1000, 1018))  # 1012-1017: session 37
    assert all(_without(argv, "--seed", "--policy") == _without(six, "--seed", "--policy") for argv in runs)
    assert _forty_chain_seeds(after, "models/trivla_cpu") == ["1003", "1004"]
    arms = [argv for argv in after if argv[0] == "train" and option(argv, "--init") == "models/trivla_cpu"
            and not option(argv, "--out").startswith(("runs/soupfollow", "runs/noisyfollow"))  # steps 42 and 44's follows
            and "anchor" not in option(argv, "--out")  # and step 43's binds
            and option(argv, "--stage") == "policy"]  # and step 45's System 2 runs
    assert sorted(option(argv, "--out") for argv in arms) == ["runs/arm3_s1", "runs/arm3_s13"]
    tables = [argv for argv in after if argv[0] == "tables" and option(argv, "--full") == "models/trivla_cpu"]
    assert [option(argv, "--out") for argv in tables] == ["results", "results/data_efficiency"]
    assert option(tables[0], "--system1") == "runs/arm3_s1_export"
    probes = [argv for argv in after if argv[0] == "probe" and option(argv, "--checkpoint") == "models/trivla_cpu"
              and "--grounding-scenes" not in argv]  # step 43 checks the shipped grounding next to its anchored ones
    # ... and probes the shipped model's grasps on 36 scenes next to its wrist-anchored one's
    assert [option(argv, "--grasp-episodes") for argv in probes] == ["6", "12"]


def test_the_soups_of_the_shipped_soups_follows_are_made_from_one_start_and_evaluated_on_eighteen_seeds(calls):
    """Step 42: two follows of the shipped soup that differ only in their seed (41, 42), with step 36's command; the
    soup of them with the shipped soup and of them alone; each soup on seeds 1000-1017 with the six seeds' flags."""
    follows = [run_writing(calls, f"runs/soupfollow{seed}") for seed in (41, 42)]
    assert option(follows[0], "--init") == option(follows[1], "--init") == "models/trivla_cpu"
    assert _without(follows[0], "--out", "--seed") == _without(follows[1], "--out", "--seed")
    step36 = run_writing(calls, "runs/heldall2_follow")
    assert _without(follows[0], "--out", "--seed", "--init") == _without(step36, "--out", "--seed", "--init")
    soups = {option(argv, "--out"): argv[1:argv.index("--out")] for argv in calls if argv[0] == "soup"}
    finals = ["runs/soupfollow41/final", "runs/soupfollow42/final"]
    assert soups["runs/soupSF"] == ["models/trivla_cpu", *finals] and soups["runs/soupF"] == finals
    six = next(argv for argv in calls if argv[0] == "evaluate" and option(argv, "--policy") == "runs/heldall2_export"
               and option(argv, "--chains") is None)
    for policy in ("runs/soupSF", "runs/soupF"):
        runs = [argv for argv in calls if argv[0] == "evaluate" and option(argv, "--policy") == policy]
        assert sorted(int(option(argv, "--seed")) for argv in runs) == list(range(1000, 1018))
        assert all(_without(argv, "--seed", "--policy") == _without(six, "--seed", "--policy") for argv in runs)


def test_the_anchored_groundings_are_bound_on_the_shipped_model_checked_and_the_wrist_one_followed(calls):
    """Step 43: two binds of the shipped model's grounding that differ only in the anchor's cameras, each
    checked with the shipped model on the same scenes; the wrist-anchored one followed with step 36's command
    and evaluated on seeds 1000-1017 with the six seeds' flags; its grasps probed next to the shipped model's."""
    static, wrist = run_writing(calls, "runs/anchor_bind"), run_writing(calls, "runs/anchor_wrist_bind")
    assert option(static, "--init") == option(wrist, "--init") == "models/trivla_cpu"
    assert "--grounding-anchor" in static and "--grounding-anchor-wrist" not in static
    assert _without(wrist, "--out") == _without(static, "--out") + ["--grounding-anchor-wrist"]
    assert option(static, "--grounding-phase") == "bind" and "--keep-grounding" in static
    assert option(static, "--grounding-carry") == option(run_writing(calls, "runs/heldall2_follow"), "--grounding-carry")
    probes = {option(argv, "--checkpoint"): argv for argv in calls if argv[0] == "probe"
              and option(argv, "--grounding-scenes") == "20"}
    checked = ["models/trivla_cpu", "runs/anchor_bind/final", "runs/anchor_wrist_bind/final"]
    assert set(checked) <= set(probes)
    assert len({tuple(_without(probes[c], "--checkpoint")) for c in checked}) == 1
    follow = run_writing(calls, "runs/anchor_wrist_follow")
    assert option(follow, "--init") == "runs/anchor_wrist_bind/final" and option(follow, "--seed") == "43"
    step36 = run_writing(calls, "runs/heldall2_follow")
    assert _without(follow, "--out", "--seed", "--init") == _without(step36, "--out", "--seed", "--init")
    assert "--drop-unused-llm-layers" in run_writing(calls, "runs/anchor_wrist_export")
    six = next(argv for argv in calls if argv[0] == "evaluate" and option(argv, "--policy") == "runs/heldall2_export"
               and option(argv, "--chains") is None)
    runs = [argv for argv in calls if argv[0] == "evaluate" and option(argv, "--policy") == "runs/anchor_wrist_export"
            and option(argv, "--tasks") is None]
    assert sorted(int(option(argv, "--seed")) for argv in runs) == list(range(1000, 1018))
    assert all(_without(argv, "--seed", "--policy") == _without(six, "--seed", "--policy") for argv in runs)
    grasps = {option(argv, "--checkpoint"): argv for argv in calls if argv[0] == "probe"
              and option(argv, "--grasp-episodes") == "12"}
    assert set(grasps) == {"runs/anchor_wrist_export", "models/trivla_cpu"}
    assert _without(grasps["runs/anchor_wrist_export"], "--checkpoint") == _without(grasps["models/trivla_cpu"], "--checkpoint")
    grasping = {option(argv, "--policy"): argv for argv in calls if argv[0] == "evaluate"
                and option(argv, "--seed") == "2000" and option(argv, "--policy") != "runs/soupN"}  # step 44's
    assert set(grasping) == {"runs/anchor_wrist_export", "models/trivla_cpu"}
    assert option(grasping["models/trivla_cpu"], "--tasks") == "lift_block,stack_block,place_in_bowl"
    assert _without(grasping["runs/anchor_wrist_export"], "--policy") == _without(grasping["models/trivla_cpu"], "--policy")


def test_the_noisy_follows_are_step_42s_follows_with_subgoal_noise_souped_and_evaluated_as_step_42s_soups(calls):
    """Step 44: step 42's two follows (same start, seeds, command) with --subgoal-noise 0.02 and nothing else
    changed; their soup on seeds 1000-1017 with the six seeds' flags and on the grasping tasks at seed 2000 as
    step 43 evaluated the shipped model there."""
    for seed in (41, 42):
        noisy, plain = run_writing(calls, f"runs/noisyfollow{seed}"), run_writing(calls, f"runs/soupfollow{seed}")
        assert _without(noisy, "--out", "--subgoal-noise") == _without(plain, "--out")
        assert option(noisy, "--subgoal-noise") == "0.02"
    soups = {option(argv, "--out"): argv[1:argv.index("--out")] for argv in calls if argv[0] == "soup"}
    assert soups["runs/soupN"] == ["runs/noisyfollow41/final", "runs/noisyfollow42/final"]
    six = next(argv for argv in calls if argv[0] == "evaluate" and option(argv, "--policy") == "runs/soupF")
    runs = [argv for argv in calls if argv[0] == "evaluate" and option(argv, "--policy") == "runs/soupN"
            and option(argv, "--tasks") is None]
    assert sorted(int(option(argv, "--seed")) for argv in runs) == list(range(1000, 1018))
    assert all(_without(argv, "--seed", "--policy") == _without(six, "--seed", "--policy") for argv in runs)
    grasping = [argv for argv in calls if argv[0] == "evaluate" and option(argv, "--seed") == "2000"]
    noisy = next(argv for argv in grasping if option(argv, "--policy") == "runs/soupN")
    shipped = next(argv for argv in grasping if option(argv, "--policy") == "models/trivla_cpu")
    assert _without(noisy, "--policy") == _without(shipped, "--policy")


def test_the_system2_scene_runs_train_the_shipped_models_image_tokens_on_ten_times_the_scenes_by_the_dense_loss(calls):
    """Step 45: two vlm runs from the shipped model on 5000 VQA scenes, the dense loss alone (the answers' weight 0),
    that differ only in their learning rate and in the 7 x 7 sub-cells of the second one's new head."""
    same_head, finer = run_writing(calls, "runs/s2more"), run_writing(calls, "runs/s2sub7")
    for run in (same_head, finer):
        assert option(run, "--stage") == "vlm" and option(run, "--init") == "models/trivla_cpu"
        assert option(run, "--answer-weight") == "0" and option(run, "--dense-weight") == "1"
        assert option(run, "--vqa-scenes") == "5000"
    assert option(same_head, "--dense-subcells") is None and option(finer, "--dense-subcells") == "7"
    assert _without(finer, "--out", "--lr", "--dense-subcells") == _without(same_head, "--out", "--lr")


def test_the_shipped_checkpoint_is_the_soup_with_its_grounding_refit_on_rendered_scenes(calls, every_call):
    """Step 46: models/trivla_cpu is last written by the re-fit of step 41's soup (the copy it kept) on 12000
    rendered scenes and DATA's grounding frames; then the grounding check, the 120 grasping scenes, eighteen
    seeds with the six seeds' flags, compared with the soup's, and its own tables."""
    at = refit_call(every_call)
    refit = every_call[at]
    assert refit[2:5] == ["runs/soup3", "data/sim", "models/trivla_cpu"]
    assert [option(refit, k) for k in ("--scenes", "--steps", "--lr")] == ["12000", "1500", "3e-4"]
    later = every_call[at + 1:]
    assert not any(option(argv, "--out") == "models/trivla_cpu" for argv in later)  # the last write
    later = every_call[at + 1:step_57_start(every_call)]  # step 57 reruns the six seeds on another CPU kind
    evaluations = [argv for argv in later if argv[0] == "evaluate" and option(argv, "--policy") == "models/trivla_cpu"
                   and option(argv, "--tasks") is None and "--home-first" not in argv]  # step 50's are a diagnostic
    runs = [argv for argv in evaluations if option(argv, "--chains") is None and option(argv, "--prelude") is None]
    assert sorted(int(option(argv, "--seed")) for argv in runs) == list(range(1000, 1018))
    # Session 45: its 40 chains and the preludes, as the soup's; session 46 (step 48): 40 more chains.
    assert sorted(option(argv, "--seed") for argv in evaluations
                  if option(argv, "--chains") == "20") == ["1003", "1004", "1005", "1006"]
    assert sorted((option(argv, "--prelude"), option(argv, "--seed")) for argv in evaluations
                  if option(argv, "--prelude") is not None) == [("1", "1000"), ("1", "1001"), ("1", "1002"), ("2", "1000")]
    tables = [argv for argv in later if argv[0] == "tables"]
    assert [(option(a, "--full"), option(a, "--out")) for a in tables] == [("models/trivla_cpu", "results/grounding_scenes/tables")]
    six = next(argv for argv in calls if argv[0] == "evaluate" and option(argv, "--policy") == "runs/heldall2_export"
               and option(argv, "--chains") is None)
    assert all(_without(argv, "--seed", "--policy") == _without(six, "--seed", "--policy") for argv in runs)
    grasp = next(argv for argv in later if argv[0] == "evaluate" and option(argv, "--tasks") is not None)
    assert (option(grasp, "--episodes"), option(grasp, "--seed")) == ("40", "2000")
    assert any(argv[0] == "probe" and option(argv, "--grounding-scenes") == "20" for argv in later)
    compare = next(argv for argv in later if argv[:2] == ["python", "results/follow_control/compare_seeds.py"])
    assert "shipped=results/model_soup/soup3" in compare and "refit=results/grounding_scenes/refit" in compare
    copy_at = SCRIPT.read_text().index('cp -r models/trivla_cpu "$RUNS/soup3"')
    # Step 47 (optional): the re-fit again with chain-start scenes, never written over the shipped model.
    chainfit = [argv for argv in later if argv[:2] == ["python", "results/grounding_scenes/refit_grounding.py"]
                and argv[4] == "runs/chainfit"]
    assert [argv[2:5] for argv in chainfit] == [["models/trivla_cpu", "data/sim", "runs/chainfit"]]
    assert [option(chainfit[0], k) for k in ("--scenes", "--chain-starts")] == ["8000", "0.5"]
    assert sorted(int(option(argv, "--seed")) for argv in later if argv[0] == "evaluate"
                  and option(argv, "--policy") == "runs/chainfit" and option(argv, "--chains") is None
                  and option(argv, "--prelude") is None) == list(range(1000, 1018))
    assert SCRIPT.read_text().index("trivla-drake soup") < copy_at < SCRIPT.read_text().index("# 42.")


def test_step_48_joins_the_shipped_tables_with_the_soups_arms_after_both_are_made(every_call):
    """Step 48: the shipped model's report is joined after its own tables (step 46) and the soup's tables with the
    arms (step 31); and the stack and carrying-sub-goal diagnostics run on the shipped checkpoint."""
    scripts = [argv[1] for argv in every_call if argv[0] == "python"]
    join = scripts.index("results/join_shipped_report.py")
    assert join > len(scripts) - 1 - scripts[::-1].index("results/join_data_efficiency.py")  # after the last soup join
    calls_before = every_call[: next(i for i, argv in enumerate(every_call)
                                     if argv[:2] == ["python", "results/join_shipped_report.py"])]
    assert any(argv[0] == "tables" and option(argv, "--out") == "results/grounding_scenes/tables" for argv in calls_before)
    stack = next(argv for argv in every_call if argv[:2] == ["python", "results/stack_destinations/stack_destinations.py"]
                 and argv[3] == "results/stack_destinations/refit.json")
    release = next(argv for argv in every_call if argv[:2] == ["python", "results/subgoal_diagnostics/true_release.py"])
    assert stack[2] == "models/trivla_cpu" and release[2:] == ["1000,1001,1002,1003,1004,1005",
                                                               "results/subgoal_diagnostics/release"]
    lamp = next(argv for argv in every_call if argv[:2] == ["python", "results/grounding_scenes/lamp_after_prelude.py"])
    assert lamp[2:] == ["results/grounding_scenes/lamp_after_prelude.json", "3"]  # the shipped checkpoint by default


def test_step_49_follows_the_shipped_model_with_step_42s_command_and_evaluates_it_as_the_shipped_one(calls):
    """Step 49 (optional): the shipped checkpoint's System 1 followed with the soup follows' command but for the
    start and seed; its export evaluated on the shipped model's chains, preludes and eighteen seeds."""
    follow, soup_follow = run_writing(calls, "runs/shipfollow"), run_writing(calls, "runs/soupfollow41")
    assert option(follow, "--init") == "models/trivla_cpu" and option(follow, "--seed") == "46"
    assert _without(follow, "--out", "--seed") == _without(soup_follow, "--out", "--seed")
    runs = [argv for argv in calls if argv[0] == "evaluate" and option(argv, "--policy") == "runs/shipfollow_export"]
    assert sorted(option(a, "--seed") for a in runs if option(a, "--chains") == "20") == ["1003", "1004", "1005", "1006"]
    assert sorted(int(option(a, "--seed")) for a in runs
                  if option(a, "--chains") is None and option(a, "--prelude") is None) == list(range(1000, 1018))
    assert len([a for a in runs if option(a, "--prelude") is not None]) == 4


def test_step_50_is_a_record_that_no_longer_overwrites_the_first_versions_files(calls):
    text = SCRIPT.read_text()
    block = text[text.index("# 50. "):text.index("# 51. ")]
    assert "git checkout d85a985" in block
    assert all(line.lstrip().startswith("#") for line in block.splitlines() if line.strip())


def test_step_51_follows_the_shipped_model_on_more_prelude_data_with_step_49_s_command(calls):
    weak = run_writing(calls, "runs/weakfollow")
    ship = run_writing(calls, "runs/shipfollow")
    assert option(weak, "--data") == "data/sim-prelude-more-weak" and option(ship, "--data") == "data/sim-prelude-more"
    assert _without(weak, "--data", "--out") == _without(ship, "--data", "--out")
    collect = next(argv for argv in calls if argv[0] == "collect" and option(argv, "--out") == "data/sim-prelude-more-weak")
    assert option(collect, "--prelude-tasks") == "4" and len(option(collect, "--tasks").split(",")) == 7
    assert calls.index(collect) < calls.index(weak)
    evaluations = [a for a in calls if a[0] == "evaluate" and option(a, "--policy") == "runs/weakfollow_export"]
    assert len(evaluations) == 3 + 4 + 18


def test_the_chain_position_tables_read_each_model_s_four_chain_seeds(every_call):
    tables = [argv for argv in every_call if argv[:2] == ["python", "results/grounding_scenes/chain_positions.py"]]
    prefixes = ["results/grounding_scenes/refit", "results/shipped_follow/shipfollow", "results/weak_preludes/weak",
                "results/grounding_scenes/more_scenes/refit30k", "results/prelude_reset/settled_home"]
    assert [argv[2:6] for argv in tables] == [[f"{p}_chains20_seed{s}.json" for s in range(1003, 1007)] for p in prefixes]
    assert all(argv.count("--expected") == 2 for argv in tables)


def test_step_52_refits_the_shipped_grounding_on_more_scenes_and_evaluates_it_as_the_shipped_one(every_call):
    refits = [argv for argv in every_call if argv[:2] == ["python", "results/grounding_scenes/refit_grounding.py"]]
    more = next(argv for argv in refits if argv[4] == "runs/refit30k")
    assert more[2:4] == ["models/trivla_cpu", "data/sim"]
    assert [option(more, k) for k in ("--scenes", "--steps", "--lr")] == ["30000", "3000", "3e-4"]
    shipped = refits.index(next(argv for argv in refits if argv[4] == "models/trivla_cpu"))
    assert shipped < refits.index(more)  # it starts from step 46's model
    runs = [argv for argv in every_call if argv[0] == "evaluate" and option(argv, "--policy") == "runs/refit30k"]
    assert sorted(int(option(a, "--seed")) for a in runs
                  if option(a, "--chains") is None and option(a, "--prelude") is None) == list(range(1000, 1018))
    assert sorted(option(a, "--seed") for a in runs if option(a, "--chains") == "20") == ["1003", "1004", "1005", "1006"]
    assert sorted((option(a, "--prelude"), option(a, "--seed")) for a in runs if option(a, "--prelude") is not None) == [
        ("1", "1000"), ("1", "1001"), ("1", "1002"), ("2", "1000")]
    compare = [argv for argv in every_call if argv[:2] == ["python", "results/follow_control/compare_seeds.py"]
               and "refit30k=results/grounding_scenes/more_scenes/refit30k" in argv]
    assert len(compare) == 1 and "shipped=results/grounding_scenes/refit" in compare[0]


def test_step_53_restarts_the_tasks_after_a_prelude_three_ways_then_homes_the_preludes_and_chains(every_call):
    resets = [argv for argv in every_call if argv[:2] == ["python", "results/prelude_reset/reset_after_prelude.py"]]
    arms = sorted((option(a, "--arm", "start"), a[3]) for a in resets)
    assert arms == sorted((arm, seed) for arm in ("start", "prelude", "home") for seed in ("1000", "1001", "1002"))
    assert all(a[2] == "models/trivla_cpu" for a in resets)
    homed = [argv for argv in every_call if argv[0] == "evaluate" and "--home-first" in argv]
    assert all(option(a, "--policy") == "models/trivla_cpu" for a in homed)
    assert sorted((option(a, "--prelude"), option(a, "--seed")) for a in homed if option(a, "--prelude")) == [
        ("1", "1000"), ("1", "1001"), ("1", "1002"), ("2", "1000")]
    assert sorted(option(a, "--seed") for a in homed if option(a, "--chains") == "20") == ["1003", "1004", "1005", "1006"]
    positions = [argv for argv in every_call if argv[:2] == ["python", "results/grounding_scenes/chain_positions.py"]]
    assert positions[-1][2:6] == [f"results/prelude_reset/settled_home_chains20_seed{s}.json" for s in range(1003, 1007)]
    assert ["python", "results/prelude_reset/compare_preludes.py"] in every_call
    assert ["python", "results/prelude_reset/handover_check.py"] in every_call


def test_step_54_traces_each_grasp_task_of_the_chains_and_summarises_it(every_call):
    traces = [argv for argv in every_call if argv[:2] == ["python", "results/chain_lifts/chain_lifts.py"]]
    assert sorted((option(a, "--task"), option(a, "--single-seeds"), a[3]) for a in traces) == [
        ("lift_block", "1000-1017", "results/chain_lifts/lifts.json"),
        ("place_in_bowl", "1000-1011", "results/chain_lifts/place.json"),
        ("stack_block", "1000-1011", "results/chain_lifts/stack.json"),
        ("unstack_block", "1000-1011", "results/chain_lifts/unstack.json")]
    summaries = [a[2] for a in every_call if a[:2] == ["python", "results/chain_lifts/summarise.py"]]
    assert summaries == [f"results/chain_lifts/{name}.json" for name in ("lifts", "stack", "place", "unstack")]
    step_55 = next(i for i, a in enumerate(every_call) if a[0] == "collect" and "data/sim-stacked-pilot" in a)
    stacked = [a for a in every_call[:step_55] if a[0] == "evaluate" and "--stacked-picks" in a]
    assert sorted((option(a, "--policy"), option(a, "--seed")) for a in stacked) == sorted(
        (policy, str(seed)) for policy in ("oracle", "models/trivla_cpu") for seed in range(1000, 1006))
    assert {option(a, "--tasks") for a in stacked} == {"lift_block,stack_block,place_in_bowl"}
    assert ["python", "results/chain_lifts/stacked_compare.py"] in every_call


def test_step_55_follows_the_shipped_model_on_clean_and_stacked_pick_demonstrations_with_step_49_s_command(calls,
                                                                                                          every_call):
    stacked = run_writing(calls, "runs/stackedfollow")
    ship = run_writing(calls, "runs/shipfollow")
    assert option(stacked, "--data") == "data/sim-stacked-pilot" and option(stacked, "--steps") == "1500"
    assert _without(stacked, "--data", "--out", "--steps") == _without(ship, "--data", "--out", "--steps")
    collects = [a for a in calls if a[0] == "collect" and option(a, "--out") == "data/sim-stacked-pilot"]
    assert [(option(a, "--episodes-per-task"), option(a, "--stacked-picks"), option(a, "--tasks")) for a in collects] == [
        ("15", None, None), ("35", "1", "lift_block,stack_block,place_in_bowl")]
    assert calls.index(collects[-1]) < calls.index(stacked)
    evaluations = [a for a in calls if a[0] == "evaluate" and option(a, "--policy") == "runs/stackedfollow_export"]
    picks = [a for a in evaluations if "--stacked-picks" in a]
    assert sorted(option(a, "--seed") for a in picks) == [str(s) for s in range(1000, 1006)]
    assert {option(a, "--tasks") for a in picks} == {"lift_block,stack_block,place_in_bowl"}
    assert sorted(option(a, "--seed") for a in evaluations if a not in picks) == [str(s) for s in range(1000, 1006)]
    compares = [a for a in every_call if a[:2] == ["python", "results/follow_control/compare_seeds.py"]
                and any(x.startswith("stackedfollow=") for x in a)]
    assert [a[3] for a in compares] == ["shipped=results/chain_lifts/stacked_picks/shipped",
                                        "shipped=results/grounding_scenes/refit"]


def test_step_56_is_step_55_s_follow_with_the_shipped_models_normalisation_kept(calls, every_call):
    kept = run_writing(calls, "runs/keepnorm")
    refit = run_writing(calls, "runs/stackedfollow")
    assert "--keep-normalization" in kept and "--keep-normalization" not in refit
    assert [a for a in _without(kept, "--out") if a != "--keep-normalization"] == _without(refit, "--out")
    assert calls.index(refit) < calls.index(kept)
    evaluations = [a for a in calls if a[0] == "evaluate" and option(a, "--policy") == "runs/keepnorm_export"]
    picks = [a for a in evaluations if "--stacked-picks" in a]
    assert sorted(option(a, "--seed") for a in picks) == [str(s) for s in range(1000, 1006)]
    assert sorted(option(a, "--seed") for a in evaluations if a not in picks) == [str(s) for s in range(1000, 1006)]
    compares = [a for a in every_call if a[:2] == ["python", "results/follow_control/compare_seeds.py"]
                and any(x.startswith("kept=") for x in a) and not any(x.startswith("mix=") for x in a)]
    assert [a[3:] for a in compares] == [
        ["shipped=results/chain_lifts/stacked_picks/shipped", "refit=results/stacked_pick_demos/stacked_picks",
         "kept=results/kept_normalization/stacked_picks"],
        ["shipped=results/grounding_scenes/refit", "refit=results/stacked_pick_demos/stackedfollow",
         "kept=results/kept_normalization/keepnorm"]]


def test_step_57_follows_with_kept_statistics_on_a_prelude_mix_with_stacked_picks_and_reruns_the_shipped_model(
        calls, every_call):
    mix = run_writing(calls, "runs/prelude_stacked")
    kept = run_writing(calls, "runs/keepnorm")
    assert option(mix, "--data") == "data/sim-prelude-stacked" and "--keep-normalization" in mix
    assert _without(mix, "--data", "--out") == _without(kept, "--data", "--out")
    collects = [a for a in calls if a[0] == "collect" and option(a, "--out") == "data/sim-prelude-stacked"]
    assert [(option(a, "--episodes-per-task"), option(a, "--prelude-tasks"), option(a, "--stacked-picks"),
             option(a, "--tasks")) for a in collects] == [
        ("8", None, None, None), ("24", "4", None, None), ("44", None, "1", "lift_block,stack_block,place_in_bowl")]
    assert calls.index(collects[-1]) < calls.index(mix)
    for policy in ("models/trivla_cpu", "runs/prelude_stacked_export"):  # the shipped model rerun on this CPU too
        evaluations = [a for a in calls[step_57_start(calls):step_58_start(calls)] if a[0] == "evaluate"
                       and option(a, "--policy") == policy]
        picks = [a for a in evaluations if "--stacked-picks" in a]
        assert sorted(option(a, "--seed") for a in picks) == [str(s) for s in range(1000, 1006)]
        assert sorted(option(a, "--seed") for a in evaluations if a not in picks) == [str(s) for s in range(1000, 1006)]
    compares = [a for a in every_call if a[:2] == ["python", "results/follow_control/compare_seeds.py"]
                and any(x.startswith("mix=") for x in a)]
    assert [a[3] for a in compares] == ["shipped=results/prelude_stacked_mix/shipped_stacked_picks",
                                        "shipped=results/prelude_stacked_mix/shipped"]


def test_step_58_replaces_the_stacked_picks_sub_goal_then_refits_the_grounding_with_stacked_scenes(calls, every_call):
    diagnostics = [a for a in every_call if a[:2] == ["python", "results/stacked_subgoal/stacked_subgoal.py"]]
    assert [a[2:] for a in diagnostics] == [[mode, "1000,1001,1002,1003,1004,1005", "results/stacked_subgoal"]
                                            for mode in ("z", "xyz")]
    refits = [a for a in every_call if a[:2] == ["python", "results/grounding_scenes/refit_grounding.py"]]
    stackfit = next(a for a in refits if a[4] == "runs/stackfit")
    shipped = next(a for a in refits if a[4] == "models/trivla_cpu")
    assert stackfit[2:4] == ["models/trivla_cpu", "data/sim"] and refits.index(shipped) < refits.index(stackfit)
    assert [option(stackfit, k) for k in ("--scenes", "--stacked-picks", "--steps", "--lr")] == [
        "12000", "0.3", "1500", "3e-4"]
    runs = [a for a in calls if a[0] == "evaluate" and option(a, "--policy") == "runs/stackfit"]
    picks = [a for a in runs if "--stacked-picks" in a]
    assert sorted(option(a, "--seed") for a in picks) == [str(s) for s in range(1000, 1006)]
    assert sorted(option(a, "--seed") for a in runs if a not in picks and option(a, "--chains") is None) == [
        str(s) for s in range(1000, 1006)]
    for policy in ("runs/stackfit", "models/trivla_cpu"):  # both models' chains run on one CPU kind
        chains = [a for a in calls[step_58_start(calls):] if a[0] == "evaluate" and option(a, "--policy") == policy
                  and option(a, "--chains") == "20"]
        assert sorted(option(a, "--seed") for a in chains) == ["1003", "1004", "1005", "1006"]
    compares = [a for a in every_call if a[:2] == ["python", "results/follow_control/compare_seeds.py"]
                and any(x.startswith("stackfit=") for x in a) and not any(x.startswith("stackhold=") for x in a)]
    assert [a[2:4] for a in compares] == [
        ["results/stacked_subgoal/stacked_picks.png", "shipped=results/chain_lifts/stacked_picks/shipped"],
        ["--chain-seeds", "1003-1006"]]
    assert compares[1][5] == "shipped=results/prelude_stacked_mix/shipped+results/stacked_subgoal/shipped"


def assert_stacked_refit_evaluations(calls: list[list[str]], policy: str) -> None:
    """`policy` was evaluated on the stacked picks and the usual scenes of seeds 1000-1005 and on 80 chains."""
    runs = [a for a in calls if a[0] == "evaluate" and option(a, "--policy") == policy]
    picks = [a for a in runs if "--stacked-picks" in a]
    chains = [a for a in runs if option(a, "--chains") == "20"]
    assert sorted(option(a, "--seed") for a in picks) == [str(s) for s in range(1000, 1006)]
    assert sorted(option(a, "--seed") for a in runs if a not in picks + chains) == [str(s) for s in range(1000, 1006)]
    assert sorted(option(a, "--seed") for a in chains) == ["1003", "1004", "1005", "1006"]


def test_step_59_refits_with_stacked_scenes_drawn_more_and_the_other_answers_held(calls, every_call):
    refits = [a for a in every_call if a[:2] == ["python", "results/grounding_scenes/refit_grounding.py"]]
    stackhold = next(a for a in refits if a[4] == "runs/stackhold")
    assert stackhold[2:4] == ["models/trivla_cpu", "data/sim"]
    assert [option(stackhold, k) for k in ("--scenes", "--stacked-picks", "--stacked-share", "--hold", "--steps", "--lr")] == [
        "12000", "0.3", "0.4", "1", "1500", "3e-4"]
    held_harder = next(a for a in refits if a[4] == "runs/stackhold5")
    assert option(held_harder, "--hold") == "5" and option(held_harder, "--report") == "results/stacked_hold/stackhold5_refit"
    assert ["python", "results/stacked_hold/stack_probe.py", "models/trivla_cpu",
            "results/stacked_hold/stack_probe.json"] in every_call
    assert not any(a[0] == "evaluate" and option(a, "--policy") == "runs/stackhold5" for a in calls)
    assert_stacked_refit_evaluations(calls, "runs/stackhold")
    compares = [a for a in every_call if a[:2] == ["python", "results/follow_control/compare_seeds.py"]
                and any(x.startswith("stackhold=") for x in a)]
    assert compares[0][2:] == ["results/stacked_hold/stacked_picks.png", "shipped=results/chain_lifts/stacked_picks/shipped",
                               "stackfit=results/stacked_subgoal/stackfit_stacked_picks",
                               "stackhold=results/stacked_hold/stackhold_stacked_picks"]
    assert compares[1][2:5] == ["--chain-seeds", "1003-1006", "results/stacked_hold/compare.png"]
    assert compares[1][5:] == ["shipped=results/prelude_stacked_mix/shipped+results/stacked_subgoal/shipped",
                               "stackfit=results/stacked_subgoal/stackfit", "stackhold=results/stacked_hold/stackhold"]


def test_step_60_holds_the_goal_token_too_and_compares_with_step_59(calls, every_call):
    refits = [a for a in every_call if a[:2] == ["python", "results/grounding_scenes/refit_grounding.py"]]
    goalhold = next(a for a in refits if a[4] == "runs/goalhold")
    stackhold = next(a for a in refits if a[4] == "runs/stackhold")
    assert goalhold[2:4] == stackhold[2:4] == ["models/trivla_cpu", "data/sim"]
    same = ("--scenes", "--stacked-picks", "--stacked-share", "--hold", "--steps", "--lr")
    assert [option(goalhold, k) for k in same] == [option(stackhold, k) for k in same]  # step 59's, plus the goal hold
    assert option(goalhold, "--goal-hold") == "1" and option(stackhold, "--goal-hold") is None
    assert option(goalhold, "--report") == "results/goal_hold/goalhold_refit"
    rerun = [a for a in refits if a[4] == "runs/stackhold" and option(a, "--report") == "results/goal_hold/stackhold_rerun_refit"]
    assert len(rerun) == 1 and [option(rerun[0], k) for k in same] == [option(stackhold, k) for k in same]
    assert_stacked_refit_evaluations(calls, "runs/goalhold")
    compares = [a for a in every_call if a[:2] == ["python", "results/follow_control/compare_seeds.py"]
                and any(x.startswith("goalhold=") for x in a)]
    assert compares[0][2:] == ["results/goal_hold/stacked_picks.png", "shipped=results/chain_lifts/stacked_picks/shipped",
                               "stackhold=results/stacked_hold/stackhold_stacked_picks",
                               "goalhold=results/goal_hold/goalhold_stacked_picks"]
    assert compares[1][2:5] == ["--chain-seeds", "1003-1006", "results/goal_hold/compare.png"]
    assert compares[1][5:] == ["shipped=results/prelude_stacked_mix/shipped+results/stacked_subgoal/shipped",
                               "stackhold=results/stacked_hold/stackhold", "goalhold=results/goal_hold/goalhold"]


def test_step_61_trains_step_30_s_arm_on_three_tenths_of_the_data_and_draws_the_curve(calls, every_call):
    """Step 61: the same three phases as step 30's arm with a fifth of its steps, on 9 + 15 demonstrations per task
    (MORE_DATA's 30 + 50 per task times 0.3), evaluated on six seeds, then the learning curve."""
    def lineage(export_dir: str) -> list[list[str]]:
        follow = run_writing(calls, export_dir.removesuffix("/final"))
        bind = run_writing(calls, option(follow, "--init").removesuffix("/final"))
        joint = run_writing(calls, option(bind, "--init").removesuffix("/final"))
        return [follow, bind, joint]

    export30 = run_writing(calls, "runs/data30_export")
    export10 = run_writing(calls, "runs/data10_export")
    arm30, arm10 = lineage(export30[1]), lineage(export10[1])

    def without_names_or_steps(argv: list[str]) -> list[str]:
        steps = argv.index("--steps") + 1
        return [a for i, a in enumerate(argv) if i != steps and not any(n in a for n in ("data10", "data30", "pct"))]
    # the same commands, with a fifth of step 30's steps (what fitted the session's time)
    assert [without_names_or_steps(a) for a in arm30] == [without_names_or_steps(a) for a in arm10]
    assert [option(a, "--steps") for a in arm10] == ["2500", "1200", "2000"]
    assert [option(a, "--steps") for a in arm30] == ["300", "300", "600"]
    data = option(arm30[0], "--data")
    collected = [argv for argv in calls if argv[0] == "collect" and option(argv, "--out") == data]
    assert [(int(option(a, "--episodes-per-task")), "--prelude-tasks" in a) for a in collected] == [(9, False), (24, True)]
    evaluated = [argv for argv in calls if argv[0] == "evaluate" and option(argv, "--policy") == "runs/data30_export"]
    assert sorted(option(a, "--seed") for a in evaluated) == [str(s) for s in range(1000, 1006)]
    assert any(a[:2] == ["python", "results/data_efficiency/learning_curve.py"] for a in every_call)


def test_step_62_binds_a_fresh_grounding_from_the_shipped_model_on_shares_of_360_clean_and_on_step_61_s_mix(calls):
    """Step 62: step 61's bind, from the shipped model, on 360 clean demonstrations, 0.8 / 0.5 / 0.3 of them and
    step 61's 288 (9 clean + 15 after a prelude a task); each checked on unseen scenes."""
    binds = {option(a, "--out"): a for a in calls if a[0] == "train" and "shippedbind_" in option(a, "--out", "")}
    assert sorted(binds) == [f"runs/shippedbind_{n}" for n in
                             ("clean360", "clean360_f0.3", "clean360_f0.5", "clean360_f0.8", "mix288")]
    step61_bind = run_writing(calls, "runs/data30_bind")
    for out, argv in binds.items():
        assert option(argv, "--init") == "models/trivla_cpu" and option(argv, "--grounding-phase") == "bind"
        for flag in ("--lr", "--steps", "--batch-size", "--beta2", "--grad-clip"):
            assert option(argv, flag) == option(step61_bind, flag) or (flag == "--steps" and option(argv, flag) == "1200")
        assert ["probe", "--checkpoint", f"{out}/final", "--grounding-scenes", "10", "--threads", "2"] in calls
    assert [option(binds[f"runs/shippedbind_clean360_f{f}"], "--fraction") for f in ("0.8", "0.5", "0.3")] == \
        ["0.8", "0.5", "0.3"]
    clean, mix = option(binds["runs/shippedbind_clean360"], "--data"), option(binds["runs/shippedbind_mix288"], "--data")
    collected = {d: [(int(option(a, "--episodes-per-task")), "--prelude-tasks" in a)
                     for a in calls if a[0] == "collect" and option(a, "--out") == d] for d in (clean, mix)}
    assert collected == {clean: [(30, False)], mix: [(9, False), (24, True)]}


def test_step_63_follows_a_fresh_system1_on_the_shipped_grounding_at_10_and_30_percent_and_draws_the_curve(calls, every_call):
    """Step 63: the small-data arms keeping the shipped grounding: a fresh System 1 in a follow run from the
    shipped model, as many steps as step 30's joint and follow together, on step 30's 96 demonstrations and on
    step 62's 288; each checked, exported and evaluated on six seeds; the curve drawn through them."""
    step30_joint, step30_follow = run_writing(calls, "runs/data10_joint"), run_writing(calls, "runs/data10_follow")
    data = {"kept10": option(step30_follow, "--data"),
            "kept30": option(run_writing(calls, "runs/shippedbind_mix288"), "--data")}
    clean = {"keptclean360": option(run_writing(calls, "runs/shippedbind_clean360"), "--data")}
    for name, expected_data in {**data, **clean}.items():
        follow = run_writing(calls, f"runs/{name}_follow")
        assert option(follow, "--data") == expected_data
        assert option(follow, "--init") == "models/trivla_cpu" and "--fresh-system1" in follow
        assert option(follow, "--grounding-phase") == "follow" and "--subgoal-offset" in follow
        assert int(option(follow, "--steps")) == \
            int(option(step30_joint, "--steps")) + int(option(step30_follow, "--steps"))
        assert option(follow, "--ema-decay") == option(step30_follow, "--ema-decay")
        assert ["probe", "--checkpoint", f"runs/{name}_follow/final", "--grounding-scenes", "10", "--threads", "2"] in calls
        export = run_writing(calls, f"runs/{name}_export")
        assert export[1] == f"runs/{name}_follow/final" and "--drop-unused-llm-layers" in export
        seeds = [option(a, "--seed") for a in calls if a[0] == "evaluate" and "--chains" not in a
                 and option(a, "--policy") == f"runs/{name}_export"]
        assert seeds == [str(s) for s in range(1000, 1006)]
    # and both arms followed on to step 30's stored arm's 8200 steps
    step30_runs = [run_writing(calls, f"runs/data10_{phase}") for phase in ("joint", "bind", "follow", "follow2")]
    for name, expected_data in data.items():
        longer = run_writing(calls, f"runs/{name}_follow2")
        assert option(longer, "--init") == f"runs/{name}_follow/final" and "--fresh-system1" not in longer
        assert option(longer, "--data") == expected_data and option(longer, "--grounding-phase") == "follow"
        assert int(option(longer, "--steps")) + 4500 == sum(int(option(argv, "--steps")) for argv in step30_runs)
        assert [option(a, "--seed") for a in calls if a[0] == "evaluate" and "--chains" not in a
                and option(a, "--policy") == f"runs/{name}_follow2_export"] == [str(s) for s in range(1000, 1006)]
    compares = {a[2]: a[3:] for a in every_call if a[:2] == ["python", "results/follow_control/compare_seeds.py"]
                and a[2].startswith("results/data_efficiency/kept")}
    kd = "results/data_efficiency"
    assert [arm.split("=")[1] for arm in compares[f"{kd}/kept_compare.png"]] == \
        [f"{kd}/data10_longer", f"{kd}/kept10", f"{kd}/kept30", "results/prelude_stacked_mix/shipped"]
    assert [arm.split("=")[1] for arm in compares[f"{kd}/kept10_longer_compare.png"]] == \
        [f"{kd}/kept10", f"{kd}/kept10_longer", f"{kd}/data10_longer"]
    assert [arm.split("=")[1] for arm in compares[f"{kd}/kept_longer_compare.png"]] == \
        [f"{kd}/kept10_longer", f"{kd}/kept30_longer", f"{kd}/kept30"]
    assert [arm.split("=")[1] for arm in compares[f"{kd}/kept_clean_compare.png"]] == \
        [f"{kd}/kept30", f"{kd}/keptclean360", f"{kd}/kept30_longer"]
    chain_compare = next(a for a in every_call if a[:2] == ["python", "results/follow_control/compare_seeds.py"]
                         and a[4:5] == [f"{kd}/kept_chains_compare.png"])
    assert chain_compare[2:4] == ["--chain-seeds", "1003-1006"]
    assert [arm.split("=")[1] for arm in chain_compare[5:]] == \
        [f"{kd}/kept30_longer", f"{kd}/keptclean360",
         "results/prelude_stacked_mix/shipped+results/stacked_subgoal/shipped"]  # its chains are in the second
    for policy in ("runs/keptclean360_export", "runs/kept30_follow2_export"):  # 20 chains on each of four seeds
        chains = [a for a in calls if a[0] == "evaluate" and option(a, "--policy") == policy and "--chains" in a]
        assert [(option(a, "--seed"), option(a, "--chains"), option(a, "--episodes")) for a in chains] == \
            [(str(seed), "20", "0") for seed in range(1003, 1007)]
    curve = next(a for a in every_call if a[:2] == ["python", "results/data_efficiency/learning_curve.py"]
                 and a[2].endswith("learning_curve_kept.png"))
    assert curve[3:] == ["10% kept=96=results/data_efficiency/kept10", "30% kept=288=results/data_efficiency/kept30",
                         "100%=960=results/prelude_stacked_mix/shipped"]
    curve_8200 = next(a for a in every_call if a[:2] == ["python", "results/data_efficiency/learning_curve.py"]
                      and a[2].endswith("learning_curve_kept_8200.png"))
    assert curve_8200[3:] == ["10% kept=96=results/data_efficiency/kept10_longer",
                              "30% kept=288=results/data_efficiency/kept30_longer",
                              "100%=960=results/prelude_stacked_mix/shipped"]


def test_step_63_collects_the_data_step_62_would_have_left_when_run_without_it(tmp_path):
    """KEPT_GROUNDING without BIND_COUNTS: step 63 collects step 62's 288 mixed and 360 clean demonstrations
    itself, once each, before its arms train on them."""
    calls = [argv for argv in _dry_run(tmp_path, skip=("BIND_COUNTS",)) if argv[0] != "python"]
    collects = {}
    for argv in calls:
        if argv[0] == "collect":
            collects.setdefault(option(argv, "--out"), []).append(argv)
    assert [option(a, "--episodes-per-task") for a in collects["data/sim-mix288"]] == ["9", "24"]
    assert [option(a, "--episodes-per-task") for a in collects["data/sim-clean360"]] == ["30"]
    assert "--prelude-tasks" not in collects["data/sim-clean360"][0]
    for name, data in (("kept30", "data/sim-mix288"), ("keptclean360", "data/sim-clean360")):
        follow = run_writing(calls, f"runs/{name}_follow")
        assert option(follow, "--data") == data
        assert calls.index(collects[data][-1]) < calls.index(follow)


def test_step_64_trains_step_63_s_arm_on_the_clean_and_the_mixed_demonstrations_together(calls, every_call):
    """Step 64: step 63's arm (the same two runs, 4500 then 3700 steps) on step 62's 360 clean demonstrations with
    its 288 mixed as --extra-data; six seeds after each run, 80 chains at the end, and the curves with it."""
    for name in ("follow", "follow2"):
        union, clean = run_writing(calls, f"runs/kept540_{name}"), run_writing(calls, f"runs/keptclean360_{name}"
                                                                              if name == "follow" else "runs/kept30_follow2")
        assert option(union, "--data") == option(run_writing(calls, "runs/keptclean360_follow"), "--data")
        assert option(union, "--extra-data") == option(run_writing(calls, "runs/kept30_follow"), "--data")
        assert _without(union, "--data", "--extra-data", "--out", "--init") == \
            _without(clean, "--data", "--extra-data", "--out", "--init")
    assert option(run_writing(calls, "runs/kept540_follow2"), "--init") == "runs/kept540_follow/final"
    for policy in ("runs/kept540_export", "runs/kept540_follow2_export"):
        assert [option(a, "--seed") for a in calls if a[0] == "evaluate" and "--chains" not in a
                and option(a, "--policy") == policy] == [str(s) for s in range(1000, 1006)]
    chains = [a for a in calls if a[0] == "evaluate" and option(a, "--policy") == "runs/kept540_follow2_export"
              and "--chains" in a]
    assert [(option(a, "--seed"), option(a, "--chains")) for a in chains] == [(str(s), "20") for s in range(1003, 1007)]
    kd = "results/data_efficiency"
    curves = {a[2]: a[3:] for a in every_call if a[:2] == ["python", "results/data_efficiency/learning_curve.py"]}
    assert [arm.split("=", 1)[1] for arm in curves[f"{kd}/learning_curve_kept_matched.png"]] == \
        [f"96={kd}/kept10_longer", f"288={kd}/kept30_longer", f"540={kd}/kept540_longer"]
    assert curves[f"{kd}/learning_curve_kept_540.png"][:3] == curves[f"{kd}/learning_curve_kept_matched.png"]

