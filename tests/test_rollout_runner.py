"""Rollouts on Ray (eval/rollout_runner.py): results in the jobs' order, jobs drawn lazily, a dying worker retried or
reported, and `evaluate`/`collect` on 2 local Ray workers giving exactly what a serial run gives."""

from __future__ import annotations

import filecmp
import json
import os
import sys
import time
from pathlib import Path

import pytest

ray = pytest.importorskip("ray")

from trivla_drake.eval import rollout_runner  # noqa: E402
from trivla_drake.eval.rollout_runner import MAX_RETRIES, RolloutError, RolloutRunner  # noqa: E402


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray with 2 worker CPUs for this file's tests (each runner then joins it instead of starting one)."""
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the jobs below live in this test file
    rollout_runner.start_local_ray(2)
    yield
    ray.shutdown()


def _slower_first(config, job):
    time.sleep(0.3 if job == 0 else 0.01)  # job 0 finishes last
    return config, job, os.getpid()


def _raises(config, job):
    if job == 2:
        raise ValueError("bad job (injected)")
    return job


def _dies_once(marker_dir, job):
    marker = Path(marker_dir) / f"{job}.died"
    if job == 1 and not marker.exists():
        marker.write_text("x")
        os._exit(1)  # the worker process dies mid-job
    return job


def _always_dies(config, job):
    os._exit(1)


def test_results_come_in_job_order_from_two_workers(local_ray):
    with RolloutRunner(workers=2) as runner:
        assert runner.parallelism() == 2
        results = list(runner.map_ordered(_slower_first, "c", range(6)))
    assert [(config, job) for config, job, _ in results] == [("c", i) for i in range(6)]
    assert len({pid for _, _, pid in results}) == 2 and os.getpid() not in {pid for _, _, pid in results}


def test_workers_get_the_text_encoder_the_driver_was_given(monkeypatch):
    """`trivla-drake --text-encoder FOLDER` reaches the workers through Ray's runtime_env, local or on a cluster (a
    local raylet would inherit the driver's environment anyway; a cluster's would not)."""
    calls = []
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", lambda **kwargs: calls.append(kwargs))
    monkeypatch.setattr(ray, "remote", lambda **kwargs: (lambda function: function))
    monkeypatch.setattr(ray, "shutdown", lambda: None)
    monkeypatch.setenv("TRIVLA_DRAKE_TEXT_ENCODER", "/models/all-MiniLM-L6-v2")
    for runner in (RolloutRunner(workers=2), RolloutRunner(address="ray://head:10001")):
        with runner:
            pass
    assert [call["runtime_env"]["env_vars"]["TRIVLA_DRAKE_TEXT_ENCODER"] for call in calls] == [
        "/models/all-MiniLM-L6-v2"] * 2
    monkeypatch.delenv("TRIVLA_DRAKE_TEXT_ENCODER")
    with RolloutRunner(address="ray://head:10001"):
        pass
    assert calls[-1]["runtime_env"] is None


def test_jobs_are_drawn_a_few_ahead_not_all_up_front(local_ray):
    drawn = []

    def jobs():
        for i in range(10_000):
            drawn.append(i)
            yield i

    with RolloutRunner(workers=2) as runner:
        results = runner.map_ordered(_slower_first, None, jobs())
        assert [next(results)[1] for _ in range(3)] == [0, 1, 2]
        assert len(drawn) <= 3 + rollout_runner.AHEAD_PER_WORKER * 2
        results.close()


def test_a_job_that_raises_stops_the_run_naming_it(local_ray):
    got = []
    with RolloutRunner(workers=2) as runner, pytest.raises(RolloutError, match=r"job 2 failed on a worker.*bad job"):
        for result in runner.map_ordered(_raises, None, range(5), describe=lambda job: f"job {job}"):
            got.append(result)
    assert got == [0, 1]  # everything before the failed job came back, nothing after it


def test_a_worker_that_dies_is_replaced_and_its_job_rerun(local_ray, tmp_path):
    with RolloutRunner(workers=2) as runner:
        assert list(runner.map_ordered(_dies_once, str(tmp_path), range(4))) == [0, 1, 2, 3]
    assert (tmp_path / "1.died").exists()


