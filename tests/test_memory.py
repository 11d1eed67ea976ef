"""drsplat.memory.small_page_zeros: a registration's large one-time arrays in ordinary pages (the
kernel's compaction for huge pages stalled every fresh array on a fragmented machine)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from drsplat.memory import SMALL_PAGES_FROM, small_page_full, small_page_zeros
from drsplat.registration.sums import Accumulator


def _thp_eligible(array: np.ndarray) -> bool | None:
    """THPeligible of the mapping holding `array` (/proc/self/smaps), None where unknown."""
    try:
        text = Path("/proc/self/smaps").read_text()
    except OSError:
        return None
    address = array.__array_interface__["data"][0] + array.nbytes // 2  # numpy advises the aligned middle of an array
    for block in re.split(r"\n(?=[0-9a-f]+-[0-9a-f]+ )", text):
        lo, hi = (int(x, 16) for x in block.split(" ", 1)[0].split("-"))
        if lo <= address < hi:
            match = re.search(r"THPeligible:\s+(\d)", block)
            return None if match is None else match.group(1) == "1"
    return None


@pytest.mark.parametrize("shape,dtype", [((1000, 512), np.float32), (3_000_000, np.float64), ((7, 3), np.int32), (0, np.float32)])
def test_small_page_zeros_is_a_writable_zero_array(shape, dtype):
    a = small_page_zeros(shape, dtype)
    assert a.shape == ((shape,) if np.isscalar(shape) else shape) and a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable
    assert not a.any()
    if a.size:
        a.flat[-1] = 3
        assert a.flat[-1] == 3 and a.sum() == 3


def test_large_arrays_are_not_advised_huge_pages():
    """Where numpy's own large array is eligible for transparent huge pages, ours is not (skipped
    where the kernel reports no THP eligibility, e.g. THP off)."""
    theirs = np.zeros(4 * SMALL_PAGES_FROM, np.uint8)
    if not _thp_eligible(theirs):
        pytest.skip("this kernel gives numpy's arrays no transparent huge pages")
    ours = small_page_zeros(4 * SMALL_PAGES_FROM, np.uint8)
    assert _thp_eligible(ours) is False
    assert _thp_eligible(Accumulator(10_000, 512).F) is False  # the sums, made once per registration


@pytest.mark.parametrize("value,dtype", [(-1, np.int32), (0, np.float64), (2.5, np.float32)])
def test_small_page_full_is_np_full(value, dtype):
    for shape in ((3_000_000,), (700, 16), (0, 4), 5):
        got = small_page_full(shape, value, dtype)
        want = np.full(shape, value, dtype)
        assert got.shape == want.shape and got.dtype == want.dtype and got.flags.writeable
        np.testing.assert_array_equal(got, want)


def test_the_per_gaussian_tables_of_a_registration_are_not_advised_huge_pages():
    """The check's and the vote's slots, the floater statistics' scratch and sums and the coalescer's
    scratch are made once per registration (or block) and touched a view's Gaussians at a time; in
    numpy's huge pages their first touches stalled on the kernel's compaction (flowers: the check's
    slots 465 ms in the first view, 3-5 ms after). Skipped where numpy's arrays get no THP."""
    from drsplat.registration.aggregate import StatsScratch, SurfaceSupport
    from drsplat.registration.check import fold_block_votes
    from drsplat.registration.coalesce import Coalescer
    from drsplat.registration.vote import VoteSink

    n = 2 * SMALL_PAGES_FROM // 8
    if not _thp_eligible(np.zeros(4 * SMALL_PAGES_FROM, np.uint8)):
        pytest.skip("this kernel gives numpy's arrays no transparent huge pages")
    slot_c, slot_v, slot_n = fold_block_votes(iter([]), [], 0, n)
    scratch = StatsScratch.new(n, 2, 40)
    support = SurfaceSupport.zeros(n)
    coalescer = Coalescer(n, parts=2)
    sink_state = VoteSink(n, 8)._empty(n)
    tables = [slot_c, slot_v, slot_n, scratch.sums, scratch.seen, support.total, support.views_seen, coalescer._seen, coalescer._acc, *sink_state[1:]]
    assert [_thp_eligible(t) for t in tables] == [False] * len(tables)


