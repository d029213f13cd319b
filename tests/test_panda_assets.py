"""Converting example-robot-data's Panda into Drake-readable meshes, once and safely."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np

from trivla_drake.robot import panda_assets


def test_conversion_honours_xdg_cache_home_and_writes_obj_with_normals(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    urdf = panda_assets.drake_panda_urdf()
    assert urdf.is_relative_to(tmp_path / "trivla_drake")
    text = urdf.read_text()
    assert ".stl" not in text and ".dae" not in text
    meshes = sorted((urdf.parent / "meshes").glob("*.obj"))
    assert len(meshes) > 20
    for mesh in meshes:
        body = mesh.read_text()
        assert "\nvn " in body, f"{mesh.name} has no normals"
    # Visual parts carry their material colours into the URDF.
    assert 'rgba="1.0000 1.0000 1.0000 1.0000"' in text and "0.2510 0.2510 0.2510" in text


def test_second_call_reuses_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    first = panda_assets.drake_panda_urdf()
    stamp = first.stat().st_mtime_ns
    second = panda_assets.drake_panda_urdf()
    assert first == second and second.stat().st_mtime_ns == stamp
    # No staging folders are left behind.
    assert [p.name for p in first.parent.parent.iterdir()] == [first.parent.name]


def test_two_processes_converting_at_once_both_succeed(tmp_path):
    code = "from trivla_drake.robot.panda_assets import drake_panda_urdf; print(drake_panda_urdf())"
    env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path))
    procs = [
        subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    try:
        outputs = [p.communicate(timeout=300)[0].strip() for p in procs]
    finally:
        for p in procs:  # a timed-out conversion must not keep burning a core for the rest of the suite
            p.kill()
    assert all(p.returncode == 0 for p in procs)
    assert outputs[0] == outputs[1]
    cache = tmp_path / "trivla_drake"
    assert [p.name for p in cache.iterdir()] == [os.path.basename(os.path.dirname(outputs[0]))]
    assert (cache / os.path.basename(os.path.dirname(outputs[0])) / panda_assets._COMPLETE_MARKER).exists()


def test_drake_reads_the_converted_panda(tmp_path, monkeypatch):
    from pydrake.multibody.parsing import Parser
    from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
    from pydrake.systems.framework import DiagramBuilder

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    plant, _ = AddMultibodyPlantSceneGraph(DiagramBuilder(), 0.0)
    (panda,) = Parser(plant).AddModels(str(panda_assets.drake_panda_urdf()))
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("panda_link0", panda))
    plant.Finalize()
    # 7 arm joints and 2 fingers, each actuated (the mimic coupling is replaced by one command).
    assert plant.num_positions() == 9 and plant.num_actuators() == 9
    visuals = sum(len(plant.GetVisualGeometriesForBody(plant.get_body(i))) for i in plant.GetBodyIndices(panda))
    assert visuals > 25
