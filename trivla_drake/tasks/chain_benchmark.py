"""The fixed chain benchmark, as CALVIN has one: 1000 five-task chains generated once with a fixed seed and shipped
in the package (tasks/data/benchmark_chains.json), so that chain j starts from the same scene and asks for the same
tasks whoever evaluates it, on whichever worker.

A chain stores its scene seed (its initial state is `benchmark_scene(scene_seed, layout)`) and its five subtasks in
order: the task, its parameters, and a seed from which the subtask's instruction and the seed given to the policy's
reset are drawn (`subtask_instance`). The generator drew every subtask in the state the scripted oracle left when the
earlier ones succeeded (from `chain_options`, restricted to task categories not yet in the chain, CALVIN's grouping:
`TASK_CATEGORIES`) and kept a chain only when the oracle then completed all five; `validate_benchmark_chains` states
the rules a chain list keeps.

    chains = load_benchmark_chains(100)                       # the first 100, the file checked against BENCHMARK_SHA256
    run_chain(chain.scene_seed, policy, chain=chain)          # trivla_drake/eval/episode.py

Generating (done once; about 7 s of CPU per chain, nearly all of it physics; resumable):

    python -m trivla_drake.tasks.chain_benchmark --generate --count 1000 --out FILE [--workers 2]
    python -m trivla_drake.tasks.chain_benchmark --check FILE   # the rules, and the digests to put below
"""

from __future__ import annotations

import argparse
import functools
import hashlib
import json
import os
import zlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from trivla_drake.tasks.chains import CHAIN_LENGTH, NEEDS_FOLLOW_UP, chain_options, lifted_scene, sample_chain_scene
from trivla_drake.tasks.scene import BLOCK_COLORS, Layout, SceneSpec, SceneState, scene_from_spec
from trivla_drake.tasks.suite import TASKS, TaskInstance

BENCHMARK_SIZE = 1000
# The generator's fixed seed (the issue that asked for the benchmark: 76).
BENCHMARK_BASE_SEED = 76
# Bumped whenever the generator would draw other chains from the same seed (2: CALVIN's task categories, where 1
# allowed each task name once, so that a chain could open the drawer and later close it).
GENERATOR_VERSION = 2
# sha256 of the shipped chains' canonical JSON (`chains_sha256`): a changed file is refused on load.
BENCHMARK_SHA256 = "f9ee5997588333bb8898fa1fe15e4fa6eec63a9461adcacc157bbf94528fdcef"
# sha256 of the shipped chains' initial scenes (`benchmark_scenes_sha256`): a scene sampler that draws other scenes
# from the same seeds would start every chain elsewhere than where it was generated (a test compares).
BENCHMARK_SCENES_SHA256 = "ff0583cf92e77b9b91ebd7e986933f20015229e10be0efc1ccaabf9a6673029b"
BENCHMARK_FILE = Path(__file__).parent / "data" / "benchmark_chains.json"
_LIFT = "lift_block"
# A chain holds each task category at most once. CALVIN's grouping (calvin_models' multistep_sequences.py): a task and
# its opposite are one category (the drawer opened or closed, the lamp on or off), and pushing and rotating a block on
# the table are one, so a chain never undoes what it did and asks five different kinds of thing.
TASK_CATEGORIES = {
    "lift_block": "lift",
    "place_in_bowl": "place",
    "stack_block": "stack",
    "unstack_block": "unstack",
    "push_block_left": "block_on_table",
    "push_block_right": "block_on_table",
    "rotate_block_left": "block_on_table",
    "rotate_block_right": "block_on_table",
    "open_drawer": "drawer",
    "close_drawer": "drawer",
    "turn_on_light": "light",
    "turn_off_light": "light",
}


class BenchmarkError(ValueError):
    """A chain list or benchmark file that breaks the benchmark's rules (the message lists what)."""


class ChainSubtask(NamedTuple):
    """One task of a stored chain: its name, its parameters and the seed of its instruction and policy reset."""

    task: str
    params: tuple[str, ...]
    seed: int


