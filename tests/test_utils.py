"""Shared helpers: atomic writes and the network probe that keeps offline errors instant."""

from __future__ import annotations

import errno
import os
import socket
from pathlib import Path

import numpy as np
import pytest

from drsplat.errors import OutputError
from drsplat.utils import (atomic_path, concat_ranges, file_stamp, describe_os_error, guard_outputs, host_reachable, replace_with_temp, save_npy_atomic,
                           temp_beside)


PROXY_VARIABLES = ("http_proxy", "https_proxy", "no_proxy", "all_proxy", "HTTP_PROXY", "HTTPS_PROXY", "NO_PROXY", "ALL_PROXY")


def test_a_host_served_by_a_proxy_is_left_to_the_download(monkeypatch):
    """Round 105a F6: behind an HTTPS proxy the direct probe failed, so weights the download (through the proxy) would
    fetch were "cannot be downloaded". A URL a proxy serves is not probed; no_proxy hosts and other schemes are."""
    import socket

    for name in PROXY_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("https_proxy", "http://proxy.invalid:3128")
    monkeypatch.setenv("no_proxy", "internal.invalid")
    probed = []
    monkeypatch.setattr(socket, "create_connection", lambda address, timeout=None: probed.append(address) or (_ for _ in ()).throw(OSError("no route")))
    assert host_reachable("https://dl.fbaipublicfiles.com/segment_anything/sam_vit_h_4b8939.pth") and not probed
    assert not host_reachable("https://internal.invalid/x") and probed == [("internal.invalid", 443)]
    assert not host_reachable("http://plain.invalid/x") and probed[-1] == ("plain.invalid", 80)  # no http_proxy
    monkeypatch.setenv("ALL_PROXY", "socks5://proxy.invalid:1080")  # round 106a F4: ALL_PROXY alone was probed past
    assert host_reachable("http://plain.invalid/x") and probed[-1] == ("plain.invalid", 80)


def test_host_reachable_on_loopback(monkeypatch):
    for name in PROXY_VARIABLES:  # a machine's proxy would take these URLs from the probe
        monkeypatch.delenv(name, raising=False)
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = server.getsockname()[1]
    try:
        assert host_reachable(f"http://127.0.0.1:{port}/weights.bin", timeout=2)
    finally:
        server.close()
    assert not host_reachable(f"http://127.0.0.1:{port}/weights.bin", timeout=2)
    assert not host_reachable("https://no-such-host.invalid/x", timeout=2)


def test_atomic_path_leaves_old_file_on_failure(tmp_path):
    target = tmp_path / "a.npy"
    save_npy_atomic(target, np.arange(3))
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("interrupted")
    np.testing.assert_array_equal(np.load(target), np.arange(3))
    assert [p.name for p in tmp_path.iterdir()] == ["a.npy"]


def test_an_output_under_a_file_is_refused_before_anything_runs(tmp_path):
    """--out a/b.ply where a is a file: one error naming the flag and the file in the way, from the
    output guard (before any work) and from the temp-file maker; nothing is created."""
    blocker = tmp_path / "scene.ply"
    blocker.write_bytes(b"ply")
    out = blocker / "sub" / "reg.ply"
    with pytest.raises(OutputError, match=r"--out lies under .*scene\.ply, which is a file, not a folder"):
        guard_outputs({"--scene": blocker}, {"--out": out})
    with pytest.raises(OutputError, match=r"scene\.ply is a file, not a folder"):
        temp_beside(out)
    with pytest.raises(OutputError, match="is a directory"):
        temp_beside(tmp_path)
    assert blocker.read_bytes() == b"ply" and sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply"]


def test_an_output_folder_that_is_created_is_said(tmp_path, caplog):
    """Round 41: `query --scores /nonexistent_dir/s.npy` made the folder without a word, so a mistyped folder went unseen."""
    import logging

    with caplog.at_level(logging.INFO, logger="drsplat"):
        save_npy_atomic(tmp_path / "made" / "deeper" / "s.npy", np.arange(3))
        save_npy_atomic(tmp_path / "made" / "deeper" / "t.npy", np.arange(3))
    said = [r.getMessage() for r in caplog.records if "created the folder" in r.getMessage()]
    assert said == [f"created the folder {tmp_path / 'made' / 'deeper'} for s.npy"]
    np.testing.assert_array_equal(np.load(tmp_path / "made" / "deeper" / "t.npy"), np.arange(3))