def test_a_job_that_kills_every_worker_is_reported_not_dropped(local_ray):
    with RolloutRunner(workers=2) as runner, pytest.raises(RolloutError, match=f"died {MAX_RETRIES + 1} times"):
        list(runner.map_ordered(_always_dies, None, [7], describe=lambda job: f"job {job}"))


def test_one_worker_runs_in_this_process_without_ray():
    runner = RolloutRunner(workers=1)
    with runner:
        assert not runner.uses_ray and runner.parallelism() == 1
        assert [pid for *_, pid in runner.map_ordered(_slower_first, None, range(2))] == [os.getpid()] * 2


def test_bad_workers_and_address_are_clear_errors(monkeypatch):
    with pytest.raises(ValueError, match="--workers must be an integer >= 1, got 0"):
        RolloutRunner(workers=0)
    monkeypatch.setenv("RAY_ADDRESS", "ray://head:10001")
    assert RolloutRunner(workers=1).address == "ray://head:10001"  # $RAY_ADDRESS sends even one worker to the cluster
    assert RolloutRunner(workers=1, address="auto").address == "auto"


def test_evaluate_on_two_ray_workers_reports_what_a_serial_run_does(local_ray):
    from trivla_drake.eval.evaluate import EvalConfig, evaluate

    # A benchmark chain capped at 40 steps a task: its first task times out, cheaply (the chain runs the same way).
    config = EvalConfig(policy="oracle", tasks=["push_block_left", "turn_off_light"], episodes=1, seeds=[3, 4],
                        chains=2, max_steps=40)
    serial = evaluate(config, progress=False)
    config.workers = 2
    parallel = evaluate(config, progress=False)
    assert json.dumps(serial) == json.dumps(parallel)  # byte for byte: the report leaves out where it ran
    assert [row["seed"] for row in serial["per_seed"]] == [3, 4] and serial["tasks"]["push_block_left"]["episodes"] == 2
    assert serial["chains"]["count"] == 4


def _dataset_files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


# The run's settings: the only files that record `workers`.
_RUN_SETTINGS = {"meta/collect_config.yaml", "meta/trivla_collection.json"}


def test_collect_on_two_ray_workers_writes_the_serial_dataset_and_resumes(local_ray, tmp_path):
    from trivla_drake.eval.collect import collect
    from trivla_drake.eval.collect_config import CollectConfig

    tasks = ["turn_on_light", "open_drawer"]
    serial = CollectConfig(out=str(tmp_path / "serial"), episodes_per_task=2, tasks=tasks, image_size=32)
    collect(serial, progress=False)
    first = CollectConfig(out=str(tmp_path / "ray"), episodes_per_task=1, tasks=tasks, image_size=32, workers=2)
    collect(first, progress=False)  # a run stopped after one episode per task, then resumed on Ray to two
    first.episodes_per_task = 2
    collect(first, progress=False)
    a, b = Path(serial.out), Path(first.out)
    assert _dataset_files(a) == _dataset_files(b)
    different = [name for name in _dataset_files(a) if not filecmp.cmp(a / name, b / name, shallow=False)]
    assert set(different) <= _RUN_SETTINGS, different


def test_a_command_starts_its_own_local_ray_and_stops_it_but_leaves_a_callers_running():
    """In a fresh process (no Ray of this file's): the runner starts a local Ray of 2 workers and shuts it down on
    exit; inside a Ray the caller started, it joins it and leaves it running."""
    import subprocess

    script = """
import operator, ray
from trivla_drake.eval.rollout_runner import RolloutRunner
assert not ray.is_initialized()
with RolloutRunner(2) as runner:
    assert ray.is_initialized() and int(ray.cluster_resources()["CPU"]) == 2
    assert list(runner.map_ordered(operator.add, 10, range(4))) == [10, 11, 12, 13]
assert not ray.is_initialized(), "the runner's own Ray is still running"
ray.init(num_cpus=2, include_dashboard=False)
with RolloutRunner(2) as runner:
    assert list(runner.map_ordered(operator.mul, 3, range(3))) == [0, 3, 6]
assert ray.is_initialized(), "the caller's Ray was stopped"
ray.shutdown()
print("ok")
"""
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0 and result.stdout.strip().endswith("ok"), result.stderr[-3000:]
