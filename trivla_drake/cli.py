"""`trivla-drake`: one thin subcommand per job."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path

# On a 2-core machine shared with physics and rendering, OpenMP threads that spin while waiting
# turn a 0.1 s inference into seconds; passive waiting keeps them polite. Must precede torch.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# The task `demo` runs when not told one.
DEMO_TASK = "place_in_bowl"


def _print_result(result: dict, as_json: bool, title: str) -> None:
    if as_json:
        print(json.dumps(result))
        return
    print(f"| {title} | value |\n| --- | --- |")
    for key, value in result.items():
        shown = f"{value:.4g}" if isinstance(value, float) else value
        print(f"| {key} | {shown} |")


def _cmd_sim(args) -> int:
    from trivla_drake.eval.cli_commands import check_port, check_record_path, check_seconds

    check_seconds(args.seconds, "--seconds")
    check_port(args.port)
    check_record_path(args.record)
    from trivla_drake.eval.scripted_run import run_scripted
    from trivla_drake.station.meshcat_setup import make_meshcat
    from trivla_drake.station.scenario import load_scenario

    scenario = load_scenario(args.scenario, args.scenario_name)
    meshcat = make_meshcat(args.port) if (args.meshcat or args.record) else None
    if meshcat is not None and args.meshcat:
        print(f"Meshcat: {meshcat.web_url()}", file=sys.stderr)
    timing = run_scripted(scenario, args.seconds, meshcat=meshcat, record_html=args.record)
    result = timing.as_dict()
    if args.record:
        result["record"] = args.record
    _print_result(result, args.json, "sim")
    if args.meshcat and not args.json and sys.stdin.isatty():
        input("Simulation done; the scene stays in Meshcat until you press Enter.")
    return 0


def _set_torch_threads(threads: int) -> None:
    import torch

    if threads < 1:
        raise ValueError(f"--threads must be at least 1, got {threads}")
    torch.set_num_threads(threads)


def _cmd_bench(args) -> int:
    from trivla_drake.eval.cli_commands import check_seconds

    check_seconds(args.seconds, "--seconds")
    result: dict = {}
    if args.precision != "float32" and not args.model:
        raise ValueError("--precision goes with --model (the station benchmarks run the model in float32)")
    if args.model:
        from trivla_drake.nn.benchmark import benchmark_model, format_benchmark_table

        model_result = benchmark_model(preset=args.preset or "cpu", precision=args.precision)
        if args.json:
            print(json.dumps(model_result))
        else:
            print(format_benchmark_table(model_result))
        return 0
    from trivla_drake.eval.model_loading import check_model_choice

    check_model_choice(args.checkpoint, args.preset)  # before the station benchmarks, not after
    from trivla_drake.eval.diffik_benchmark import benchmark_diffik
    from trivla_drake.eval.station_benchmark import benchmark_station
    from trivla_drake.station.scenario import load_scenario

    from trivla_drake.eval.closed_loop import benchmark_closed_loop
    from trivla_drake.eval.model_loading import load_model

    result.update(benchmark_diffik(num_problems=args.diffik_problems))
    result.update(benchmark_station(load_scenario(args.scenario), seconds=args.seconds))
    _set_torch_threads(args.threads)
    model = load_model(args.checkpoint, preset=args.preset)
    result.update(benchmark_closed_loop(load_scenario(args.scenario), model, seconds=args.seconds))
    _print_result(result, args.json, "benchmark")
    return 0


def _check_chunk_execution(args, model) -> None:
    """--execute-steps / --ensemble-decay against the model's chunk length, named as the user typed them."""
    from trivla_drake.eval.trivla_harness_policy import check_ensemble_decay, check_execute_steps

    if args.execute_steps is not None:
        check_execute_steps(args.execute_steps, int(model.config.policy.action_horizon), "--execute-steps")
    if args.ensemble_decay is not None:
        check_ensemble_decay(args.ensemble_decay, "--ensemble-decay")


