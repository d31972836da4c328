"""The layers import only downwards (docs/architecture.md), read from the source with `ast`: every import
statement of every module under daemon/, drivers/, importers/, sim/, mapping/ and exporters/, at top level or inside
a function."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("daemon", "drivers", "importers", "sim", "mapping", "exporters")
ABOVE_THE_SPINE = ("daemon.bus", "daemon.log_format", "daemon.processes", "daemon.commands", "drivers", "importers",
                   "sim", "exporters")
MAX_LINES = 500
SIZE_CHECKED = ("daemon", "drivers", "importers", "sim", "mapping", "exporters")


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(tree: ast.AST, importer: str) -> list[str]:
    """Every module an import statement names: `import a.b`, `from a.b import c` (also `a.b.c`, c may be a
    module), relative imports resolved against the importer."""
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = importer.split(".")[: -node.level]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            names.append(module)
            names += [f"{module}.{alias.name}" for alias in node.names]
    return names


def sources() -> dict[str, tuple[Path, str]]:
    return {module_name(p): (p, p.read_text()) for package in PACKAGES for p in sorted((ROOT / package).rglob("*.py"))}


def under(module: str, *prefixes: str) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def is_driver_process(module: str) -> bool:
    parts = module.split(".")
    return len(parts) == 3 and parts[0] == "drivers" and parts[2].endswith("_driver")


def layer_violations(modules: dict[str, tuple[Path, str]]) -> list[str]:
    found = []
    for importer, (_, text) in modules.items():
        for imported in imported_modules(ast.parse(text), importer):
            if under(importer, "daemon", "drivers", "importers", "sim") and under(imported, "mapping"):
                found.append(f"(a) {importer} imports {imported}: daemon/, drivers/, importers/, sim/ sit below "
                             f"mapping/")
            if under(importer, "daemon.spine") and under(imported, *ABOVE_THE_SPINE):
                found.append(f"(b) {importer} imports {imported}: the spine imports nothing above it")
            if under(imported, "daemon.processes") and not under(importer, "daemon.processes"):
                found.append(f"(c) {importer} imports {imported}: only the processes import process modules "
                             f"(the CLI names them as strings)")
            if under(importer, "mapping", "sim", "exporters") and is_driver_process(imported):
                found.append(f"(d) {importer} imports {imported}: a driver process; use its codec modules")
            if under(imported, "exporters") and not under(importer, "exporters"):
                found.append(f"(f) {importer} imports {imported}: exporters/ sits on top (the CLI names it as a "
                             f"string)")
    return sorted(set(found))


def oversized(modules: dict[str, tuple[Path, str]]) -> list[str]:
    return [f"(e) {m}: {len(text.splitlines())} lines (at most {MAX_LINES})" for m, (_, text) in modules.items()
            if under(m, *SIZE_CHECKED) and len(text.splitlines()) > MAX_LINES]


def test_the_layers_import_only_downwards():
    assert layer_violations(sources()) == []


def test_no_module_is_over_500_lines():
    assert oversized(sources()) == []


@pytest.mark.parametrize("importer, code, rule", [
    ("daemon.processes.recorder", "def f():\n    from mapping.live import mapping_worker\n", "(a)"),
    ("sim.world.scene", "import mapping.method.mesh as m\n", "(a)"),
    ("drivers.lidar.ouster_xyz", "from mapping import demo\n", "(a)"),
    ("importers.kitti_raw", "from mapping.localization import pose_fusion\n", "(a)"),
    ("daemon.spine.topics", "from daemon.bus.pubsub import open_publisher\n", "(b)"),
    ("daemon.spine.config", "from ..log_format import reader\n", "(b)"),
    ("daemon.spine.health", "import sim.world.scene\n", "(b)"),
    ("mapping.live.mapping_worker", "from daemon.processes.status_server import preview_dir\n", "(c)"),
    ("daemon.bus.pubsub", "from daemon.processes import supervisor\n", "(c)"),
    ("sim.camera_playback", "from drivers.camera.camera_driver import main\n", "(d)"),
    ("mapping.inputs.drive_inputs", "from drivers.lidar import udp_driver\n", "(d)"),
    ("exporters.ros2_bag", "from drivers.lidar.udp_driver import main\n", "(d)"),
    ("mapping.offline.reconstruct_command", "from exporters import ros2_bag\n", "(f)"),
    ("importers.ros2_bag", "import exporters.ros2_messages\n", "(f)"),
])
def test_each_rule_catches_a_planted_import(importer, code, rule):
    found = layer_violations({importer: (Path(), code)})
    assert found and all(f.startswith(rule) for f in found), found


def test_allowed_imports_pass():
    allowed = {
        "daemon.processes.daemon_main": (Path(), "from daemon.processes.supervisor import Supervisor\n"),
        "daemon.spine.topics": (Path(), "from daemon.spine.config import CarConfig\n"),
        "mapping.inputs.lidar_ground": (Path(), "from drivers.lidar.ouster_decoder import decode_packets\n"),
        "sim.camera_playback": (Path(), "from drivers.camera.camera_process import camera_process_main\n"),
        "exporters.ros2_bag": (Path(), "from mapping.inputs.lidar_ground import packet_scan_points\n"),
    }
    assert layer_violations(allowed) == []


def test_the_size_rule_catches_a_long_module():
    long = "x = 1\n" * (MAX_LINES + 1)
    assert oversized({"drivers.lidar.big": (Path(), long), "drivers.lidar.ok": (Path(), "x = 1\n" * MAX_LINES)}) == [
        f"(e) drivers.lidar.big: {MAX_LINES + 1} lines (at most {MAX_LINES})"]
