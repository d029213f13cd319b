"""`evaluate --out`'s report.md and report.png (eval/report_plot.py)."""

import struct

from trivla_drake.eval.evaluate import EvalConfig, summarize, write_report
from trivla_drake.eval.report_plot import plot_evaluation


def _png_size(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


def _episodes():
    return [{"task": task, "success": success, "seed": seed, "instruction": "", "reason": "" if success else "timeout"}
            for task, success, seed in [("lift_block", True, 1), ("lift_block", False, 2), ("open_drawer", True, 1),
                                        ("open_drawer", True, 2)]]


def _chains():
    done = [("lift_block", "open_drawer", "turn_on_light"), ("push_block_left",), ()]
    return [{"seed": j, "completed": len(tasks) - 1 if tasks else 0, "reason": "timeout",
             "subtasks": [{"task": t} for t in tasks]} for j, tasks in enumerate(done)]


def test_report_with_tasks_and_chains_gets_both_panels_and_markdown(tmp_path):
    tasks_only = EvalConfig(tasks=["lift_block", "open_drawer"], episodes=2, out=str(tmp_path / "tasks"))
    files = write_report(tasks_only, summarize(tasks_only, _episodes(), []))
    assert set(files) == {"config", "json", "markdown", "plot"}
    assert "lift_block" in files["markdown"].read_text() and "Avg. Len" not in files["markdown"].read_text()
    one_panel = _png_size(files["plot"])

    both = EvalConfig(tasks=["lift_block", "open_drawer"], episodes=2, chains=3, out=str(tmp_path / "both"))
    report = summarize(both, _episodes(), _chains())
    files = write_report(both, report)
    assert "Avg. Len" in files["markdown"].read_text()
    width, height = _png_size(files["plot"])
    assert (width, height) == (2 * one_panel[0], one_panel[1])
    assert sorted(p.name for p in (tmp_path / "both").iterdir()) == [
        "eval_config.yaml", "report.json", "report.md", "report.png"]  # no temporary file left


def test_chains_only_report_is_one_panel_and_an_empty_one_writes_nothing(tmp_path):
    config = EvalConfig(episodes=0, chains=3, out=str(tmp_path / "c"))
    report = summarize(config, [], _chains())
    assert report["tasks"] == {}
    path = plot_evaluation(report, tmp_path / "c.png")
    width, height = _png_size(path)
    assert path == tmp_path / "c.png" and width < 2 * height  # one panel (two are over three heights wide)
    assert plot_evaluation(summarize(config, [], []), tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()
