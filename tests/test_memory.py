"""drsplat.memory.small_pages: numpy's huge-page advice off while the CLI, the viewer and the Ray
workers run (the kernel's compaction stalls every fresh array on a fragmented machine), numpy's own
setting put back after, and a user's NUMPY_MADVISE_HUGEPAGE obeyed."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from drsplat import cli
from drsplat.cluster import _runtime_env
from drsplat.memory import HUGEPAGE_ENV, small_pages

get_advice = getattr(getattr(np, "_core", None) or np.core, "multiarray")._get_madvise_hugepage


@pytest.fixture
def no_user_choice(monkeypatch):
    monkeypatch.delenv(HUGEPAGE_ENV, raising=False)


def test_small_pages_turns_the_advice_off_and_puts_it_back(no_user_choice):
    before = get_advice()
    with small_pages():
        assert get_advice() is False
    assert get_advice() == before
    with pytest.raises(ValueError), small_pages():
        raise ValueError("a failing command")
    assert get_advice() == before


def test_a_users_numpy_switch_decides(monkeypatch):
    monkeypatch.setenv(HUGEPAGE_ENV, "1")
    before = get_advice()
    with small_pages():
        assert get_advice() == before
    assert _runtime_env(None)["env_vars"][HUGEPAGE_ENV] == "1"


def test_the_cli_and_the_ray_workers_run_with_small_pages(no_user_choice, monkeypatch):
    seen = []
    parser = argparse.ArgumentParser()
    parser.set_defaults(func=lambda args: seen.append(get_advice()), verbose=0, quiet=False)
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    before = get_advice()
    assert cli.main([]) == 0
    assert seen == [False] and get_advice() == before
    assert _runtime_env(None)["env_vars"][HUGEPAGE_ENV] == "0"
    assert _runtime_env("10.255.255.1:6379")["env_vars"][HUGEPAGE_ENV] == "0"  # another host: the package shipped, the same choice
