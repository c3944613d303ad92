"""`colcon build` installs the layout that `ros2 run sma_stage <executable>` relies on."""

import configparser
import importlib.util
import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "sma_stage"
ENTRY_POINTS = {
    "stage_node": "sma_stage.nodes.stage_node:main",
    "compensator_node": "sma_stage.nodes.compensator_node:main",
    "identification_node": "sma_stage.nodes.identification_node:main",
    "stage_and_compensator": "sma_stage.nodes.stage_and_compensator:main",
    "gpi_tool": "sma_stage.cli:main",
}
BUILD_LEFTOVERS = ("build", "install", "log", f"{PACKAGE}.egg-info")


def _leftovers_in_repo() -> set[str]:
    return {name for name in BUILD_LEFTOVERS if (REPO / name).exists()}


def _where_python_imports_package(cwd: Path) -> str:
    """Where a fresh interpreter outside the repository finds the package (editable install or PYTHONPATH)."""
    python_path = os.environ.get("PYTHONPATH", "")
    absolute = os.pathsep.join(str(Path(entry).resolve()) for entry in python_path.split(os.pathsep) if entry)
    code = f"import importlib.util; spec = importlib.util.find_spec({PACKAGE!r}); print(spec and spec.origin)"
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=cwd,
        env={**os.environ, "PYTHONPATH": absolute},
    ).stdout.strip()