@dataclass(frozen=True)
class BenchmarkChain:
    """Chain `index` of the benchmark: the seed of its initial scene and its subtasks in order."""

    index: int
    scene_seed: int
    subtasks: list[ChainSubtask]

    def to_dict(self) -> dict:
        """The chain as stored: {"index", "scene_seed", "subtasks": [[task, [params...], seed], ...]}."""
        return {
            "index": self.index,
            "scene_seed": self.scene_seed,
            "subtasks": [[s.task, list(s.params), s.seed] for s in self.subtasks],
        }

    @classmethod
    def from_dict(cls, data: dict) -> BenchmarkChain:
        """The chain stored as `data` (`to_dict`'s form); BenchmarkError naming the entry otherwise."""
        try:
            subtasks = [ChainSubtask(str(task), tuple(str(p) for p in params), int(seed))
                        for task, params, seed in data["subtasks"]]
            return cls(int(data["index"]), int(data["scene_seed"]), subtasks)
        except (KeyError, TypeError, ValueError) as error:
            raise BenchmarkError(f"a benchmark chain must be {{'index', 'scene_seed', 'subtasks': [[task, [params], "
                                 f"seed], ...]}}, got {data!r} ({type(error).__name__}: {error})") from None


def derive_benchmark_seed(base_seed: int, purpose: str, candidate: int) -> int:
    """The 32-bit seed of `purpose` ("scene" or "tasks") for the generator's candidate chain `candidate`."""
    words = [int(base_seed) & 0xFFFFFFFF, zlib.crc32(purpose.encode()), int(candidate)]
    return int(np.random.SeedSequence(words).generate_state(1)[0])


def benchmark_scene(scene_seed: int, layout: Layout) -> SceneSpec:
    """The initial state of the chain with `scene_seed` (a chain's scene, drawn as adaptive chains draw theirs)."""
    return sample_chain_scene(np.random.default_rng(scene_seed), layout)


def subtask_instance(subtask: ChainSubtask, *, paraphrase: bool = False) -> tuple[TaskInstance, int]:
    """The subtask's TaskInstance, its instruction drawn from the subtask's seed (a held-out paraphrase with
    `paraphrase`), and the seed for the policy's reset (drawn first, so it does not depend on `paraphrase`)."""
    rng = np.random.default_rng(subtask.seed)
    policy_seed = int(rng.integers(2**31))
    instruction = TASKS[subtask.task].instruction(subtask.params, rng, paraphrase=paraphrase)
    return TaskInstance(subtask.task, subtask.params, instruction), policy_seed


def param_count(task_name: str) -> int:
    """How many block colours the task's parameters hold: as many as its instructions name ({color}, {other})."""
    task = TASKS[task_name]
    texts = task.templates + task.paraphrases
    return 2 if any("{other}" in t for t in texts) else 1 if any("{color}" in t for t in texts) else 0


def benchmark_options(scene: SceneState, used: set[str], *, last: bool) -> dict[str, list[tuple]]:
    """The tasks the generator may draw next in `scene` (task name -> parameters): `chain_options` restricted to the
    categories (`TASK_CATEGORIES`) of no task in `used`; a lift only where a place or stack of an unused category can
    follow it with that block, and never `last`."""
    taken = {TASK_CATEGORIES[name] for name in used}
    options = {name: params for name, params in chain_options(scene, used).items()
               if TASK_CATEGORIES[name] not in taken}
    if _LIFT in options:
        taken.add(TASK_CATEGORIES[_LIFT])
        follow = [name for name in NEEDS_FOLLOW_UP[_LIFT] if TASK_CATEGORIES[name] not in taken]
        lifts = [] if last else [p for p in options[_LIFT]
                                 if any(TASKS[f].candidates(lifted_scene(scene, p[0])) for f in follow)]
        if lifts:
            options[_LIFT] = lifts
        else:
            del options[_LIFT]
    return options


# ---------------------------------------------------------------- the rules
@functools.lru_cache(maxsize=4 * BENCHMARK_SIZE)
def _starts_in_its_scene(scene_seed: int, task: str, params: tuple[str, ...]) -> bool:
    """Whether `task` with `params` is among the task's candidates in the initial scene of `scene_seed` (with the
    default scenario's layout; remembered, as the candidates take tens of milliseconds)."""
    layout = Layout.default()
    return params in TASKS[task].candidates(scene_from_spec(benchmark_scene(scene_seed, layout), layout))


