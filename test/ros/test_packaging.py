"""Packaging: package.xml and setup.py name what the code imports, and `colcon build` of the package
works (colcon, pinned in colcon_requirements.txt, installed from the package index into a folder of
the test's own)."""
from __future__ import annotations

import ast
import importlib.util
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from senfunet_ros.cli import build_parser

REPO = Path(__file__).resolve().parents[2]
# import name -> distribution name in install_requires (where they differ)
DIST = {"cv2": "opencv-python-headless", "PIL": "pillow", "yaml": "pyyaml", "skimage": "scikit-image",
        "ruamel": "ruamel.yaml"}
ROS = {"rclpy", "rcl_interfaces", "std_msgs", "sensor_msgs", "geometry_msgs", "nav_msgs", "visualization_msgs",
       "diagnostic_msgs", "std_srvs", "rosgraph_msgs", "builtin_interfaces", "tf2_ros", "tf2_msgs", "launch",
       "launch_ros", "ament_index_python"}


def _third_party_imports() -> set[str]:
    """Top-level modules imported anywhere in the two packages (and the launch file), minus the
    standard library and the packages themselves."""
    names: set[str] = set()
    files = [*REPO.glob("senfunet_core/**/*.py"), *REPO.glob("senfunet_ros/**/*.py"), *REPO.glob("launch/*.py")]
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return {n for n in names if n not in sys.stdlib_module_names and not n.startswith("senfunet_")}


def _setup_kwargs() -> dict:
    tree = ast.parse((REPO / "setup.py").read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup")
    return {k.arg: k.value for k in call.keywords}


def test_install_requires_and_package_xml_cover_every_import() -> None:
    kwargs = _setup_kwargs()
    requires = {str(ast.literal_eval(e)).split("=")[0].split(">")[0] for e in kwargs["install_requires"].elts}
    assert ast.literal_eval(kwargs["python_requires"]) == ">=3.11"
    xml = (REPO / "package.xml").read_text()
    exec_depends = set(re.findall(r"<exec_depend>([^<]+)</exec_depend>", xml))
    for name in sorted(_third_party_imports()):
        if name in ROS:
            key = "tf2_ros_py" if name == "tf2_ros" else name
            assert key in exec_depends, f"package.xml lacks <exec_depend>{key}</exec_depend>"
        else:
            assert DIST.get(name, name) in requires, f"setup.py install_requires lacks {DIST.get(name, name)}"
    # keys rosdep no longer resolves, or never did (rosdistro's rosdep/python.yaml)
    assert not exec_depends & {"python3-pytorch-pip", "python3-mcap-pip"}


@pytest.mark.slow
def test_colcon_build_installs_the_package(tmp_path: Path) -> None:
    colcon = tmp_path / "colcon"  # not in the suite's environment: colcon's pytest plugins stay out of it
    pip = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--disable-pip-version-check", "--no-deps",
                          "--target", str(colcon), "-r", str(Path(__file__).with_name("colcon_requirements.txt"))],
                         capture_output=True, text=True, timeout=600)
    if pip.returncode != 0:
        pytest.skip(f"colcon cannot be installed from the package index here: {pip.stderr.strip()[-300:]}")
    src = tmp_path / "ws" / "src" / "senfunet_ros"
    files = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True).stdout.split()
    for name in files:  # the tracked files only: no build products of the working copy
        if name.startswith(("bags/", "docs/", "test/")):
            continue
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / name, src / name)
    build = subprocess.run([sys.executable, "-c", "import sys; from colcon_core.command import main; sys.exit(main())",
                            "build", "--packages-select", "senfunet_ros"], cwd=tmp_path / "ws", capture_output=True,
                           text=True, timeout=600, env={**os.environ, "PYTHONPATH": str(colcon)})
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    install = tmp_path / "ws" / "install" / "senfunet_ros"
    for executable in ("fusion_node", "senfunet"):
        assert (install / "lib" / "senfunet_ros" / executable).is_file()  # where `ros2 run` looks
    share = install / "share" / "senfunet_ros"
    for name in ("package.xml", "config/default.yaml", "config/senfunet.rviz", "launch/senfunet.launch.py"):
        assert (share / name).is_file(), name
    assert (install / "share" / "ament_index" / "resource_index" / "packages" / "senfunet_ros").is_file()
    site = next((install / "lib").glob("python3*/site-packages"))
    assert list((site / "senfunet_core" / "weights").glob("*.pt"))
    assert (site / "senfunet_ros" / "fastdds_profile.xml").is_file()
    assert importlib.util.find_spec("senfunet_ros") is not None


def test_top_level_help_is_for_users():
    text = build_parser().format_help()
    assert "senfunet_ros.commands" not in text
    assert "mesh" in text and "senfunet demo" in text and "COMMAND --help" in text


def test_every_command_reports_its_errors_on_stderr(tmp_path: Path, ros_domain_id: int) -> None:
    """node, train and evaluate as replay and play do: the error on stderr, nothing on stdout, exit code
    2; the node's own refusal to start too (a parameter out of range, given after '--' or not)."""
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text("senfunet:\n  ros__parameters:\n    voxel_size: 0.02\n")
    cases = [
        (["node", "--params", str(tmp_path / "missing.yaml")], "senfunet node: parameter file"),
        (["node", "--params", str(unknown)], "senfunet node: "),
        (["node", "--", "--ros-args", "-p", "voxel_size_m:=-1.0"], "senfunet: cannot start: "),
        # as ros2 run takes them, without the '--' (argparse refused them: "unrecognized arguments")
        (["node", "--ros-args", "-p", "voxel_size_m:=-1.0"], "senfunet: cannot start: "),
        (["train", "--config", str(tmp_path / "missing.yaml")], "senfunet train: config"),
        (["evaluate", "--scenes", "999", "--out", str(tmp_path / "eval")], "senfunet evaluate: --scenes"),
        (["simulate", "--seed", "1"], "senfunet simulate: nothing to write"),
    ]
    # side by side: each spends most of its time importing
    procs = [subprocess.Popen([sys.executable, "-m", "senfunet_ros.cli", *args], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, cwd=tmp_path) for args, _ in cases]
    for proc, (args, expected) in zip(procs, cases):
        stdout, stderr = proc.communicate(timeout=300)
        assert proc.returncode == 2, (args, stdout, stderr)
        assert stdout == "", (args, stdout)
        assert expected in stderr and "Traceback" not in stderr, (args, stderr)
