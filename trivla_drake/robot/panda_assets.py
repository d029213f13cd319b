"""Convert example-robot-data's Panda (DAE visuals, STL collisions) into a URDF that Drake reads.

Drake reads .obj/.gltf/.vtk meshes only: an STL collision mesh is an error and a DAE visual is
silently left out of camera images. We convert once into a per-user cache (honouring
XDG_CACHE_HOME): every DAE is split by material colour into OBJ files with normals, each becoming
its own <visual> with that colour, and every STL becomes an OBJ. The cache folder is built beside
its final name and renamed into place, so concurrent first runs never see a half-written cache.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import tempfile
import xml.etree.ElementTree as ET
from importlib import metadata
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from trivla_drake.robot.panda_description import (
    ARM_JOINTS,
    FINGER_JOINTS,
    original_panda_urdf,
    panda_description_dir,
)

# Bump when the conversion's output changes, so old caches are not reused.
CONVERTER_VERSION = 6
# Visual parts are decimated to at most this many triangles each: the cameras render 224 px
# images, where the CAD meshes' detail is invisible but costs render time.
MAX_VISUAL_FACES = 2000
PACKAGE_NAME = "trivla_panda"
_COMPLETE_MARKER = "conversion_complete"


def cache_root() -> Path:
    """The per-user cache folder: $XDG_CACHE_HOME/trivla_drake (default ~/.cache/trivla_drake)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "trivla_drake"


def _cache_key() -> str:
    try:
        erd_version = metadata.version("example-robot-data")
    except metadata.PackageNotFoundError:
        erd_version = "unknown"
    source = original_panda_urdf().read_bytes()
    digest = hashlib.sha256(source + f"{CONVERTER_VERSION}/{erd_version}".encode()).hexdigest()
    return f"panda-{digest[:12]}"


def drake_panda_dir() -> Path:
    """The converted package folder (package.xml, panda.urdf, meshes/), converting on first use."""
    final = cache_root() / _cache_key()
    if (final / _COMPLETE_MARKER).exists():
        return final
    final.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=final.name + ".tmp-", dir=final.parent))
    try:
        # Thousands of small matrix products: BLAS threads only spin, and with other busy processes on the cores
        # (a parallel test run, Ray workers converting at once) spinning threads made a 2 s conversion take minutes.
        # One thread gives the same numbers.
        with threadpool_limits(limits=1, user_api="blas"):
            _convert_into(staging)
        (staging / _COMPLETE_MARKER).write_text("ok\n")
        try:
            os.rename(staging, final)
        except OSError:
            # Another process renamed its finished copy into place first; theirs is as good.
            if not (final / _COMPLETE_MARKER).exists():
                raise
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return final


def drake_panda_urdf() -> Path:
    """The Drake-readable Panda URDF (converted meshes, actuated arm and fingers), converting on first use.
    Its meshes are `package://trivla_panda/...` URLs: load it with a Parser that knows that package
    (`trivla_drake.station.station.make_parser(plant)`), then weld `panda_link0` where the base stands."""
    return drake_panda_dir() / "panda.urdf"


def _mesh_source(filename: str) -> Path:
    relative = re.sub(r"^package://example-robot-data/robots/panda_description/", "", filename)
    return panda_description_dir() / relative


def _visual_parts_by_colour(dae_path: Path) -> list[tuple[np.ndarray, "object"]]:
    """Load a DAE scene and merge its geometry per RGBA colour, in the DAE's own frame."""
    import trimesh

    scene = trimesh.load(dae_path, force="scene")
    groups: dict[tuple, list] = {}
    for node in scene.graph.nodes_geometry:
        transform, geometry_name = scene.graph[node]
        mesh = scene.geometry[geometry_name].copy()
        mesh.apply_transform(transform)
        material = getattr(mesh.visual, "material", None)
        colour = getattr(material, "baseColorFactor", None)
        if colour is None:
            colour = getattr(material, "diffuse", np.array([200, 200, 200, 255]))
        key = tuple(int(c) for c in np.asarray(colour).ravel()[:4])
        groups.setdefault(key, []).append(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False))
    return [
        (np.array(key, dtype=float) / 255.0, trimesh.util.concatenate(parts))
        for key, parts in sorted(groups.items())
    ]