def _cmd_demo(args) -> int:
    from trivla_drake.eval.cli_commands import check_instruction_text, check_port, check_record_path, check_seconds
    from trivla_drake.eval.demo import run_oracle_demo, run_trivla_demo
    from trivla_drake.eval.evaluate import check_episode_count
    from trivla_drake.station.meshcat_setup import make_meshcat, save_static_html
    from trivla_drake.systems.latency import LatencyModel
    from trivla_drake.tasks.suite import check_run_settings

    if args.chains is not None:
        check_episode_count(args.chains, "--chains")
        given = [flag for flag, value in (("--task", args.task), ("--instruction", args.instruction),
                                          ("--episodes", args.episodes)) if value is not None]
        if given:
            raise ValueError(f"--chains draws every chain's tasks and instructions: leave out {', '.join(given)}")
        if args.policy == "oracle":
            raise ValueError("--chains runs TriVLA as Drake systems; the oracle's chains: "
                             "trivla-drake evaluate --policy oracle --episodes 0 --chains N")
    args.task = args.task or DEMO_TASK
    args.episodes = 1 if args.episodes is None else args.episodes
    # `evaluate`'s checks of the task (an unknown name lists the valid ones) and --seed; then the rest, all before
    # a model loads or a simulation runs.
    check_run_settings([args.task], args.seed)
    check_episode_count(args.episodes, "--episodes")
    check_seconds(args.max_seconds, "--max-seconds")
    check_instruction_text(args.instruction)
    check_port(args.port)
    check_record_path(args.record)
    latency = LatencyModel.parse(args.latency)
    if args.policy == "oracle":
        if (args.meshcat or args.record or args.instruction or args.checkpoint or args.preset or args.noise_scale is not None
                or args.execute_steps is not None or args.ensemble_decay is not None or latency.mode != "zero"):
            raise ValueError("--meshcat, --record, --instruction, --checkpoint, --preset, --noise-scale, --execute-steps, "
                             "--ensemble-decay and --latency go with --policy trivla (the oracle runs in the "
                             "evaluation harness, without latency)")
        report = run_oracle_demo(args.task, episodes=args.episodes, seed=args.seed, progress=not args.no_progress)
    else:
        from trivla_drake.eval.model_loading import load_model

        _set_torch_threads(args.threads)
        model = load_model(args.checkpoint, preset=args.preset)
        if args.noise_scale is not None:
            model.set_initial_noise_scale(args.noise_scale)
        _check_chunk_execution(args, model)
        meshcat = make_meshcat(args.port) if (args.meshcat or args.record) else None
        if args.meshcat:
            print(f"Meshcat: {meshcat.web_url()}", file=sys.stderr)
        if args.record:
            meshcat.StartRecording(frames_per_second=30.0)
        settings = dict(seed=args.seed, latency=latency, meshcat=meshcat, max_seconds=args.max_seconds,
                        execute_steps=args.execute_steps, ensemble_decay=args.ensemble_decay,
                        progress=not args.no_progress)
        if args.chains is not None:
            from trivla_drake.eval.demo_chains import run_trivla_chain_demo

            report = run_trivla_chain_demo(model, chains=args.chains, **settings)
        else:
            report = run_trivla_demo(model, args.task, episodes=args.episodes, instruction=args.instruction,
                                     **settings)
        if args.record:
            meshcat.StopRecording()
            meshcat.PublishRecording()
            save_static_html(meshcat, args.record)
    result = report.as_dict()
    if args.json:
        print(json.dumps(result))
    else:
        print(format_demo_markdown(result))
    return 0


def format_demo_markdown(result: dict) -> str:
    """`demo`'s report (`DemoReport.as_dict`, or a chain demo's) as Markdown: a row per episode (per chain task),
    then the success rate (the chains' table and Avg. Len), the control rate and the real-time factor."""
    from trivla_drake.eval.evaluate import format_chain_markdown

    chains = "chain_runs" in result
    lines = ["| chain | task | instruction | success | sim time [s] |" if chains else
             "| episode | task | instruction | success | sim time [s] |", "| --- | --- | --- | --- | --- |"]
    rows = ([(f"{i} ({k + 1}/5)", e) for i, c in enumerate(result["chain_runs"]) for k, e in enumerate(c["subtasks"])]
            if chains else list(enumerate(result["episodes"])))
    for label, e in rows:
        lines.append(f"| {label} | {e['task']} | {e['instruction']} | {'yes' if e['success'] else 'no: ' + e['reason']} "
                     f"| {e['sim_time']:.2f} |")
    lines += format_chain_markdown(result) if chains else []
    measure = (f"Avg. Len {result['chain_avg_len']:.2f}" if chains
               else f"success rate {result['success_rate']:.2f}")
    lines.append(f"\n{measure}, control {result['control_hz']:.1f} Hz in sim time, real-time factor "
                 f"{result['realtime_factor']:.2f} ({result['policy']}, latency {result['latency']})")
    return "\n".join(lines)


def _names(comma_separated: str) -> list[str]:
    return [name.strip() for name in comma_separated.split(",") if name.strip()]


def _seeds(comma_separated: str) -> tuple[int, ...]:
    """`tables --seeds`: the integers of a comma-separated list such as '1000,1001,1002'; else ValueError naming the
    flag (their range is TablesConfig's to check)."""
    try:
        return tuple(int(seed) for seed in comma_separated.split(","))
    except ValueError:
        raise ValueError(f"--seeds must be comma-separated integer base seeds, e.g. 1000,1001,1002; got "
                         f"{comma_separated!r}") from None