def _chain_problems(chain: BenchmarkChain) -> list[str]:
    """What breaks the rules in one chain (empty if nothing)."""
    where = f"chain {chain.index}"
    problems = []
    if len(chain.subtasks) != CHAIN_LENGTH:
        problems.append(f"{where}: {len(chain.subtasks)} subtasks, not {CHAIN_LENGTH}")
    if not 0 <= chain.scene_seed < 2**32:
        problems.append(f"{where}: scene seed {chain.scene_seed} is not a 32-bit seed")
    shaped = True
    for position, (task, params, seed) in enumerate(chain.subtasks):
        at = f"{where} subtask {position}"
        if task not in TASKS:
            problems.append(f"{at}: unknown task {task!r}")
            shaped = False
            continue
        if len(params) != param_count(task) or len(set(params)) != len(params) \
                or any(p not in BLOCK_COLORS for p in params):
            problems.append(f"{at}: {task} parameters {list(params)} are not {param_count(task)} different block "
                            f"colours of {list(BLOCK_COLORS)}")
            shaped = False
        if not 0 <= seed < 2**31:
            problems.append(f"{at}: seed {seed} is not in [0, 2**31)")
    names = [s.task for s in chain.subtasks]
    repeated = sorted(category for category, n in Counter(TASK_CATEGORIES.get(name) for name in names).items()
                      if n > 1 and category is not None)
    if repeated:
        problems.append(f"{where}: task category {', '.join(repeated)} more than once ({names}; TASK_CATEGORIES)")
    for position, (task, params, _) in enumerate(chain.subtasks):
        if task != _LIFT:
            continue
        follow = chain.subtasks[position + 1] if position + 1 < len(chain.subtasks) else None
        if follow is None or follow.task not in NEEDS_FOLLOW_UP[_LIFT] or follow.params[:1] != params[:1]:
            problems.append(f"{where}: the lift at subtask {position} (of {list(params)}) is not followed by "
                            f"{' or '.join(NEEDS_FOLLOW_UP[_LIFT])} of the same block")
    if shaped and chain.subtasks and 0 <= chain.scene_seed < 2**32:
        first = chain.subtasks[0]
        if not _starts_in_its_scene(chain.scene_seed, first.task, first.params):
            problems.append(f"{where}: the first task {first.task} {list(first.params)} cannot start in the chain's "
                            f"initial scene (not among its candidates there)")
    return problems


def validate_benchmark_chains(chains: list[BenchmarkChain], *, count: int | None = BENCHMARK_SIZE) -> None:
    """Raise BenchmarkError listing every broken rule; the rules of the benchmark's chains:

    `count` chains (None: any number), chain i with index i, unique scene seeds; each chain has CHAIN_LENGTH
    subtasks of known tasks, each task's parameters shaped as its candidates (`param_count` different block
    colours) and a seed in [0, 2**31); no task category twice in a chain (`TASK_CATEGORIES`, CALVIN's: the drawer's
    opening and closing are one, the lamp's on and off one, pushing and rotating a block one); the first task can
    start in the initial scene (its parameters are among
    `TASKS[task].candidates` of the scene drawn from the scene seed in the default scenario); a lift is followed
    by place_in_bowl or stack_block of the same block (so never last). The later tasks' feasibility depends on the
    physics: the generator checked it with the oracle."""
    problems = []
    if count is not None and len(chains) != count:
        problems.append(f"{len(chains)} chains, not {count}")
    seen: dict[int, int] = {}
    for position, chain in enumerate(chains):
        if chain.index != position:
            problems.append(f"chain at position {position} has index {chain.index}")
        if chain.scene_seed in seen:
            problems.append(f"chain {chain.index}: scene seed {chain.scene_seed} is also chain "
                            f"{seen[chain.scene_seed]}'s")
        seen.setdefault(chain.scene_seed, chain.index)
        problems += _chain_problems(chain)
    if problems:
        shown = "\n  ".join(problems[:20])
        more = f"\n  ... and {len(problems) - 20} more" if len(problems) > 20 else ""
        raise BenchmarkError(f"the benchmark chains break {len(problems)} rule(s):\n  {shown}{more}")


def _canonical(value) -> bytes:
    return json.dumps(value, sort_keys=True, separators=(",", ":")).encode()


def chains_sha256(chains: list[BenchmarkChain]) -> str:
    """sha256 of the chains' canonical JSON (sorted keys, no spaces): what BENCHMARK_SHA256 holds."""
    return hashlib.sha256(_canonical([c.to_dict() for c in chains])).hexdigest()


def benchmark_scenes_sha256(chains: list[BenchmarkChain]) -> str:
    """sha256 of the canonical JSON of the chains' initial scenes (`benchmark_scene` in the default scenario): what
    BENCHMARK_SCENES_SHA256 holds."""
    layout = Layout.default()
    return hashlib.sha256(_canonical([benchmark_scene(c.scene_seed, layout).to_dict() for c in chains])).hexdigest()