def _export_obj(mesh, path: Path) -> None:
    from trimesh.exchange.obj import export_obj

    mesh.fix_normals() if mesh.is_watertight else None
    text = export_obj(mesh, include_normals=True, include_color=False, include_texture=False)
    path.write_text(text)


def _convert_into(out_dir: Path) -> None:
    import trimesh

    (out_dir / "meshes").mkdir(parents=True)
    tree = ET.parse(original_panda_urdf())
    robot = tree.getroot()
    converted: dict[str, list[tuple[str, np.ndarray]]] = {}

    for link in robot.findall("link"):
        for visual in list(link.findall("visual")):
            mesh_el = visual.find("geometry/mesh")
            if mesh_el is None:
                continue
            source = _mesh_source(mesh_el.get("filename"))
            if source.name not in converted:
                parts = []
                for i, (rgba, mesh) in enumerate(_visual_parts_by_colour(source)):
                    if len(mesh.faces) > MAX_VISUAL_FACES:
                        # Decimation needs shared vertices; the CAD export repeats them per face.
                        mesh.merge_vertices()
                        mesh = mesh.simplify_quadric_decimation(face_count=MAX_VISUAL_FACES)
                    name = f"meshes/{source.stem}_visual_{i}.obj"
                    _export_obj(mesh, out_dir / name)
                    parts.append((name, rgba))
                converted[source.name] = parts
            link.remove(visual)
            for i, (name, rgba) in enumerate(converted[source.name]):
                part = ET.SubElement(link, "visual", name=f"{link.get('name')}_visual_{i}")
                origin = visual.find("origin")
                if origin is not None:
                    part.append(origin)
                geometry = ET.SubElement(part, "geometry")
                ET.SubElement(geometry, "mesh", filename=name)
                material = ET.SubElement(part, "material", name=f"{source.stem}_colour_{i}")
                ET.SubElement(material, "color", rgba=" ".join(f"{c:.4f}" for c in rgba))
        for collision in link.findall("collision"):
            mesh_el = collision.find("geometry/mesh")
            if mesh_el is None:
                continue
            source = _mesh_source(mesh_el.get("filename"))
            name = f"meshes/{source.stem}_collision.obj"
            if not (out_dir / name).exists():
                _export_obj(trimesh.load(source, force="mesh"), out_dir / name)
            mesh_el.set("filename", name)

    for joint in robot.findall("joint"):
        # Each finger is driven on its own (same setpoint): Drake's mimic coupler needs SAP and
        # adds a constraint we do not need when both fingers track one command.
        # safety_controller is ROS-only; Drake warns about it on every parse.
        for tag in ("mimic", "safety_controller"):
            for element in joint.findall(tag):
                joint.remove(element)
    for joint_name in ARM_JOINTS + FINGER_JOINTS:
        transmission = ET.SubElement(robot, "transmission", name=f"{joint_name}_transmission")
        ET.SubElement(transmission, "type").text = "transmission_interface/SimpleTransmission"
        joint_el = ET.SubElement(transmission, "joint", name=joint_name)
        ET.SubElement(joint_el, "hardwareInterface").text = "EffortJointInterface"
        actuator = ET.SubElement(transmission, "actuator", name=f"{joint_name}_motor")
        ET.SubElement(actuator, "mechanicalReduction").text = "1"

    ET.indent(tree)
    tree.write(out_dir / "panda.urdf", encoding="unicode", xml_declaration=True)
    (out_dir / "package.xml").write_text(
        f'<?xml version="1.0"?>\n<package format="2">\n  <name>{PACKAGE_NAME}</name>\n'
        "  <version>0.0.0</version>\n  <description>Franka Panda converted from "
        "example-robot-data for Drake</description>\n  <maintainer email=\"none@example.com\">"
        "trivla-drake</maintainer>\n  <license>Apache-2.0</license>\n</package>\n"
    )
