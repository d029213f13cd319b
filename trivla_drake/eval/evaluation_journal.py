"""`evaluate`'s journal: every episode's and chain's result, one JSON line each, appended as it finishes, so that a
killed evaluation resumes where it stopped and a larger one reuses a smaller one's results (`--chains 1000` after
`--chains 200` runs only chains 200-999).

OUT/episodes.jsonl starts with a header line holding the journal's key: the settings that decide each job's result
(the policy with the sha256 of its checkpoint's contents, the torch threads a rollout runs with, every other EvalConfig
field that differs from its default, the package version and the benchmark chains' sha256), not those that only
decide which jobs run (tasks, episodes, chains, seeds) nor where they run (workers, Ray). Each further line is
{"job": [kind, name, index, base seed], "result": {...}}. A job's result depends only on the key and the job
(rollouts are byte-identical whatever the workers), so a stored one is the one a rerun of the same code would
compute; a change of the code within one package version is not seen (give another --out after one).

A journal of other settings is never overwritten: opening it raises ValueError naming the settings that differ. A
line cut short by a kill is dropped (its job runs again) and the file is cut back to its last whole line.
"""

from __future__ import annotations

import functools
import json
import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

JOURNAL_FILE = "episodes.jsonl"
JOURNAL_VERSION = 1
# EvalConfig fields that choose the jobs or where they run, not what a job gives.
_ABSENT = object()
NOT_IN_KEY = ("tasks", "episodes", "chains", "seed", "seeds", "workers", "ray_address", "out", "record_dir")


@functools.lru_cache(maxsize=None)
def _checkpoint_digest(path: str, modified: float) -> str:
    from trivla_drake.nn.checkpoint import checkpoint_digest

    return checkpoint_digest(path)


def policy_fingerprint(policy: str) -> str:
    """'oracle' and 'random' as they are; a checkpoint (a folder, or 'trivla': the shipped one) as the sha256 of its
    config and weights, so a checkpoint retrained into the same folder is another policy."""
    if policy == "trivla":
        from trivla_drake.eval.model_loading import default_checkpoint_dir

        path = default_checkpoint_dir()
    else:
        path = Path(policy)
    if not (path / "config.json").is_file():
        return policy
    weights = path / "model.safetensors"
    modified = max((path / "config.json").stat().st_mtime, weights.stat().st_mtime if weights.exists() else 0.0)
    return "checkpoint sha256 " + _checkpoint_digest(str(path.resolve()), modified)


def journal_key(config) -> dict[str, Any]:
    """The settings of an EvalConfig that decide each job's result (JSON-ready; see the module docstring). Fields at
    their defaults are left out, so a field added to EvalConfig later leaves earlier journals valid."""
    from trivla_drake import __version__
    from trivla_drake.tasks.chain_benchmark import BENCHMARK_SHA256

    defaults = asdict(type(config)())
    key: dict[str, Any] = {"trivla_drake": __version__, "benchmark_sha256": BENCHMARK_SHA256,
                           "policy": policy_fingerprint(config.policy), "threads": config.rollout_threads()}
    for name, value in asdict(config).items():
        if name not in NOT_IN_KEY and name not in key and value != defaults[name]:
            key[name] = value
    return json.loads(json.dumps(key))


def _job_id(job) -> tuple:
    kind, name, index, seed = job
    return (str(kind), str(name), int(index), int(seed))


class EvaluationJournal:
    """The journal at OUT/episodes.jsonl for one key: `done` (the stored results by job) and `append`."""

    def __init__(self, out: str | os.PathLike, key: dict[str, Any]):
        self.path = Path(out) / JOURNAL_FILE
        self.key = key
        self.done: dict[tuple, dict] = {}
        if self.path.exists():
            self._read()
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._write_line({"journal": JOURNAL_VERSION, "key": key}, mode="w")

    def _read(self) -> None:
        data = self.path.read_bytes()
        whole = data[: data.rfind(b"\n") + 1]  # what follows the last newline was cut short by a kill
        lines = whole.decode(errors="replace").splitlines()
        if not lines and (not data or data.startswith(b'{"journal"')):  # killed while writing its header
            self._write_line({"journal": JOURNAL_VERSION, "key": self.key}, mode="w")
            return
        try:
            header = json.loads(lines[0]) if lines else None
        except ValueError:
            header = None
        if not isinstance(header, dict) or not isinstance(header.get("key"), dict):
            raise ValueError(f"{self.path} is not an evaluation journal (its first line is no journal header): it is "
                             "kept as it is; move it away, or give another out folder (--out)")
        if header.get("journal") != JOURNAL_VERSION:
            raise ValueError(f"{self.path} is a journal of version {header.get('journal')!r}; this code writes "
                             f"version {JOURNAL_VERSION}: it is kept as it is; give another out folder (--out)")
        if header["key"] != self.key:
            def shown(key: dict, name: str) -> str:
                return repr(key[name]) if name in key else "the default"

            differ = sorted(name for name in set(header["key"]) | set(self.key)
                            if header["key"].get(name, _ABSENT) != self.key.get(name, _ABSENT))
            listed = "; ".join(f"{name}: {shown(header['key'], name)} there, {shown(self.key, name)} now"
                               for name in differ)
            raise ValueError(f"{self.path} holds the results of an evaluation with other settings ({listed}); it is "
                             "kept as it is: give another out folder (--out), or the same settings to resume it")
        for number, line in enumerate(lines[1:], start=2):
            try:
                entry = json.loads(line)
                self.done[_job_id(entry["job"])] = entry["result"]
            except (ValueError, KeyError, TypeError) as exc:
                raise ValueError(f"{self.path} line {number} is not a job's result ({exc}): the journal was edited; "
                                 "move it away, or give another --out") from None
        if len(whole) != len(data):
            with open(self.path, "r+b") as f:
                f.truncate(len(whole))

    def _write_line(self, entry: dict, mode: str = "a") -> None:
        with open(self.path, mode) as f:
            f.write(json.dumps(entry) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def result(self, job) -> dict | None:
        """The stored result of `job` (kind, name, index, base seed), None when it has not run."""
        return self.done.get(_job_id(job))

    def append(self, job, result: dict) -> None:
        """Stores `job`'s result (one line, flushed to disk before returning)."""
        self._write_line({"job": list(_job_id(job)), "result": result})
        self.done[_job_id(job)] = result
