"""`trivla-drake`: one thin subcommand per job."""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys

# On a 2-core machine shared with physics and rendering, OpenMP threads that spin while waiting
# turn a 0.1 s inference into seconds; passive waiting keeps them polite. Must precede torch.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _print_result(result: dict, as_json: bool, title: str) -> None:
    if as_json:
        print(json.dumps(result))
        return
    print(f"| {title} | value |\n| --- | --- |")
    for key, value in result.items():
        shown = f"{value:.4g}" if isinstance(value, float) else value
        print(f"| {key} | {shown} |")


def _cmd_sim(args) -> int:
    from trivla_drake.eval.cli_commands import SIM_FLAGS, command_config, flag_values
    from trivla_drake.eval.sim_config import SimConfig

    config = command_config(SimConfig, args, flag_values(args, SIM_FLAGS))
    if config is None:
        return 0
    config.validate()
    from trivla_drake.eval.scripted_run import run_scripted
    from trivla_drake.station.meshcat_setup import make_meshcat
    from trivla_drake.station.scenario import load_scenario

    scenario = load_scenario(config.scenario, config.scenario_name)
    meshcat = make_meshcat(config.port) if (config.meshcat or config.record) else None
    if meshcat is not None and config.meshcat:
        print(f"Meshcat: {meshcat.web_url()}", file=sys.stderr)
    timing = run_scripted(scenario, config.seconds, meshcat=meshcat, record_html=config.record)
    result = timing.as_dict()
    if config.record:
        result["record"] = config.record
    _print_result(result, args.json, "sim")
    if config.meshcat and not args.json and sys.stdin.isatty():
        input("Simulation done; the scene stays in Meshcat until you press Enter.")
    return 0


def _set_torch_threads(threads: int) -> None:
    import torch

    if threads < 1:
        raise ValueError(f"--threads must be at least 1, got {threads}")
    torch.set_num_threads(threads)


def _cmd_bench(args) -> int:
    from trivla_drake.eval.bench_config import BenchConfig
    from trivla_drake.eval.cli_commands import BENCH_FLAGS, command_config, flag_values

    config = command_config(BenchConfig, args, flag_values(args, BENCH_FLAGS))
    if config is None:
        return 0
    config.validate()
    if config.model:
        from trivla_drake.nn.benchmark import benchmark_model, format_benchmark_table

        model_result = benchmark_model(preset=config.preset or "cpu", precision=config.precision)
        if args.json:
            print(json.dumps(model_result))
        else:
            print(format_benchmark_table(model_result))
        return 0
    if config.throughput:
        from trivla_drake.eval.throughput import format_throughput, run_throughput

        figures = run_throughput(config.pipeline, progress=not args.json)
        print(json.dumps(figures) if args.json else format_throughput(figures))
        return 0
    from trivla_drake.eval.model_loading import check_model_choice

    check_model_choice(config.checkpoint, config.preset)  # before the station benchmarks, not after
    from trivla_drake.eval.closed_loop import benchmark_closed_loop
    from trivla_drake.eval.diffik_benchmark import benchmark_diffik
    from trivla_drake.eval.model_loading import load_model
    from trivla_drake.eval.station_benchmark import benchmark_station
    from trivla_drake.station.scenario import load_scenario

    result: dict = {}
    result.update(benchmark_diffik(num_problems=config.diffik_problems))
    result.update(benchmark_station(load_scenario(config.scenario), seconds=config.seconds))
    _set_torch_threads(config.threads)
    model = load_model(config.checkpoint, preset=config.preset)
    result.update(benchmark_closed_loop(load_scenario(config.scenario), model, seconds=config.seconds))
    _print_result(result, args.json, "benchmark")
    return 0


def _cmd_demo(args) -> int:
    from trivla_drake.eval.cli_commands import DEMO_FLAGS, command_config, flag_values
    from trivla_drake.eval.demo import run_oracle_demo, run_trivla_demo
    from trivla_drake.eval.demo_config import DemoConfig
    from trivla_drake.station.meshcat_setup import make_meshcat, save_static_html
    from trivla_drake.systems.latency import LatencyModel

    config = command_config(DemoConfig, args, flag_values(args, DEMO_FLAGS))
    if config is None:
        return 0
    config.validate()  # all before a model loads or a simulation runs
    task, episodes, inference = config.task_name(), config.episode_count(), config.inference
    if config.policy == "oracle":
        report = run_oracle_demo(task, episodes=episodes, seed=config.seed, progress=not args.no_progress)
    else:
        from trivla_drake.eval.model_loading import load_model

        _set_torch_threads(config.threads)
        model = load_model(config.checkpoint, preset=config.preset)
        if inference.noise_scale is not None:
            model.set_initial_noise_scale(inference.noise_scale)
        inference.validate(chunk_length=int(model.config.policy.action_horizon))
        meshcat = make_meshcat(config.port) if (config.meshcat or config.record) else None
        if config.meshcat:
            print(f"Meshcat: {meshcat.web_url()}", file=sys.stderr)
        if config.record:
            meshcat.StartRecording(frames_per_second=30.0)
        settings = dict(seed=config.seed, latency=LatencyModel.parse(config.latency), meshcat=meshcat,
                        max_seconds=config.max_seconds, execute_steps=inference.execute_steps,
                        ensemble_decay=inference.ensemble_decay, progress=not args.no_progress)
        if config.chains is not None:
            from trivla_drake.eval.demo_chains import run_trivla_chain_demo

            report = run_trivla_chain_demo(model, chains=config.chains, **settings)
        else:
            report = run_trivla_demo(model, task, episodes=episodes, instruction=config.instruction, **settings)
        if config.record:
            meshcat.StopRecording()
            meshcat.PublishRecording()
            save_static_html(meshcat, config.record)
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