def test_a_temp_beside_an_output_is_committed_through_a_link(tmp_path):
    """temp_beside + replace_with_temp (what atomic_path does): the temp lies beside the link's
    target with normal permissions, and the link stays a link to the new bytes."""
    real = tmp_path / "real" / "out.bin"
    real.parent.mkdir()
    real.write_bytes(b"old")
    link = tmp_path / "link.bin"
    link.symlink_to(real)
    tmp = temp_beside(link)
    assert tmp.parent == real.parent and tmp.name.startswith(".out.bin.")
    with atomic_path(tmp_path / "probe") as probe:
        probe.write_bytes(b"x")
    assert (tmp.stat().st_mode & 0o777) == ((tmp_path / "probe").stat().st_mode & 0o777)
    tmp.write_bytes(b"new")
    replace_with_temp(tmp, link)
    assert link.is_symlink() and real.read_bytes() == b"new" and not tmp.exists()


def test_concat_ranges_lists_each_range_in_turn():
    rng = np.random.default_rng(0)
    for _ in range(50):
        sizes = rng.integers(0, 5, rng.integers(0, 8))
        starts = rng.integers(-20, 20, sizes.size)
        expected = [v for s, n in zip(starts, sizes) for v in range(s, s + n)]
        got = concat_ranges(starts, sizes)
        assert got.dtype == np.int64 and got.tolist() == expected


@pytest.mark.skipif(not Path("/proc/version").is_file(), reason="needs Linux's /proc")
def test_an_output_in_proc_names_its_file_system_not_a_missing_folder():
    """Was: `query --scores /proc/version` said "/proc/version: the parent directory does not exist"
    (/proc refuses new files with ENOENT). Now the cause is the file system (run as root), or
    permission (as another user); never a missing folder."""
    before = Path("/proc/version").read_bytes()
    with pytest.raises((OutputError, OSError)) as caught:
        save_npy_atomic(Path("/proc/version"), np.zeros(3, np.float32))
    message = str(caught.value) if isinstance(caught.value, OutputError) else describe_os_error(caught.value)
    assert "/proc" in message and "does not exist" not in message, message
    if isinstance(caught.value, OutputError):
        assert "the folder /proc does not accept new files: its file system creates none on request" in message
    assert Path("/proc/version").read_bytes() == before


def test_a_missing_file_says_its_folder_is_missing_only_when_it_is(tmp_path):
    """describe_os_error on ENOENT (what the CLI prints for an OSError): "the parent directory does
    not exist" only when it does not."""
    inside = OSError(errno.ENOENT, "No such file or directory", str(tmp_path / "gone.npy"))
    assert describe_os_error(inside) == f"{tmp_path / 'gone.npy'}: no such file or directory, though its folder {tmp_path} exists"
    deeper = OSError(errno.ENOENT, "No such file or directory", str(tmp_path / "no" / "gone.npy"))
    assert describe_os_error(deeper).endswith(": the parent directory does not exist")


def test_clipped_quotes_a_long_value_by_its_start_and_length():
    from drsplat.utils import clipped

    assert clipped("abc", 3) == "abc"
    assert clipped("9" * 5000, 4) == "9999... (5,000 characters)"


def test_log_lines_show_hidden_characters_escaped(capsys):
    """Was (a probe, 2026-12-01): an image named `evil<U+202E>gnp.exe.png` was accepted (a file may
    be named so) and every warning that named it printed the override raw, so a terminal showed the
    rest of the line reversed; U+2028 split lines in log viewers. The CLI's log handler escapes
    them now (ESC too), keeping newlines and tabs, and plain text unchanged."""
    import logging

    from drsplat.cli import _StderrHandler
    from drsplat.errors import escape_hidden

    assert escape_hidden("view_001: 3 masks\n\tok") == "view_001: 3 masks\n\tok"
    assert escape_hidden("evil\u202egnp.exe \x1b[2J \u2028x") == "evil\\u202egnp.exe \\u001b[2J \\u2028x"
    logger = logging.getLogger("drsplat.test_escape")
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
    logger.addHandler(handler)
    try:
        logger.warning("%s: one flat colour", "evil\u202egnp.exe")
    finally:
        logger.removeHandler(handler)
    err = capsys.readouterr().err
    assert err == "WARNING: evil\\u202egnp.exe: one flat colour\n", err


