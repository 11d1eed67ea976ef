"""Shared fixtures. Real fixtures live in ../shared/data; tests using them skip when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# ../shared/data beside the checkout (a symlink works), or wherever DRSPLAT_SHARED_DATA points
SHARED_DATA = Path(os.environ.get("DRSPLAT_SHARED_DATA") or Path(__file__).resolve().parents[1].parent / "shared" / "data")


def shared_path(*parts: str) -> Path:
    """Path inside ../shared/data, skipping the test with a reason when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real fixture {path} is absent (../shared/data is not beside the project)")
    return path


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