def _cmd_tables(args) -> int:
    from trivla_drake.eval.cli_commands import TABLES_CHECKPOINT_FLAGS, TABLES_FLAGS, command_config, flag_values
    from trivla_drake.eval.paper_tables import TablesConfig, format_tables, make_tables, write_tables

    def add_checkpoints(config: TablesConfig) -> None:
        for role, path in flag_values(args, TABLES_CHECKPOINT_FLAGS).items():
            if path is not None:
                config.checkpoints[role] = path

    from trivla_drake.eval.evaluate_config import parse_seeds

    args.seeds = None if args.seeds is None else parse_seeds(args.seeds)
    config = command_config(TablesConfig, args, flag_values(args, TABLES_FLAGS), finish=add_checkpoints)
    if config is None:
        return 0
    if not config.out:
        raise ValueError("--out is missing: the folder for report.md, report.json and the plots")
    config.validate()
    _set_torch_threads(config.threads)
    report = make_tables(config)
    files = write_tables(report, config.out, config)
    if args.json:
        print(json.dumps(report))
    else:
        print(format_tables(report))
        print("\nwritten: " + ", ".join(str(p) for p in files.values()))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="trivla-drake", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log Drake's warnings too")
    parser.add_argument("--text-encoder", metavar="FOLDER", default=None,
                        help="the folder (config.json, model.safetensors, tokenizer.json) of the pretrained text "
                             "encoder checkpoints record, tried where the one they name is missing or another model "
                             "(checked against the hash they record); before the command, e.g. "
                             "`trivla-drake --text-encoder ~/all-MiniLM-L6-v2 evaluate ...`")
    commands = parser.add_subparsers(dest="command", required=True)
    from trivla_drake.config_io import add_config_arguments
    from trivla_drake.eval.cli_commands import add_collect_parser, add_evaluate_parser, add_ray_arguments
    from trivla_drake.eval.demo_config import DEMO_TASK
    from trivla_drake.eval.evaluate_config import EVAL_BASE_SEED

    more = "settings beyond these flags: --set field=value (see --print-config)"
    sim = commands.add_parser("sim", help=f"run the station closed loop along a scripted end-effector path; {more}, "
                                          "e.g. --set scenario=FILE --set port=7001")
    sim.add_argument("--seconds", type=float, default=None, help="simulated time [s] (default 8)")
    sim.add_argument("--meshcat", action="store_true", default=None, help="show the run live in Meshcat (localhost)")
    sim.add_argument("--record", metavar="FILE.html", help="save the run as a self-contained HTML page")
    add_config_arguments(sim)
    sim.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    sim.set_defaults(run=_cmd_sim)

    demo = commands.add_parser("demo", help="closed-loop episodes: TriVLA as Drake systems, or the oracle; "
                                            f"{more}, e.g. --set max_seconds=5 --set inference.execute_steps=5")
    demo.add_argument("--policy", choices=("trivla", "oracle"), default=None, help="trivla (the default) or oracle")
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
    demo.add_argument("--seed", type=int, default=None,
                      help=f"base seed (default {EVAL_BASE_SEED}: scenes unseen by demonstrations collected with seed 0)")
    demo.add_argument("--latency", default=None,
                      help="zero (the default), measured (each inference's wall time) or seconds")
    demo.add_argument("--meshcat", action="store_true", default=None, help="show it live in Meshcat (localhost)")
    demo.add_argument("--record", metavar="FILE.html", help="save the run as a self-contained HTML page")
    add_config_arguments(demo)
    demo.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    demo.add_argument("--no-progress", action="store_true",
                      help="no progress bar (on stderr, with the successes so far)")
    demo.set_defaults(run=_cmd_demo)

    add_collect_parser(commands)
    add_evaluate_parser(commands)
    from trivla_drake.train.cli_commands import add_export_parser, add_refit_parser, add_soup_parser, add_train_parser

    add_train_parser(commands)
    add_export_parser(commands)
    add_soup_parser(commands)
    add_refit_parser(commands)

    tables = commands.add_parser("tables", help="the paper's tables for our suite (success, chains, ablation, "
                                 f"data efficiency, paraphrases, latency), Markdown + JSON + plots; {more}, e.g. "
                                 "--set chains=3 --set latency_tasks=[lift_block] --set results_dir=DIR")
    tables.add_argument("--full", help="checkpoint: Systems 1+2+3, all demonstrations (required)")
    tables.add_argument("--system1-3", help="checkpoint trained without System 2")
    tables.add_argument("--system1", help="checkpoint trained without Systems 2 and 3")
    tables.add_argument("--data10", help="checkpoint trained on 10%% of the demonstrations")
    tables.add_argument("--out", default=None, help="folder for report.md, report.json, the plots, tables_config.yaml "
                                                    "and (unless --set reuse=false) the evaluations/ it reuses")
    tables.add_argument("--episodes", type=int, default=None, help="episodes per task and seed (default 5)")
    tables.add_argument("--seeds", default=None,
                        help="base seeds, a range or a list, e.g. 1000-1002 or 1000,1001,1002 (the default: unseen by "
                             "`collect`'s seed 0)")
    add_ray_arguments(tables)
    add_config_arguments(tables)
    tables.add_argument("--json", action="store_true")
    tables.set_defaults(run=_cmd_tables)

    bench = commands.add_parser("bench", help=f"benchmarks: diff-IK and station speed, or --model latency; {more}, "
                                              "e.g. --set precision=bfloat16 --set seconds=2")
    bench.add_argument("--model", action="store_true", default=None, help="benchmark the TriVLA model instead")
    bench.add_argument("--throughput", action="store_true", default=None,
                       help="the data pipeline's speed at 1 and 2 workers instead: collect, feature cache, training, "
                            "evaluate (a few minutes; settings: --set pipeline.FIELD=...)")
    bench.add_argument("--preset", default=None,
                       help="model preset (tiny, cpu, paper): with --model, the preset timed (default cpu); without, "
                            "an UNTRAINED model of it for the closed-loop figure instead of the shipped checkpoint")
    bench.add_argument("--checkpoint", default=None, help="TriVLA checkpoint for the closed-loop figure "
                       "(default: models/trivla_cpu, else an untrained cpu model)")
    add_config_arguments(bench)
    bench.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    bench.set_defaults(run=_cmd_bench)

    from trivla_drake.recipe_command import add_recipe_parser

    add_recipe_parser(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # Drake's parser warnings (ROS-only URDF tags) are noise for a user; -v shows them.
    logging.getLogger("drake").setLevel(logging.INFO if args.verbose else logging.ERROR)
    if args.text_encoder is not None:
        if not args.text_encoder.strip():
            print("trivla-drake: error: --text-encoder is empty: give a folder or 'all-minilm-l6-v2'", file=sys.stderr)
            return 2
        from trivla_drake.nn.text_encoder import OVERRIDE_ENV, PACKAGE_SPEC

        # Read by load_checkpoint in this process and, forwarded, in every rollout worker (eval/rollout_runner.py),
        # whose working folder may be another: a path is made absolute (PACKAGE_SPEC names the pip package's).
        spec = args.text_encoder
        os.environ[OVERRIDE_ENV] = spec if spec == PACKAGE_SPEC else os.path.abspath(os.path.expanduser(spec))
    try:
        return args.run(args)
    except (ValueError, FileNotFoundError) as error:  # ScenarioError, UnknownTaskError, ... are ValueErrors
        print(f"trivla-drake {args.command}: error: {error}", file=sys.stderr)
        return 2
    except RuntimeError as error:
        from trivla_drake.eval.rollout_runner import RolloutError, WorkerDiedError

        if not isinstance(error, RolloutError) or args.verbose:
            raise  # --verbose: the job's own traceback
        # A rollout job raised on a worker, or its worker died every time: what finished is kept (collect's dataset,
        # evaluate --out's journal), so a rerun goes on from there; a job's own error fails the same way again.
        hint = ("rerun the command to go on" if isinstance(error, WorkerDiedError) else
                "the job's own error fails the same way on a rerun: --verbose shows its traceback")
        print(f"trivla-drake {args.command}: error: {error}\n(finished episodes are kept where the command stores "
              f"them: a dataset, or evaluate --out's journal; {hint})", file=sys.stderr)
        return 1
    except ModuleNotFoundError as error:
        # Parsing and `bench --model`, `train`, `export` need only torch; the simulation commands need Drake.
        if error.name != "pydrake" and not (error.name or "").startswith("pydrake."):
            raise
        print(f"trivla-drake {args.command}: error: this command needs Drake (pip install drake), which is missing or too old: {error}",
              file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