# ---------------------------------------------------------------- the file
def read_benchmark_file(path: str | Path) -> tuple[dict, list[BenchmarkChain]]:
    """(header, chains) of a benchmark file, unchecked; BenchmarkError naming the file if it is not one."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        header, entries = data["header"], data["chains"]
    except (ValueError, KeyError, TypeError) as error:
        raise BenchmarkError(f"{path} is not a benchmark chain file ({{'header': ..., 'chains': [...]}}): "
                             f"{type(error).__name__}: {error}") from None
    return header, [BenchmarkChain.from_dict(entry) for entry in entries]


def write_benchmark_file(path: str | Path, header: dict, chains: list[BenchmarkChain]) -> None:
    """Write a benchmark file (JSON: the header on the first line, then one chain per line), atomically."""
    path = Path(path)
    lines = [json.dumps(c.to_dict(), separators=(",", ":")) for c in chains]
    text = '{"header": ' + json.dumps(header, sort_keys=True) + ',\n"chains": [\n' + ",\n".join(lines) + "\n]}\n"
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(text)
    os.replace(temporary, path)


def load_benchmark_chains(n: int | None = None, *, path: str | Path | None = None) -> list[BenchmarkChain]:
    """The first `n` chains of the benchmark (all BENCHMARK_SIZE when None), from the file shipped in the package
    (or `path`); a file whose chains are not the ones generated (sha256 other than BENCHMARK_SHA256) is refused."""
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= BENCHMARK_SIZE):
        raise ValueError(f"n (how many benchmark chains) must be a whole number from 1 to {BENCHMARK_SIZE}, got {n!r}")
    chains = _shipped_chains() if path is None else _checked_chains(Path(path))
    return list(chains[:n])


@functools.lru_cache(maxsize=1)
def _shipped_chains() -> tuple[BenchmarkChain, ...]:
    """The shipped file's chains, read and checked once per process (evaluation workers ask for them job by job)."""
    return _checked_chains(BENCHMARK_FILE)


def _checked_chains(path: Path) -> tuple[BenchmarkChain, ...]:
    """The chains of the benchmark file at `path`, refused unless their sha256 is BENCHMARK_SHA256."""
    if not path.is_file():
        raise FileNotFoundError(f"the benchmark chain file {path} is missing (the package is installed without its "
                                f"data? pyproject's [tool.setuptools.package-data] ships tasks/data/*.json)")
    _, chains = read_benchmark_file(path)
    digest = chains_sha256(chains)
    if digest != BENCHMARK_SHA256:
        raise BenchmarkError(
            f"{path} holds other chains than the benchmark's (sha256 {digest}, expected BENCHMARK_SHA256 "
            f"{BENCHMARK_SHA256 or '(unset)'} in trivla_drake/tasks/chain_benchmark.py): the fixed benchmark never "
            f"changes; restore the file, or, for a new benchmark, regenerate it and update the constant")
    return tuple(chains)


# ---------------------------------------------------------------- the generator
def _attempt(base_seed: int, candidate: int) -> dict:
    """Candidate chain `candidate`: its scene, and its tasks drawn one by one in the state the oracle leaves, each
    run by the oracle (physics only). A record for the generation log: the chain, or why it is discarded."""
    from trivla_drake.eval.env import SimulationError
    from trivla_drake.eval.episode import run_unrecorded, shared_env
    from trivla_drake.tasks.oracle import OraclePolicy

    scene_seed = derive_benchmark_seed(base_seed, "scene", candidate)
    rng = np.random.default_rng(derive_benchmark_seed(base_seed, "tasks", candidate))
    env = shared_env(None)
    layout = env.layout()
    spec = benchmark_scene(scene_seed, layout)
    policy = OraclePolicy()
    subtasks: list[ChainSubtask] = []
    try:
        obs = env.reset(spec)
        for position in range(CHAIN_LENGTH):
            options = benchmark_options(env.scene(), {s.task for s in subtasks}, last=position == CHAIN_LENGTH - 1)
            if not options:
                return {"candidate": candidate,
                        "discarded": f"no task of an unused category can start: at subtask {position}"}
            names = sorted(options)
            name = names[int(rng.integers(len(names)))]
            params = tuple(options[name][int(rng.integers(len(options[name])))])
            if position == 0 and params not in TASKS[name].candidates(scene_from_spec(spec, layout)):
                return {"candidate": candidate,
                        "discarded": f"first task infeasible in the specified scene: {name} {list(params)}"}
            subtask = ChainSubtask(name, params, int(rng.integers(2**31)))
            instance, policy_seed = subtask_instance(subtask)
            result, obs = run_unrecorded(env, obs, policy, instance, policy_seed)
            if not result.success:
                return {"candidate": candidate,
                        "discarded": f"oracle failed: {name} {list(params)} at subtask {position}: {result.reason}"}
            subtasks.append(subtask)
    except (SimulationError, ValueError, RuntimeError) as error:
        return {"candidate": candidate, "discarded": f"simulation error: {type(error).__name__}: {error}"}
    chain = BenchmarkChain(0, scene_seed, subtasks)
    problems = _chain_problems(chain)
    if problems:  # not expected: the draws keep the rules
        return {"candidate": candidate, "discarded": f"rules: {'; '.join(problems)}"}
    stored = chain.to_dict()
    return {"candidate": candidate, "scene_seed": stored["scene_seed"], "subtasks": stored["subtasks"]}