@pytest.mark.parametrize("shape,dtype", [((1000, 512), np.float32), ((7, 3), np.int32), (0, np.float64), ((5,), np.float64), ((2, 3, 4), np.uint8)])
def test_zeroing_in_parallel_equals_fill_in_place(shape, dtype):
    """The sums' first touch on numba's threads (`zero_in_parallel`) against its reference `fill(0)`:
    every element zero, in place (the same buffer), any shape; a non-contiguous array is refused."""
    from drsplat.registration.sums import zero_in_parallel

    a = (np.random.default_rng(1).random(shape) * 100 + 1).astype(dtype)
    want = a.copy()
    want.fill(0)
    before = a.__array_interface__["data"][0]
    assert zero_in_parallel(a) is a and a.__array_interface__["data"][0] == before
    np.testing.assert_array_equal(a, want)
    with pytest.raises(ValueError, match="C-contiguous"):
        zero_in_parallel(np.ones((4, 6))[:, ::2])


def test_the_smallest_budget_a_refusal_names_is_accepted():
    """A refused --memory-budget named a minimum that was itself refused (635 MB asked for, 620 MB
    working, 600 MB refused above the printed peak): the figure is now block_for's own threshold,
    rounded up, so typing it back registers in blocks."""
    from drsplat.errors import DrsplatError
    from drsplat.memory import format_size, parse_size
    from drsplat.registration.plan import BLOCK_ALIGN, MemoryPlan, choose_block

    plan = MemoryPlan(num_gaussians=8_289, dim=512, base=180_000_000, views=485_000_000, sum_bytes=2_600, write_bytes=3_000, pair_buffer=100_663_296)
    minimum = plan.minimum_budget()
    assert plan.block_for(minimum) >= BLOCK_ALIGN and plan.block_for(minimum - 1) == 0
    with pytest.raises(DrsplatError) as info:
        choose_block(plan, minimum - 1)
    named = str(info.value).split("give at least ")[1].split(" (")[0]
    assert choose_block(plan, parse_size(named.replace(" ", ""))) >= BLOCK_ALIGN
    assert format_size(1) == "1 byte" and format_size(512) == "512 bytes" and format_size(1_234_567, up=True) == "2 MB"


@pytest.mark.parametrize("text, words", [("0.5", "less than one byte"), ("1e400", "larger than any memory"), ("abc", "is not a size")])
def test_memory_budget_sizes_that_are_not_budgets(text, words):
    from drsplat.memory import parse_size

    with pytest.raises(ValueError, match=words):
        parse_size(text)
    assert parse_size("1E9") == parse_size("1e9") == 10**9


@pytest.fixture(scope="module")
def tiny_room(tmp_path_factory) -> Path:
    from drsplat.synthetic import write_dataset

    return write_dataset(tmp_path_factory.mktemp("tiny") / "data", "tiny", 0, show_progress=False)


