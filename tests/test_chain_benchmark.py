"""The fixed chain benchmark (tasks/chain_benchmark.py): the shipped file keeps the rules and never changes by accident,
broken chains are refused, the generator draws the shipped chains again and resumes a killed run, and a stored chain
runs from its own scene with its own tasks whoever runs it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from trivla_drake.eval.episode import run_chain
from trivla_drake.eval.policies import RandomPolicy
from trivla_drake.tasks import chain_benchmark
from trivla_drake.tasks.chain_benchmark import (
    BENCHMARK_BASE_SEED,
    BENCHMARK_FILE,
    BENCHMARK_SCENES_SHA256,
    BENCHMARK_SHA256,
    BENCHMARK_SIZE,
    GENERATOR_VERSION,
    TASK_CATEGORIES,
    BenchmarkChain,
    BenchmarkError,
    ChainSubtask,
    benchmark_options,
    benchmark_scene,
    benchmark_scenes_sha256,
    chains_sha256,
    generate_benchmark_chains,
    load_benchmark_chains,
    read_benchmark_file,
    subtask_instance,
    validate_benchmark_chains,
)
from trivla_drake.tasks.oracle import OraclePolicy
from trivla_drake.tasks.scene import BLOCK_COLORS, Layout, scene_from_spec
from trivla_drake.tasks.suite import TASK_NAMES

LAYOUT = Layout.default()


@pytest.fixture(scope="module")
def chains() -> list[BenchmarkChain]:
    return load_benchmark_chains()


# ---------------------------------------------------------------- the shipped file
def test_the_shipped_file_keeps_the_rules(chains):
    assert len(chains) == BENCHMARK_SIZE == 1000
    validate_benchmark_chains(chains)  # raises on any broken rule
    header, _ = read_benchmark_file(BENCHMARK_FILE)
    assert header["count"] == BENCHMARK_SIZE
    assert header["base_seed"] == BENCHMARK_BASE_SEED and header["generator_version"] == GENERATOR_VERSION
    assert header["discarded"] == sum(header["discarded_by_reason"].values())


def test_the_shipped_chains_never_change_by_accident(chains, tmp_path):
    assert chains_sha256(chains) == BENCHMARK_SHA256
    copy = tmp_path / "benchmark_chains.json"
    copy.write_text(BENCHMARK_FILE.read_text())
    assert load_benchmark_chains(path=copy) == chains  # an unchanged copy loads
    text = copy.read_text()
    seed = chains[7].subtasks[2].seed
    assert text.count(f",{seed}]") == 1
    copy.write_text(text.replace(f",{seed}]", f",{seed + 1}]"))  # one subtask's seed changed
    with pytest.raises(BenchmarkError, match="other chains than the benchmark's.*BENCHMARK_SHA256"):
        load_benchmark_chains(path=copy)


def test_the_shipped_chains_start_from_the_scenes_they_were_generated_in(chains):
    assert benchmark_scenes_sha256(chains) == BENCHMARK_SCENES_SHA256, (
        "sample_chain_scene/sample_scene draw other scenes from the benchmark's scene seeds than when the chains "
        "were generated: restore the sampler, or regenerate the benchmark (a new generator version)")


def test_load_gives_the_first_n_chains_and_refuses_other_counts(chains):
    assert load_benchmark_chains(3) == chains[:3]
    assert [c.index for c in load_benchmark_chains(BENCHMARK_SIZE)] == list(range(BENCHMARK_SIZE))
    for n in (0, BENCHMARK_SIZE + 1, -1, 2.5, True):
        with pytest.raises(ValueError, match=r"n \(how many benchmark chains\) must be a whole number from 1 to 1000"):
            load_benchmark_chains(n)


def test_a_missing_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="benchmark chain file .*missing.*package-data"):
        load_benchmark_chains(path=tmp_path / "none.json")


# ---------------------------------------------------------------- the rules refuse broken chains
def _with_chain(chains, index, chain):
    return chains[:index] + [chain] + chains[index + 1:]


def _replaced(chain, position, subtask):
    subtasks = list(chain.subtasks)
    subtasks[position] = subtask
    return BenchmarkChain(chain.index, chain.scene_seed, subtasks)


def _repeated_category(chains):
    chain = next(c for c in chains if all(s.task != "lift_block" for s in c.subtasks))
    return chain.index, _replaced(chain, 3, chain.subtasks[0]), r"task category .* more than once"


def _opposite_of_an_earlier_task(chains):
    """CALVIN's categories: closing the drawer a chain opened repeats the drawer's category."""
    opposite = {"open_drawer": "close_drawer", "close_drawer": "open_drawer", "turn_on_light": "turn_off_light",
                "turn_off_light": "turn_on_light", "push_block_left": "rotate_block_right"}
    chain, first = next((c, p) for c in chains for p, s in enumerate(c.subtasks[:4]) if s.task in opposite)
    later = ChainSubtask(opposite[chain.subtasks[first].task], (), 5)
    if later.task.startswith(("push", "rotate")):
        later = later._replace(params=chain.subtasks[first].params)
    return chain.index, _replaced(chain, 4, later), r"task category \w+ more than once"


def _infeasible_first_task(chains):
    def light_task(chain):  # the lamp task that cannot start in the chain's scene
        return "turn_on_light" if benchmark_scene(chain.scene_seed, LAYOUT).lamp_on else "turn_off_light"

    chain = next(c for c in chains
                 if not any("light" in s.task for s in c.subtasks) and c.subtasks[0].task != "lift_block")
    broken = _replaced(chain, 0, ChainSubtask(light_task(chain), (), chain.subtasks[0].seed))
    return chain.index, broken, r"the first task turn_o.._light \[\] cannot start in the chain's initial scene"


def _lift_followed_by_another_block(chains):
    chain = next(c for c in chains if any(s.task == "lift_block" for s in c.subtasks))
    position = [s.task for s in chain.subtasks].index("lift_block")
    follow = chain.subtasks[position + 1]
    other = next(c for c in BLOCK_COLORS if c not in follow.params)
    broken = _replaced(chain, position + 1, follow._replace(params=(other,) + follow.params[1:]))
    return chain.index, broken, rf"the lift at subtask {position} .* is not followed by place_in_bowl or stack_block"


def _lift_last(chains):
    chain = next(c for c in chains if all(s.task != "lift_block" for s in c.subtasks))
    broken = _replaced(chain, 4, ChainSubtask("lift_block", ("red",), 5))
    return chain.index, broken, r"the lift at subtask 4 .* is not followed"


def _unknown_task(chains):
    chain = chains[3]
    return 3, _replaced(chain, 2, ChainSubtask("fly_away", (), 5)), r"subtask 2: unknown task 'fly_away'"


def _misshapen_params(chains):
    chain = chains[4]
    task = chain.subtasks[1].task
    return 4, _replaced(chain, 1, ChainSubtask(task, ("red", "red", "blue"), 5)), rf"{task} parameters .* are not"


def _four_subtasks(chains):
    chain = chains[5]
    return 5, BenchmarkChain(5, chain.scene_seed, chain.subtasks[:4]), r"chain 5: 4 subtasks, not 5"


def _repeated_scene_seed(chains):
    return 6, BenchmarkChain(6, chains[2].scene_seed, chains[6].subtasks), r"scene seed \d+ is also chain 2's"


@pytest.mark.parametrize("breaker", [_repeated_category, _opposite_of_an_earlier_task, _infeasible_first_task, _lift_followed_by_another_block,
                                     _lift_last, _unknown_task, _misshapen_params, _four_subtasks,
                                     _repeated_scene_seed])
def test_validation_refuses_a_broken_chain(chains, breaker):
    index, broken, message = breaker(chains)
    with pytest.raises(BenchmarkError, match=message):
        validate_benchmark_chains(_with_chain(chains, index, broken))


def test_validation_refuses_a_wrong_count_or_order(chains):
    with pytest.raises(BenchmarkError, match="999 chains, not 1000"):
        validate_benchmark_chains(chains[:-1])
    with pytest.raises(BenchmarkError, match="chain at position 0 has index 1"):
        validate_benchmark_chains(chains[1:2], count=None)
    validate_benchmark_chains(chains[:2], count=None)  # a prefix keeps the rules


def test_a_lift_is_offered_only_where_an_unused_follow_up_can_take_its_block():
    spec = next(s for s in (benchmark_scene(k, LAYOUT) for k in range(50))
                if any(s.blocks[c].position[2] < 0.03 for c in BLOCK_COLORS))
    scene = scene_from_spec(spec, LAYOUT)
    assert "lift_block" in benchmark_options(scene, set(), last=False)
    assert "lift_block" not in benchmark_options(scene, set(), last=True)
    assert "lift_block" not in benchmark_options(scene, {"place_in_bowl", "stack_block"}, last=False)
    assert not {"lift_block", "open_drawer"} & set(benchmark_options(scene, {"lift_block", "open_drawer"}, last=False))
    # CALVIN's categories: after an open drawer, no closing; after a push, no rotation (nor the other push)
    assert "close_drawer" not in benchmark_options(scene, {"open_drawer"}, last=False)
    pushed = benchmark_options(scene, {"push_block_left"}, last=False)
    assert not {"push_block_right", "rotate_block_left", "rotate_block_right"} & set(pushed) and pushed


def test_every_task_has_a_category_and_the_shipped_chains_repeat_none(chains):
    assert set(TASK_CATEGORIES) == set(TASK_NAMES)
    assert len(set(TASK_CATEGORIES.values())) == 7  # lift, place, stack, unstack, block on the table, drawer, lamp
    for chain in chains:
        categories = [TASK_CATEGORIES[s.task] for s in chain.subtasks]
        assert len(set(categories)) == len(categories), (chain.index, categories)


def test_a_subtask_seed_gives_its_instruction_and_policy_seed():
    subtask = ChainSubtask("stack_block", ("red", "blue"), 12345)
    instance, policy_seed = subtask_instance(subtask)
    assert (instance.task, instance.params) == ("stack_block", ("red", "blue"))
    assert subtask_instance(subtask) == (instance, policy_seed)
    paraphrased, same_seed = subtask_instance(subtask, paraphrase=True)
    assert same_seed == policy_seed and paraphrased.instruction != instance.instruction
    assert "red" in instance.instruction and "red" in paraphrased.instruction


# ---------------------------------------------------------------- the generator
def test_the_generator_draws_the_shipped_chains_again_and_resumes_a_killed_run(chains, tmp_path, monkeypatch):
    out = tmp_path / "chains.json"
    first = generate_benchmark_chains(1, BENCHMARK_BASE_SEED, 1, out=out)
    assert first == chains[:1]
    log = tmp_path / "chains.json.partial"
    done = len(log.read_text().splitlines()) - 1  # candidates the first chain took
    with open(log, "a") as f:  # a kill in the middle of writing the next candidate's line
        f.write('{"candidate":%d,"scene_seed":12' % done)
    attempted = []
    attempt = chain_benchmark._attempt
    monkeypatch.setattr(chain_benchmark, "_attempt", lambda seed, k: attempted.append(k) or attempt(seed, k))
    second = generate_benchmark_chains(2, BENCHMARK_BASE_SEED, 1, out=out)
    assert second == chains[:2]
    assert attempted and attempted[0] == done  # went on from the log, the cut line dropped
    records = [json.loads(line) for line in log.read_text().splitlines()[1:]]
    assert [r["candidate"] for r in records] == list(range(len(records)))
    header, stored = read_benchmark_file(out)
    assert stored == chains[:2] and header["count"] == 2 and header["discarded"] == len(records) - 2


def test_the_generator_refuses_another_generations_log_and_bad_counts(tmp_path):
    out = tmp_path / "chains.json"
    (tmp_path / "chains.json.partial").write_text(json.dumps({"base_seed": 5, "generator_version": 1}) + "\n")
    with pytest.raises(BenchmarkError, match="log of another generation"):
        generate_benchmark_chains(1, BENCHMARK_BASE_SEED, 1, out=out)
    with pytest.raises(ValueError, match=r"count \(--count\) must be a whole number of chains of at least 1"):
        generate_benchmark_chains(0, out=out)
    with pytest.raises(ValueError, match=r"workers \(--workers\) must be a whole number of processes"):
        generate_benchmark_chains(1, workers=0, out=out)


@pytest.mark.parametrize("argv, message", [
    (["--generate", "--count", "0", "--out", "x.json"], "--count must be at least 1, got 0"),
    (["--generate", "--workers", "0", "--out", "x.json"], "--workers must be at least 1, got 0"),
    (["--generate"], "--generate needs --out FILE"),
    ([], "one of the arguments --generate --check is required"),
])
def test_the_command_line_names_a_bad_flag(argv, message, capsys):
    with pytest.raises(SystemExit):
        chain_benchmark.main(argv)
    assert message in capsys.readouterr().err


def test_check_reports_the_shipped_digests_and_refuses_a_broken_file(tmp_path, capsys):
    chain_benchmark.main(["--check", str(BENCHMARK_FILE)])
    assert f'BENCHMARK_SHA256 = "{BENCHMARK_SHA256}"  (the shipped one)' in capsys.readouterr().out
    broken = tmp_path / "broken.json"
    broken.write_text(BENCHMARK_FILE.read_text().replace('"count": 1000', '"count": 999'))
    with pytest.raises(SystemExit):
        chain_benchmark.main(["--check", str(broken)])
    assert "1000 chains, not 999" in capsys.readouterr().err


# ---------------------------------------------------------------- running a stored chain
@pytest.mark.parametrize("index", [0, 1])
def test_the_oracle_completes_a_stored_chain_with_its_own_tasks(chains, index):
    chain = chains[index]
    result = run_chain(chain.scene_seed, OraclePolicy(), chain=chain)
    assert result.completed == 5, result.reason
    assert [(s.task, s.params) for s in result.subtasks] == [(s.task, s.params) for s in chain.subtasks]
    assert [s.instruction for s in result.subtasks] == [subtask_instance(s)[0].instruction for s in chain.subtasks]
    assert result.stored_task_feasible == [True] * 5
    assert result.to_dict()["chain_index"] == index


class _SceneSpy:
    """A policy that notes the scene it first sees and holds still."""

    name, uses_images, privileged = "spy", False, True

    def __init__(self):
        self.scenes = []

    def reset(self, instruction, seed):
        pass

    def act(self, observation):
        self.scenes.append(observation["privileged"]["scene"])
        return np.zeros(7)


def test_a_stored_chain_starts_from_its_scene_whatever_seed_runs_it(chains):
    chain = chains[0]
    spec = benchmark_scene(chain.scene_seed, LAYOUT)
    seen = []
    for seed in (0, 987654):
        spy = _SceneSpy()
        result = run_chain(seed, spy, chain=chain, max_steps=1)
        assert result.seed == seed
        assert result.subtasks[0].instruction == subtask_instance(chain.subtasks[0])[0].instruction
        seen.append(spy.scenes[0])
    for color in BLOCK_COLORS:
        np.testing.assert_array_equal(seen[0].blocks[color], seen[1].blocks[color])
        np.testing.assert_allclose(seen[0].blocks[color][:3, 3], spec.blocks[color].position, atol=1e-9)
    assert seen[0].drawer_opening == pytest.approx(spec.drawer_opening) and seen[0].lamp_on == spec.lamp_on
    paraphrased = run_chain(0, RandomPolicy(), chain=chain, max_steps=1, paraphrase=True)
    assert paraphrased.subtasks[0].instruction == subtask_instance(chain.subtasks[0], paraphrase=True)[0].instruction
    with pytest.raises(ValueError, match="length must be from 1 to the stored chain's 5 subtasks, got 6"):
        run_chain(0, RandomPolicy(), chain=chain, length=6)


def test_a_stored_task_that_cannot_start_is_attempted_and_flagged(chains):
    index, broken, _ = _infeasible_first_task(chains)
    result = run_chain(broken.scene_seed, RandomPolicy(), chain=broken, max_steps=1)
    assert result.stored_task_feasible == [False]
    assert [s.task for s in result.subtasks] == [broken.subtasks[0].task] and result.completed == 0
    assert result.to_dict()["stored_task_feasible"] == [False]