def test_a_replaced_output_keeps_the_permissions_of_the_file_it_replaces(tmp_path):
    """Was (a probe, 2026-12-01): `register --out out.ply` over a file made private with chmod 600
    wrote a new one readable by all (0644). An output now keeps the mode of the file it replaces;
    a new one gets 0666 less the umask."""
    import stat

    from drsplat.utils import _current_umask

    private = tmp_path / "out.ply"
    private.write_bytes(b"old")
    private.chmod(0o600)
    with atomic_path(private) as tmp:
        tmp.write_bytes(b"new")
    assert private.read_bytes() == b"new" and stat.S_IMODE(private.stat().st_mode) == 0o600
    fresh = tmp_path / "fresh.ply"
    with atomic_path(fresh) as tmp:
        tmp.write_bytes(b"new")
    assert stat.S_IMODE(fresh.stat().st_mode) == 0o666 & ~_current_umask()


def test_an_in_place_stamp_sees_a_rewrite_that_restores_size_and_mtime(tmp_path):
    """`cp -p` puts the size and modification time back; the plain stamp (what `features` keeps
    across copies of a dataset) then matches, the in-place one (a registration's checkpoint) does not."""
    import os
    import time

    f = tmp_path / "x.npy"
    f.write_bytes(b"abcd")
    before, before_in_place, st = file_stamp(f), file_stamp(f, in_place=True), f.stat()
    time.sleep(0.05)  # past a coarse clock's tick (kernels before 6.13 stamp ctime per jiffy)
    f.write_bytes(b"dcba")
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert file_stamp(f) == before
    assert file_stamp(f, in_place=True) != before_in_place
    assert file_stamp(tmp_path / "missing", in_place=True) is None


def test_an_input_link_loop_or_dangling_link_says_so(tmp_path):
    """A loop of links and a link to a missing file were both "file not found" (round 29a), though
    `ls` lists them: the error now says which."""
    from drsplat.errors import InputError
    from drsplat.utils import load_npy

    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    (tmp_path / "d").symlink_to(tmp_path / "gone.npy")
    with pytest.raises(InputError, match="a: is a loop of symbolic links"):
        load_npy(tmp_path / "a")
    with pytest.raises(InputError, match=r"d: is a symbolic link to .*gone\.npy, which does not exist"):
        load_npy(tmp_path / "d")
    with pytest.raises(InputError, match="x.npy: file not found"):
        load_npy(tmp_path / "x.npy")


def test_label_names_that_differ_only_in_how_accents_are_encoded_are_one_name(tmp_path):
    """"café" composed (U+00E9) and as "cafe" + U+0301 print alike: the segment table showed two
    identical rows (round 29a). They are the same name, refused as a repeat."""
    from drsplat.errors import InputError
    from drsplat.utils import checked_names

    with pytest.raises(InputError, match=r"entry 2 of 2 repeats the name .* of entry 1 \(apart from spaces around it or how its accents"):
        checked_names(tmp_path / "names.json", ["caf\u00e9", "cafe\u0301"])
    # round 100b F5: counted from 0 here and from 1 in --labels, "entry 1" was the second name and the first label
    with pytest.raises(InputError, match=r"entry 1 of 3 is an empty name"):
        checked_names(tmp_path / "names.json", ["", "b", "c"])
    assert checked_names(tmp_path / "names.json", ["caf\u00e9", "cafe"]) == ["caf\u00e9", "cafe"]


def test_an_output_under_a_link_to_nothing_is_refused_naming_the_link_not_said_created(tmp_path, caplog):
    """Review of round 41: `query --scores dang/s.npy`, dang a symbolic link to a folder that does not exist, logged
    "created the folder .../dang for s.npy" and then failed with the OS's "File exists"."""
    import logging
    import os

    os.symlink(tmp_path / "gone", tmp_path / "dang")
    with caplog.at_level(logging.INFO, logger="drsplat"), pytest.raises(OutputError, match=f"{tmp_path / 'dang'} is a link to {tmp_path / 'gone'}, which does not exist"):
        save_npy_atomic(tmp_path / "dang" / "s.npy", np.arange(3))
    assert "created the folder" not in caplog.text and not (tmp_path / "gone").exists()
    with pytest.raises(OutputError, match="--scores lies under .*dang, a link to .*gone, which does not exist"):
        guard_outputs({}, {"--scores": tmp_path / "dang" / "s.npy"})