@pytest.mark.parametrize("mode", ["paper", "fit-check-vote-reject"])
def test_the_budget_a_refusal_names_registers_in_a_new_process(tiny_room, tmp_path, mode):
    """Typed back into a new `drsplat register`, the minimum a refusal named was refused in turn: by a
    MB (the process's memory differs from run to run), or, in a fit mode, after the probe views
    (the probe's kernels and geometry were not in the figure named before it). A fit mode's
    refusal comes before its probe."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]

    def register(budget: str) -> subprocess.CompletedProcess:
        argv = ["register", str(tiny_room / "scene.ply"), "--source", str(tiny_room), "--features", str(tiny_room / "features"),
                "--out", str(tmp_path / "reg.ply"), "--no-progress", "--aggregate", mode, "--memory-budget", budget]
        return subprocess.run([sys.executable, "-m", "drsplat", *argv], capture_output=True, text=True, cwd=root, timeout=300)

    refused = register("1MB")
    assert refused.returncode == 1 and "fit:" not in refused.stderr, refused.stderr
    named = re.search(r"give at least ([0-9.]+ [kMG]B)", refused.stderr).group(1)
    accepted = register(named.replace(" ", ""))
    assert accepted.returncode == 0, accepted.stderr
    assert (tmp_path / "reg.ply").is_file()


def test_trim_heap_gives_freed_memory_back_so_the_plan_does_not_count_it():
    """Probe round 12: after a fit stage's probe views, 200 of the process's 539 MB were arrays it had
    freed and the allocator kept; the plan read them as memory in use and refused the budget its own
    refusal had just named. `_plan_block` trims the heap before it reads the process's memory. (In a
    fresh interpreter: in the test process, earlier tests' freed heap would take the allocations.)"""
    import platform
    import subprocess
    import sys

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("malloc_trim is glibc's; elsewhere trim_heap does nothing")
    script = (
        "from drsplat.memory import current_rss, trim_heap\n"
        "before = current_rss()\n"
        "chunks = [bytearray(b'\\1' * (64 << 10)) for _ in range(1600)]  # 100 MB of heap chunks, below mmap's threshold\n"
        "last = chunks[-1]  # held: the heap's top cannot shrink past it, so free() alone gives nothing back\n"
        "del chunks[:-1]\n"
        "held = current_rss()\n"
        "trim_heap()\n"
        "print(before, held, current_rss(), last[0])\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    before, held, trimmed, first = map(int, out.stdout.split())
    assert held - before > 80 << 20 and held - trimmed > 80 << 20 and first == 1, (before, held, trimmed)


def test_a_views_pairs_are_counted_at_most_every_gaussian_in_every_mask():
    """A 1920x1080 view at k = 40 has 83 M top-k slots, but 20,000 Gaussians in 102 masks give at most
    2 M distinct pairs: the plan counted a pair per slot and put a default registration that peaked
    at 1.2 GB at 8 GB, refusing it on a 4 GB machine (a probe on real photos, 2026-11-30)."""
    from drsplat.bench.register import blob_scene, orbit_cameras
    from drsplat.registration.plan import PAIR_BYTES, estimate_memory, view_pairs_bound

    assert view_pairs_bound(20_000, 1920 * 1080, 40, 102) == 20_000 * 102
    assert view_pairs_bound(20_000, 64 * 48, 40, 102) == 64 * 48 * 40  # few pixels: the slots bound it
    assert view_pairs_bound(20_000, 1920 * 1080, 40) == 1920 * 1080 * 40  # masks not known
    scene = blob_scene(20_000, seed=0)
    cams = orbit_cameras(scene.means, 1, 1920, 1080)
    known = estimate_memory(scene, cams, 512, 40, base=0, aggregate="paper", total_masks=102, max_masks=102)
    unknown = estimate_memory(scene, cams, 512, 40, base=0, aggregate="paper")
    assert unknown.views - known.views == 2 * PAIR_BYTES * (1920 * 1080 * 40 - 20_000 * 102)


@pytest.mark.parametrize("version", ["v2", "v1"])
def test_a_containers_memory_limit_bounds_the_memory_available(tmp_path, version):
    """Inside a container /proc/meminfo shows the host's memory: a plan made from it alone is killed
    at the container's limit (a probe, 2026-11-30). The memory cgroup's limit less what it uses (its
    inactive page cache not counted) bounds it; no limit ("max", or v1's huge number) leaves it."""
    from drsplat.memory import cgroup_room

    proc = tmp_path / "cgroup"
    if version == "v2":
        proc.write_text("0::/box\n")
        folder = tmp_path / "fs" / "box"
        names = ("memory.max", "memory.current", "inactive_file")
    else:
        proc.write_text("9:cpu:/\n4:memory:/box\n")
        folder = tmp_path / "fs" / "memory" / "box"
        names = ("memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file")
    folder.mkdir(parents=True)
    (folder / names[0]).write_text(f"{4 << 30}\n")
    (folder / names[1]).write_text(f"{3 << 30}\n")
    (folder / "memory.stat").write_text(f"anon 123\n{names[2]} {1 << 30}\n")
    assert cgroup_room(proc, tmp_path / "fs") == (4 << 30) - (2 << 30)
    (folder / names[0]).write_text("max\n" if version == "v2" else f"{(1 << 63) - 4096}\n")
    assert cgroup_room(proc, tmp_path / "fs") is None
    assert cgroup_room(tmp_path / "missing", tmp_path / "fs") is None