def _cmd_tables(args) -> int:
    from trivla_drake.eval.paper_tables import TablesConfig, format_tables, make_tables, write_tables

    from trivla_drake.eval.evaluate import check_episode_count

    check_episode_count(args.latency_episodes, "--latency-episodes", minimum=0)
    if args.evaluations and args.no_reuse:
        raise ValueError("--evaluations names a folder of evaluations to reuse, and --no-reuse reuses none: pass one")
    checkpoints = {role: path for role, path in (("full", args.full), ("system1_3", args.system1_3),
                                                 ("system1", args.system1), ("data10", args.data10)) if path}
    config = TablesConfig(checkpoints=checkpoints, episodes=args.episodes, chains=args.chains,
                          seeds=_seeds(args.seeds), workers=args.workers,
                          max_steps=args.max_steps, latency_episodes=args.latency_episodes,
                          noise_scale=args.noise_scale, execute_steps=args.execute_steps,
                          ensemble_decay=args.ensemble_decay, threads=args.threads,
                          results_dir=None if args.no_reuse else (args.evaluations or str(Path(args.out) / "evaluations")))
    if args.tasks != "all":
        config.tasks = _names(args.tasks)
    if args.latency_tasks:
        config.latency_tasks = _names(args.latency_tasks)
    _set_torch_threads(args.threads)
    report = make_tables(config)
    files = write_tables(report, args.out)
    if args.json:
        print(json.dumps(report))
    else:
        print(format_tables(report))
        print("\nwritten: " + ", ".join(str(p) for p in files.values()))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="trivla-drake", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log Drake's warnings too")
    commands = parser.add_subparsers(dest="command", required=True)
    from trivla_drake.eval.cli_commands import (add_chunk_execution_arguments, add_collect_parser, add_evaluate_parser,
                                                 add_noise_scale_argument)
    from trivla_drake.eval.evaluate import EVAL_BASE_SEED
    from trivla_drake.eval.paper_tables import TablesConfig

    sim = commands.add_parser("sim", help="run the station closed loop along a scripted end-effector path")
    sim.add_argument("--seconds", type=float, default=8.0, help="simulated time [s] (default 8)")
    sim.add_argument("--meshcat", action="store_true", help="show the run live in Meshcat (localhost)")
    sim.add_argument("--port", type=int, default=None, help="Meshcat port (default: Drake's, 7000 up)")
    sim.add_argument("--record", metavar="FILE.html", help="save the run as a self-contained HTML page")
    sim.add_argument("--scenario", default=None, help="scenarios YAML file (default: models/default.scenarios.yaml)")
    sim.add_argument("--scenario-name", default="default", help="scenario to load from the file")
    sim.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    sim.set_defaults(run=_cmd_sim)

    demo = commands.add_parser("demo", help="closed-loop episodes: TriVLA as Drake systems, or the oracle")
    demo.add_argument("--policy", choices=("trivla", "oracle"), default="trivla")
    demo.add_argument("--checkpoint", help="TriVLA checkpoint (default: models/trivla_cpu)")
    demo.add_argument("--preset", choices=("tiny", "cpu"), default=None,
                      help="an UNTRAINED model of this preset instead (for wiring and timing, not success)")
    demo.add_argument("--task", default=None, help=f"task name (default {DEMO_TASK}; see `trivla-drake evaluate --help`)")
    demo.add_argument("--instruction", help="say this instead of the task's own instruction")
    demo.add_argument("--episodes", type=int, default=None, help="episodes (default 1)")
    demo.add_argument("--chains", type=int, default=None, metavar="N",
                      help="instead of episodes of one task, N 5-task chains in one simulation each, the instruction "
                           "input changed as each task is done (chain j starts as `evaluate --chains`'s chain j); "
                           "reports Avg. Len")
    demo.add_argument("--seed", type=int, default=EVAL_BASE_SEED,
                      help=f"base seed (default {EVAL_BASE_SEED}: scenes unseen by demonstrations collected with seed 0)")
    demo.add_argument("--latency", default="zero", help="zero, measured (each inference's wall time) or seconds")
    demo.add_argument("--max-seconds", type=float, default=None,
                      help="episode time limit in sim seconds (default: the task's own limit)")
    demo.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    add_noise_scale_argument(demo)
    add_chunk_execution_arguments(demo)
    demo.add_argument("--meshcat", action="store_true", help="show it live in Meshcat (localhost)")
    demo.add_argument("--port", type=int, default=None, help="Meshcat port")
    demo.add_argument("--record", metavar="FILE.html", help="save the run as a self-contained HTML page")
    demo.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    demo.add_argument("--no-progress", action="store_true",
                      help="no progress bar (on stderr, with the successes so far)")
    demo.set_defaults(run=_cmd_demo)

    add_collect_parser(commands)
    add_evaluate_parser(commands)
    from trivla_drake.train.cli_commands import add_export_parser, add_soup_parser, add_train_parser

    add_train_parser(commands)
    add_export_parser(commands)
    add_soup_parser(commands)

    tables = commands.add_parser("tables", help="the paper's tables for our suite (success, chains, ablation, "
                                 "data efficiency, paraphrases, latency), Markdown + JSON + plots")
    tables.add_argument("--full", required=True, help="checkpoint: Systems 1+2+3, all demonstrations")
    tables.add_argument("--system1-3", help="checkpoint trained without System 2")
    tables.add_argument("--system1", help="checkpoint trained without Systems 2 and 3")
    tables.add_argument("--data10", help="checkpoint trained on 10%% of the demonstrations")
    tables.add_argument("--out", required=True, help="folder for report.md, report.json and the plots")
    tables.add_argument("--tasks", default="all")
    tables.add_argument("--episodes", type=int, default=5, help="episodes per task and seed (default 5)")
    default_seeds = ",".join(map(str, TablesConfig.seeds))
    tables.add_argument("--seeds", default=default_seeds,
                        help=f"comma-separated base seeds (default {default_seeds}: unseen by `collect`'s seed 0)")
    tables.add_argument("--chains", type=int, default=5, help="5-task chains per seed (default 5)")
    tables.add_argument("--latency-episodes", type=int, default=2, help="episodes per task, latency rows")
    tables.add_argument("--latency-tasks", default=None,
                        help="comma-separated tasks of the latency rows (default lift_block,turn_on_light,open_drawer)")
    tables.add_argument("--workers", type=int, default=1)
    tables.add_argument("--max-steps", type=int, default=None, help="cap on steps per episode")
    tables.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    add_noise_scale_argument(tables)
    add_chunk_execution_arguments(tables)
    tables.add_argument("--no-reuse", action="store_true",
                        help="do not store or reuse evaluations in OUT/evaluations/ (default: reuse, so a "
                             "killed or extended run redoes only what is missing)")
    tables.add_argument("--evaluations", default=None, metavar="DIR",
                        help="folder of stored evaluations to reuse and add to (default OUT/evaluations/), e.g. "
                             "another report's, so a report with one more checkpoint reruns only that one's")
    tables.add_argument("--json", action="store_true")
    tables.set_defaults(run=_cmd_tables)


    bench = commands.add_parser("bench", help="benchmarks: diff-IK and station speed, or --model latency")
    bench.add_argument("--model", action="store_true", help="benchmark the TriVLA model instead")
    bench.add_argument("--preset", default=None,
                       help="model preset (tiny, cpu, paper): with --model, the preset timed (default cpu); without, "
                            "an UNTRAINED model of it for the closed-loop figure instead of the shipped checkpoint")
    bench.add_argument("--precision", default="float32", choices=("float32", "bfloat16", "float16"),
                       help="--model: autocast dtype of the timed calls (weights stay float32; default float32)")
    bench.add_argument("--seconds", type=float, default=4.0, help="simulated time per station run [s]")
    bench.add_argument("--diffik-problems", type=int, default=2000, help="diff-IK problems to time")
    bench.add_argument("--scenario", default=None, help="scenarios YAML file")
    bench.add_argument("--checkpoint", default=None, help="TriVLA checkpoint for the closed-loop figure "
                       "(default: models/trivla_cpu, else an untrained cpu model)")
    bench.add_argument("--threads", type=int, default=1,
                       help="torch threads in the closed loop (default 1: physics and rendering share the cores)")
    bench.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    bench.set_defaults(run=_cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # Drake's parser warnings (ROS-only URDF tags) are noise for a user; -v shows them.
    logging.getLogger("drake").setLevel(logging.INFO if args.verbose else logging.ERROR)
    try:
        return args.run(args)
    except (ValueError, FileNotFoundError) as error:  # ScenarioError, UnknownTaskError, ... are ValueErrors
        print(f"trivla-drake {args.command}: error: {error}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as error:
        # Parsing and `bench --model`, `train`, `export` need only torch; the simulation commands need Drake.
        if error.name != "pydrake" and not (error.name or "").startswith("pydrake."):
            raise
        print(f"trivla-drake {args.command}: error: this command needs Drake (pip install drake), which is missing or too old: {error}",
              file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
