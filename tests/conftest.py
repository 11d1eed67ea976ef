"""Shared fixtures. Real fixtures live in ../shared/data; tests using them skip when it is absent."""

from __future__ import annotations

import importlib
import os
import shutil
from pathlib import Path

import pytest

from tests.process_state import ProcessState, root_logger_kept

if os.environ.get("PYTEST_XDIST_WORKER"):
    # Two test processes (and their Ray nodes) share the cores: an OpenMP thread that spins while it
    # waits takes them from the other process (numba's small parallel regions ran up to 7x slower).
    # Set before numba or torch loads the OpenMP runtime, which reads it once.
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")

# ../shared/data beside the checkout (a symlink works), or wherever DRSPLAT_SHARED_DATA points
SHARED_DATA = Path(os.environ.get("DRSPLAT_SHARED_DATA") or Path(__file__).resolve().parents[1].parent / "shared" / "data")


def shared_path(*parts: str) -> Path:
    """Path inside ../shared/data, skipping the test with a reason when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real fixture {path} is absent (../shared/data is not beside the project)")
    return path


def tiny_registered(root: Path, seed: int) -> tuple[Path, Path]:
    """(dataset folder, registered PLY) of the `tiny` synthetic preset under `root`, registered
    with the CLI's defaults: the viewer tests' scene."""
    from drsplat.cameras import load_cameras
    from drsplat.registration import register
    from drsplat.scene import load_ply
    from drsplat.synthetic import write_dataset

    dataset = write_dataset(root / "tiny", "tiny", seed=seed, show_progress=False)
    out = root / "reg" / "registered.ply"
    out.parent.mkdir(parents=True, exist_ok=True)
    register(load_ply(dataset / "scene.ply"), load_cameras(dataset, require_images=False), dataset / "features", out, show_progress=False)
    return dataset, out


def splat_transform_command() -> list[str]:
    """PlayCanvas splat-transform (npm), a peer for scene files: $SPLAT_TRANSFORM (a path to its bin),
    or on PATH; the test is skipped with a reason when neither is there."""
    explicit = os.environ.get("SPLAT_TRANSFORM")
    if explicit and Path(explicit).is_file():
        return [explicit]
    found = shutil.which("splat-transform")
    if found is None:
        pytest.skip("splat-transform is not installed (npm install @playcanvas/splat-transform; set SPLAT_TRANSFORM to its bin)")
    return [found]


def import_needing_system_library(module: str, apt_package: str):
    """`module`, imported; when it is installed but cannot load (a system library it links
    against is missing), the test is skipped with the package that provides the library."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name != module:
            pytest.skip(f"{module} failed to import ({exc}); on Debian/Ubuntu: apt install {apt_package}")
        pytest.skip(f"{module} is not installed (pip install {module})")
    except (ImportError, OSError) as exc:  # e.g. "libusb-1.0.so.0: cannot open shared object file"
        pytest.skip(f"{module} failed to import ({exc}); on Debian/Ubuntu: apt install {apt_package}")


@pytest.fixture
def shared_data() -> Path:
    return shared_path()


@pytest.fixture
def one_torch_thread():
    """Small tensors on a shared 2-core machine: torch's thread pool only adds waiting."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# The test files that start a Ray cluster on this machine. Under pytest-xdist (the README's `-n 2
# --dist loadfile`) they run on one worker, one after another: a second cluster started while the first
# runs is one that `ray.init()` without an address could join (it finds the newest on the machine).
RAY_CLUSTER_FILES = frozenset({"test_distributed.py", "test_features.py", "test_ray_cluster_faults.py", "test_ray_node_loss.py", "test_reduce.py"})


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log):
    """`--dist loadfile` with RAY_CLUSTER_FILES as one unit of work; other modes are xdist's own."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class RayFilesTogether(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = super()._split_scope(nodeid)
            return "the Ray cluster files" if Path(path).name in RAY_CLUSTER_FILES else path

    return RayFilesTogether(config, log)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--reverse-files", action="store_true", help="run the test files in reverse order (each file's tests keep their order): finds tests that depend on what an earlier file left behind")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--reverse-files"):
        items[:] = reversed_by_file(items)


def reversed_by_file(items: list[pytest.Item]) -> list[pytest.Item]:
    """The items with their files in reverse order; within a file the order is unchanged."""
    by_file: dict[Path, list[pytest.Item]] = {}
    for item in items:
        by_file.setdefault(item.path, []).append(item)
    return [item for path in reversed(by_file) for item in by_file[path]]


@pytest.fixture(autouse=True, scope="module")
def module_leaves_the_process_as_it_found_it():
    """Module fixtures (a Ray cluster, a window) included: checked after the module's teardown."""
    yield from _unchanged_process("this module's tests or fixtures")


@pytest.fixture(autouse=True)
def test_leaves_the_process_as_it_found_it():
    yield from _unchanged_process("this test")


def _unchanged_process(what: str):
    before = ProcessState.capture()
    with root_logger_kept():
        yield
    changed = before.changes(ProcessState.capture())
    if changed:
        pytest.fail(f"{what} changed process-wide state that later tests see (restore it): " + "; ".join(changed), pytrace=False)
