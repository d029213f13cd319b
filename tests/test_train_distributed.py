"""`torchrun --nproc_per_node 2` (two CPU processes, gloo): both ranks end with identical weights,
the feature cache is split between them, and only rank 0 writes checkpoints."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

from trivla_drake.train.synthetic import write_synthetic_dataset


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_end_with_identical_weights(tmp_path):
    data = write_synthetic_dataset(tmp_path / "data", episodes=3, length=12, image_size=16)
    out = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE"}
    command = [
        sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc_per_node", "2",
        "--master_addr", "127.0.0.1", "--master_port", str(_free_port()),
        "-m", "trivla_drake.train.cli_commands", "train", "--stage", "policy", "--data", data,
        "--out", str(out), "--preset", "tiny", "--steps", "3", "--set", "batch_size=2", "--set", "checkpoint_every=2",
        "--set", f"cache_dir={tmp_path / 'cache'}", "--threads", "1", "--no-progress", "--json",
    ]
    result = subprocess.run(command, env=env, capture_output=True, text=True, timeout=280)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["world_size"] == 2 and summary["steps"] == 3
    digests = summary["weights_sha256_per_rank"]
    assert len(digests) == 2 and digests[0] == digests[1]
    assert summary["feature_shards_computed"] == 3
    assert len(list((tmp_path / "cache" / "features").glob("*/*.safetensors"))) == 3
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["step-00000002", "step-00000003"]
    # the printed summary comes from rank 0 alone
    assert result.stdout.count('"weights_sha256_per_rank"') == 1