def test_a_folder_output_given_as_a_link_is_replaced_behind_the_link(tmp_path):
    """Round 44: `synth` into a link to a folder renamed the new folder over the link (the link became
    a folder, the target kept the old output) and left a `.<name>.dslink...partial` temp link. Now the
    target folder gets the new output and the link stays; a link to nothing gets its target made."""
    from drsplat.utils import atomic_folder

    real = tmp_path / "real"
    real.mkdir()
    (real / "old.txt").write_text("old")
    link = tmp_path / "out"
    link.symlink_to(real)
    with atomic_folder(link, replaceable=lambda p: (p / "old.txt").is_file()) as tmp:
        (tmp / "new.txt").write_text("new")
    assert link.is_symlink() and os.readlink(link) == str(real)
    assert [p.name for p in real.iterdir()] == ["new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "real"]
    dangling = tmp_path / "later"
    dangling.symlink_to(tmp_path / "made")
    with atomic_folder(dangling, replaceable=lambda p: False) as tmp:
        (tmp / "x.txt").write_text("x")
    assert dangling.is_symlink() and (tmp_path / "made" / "x.txt").read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["later", "made", "out", "real"]


def test_spread_rows_takes_at_most_count_rows_spread_over_all_of_them():
    """The sample the scene-wide estimates take (the near plane's shares, the frame decision):
    every ⌈N / count⌉-th row, so never more than `count`, from the first row to near the last."""
    from drsplat.utils import spread_rows

    rows = np.arange(30).reshape(10, 3)
    assert spread_rows(rows, 3)[:, 0].tolist() == [0, 12, 24]  # every 4th of 10
    assert spread_rows(rows, 10).shape == (10, 3) and spread_rows(rows, 100).shape == (10, 3)
    assert spread_rows(rows, 1)[:, 0].tolist() == [0]
    assert spread_rows(np.zeros((0, 3)), 5).shape == (0, 3)
    for n, count in ((100_001, 100_000), (7, 2), (1_000, 999)):
        assert 1 <= len(spread_rows(np.zeros(n), count)) <= count


def test_a_folder_output_where_no_folder_can_be_made_names_the_output():
    """Round 57c: `drsplat synth RO/syn` on a read-only folder named its temp folder (.syn.<pid>@...partial), which
    the user never gave; the output and the folder that refuses are named now."""
    from drsplat.errors import OutputError
    from drsplat.utils import atomic_folder

    with pytest.raises(OutputError, match=r"cannot write /proc/drsplat_probe: the folder /proc does not accept new files") as err:
        with atomic_folder("/proc/drsplat_probe", lambda p: False):
            pass
    assert "partial" not in str(err.value)


def test_a_write_protected_output_is_never_replaced_even_by_root(tmp_path, capsys):
    """Round 59a: `pq train --out` replaced a 0444 file in a 0555 folder (the shared official codebook), since root may
    rename over anything. A file without any write bit is kept, with one error, by the up-front check and by every
    atomic write; a writable one is replaced as before."""
    from drsplat.cli import main
    from drsplat.utils import check_output_writable, write_bytes_atomic

    kept = tmp_path / "codebook.faiss"
    kept.write_bytes(b"official")
    kept.chmod(0o444)
    try:
        for attempt in (lambda: check_output_writable(kept), lambda: write_bytes_atomic(kept, b"new")):
            with pytest.raises(OutputError, match=r"codebook.faiss: exists and is write-protected \(mode 0444\); make it writable"):
                attempt()
        np.save(tmp_path / "e.npy", np.random.default_rng(0).standard_normal((300, 16)).astype(np.float32))
        assert main(["pq", "train", "--embeddings", str(tmp_path / "e.npy"), "--out", str(kept), "--m", "4"]) == 1
        assert "exists and is write-protected" in capsys.readouterr().err
        assert kept.read_bytes() == b"official" and not list(tmp_path.glob("*.tmp*"))
    finally:
        kept.chmod(0o644)
    write_bytes_atomic(kept, b"new")
    assert kept.read_bytes() == b"new"


def test_an_input_named_by_a_phrase_reads_as_a_sentence_in_the_refusal(tmp_path):
    """Round 59a: "--scores is the same file as the input the registered PLY's codebook"; an input named by a phrase now
    reads "... as the registered PLY's codebook (an input)", one named by a flag as before."""
    book = tmp_path / "r.codebook.faiss"
    book.write_bytes(b"x")
    with pytest.raises(OutputError, match=r"--scores is the same file as the registered PLY's codebook \(an input\); writing it"):
        guard_outputs({"--embedding": tmp_path / "q.npy", "the registered PLY's codebook": book}, {"--scores": book})
    with pytest.raises(OutputError, match=r"--scores is the same file as the input --embedding; writing it"):
        guard_outputs({"--embedding": book}, {"--scores": book})
    assert book.read_bytes() == b"x"


def test_a_folder_output_holding_a_write_protected_file_is_never_replaced(tmp_path):
    """Round 60a: `synth` over an earlier dataset (a folder output, replaced whole) deleted a 0444 scene.ply in it, and
    replaced a 0555 folder, as root, without a word. Either is refused before anything is built; a link in the folder
    to a protected file elsewhere is not in the way (only the link is deleted)."""
    from drsplat.utils import atomic_folder

    out = tmp_path / "syn"
    out.mkdir()
    (out / "scene.ply").write_bytes(b"kept")
    (out / "scene.ply").chmod(0o444)
    try:
        with pytest.raises(OutputError, match=r"syn/scene.ply: exists and is write-protected \(mode 0444\)"):
            with atomic_folder(out, lambda p: True) as tmp:
                (tmp / "new").write_bytes(b"x")
        assert (out / "scene.ply").read_bytes() == b"kept"
    finally:
        (out / "scene.ply").chmod(0o644)
    out.chmod(0o555)
    try:
        with pytest.raises(OutputError, match=r"syn: is a write-protected folder \(mode 0555\)"):
            with atomic_folder(out, lambda p: True):
                pass
    finally:
        out.chmod(0o755)
    (out / "gt").mkdir()  # round 60c: a write-protected folder inside was replaced
    (out / "gt").chmod(0o555)
    try:
        with pytest.raises(OutputError, match=r"syn/gt: is a write-protected folder \(mode 0555\)"):
            with atomic_folder(out, lambda p: True):
                pass
    finally:
        (out / "gt").chmod(0o755)
    (out / "gt").rmdir()
    protected = tmp_path / "elsewhere.ply"
    protected.write_bytes(b"not ours")
    protected.chmod(0o444)
    (out / "scene.ply").unlink()
    (out / "link.ply").symlink_to(protected)
    with atomic_folder(out, lambda p: True) as tmp:
        (tmp / "new").write_bytes(b"x")
    assert sorted(p.name for p in out.iterdir()) == ["new"] and protected.read_bytes() == b"not ours"


def test_an_atomic_write_syncs_its_data_before_the_rename_and_the_folder_after(tmp_path, monkeypatch):
    """Round 72b F3: the registered PLY was renamed into place without an fsync, and the checkpoint deleted right after:
    a power loss then could keep the new name over lost data, with nothing left to resume. The temp file is synced before
    the rename, the folder after it."""
    import os

    from drsplat import utils

    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: events.append(("fsync", os.path.realpath(f"/proc/self/fd/{fd}"))) or real_fsync(fd))
    monkeypatch.setattr(os, "replace", lambda a, b: events.append(("replace", str(b))) or real_replace(a, b))
    out = tmp_path / "out.bin"
    utils.write_bytes_atomic(out, b"abc")
    assert out.read_bytes() == b"abc"
    kinds = [kind for kind, _ in events]
    assert kinds == ["fsync", "replace", "fsync"], events
    assert events[0][1].startswith(str(tmp_path / ".out.bin")) and events[2][1] == str(tmp_path), events


def test_an_output_only_writable_is_still_replaced(tmp_path):
    """Round 73a F1 (a regression of the fsync above): the temp file takes the mode of the output it replaces, and an
    output of mode 0200 (write-only) made the fsync's read-only open fail with EACCES after the whole registration. The
    fsync opens for writing; run without the capabilities that let root read any file."""
    import shutil
    import subprocess
    import sys

    if shutil.which("setpriv") is None and os.geteuid() == 0:
        pytest.skip("root reads any file, and setpriv (util-linux) is not there to drop that")
    out = tmp_path / "out.txt"
    out.write_text("old\n")
    out.chmod(0o200)
    code = f"from drsplat.utils import write_bytes_atomic; write_bytes_atomic({str(out)!r}, b'new')"
    prefix = ["setpriv", "--bounding-set=-dac_override,-dac_read_search"] if os.geteuid() == 0 else []
    proc = subprocess.run([*prefix, sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 0, proc.stderr
    out.chmod(0o600)
    assert out.read_bytes() == b"new" and sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]
