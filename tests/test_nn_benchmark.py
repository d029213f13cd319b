"""benchmark_model / format_benchmark_table (figures are printed by the benchmark, not asserted)."""

import pytest
import torch

from trivla_drake.nn.benchmark import benchmark_model, format_benchmark_table


def test_tiny_benchmark_reports_every_system_and_table4_row():
    threads = torch.get_num_threads()
    torch.set_num_threads(2)  # not the benchmark's own setting, so both its setting and the restore are seen
    try:
        result = benchmark_model("tiny", repeats=1, seed=0, threads=1)
        assert torch.get_num_threads() == 2  # restored
    finally:
        torch.set_num_threads(threads)
    assert result["skipped"] is False and result["torch_threads"] == 1
    assert set(result["params_millions"]) == {"system1", "system2", "system3", "total"}
    assert set(result["latency_ms"]) == {"system1", "system2", "system3", "full"}
    assert all(v > 0 for v in result["latency_ms"].values())
    assert [row["systems"] for row in result["ablations"]] == ["1", "1+3", "1+2+3"]
    params = [row["params_millions"] for row in result["ablations"]]
    assert params[0] < params[1] < params[2] == result["params_millions"]["total"]
    table = format_benchmark_table(result)
    for text in ("System 2", "System 3", "System 1", "Full inference", "VL-M", "Hz"):
        assert text in table


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is present: the paper preset would be timed")
def test_paper_preset_is_skipped_without_cuda_and_never_built_on_cpu():
    result = benchmark_model("paper")
    assert result["skipped"] is True and "CUDA" in result["reason"]
    # parameter counts come from a meta-device build: billions of parameters, no memory used
    assert 3000 < result["params_millions"]["total"] < 5000
    assert "Skipped" in format_benchmark_table(result)


def test_bfloat16_autocast_runs_every_row_and_is_named_in_the_table():
    result = benchmark_model("tiny", repeats=1, seed=0, threads=1, precision="bfloat16")
    assert result["precision"] == "bfloat16" and result["skipped"] is False
    assert all(row["latency_ms"] > 0 for row in result["ablations"])
    assert "bfloat16 autocast" in format_benchmark_table(result)
    assert "autocast" not in format_benchmark_table(benchmark_model("tiny", repeats=1, threads=1))


def test_bad_arguments():
    with pytest.raises(ValueError, match="valid presets"):
        benchmark_model("huge")
    with pytest.raises(ValueError, match="repeats"):
        benchmark_model("tiny", repeats=0)
    with pytest.raises(ValueError, match="precision must be one of float32, bfloat16, float16; got 'fp8'"):
        benchmark_model("tiny", precision="fp8")
