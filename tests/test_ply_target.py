"""The registered PLY writer (drsplat.registration.output.PlyTarget): the body written once behind a
reserved header gives the bytes of the header + body copy, whatever the hint, and the output is
replaced atomically (no temp file left, normal permissions, a symlink kept)."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from drsplat.registration.output import PlyTarget
from drsplat.registration.sink import Block
from drsplat.registration.sums import normalize_rows
from drsplat.scene import GaussianScene, load_ply

DIM = 8


def _scene(n: int, rng) -> GaussianScene:
    return GaussianScene(means=rng.normal(size=(n, 3)).astype(np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                         log_scales=np.full((n, 3), -3, np.float32), opacity_logits=np.zeros(n, np.float32),
                         sh=np.zeros((n, 1, 3), np.float32))


def _write(scene: GaussianScene, out, blocks, rows_hint) -> int:
    target = PlyTarget(scene, out, "oracle")
    target.open("none", rows_hint=rows_hint)
    for block in blocks:
        target.add(Block(block.lo, block.hi, block.F.copy(), block.W.copy()), block.W > 0)
    return target.close()


def _blocks(n: int, kept: int, rng, block: int = 500) -> list[Block]:
    W = np.zeros(n, np.float32)
    W[rng.choice(n, kept, replace=False)] = rng.uniform(0.1, 1, kept)
    F = rng.normal(size=(n, DIM)).astype(np.float32) * W[:, None]
    normalize_rows(F, W)
    return [Block(lo, min(n, lo + block), F[lo : lo + block], W[lo : lo + block]) for lo in range(0, n, block)]


@pytest.mark.parametrize("kept, hint", [(1500, 1500), (1500, 1999), (1500, 900), (1500, 20_000), (40, 40), (1, 1)])
def test_the_body_written_in_place_gives_the_copied_bytes(tmp_path, monkeypatch, kept, hint):
    """Hints with the final count's digits write in place (no copy: copyfileobj is made to fail);
    other digits and short files (widened metadata) fall back to the copy; the bytes are the same."""
    rng = np.random.default_rng(kept)
    n = 2000
    scene, blocks = _scene(n, rng), _blocks(n, kept, rng)
    want = tmp_path / "copied.ply"
    assert _write(scene, want, blocks, None) == kept
    in_place = len(str(hint)) == len(str(kept)) and kept >= 500  # a short file's metadata is widened by a rewrite
    if in_place:
        monkeypatch.setattr(shutil, "copyfileobj", lambda *a, **k: pytest.fail("the body was copied"))
    out = tmp_path / "sub" / "reg.ply"
    assert _write(scene, out, blocks, hint) == kept
    assert out.read_bytes() == want.read_bytes()
    assert load_ply(out).num_gaussians == kept
    assert sorted(p.name for p in out.parent.iterdir()) == ["reg.ply"]  # no temp file left
    assert (out.stat().st_mode & 0o777) == (want.stat().st_mode & 0o777)


def test_a_symlinked_output_stays_a_link_and_an_old_file_is_replaced(tmp_path):
    rng = np.random.default_rng(3)
    scene, blocks = _scene(1000, rng), _blocks(1000, 700, rng)
    real = tmp_path / "real.ply"
    real.write_bytes(b"old")
    link = tmp_path / "link.ply"
    link.symlink_to(real)
    assert _write(scene, link, blocks, 700) == 700
    assert link.is_symlink() and os.path.realpath(link) == str(real)
    assert load_ply(real).num_gaussians == 700
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.ply", "real.ply"]


def test_an_aborted_write_leaves_nothing_and_keeps_the_old_file(tmp_path):
    rng = np.random.default_rng(4)
    scene, blocks = _scene(1000, rng), _blocks(1000, 600, rng)
    out = tmp_path / "reg.ply"
    out.write_bytes(b"old")
    target = PlyTarget(scene, out, "oracle")
    target.open("none", rows_hint=600)
    target.add(blocks[0], blocks[0].W > 0)
    target.abort()
    assert out.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["reg.ply"]