@pytest.fixture(scope="module")
def colcon_install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Build the package with colcon into a temporary workspace; return its install prefix."""
    if importlib.util.find_spec("colcon_core") is None:
        pytest.skip("colcon is not installed in this Python environment (./run.sh test installs it)")
    work = tmp_path_factory.mktemp("colcon")
    leftovers_before = _leftovers_in_repo()
    import_origin_before = _where_python_imports_package(work)
    env = {**os.environ, "COLCON_HOME": str(work / "colcon_home")}
    command = [
        sys.executable, "-m", "colcon", "--log-base", str(work / "log"),
        "build", "--base-paths", str(REPO), "--packages-select", PACKAGE,
        "--build-base", str(work / "build"), "--install-base", str(work / "install"),
    ]
    result = subprocess.run(command, cwd=work, env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, f"colcon build failed:\n{result.stdout}\n{result.stderr}"
    assert _leftovers_in_repo() == leftovers_before, "colcon build left files in the repository"
    assert _where_python_imports_package(work) == import_origin_before, "colcon build moved the package"
    return work / "install" / PACKAGE


def test_ament_index_marker_is_installed(colcon_install: Path) -> None:
    assert (colcon_install / "share/ament_index/resource_index/packages" / PACKAGE).is_file()


def test_package_xml_is_installed(colcon_install: Path) -> None:
    installed = colcon_install / "share" / PACKAGE / "package.xml"
    assert installed.read_bytes() == (REPO / "package.xml").read_bytes()


@pytest.mark.parametrize("executable", sorted(ENTRY_POINTS))
def test_entry_point_is_an_executable_under_lib(colcon_install: Path, executable: str) -> None:
    script = colcon_install / "lib" / PACKAGE / executable
    assert script.is_file()
    assert os.access(script, os.X_OK)
    assert f"'console_scripts', '{executable}'" in script.read_text()


def test_installed_entry_points_name_their_modules(colcon_install: Path) -> None:
    (metadata,) = colcon_install.glob(f"lib/python*/site-packages/{PACKAGE}-*.egg-info")
    parser = configparser.ConfigParser()
    parser.read(metadata / "entry_points.txt")
    assert dict(parser["console_scripts"]) == ENTRY_POINTS


def test_config_files_are_installed(colcon_install: Path) -> None:
    sources = sorted(path.name for path in (REPO / "config").iterdir() if path.is_file())
    installed = sorted(path.name for path in (colcon_install / "share" / PACKAGE / "config").iterdir())
    assert installed == sources and "foxglove_layout.json" in installed and "plotjuggler_layout.xml" in installed


def test_versions_agree(colcon_install: Path) -> None:
    manifest_version = ET.parse(REPO / "package.xml").getroot().findtext("version")
    init_text = (REPO / PACKAGE / "__init__.py").read_text()
    module_version = re.search(r'__version__\s*=\s*"([^"]+)"', init_text).group(1)
    (metadata,) = colcon_install.glob(f"lib/python*/site-packages/{PACKAGE}-*.egg-info")
    setup_version = metadata.name.split("-")[1]
    assert manifest_version == module_version == setup_version


def test_installed_gpi_tool_runs(colcon_install: Path) -> None:
    if not (REPO / PACKAGE / "cli.py").exists():
        pytest.skip("sma_stage/cli.py is not written yet")
    site_packages = next(colcon_install.glob("lib/python*/site-packages"))
    env = {**os.environ, "PYTHONPATH": str(site_packages)}
    result = subprocess.run(
        [str(colcon_install / "lib" / PACKAGE / "gpi_tool"), "--help"],
        capture_output=True, text=True, env=env, cwd="/", timeout=60,
    )
    assert result.returncode == 0, result.stderr
    assert "usage" in result.stdout.lower()


def test_an_installed_package_finds_its_installed_config(colcon_install: Path) -> None:
    from sma_stage.nodes.launch import find_config_dir

    launchers = list(colcon_install.glob("lib/python*/site-packages/sma_stage/nodes/launch.py"))
    assert len(launchers) == 1, launchers
    assert find_config_dir(launchers[0]) == colcon_install / "share" / PACKAGE / "config"


LAUNCH_ARGUMENTS = {
    "stage.launch.py": ["namespace", "backend", "hardware_file", "params_file", "use_sim_time", "time_scale",
                        "lockstep", "record_bag", "bag_storage"],
    "stages.launch.py": ["count", "params_file", "use_sim_time", "time_scale"],
}


def launch_arguments(path: Path) -> dict[str, tuple[str, str]]:
    """The ARGUMENTS literal of a launch file (name -> (default, description)), read without importing it:
    `launch` is not installed here (it is checked with the real `ros2 launch` outside the project)."""
    import ast

    tree = ast.parse(path.read_text(), str(path))
    (assignment,) = [node for node in tree.body if isinstance(node, ast.Assign)
                     and [getattr(target, "id", None) for target in node.targets] == ["ARGUMENTS"]]
    return ast.literal_eval(assignment.value)


def test_launch_files_are_installed_and_declare_the_documented_arguments(colcon_install: Path) -> None:
    installed = colcon_install / "share" / PACKAGE / "launch"
    assert sorted(path.name for path in installed.glob("*.launch.py")) == sorted(LAUNCH_ARGUMENTS)
    readme = (REPO / "README.md").read_text()
    for name, arguments in LAUNCH_ARGUMENTS.items():
        assert (installed / name).read_bytes() == (REPO / "launch" / name).read_bytes()
        declared = launch_arguments(installed / name)
        assert list(declared) == arguments, name
        assert all(isinstance(default, str) and description for default, description in declared.values())
        assert all(f"{argument}:=" in readme for argument in arguments), f"README documents {name}'s arguments"


def test_compiled_kernels_are_cached_in_the_user_cache_not_the_install_tree(tmp_path: Path) -> None:
    """A copy of the package used from another folder (as an install tree is) compiles its kernels into
    $XDG_CACHE_HOME/sma_stage/numba and writes nothing beside its modules (an /opt/ros install is read-only)."""
    import shutil

    tree = tmp_path / "site"
    shutil.copytree(REPO / PACKAGE, tree / PACKAGE, ignore=shutil.ignore_patterns("__pycache__"))
    cache = tmp_path / "cache"
    env = {key: value for key, value in os.environ.items() if key != "NUMBA_CACHE_DIR"}
    env.update(PYTHONPATH=str(tree), XDG_CACHE_HOME=str(cache), PYTHONDONTWRITEBYTECODE="1")
    code = ("import numpy as np; from sma_stage.model import GPIParameters, forward; "
            "p = GPIParameters(5e-4, 0.6, 0.1, 0.0, 5e-4, 0.6, -0.2, 5e-5, 5e-5, 0.2, 5e3); "
            "print(forward(np.linspace(-5, 5, 50), p, 10)[-1])")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tmp_path,
                          timeout=180)
    assert done.returncode == 0, done.stderr
    assert list((cache / "sma_stage" / "numba").rglob("*.nbi")), "kernels cached in the user cache"
    assert not [path for path in tree.rglob("*") if path.suffix in (".nbi", ".nbc")], "nothing in the tree"