def _read_log(log: Path, header: dict) -> list[dict]:
    """The records of a generation log (candidates 0, 1, ... in order); a last line cut off by a kill is dropped from
    the file. A log of another generator or seed is refused."""
    if not log.exists():
        log.parent.mkdir(parents=True, exist_ok=True)
        log.write_text(json.dumps(header, sort_keys=True) + "\n")
        return []
    text = log.read_bytes().decode()
    lines = text.split("\n")
    try:
        found = json.loads(lines[0])
    except ValueError:
        found = None
    if found != header:
        raise BenchmarkError(f"{log} is the log of another generation ({found}, this one is {header}): delete it or "
                             f"write to another --out")
    records, kept = [], len(lines[0]) + 1
    for line in lines[1:]:
        try:
            record = json.loads(line)
        except ValueError:
            break  # the line a kill cut off (or the end)
        if record.get("candidate") != len(records):
            raise BenchmarkError(f"{log}: expected candidate {len(records)}, found {record.get('candidate')}")
        records.append(record)
        kept += len(line) + 1
    if kept < len(text):
        with open(log, "r+b") as f:
            f.truncate(len(text[:kept].encode()))
    elif kept > len(text):  # killed between a record and its line's end
        with open(log, "a") as f:
            f.write("\n")
    return records


def _attempt_job(base_seed: int, candidate: int) -> dict:
    """`_attempt` as a rollout job (eval/rollout_runner.py): top level, so that workers run it."""
    return _attempt(base_seed, candidate)


def _attempts(base_seed: int, first: int, workers: int):
    """Records of candidates first, first + 1, ... in order, computed in this process (`workers` 1) or on a local Ray
    with `workers` processes (RAY_ADDRESS: on that cluster)."""
    import itertools

    from trivla_drake.eval.rollout_runner import RolloutRunner

    with RolloutRunner(workers) as runner:
        yield from runner.map_ordered(_attempt_job, base_seed, itertools.count(first),
                                      describe=lambda candidate: f"benchmark chain candidate {candidate}")


def generate_benchmark_chains(count: int = BENCHMARK_SIZE, seed: int = BENCHMARK_BASE_SEED, workers: int = 1, *,
                              out: str | Path, progress: bool = False) -> list[BenchmarkChain]:
    """Generate `count` benchmark chains from `seed` and write them to `out` (a benchmark file); returns them.

    Candidate k draws its scene from `derive_benchmark_seed(seed, "scene", k)` and its tasks from
    `derive_benchmark_seed(seed, "tasks", k)`, each in the state the oracle left (`benchmark_options`), and runs the
    oracle through them; a candidate that fails (the oracle, a dead end, a repeated scene seed) is discarded and the
    next one tried. Every candidate's outcome is appended, in order, to the log `out`.partial, so a killed run
    resumes where it stopped; the result depends on `seed` and `count` only (not on `workers` or on kills)."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise ValueError(f"count (--count) must be a whole number of chains of at least 1, got {count!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers (--workers) must be a whole number of processes of at least 1, got {workers!r}")
    from tqdm import tqdm

    out = Path(out)
    log = out.with_name(out.name + ".partial")
    records = _read_log(log, {"generator_version": GENERATOR_VERSION, "base_seed": int(seed)})
    chains: list[BenchmarkChain] = []
    seen: set[int] = set()
    used = 0  # the candidates that made the first `count` chains, or all of the log's
    for record in records:
        if len(chains) == count:
            break
        used += 1
        if "discarded" not in record:
            chains.append(BenchmarkChain.from_dict({**record, "index": len(chains)}))
            seen.add(chains[-1].scene_seed)
    bar = tqdm(total=count, initial=len(chains), desc="benchmark chains", unit="chain", disable=not progress)
    try:
        if len(chains) < count:
            with open(log, "a") as f:
                for record in _attempts(int(seed), len(records), workers):
                    if "discarded" not in record and record["scene_seed"] in seen:
                        record = {"candidate": record["candidate"], "discarded": "duplicate scene seed"}
                    f.write(json.dumps(record, separators=(",", ":")) + "\n")
                    f.flush()
                    records.append(record)
                    used = len(records)
                    if "discarded" not in record:
                        chains.append(BenchmarkChain.from_dict({**record, "index": len(chains)}))
                        seen.add(chains[-1].scene_seed)
                        bar.update(1)
                    bar.set_postfix(discarded=used - len(chains))
                    if len(chains) == count:
                        break
    finally:
        bar.close()
    validate_benchmark_chains(chains, count=count)
    reasons = Counter(r["discarded"].split(":")[0] for r in records[:used] if "discarded" in r)
    header = {
        "benchmark": "trivla_drake five-task chains (tasks/chain_benchmark.py)",
        "generator_version": GENERATOR_VERSION,
        "base_seed": int(seed),
        "count": count,
        "discarded": used - count,
        "discarded_by_reason": dict(sorted(reasons.items())),
        "chains_sha256": chains_sha256(chains),
        "scenes_sha256": benchmark_scenes_sha256(chains),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    write_benchmark_file(out, header, chains)
    return chains


def check_benchmark_file(path: str | Path) -> str:
    """The rules checked on the file at `path` (BenchmarkError otherwise) and a report of its digests."""
    header, chains = read_benchmark_file(path)
    validate_benchmark_chains(chains, count=header.get("count"))
    digest, scenes = chains_sha256(chains), benchmark_scenes_sha256(chains)
    return (f"{path}: {len(chains)} chains keep the rules ({header.get('discarded')} candidates discarded: "
            f"{header.get('discarded_by_reason')})\n"
            f'BENCHMARK_SHA256 = "{digest}"{"  (the shipped one)" if digest == BENCHMARK_SHA256 else ""}\n'
            f'BENCHMARK_SCENES_SHA256 = "{scenes}"')


def main(argv: list[str] | None = None) -> None:
    """`--generate --count N --out FILE [--workers W] [--seed S]`, or `--check FILE`."""
    parser = argparse.ArgumentParser(prog="python -m trivla_drake.tasks.chain_benchmark", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    action = parser.add_mutually_exclusive_group(required=True)
    action.add_argument("--generate", action="store_true", help="generate chains into --out (resumes its .partial)")
    action.add_argument("--check", metavar="FILE", help="check a benchmark file's rules and print its digests")
    parser.add_argument("--count", type=int, default=BENCHMARK_SIZE, help="chains to generate")
    parser.add_argument("--out", type=Path, help="the benchmark file to write (its log: FILE.partial)")
    parser.add_argument("--workers", type=int, default=1, help="processes running the oracle")
    parser.add_argument("--seed", type=int, default=BENCHMARK_BASE_SEED, help="the generator's base seed")
    args = parser.parse_args(argv)
    if args.check:
        try:
            print(check_benchmark_file(args.check))
        except (BenchmarkError, FileNotFoundError) as error:
            parser.exit(1, f"error: {error}\n")
        return
    if args.out is None:
        parser.error("--generate needs --out FILE (the benchmark file to write)")
    if args.count < 1:
        parser.error(f"--count must be at least 1, got {args.count}")
    if args.workers < 1:
        parser.error(f"--workers must be at least 1, got {args.workers}")
    try:
        chains = generate_benchmark_chains(args.count, args.seed, args.workers, out=args.out, progress=True)
    except BenchmarkError as error:
        parser.exit(1, f"error: {error}\n")
    print(f"wrote {len(chains)} chains to {args.out}\n{check_benchmark_file(args.out)}")


if __name__ == "__main__":
    # Run through the package's module, not this `__main__` copy, so that Ray workers find the jobs' functions by name.
    from trivla_drake.tasks.chain_benchmark import main as package_main

    package_main()
