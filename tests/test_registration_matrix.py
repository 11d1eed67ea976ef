"""Every engine x memory plan x aggregation mode, in this process: the same registered file, or a refusal up front.

The reference is the numba engine in one block. The torch engine (on the CPU here) and Gaussian
blocks must write the same bytes for every `--aggregate` mode (the torch engine with DEVICE_MODES
weights, coalesces and sums on its device: drsplat.registration.device_sums); the Ray place is covered the same
way on a real cluster in tests/test_distributed.py. Options that cannot run are refused before
anything is loaded, in one sentence.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from drsplat.cameras import load_cameras
from drsplat.defaults import AGGREGATE_MODES
from drsplat.errors import InputError, UsageError
from drsplat.registration import RegisterOptions, register
from drsplat.registration.aggregate import mode_stages
from drsplat.registration.fit import probe_picks, probe_space, resolve_mode
from drsplat.scene import load_ply
from drsplat.synthetic import write_dataset

VIEWS = 6  # enough views for every mode to assign, reject and reweight something
BLOCK = 512  # hard-tiny has ~2,300 Gaussians: five blocks


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    # mislabelled masks: the check stage drops some (on clean masks its modes would write their base modes' files)
    data = write_dataset(tmp_path_factory.mktemp("matrix") / "hard", "hard-tiny", 0, mislabel_fraction=0.2, show_progress=False)
    return load_ply(data / "scene.ply"), load_cameras(data)[:VIEWS], data / "features"


def one_block_files(room, folder, modes, **options) -> dict[str, bytes]:
    """The numba engine's one-block file of each of `modes` (RegisterOptions `options` besides)."""
    scene, cams, features = room
    files = {}
    for mode in modes:
        out = folder / mode / "reg.ply"
        register(scene, cams, features, out, RegisterOptions(topk=10, aggregate=mode, **options), show_progress=False)
        files[mode] = out.read_bytes()
    return files


@pytest.fixture(scope="module")
def reference(room, tmp_path_factory) -> dict[str, bytes]:
    """The numba engine's one-block file of every mode."""
    return one_block_files(room, tmp_path_factory.mktemp("reference"), AGGREGATE_MODES)


def test_modes_give_different_fields(reference):
    """The matrix would prove nothing if the modes all wrote the same file. A fit mode resolves to
    one of them (drsplat.registration.fit): on this room's footprint masks, the paper's."""
    concrete = [m for m in AGGREGATE_MODES if mode_stages(m).weighting != "fit"]
    assert len({reference[m] for m in concrete}) == len(concrete)
    for mode in set(AGGREGATE_MODES) - set(concrete):
        assert reference[mode] == reference[resolve_mode(mode, "paper")]


@pytest.mark.parametrize("engine,block", [("numba", BLOCK), ("torch", None), ("torch", BLOCK)])
@pytest.mark.parametrize("mode", AGGREGATE_MODES)
def test_every_engine_and_plan_writes_the_reference_file(room, reference, tmp_path, engine, block, mode):
    scene, cams, features = room
    out = tmp_path / mode / "reg.ply"
    options = RegisterOptions(topk=10, aggregate=mode, engine=engine, device="cpu", block_size=block)
    stages = mode_stages(mode)
    if block is not None and stages.solve:  # the solve needs every Gaussian in one block: refused up front
        with pytest.raises(UsageError, match="in one block in memory and cannot run under a --memory-budget"):
            register(scene, cams, features, out, options, show_progress=False)
        assert not out.parent.exists() or list(out.parent.iterdir()) == []
        return
    result = register(scene, cams, features, out, options, show_progress=False)
    assert result.num_blocks == (1 if block is None else -(-scene.num_gaussians // block))
    # the torch engine weights, coalesces, rejects and votes on its device in every mode and plan, and sums there in one
    # block (a check mode copies the views' pairs to the host for its judging, then sums the kept ones on the device)
    assert result.pairs_on == ("cpu" if engine == "torch" else "host")
    assert result.sums_on == ("cpu" if engine == "torch" and block is None else "host")
    assert out.read_bytes() == reference[mode]


@pytest.mark.parametrize("options,message", [
    (RegisterOptions(engine="numba", device="cuda"), "numba engine runs on the CPU only"),
    (RegisterOptions(engine="reference"), "unknown registration engine 'reference'"),
    (RegisterOptions(aggregate="median"), "unknown aggregation mode 'median'"),
    (RegisterOptions(topk=0), "topk must be between 1 and 1024"),
    (RegisterOptions(memory_budget=0), "memory-budget must be at least 1"),
    (RegisterOptions(ray="auto", ray_workers=0), "ray-workers must be at least 1"),
])
def test_what_cannot_run_is_refused_up_front(room, tmp_path, options, message):
    scene, cams, features = room
    with pytest.raises(UsageError, match=message):
        register(scene, cams, features, tmp_path / "x.ply", options, show_progress=False)
    assert list(tmp_path.iterdir()) == []  # nothing written, no checkpoint


@pytest.mark.parametrize("bad_view", [0, 3, 4])
def test_a_failed_run_leaves_its_checkpoint_only_when_it_holds_views(room, tmp_path, bad_view, caplog):
    """A run that fails on its first view, or in the default mode's fit stage (views 0, 2, 3 and 5 of
    6 are its probe views), on a fault in a view's data that its headers do not show, leaves nothing behind; one that fails later keeps the log of the views
    done, says so in one warning, and the rerun (input fixed) resumes and writes the reference file."""
    scene, cams, features = room
    copy = tmp_path / "features"
    shutil.copytree(features, copy)
    bad = copy / f"{cams[bad_view].name}_s.npy"
    good = bad.read_bytes()
    ids = np.load(bad)
    ids[..., 0, 0] = 10_000  # past the view's embeddings: only reading the view finds it (a truncated file fails before any view)
    np.save(bad, ids)
    out = tmp_path / "out" / "reg.ply"
    with caplog.at_level("WARNING"), pytest.raises(InputError, match=bad.name):
        register(scene, cams, copy, out, RegisterOptions(topk=10), show_progress=False)
    assert not out.exists()
    left = sorted(p.name for p in out.parent.iterdir()) if out.parent.exists() else []
    if bad_view in probe_picks(cams, space=probe_space(scene)):
        assert left == [] and "checkpoint" not in caplog.text
        return
    # the log, and the default mode's per-view statistics beside it (its -reject stage keeps some)
    assert left[0] == ".reg.ply.register.log" and all(name.startswith(".reg.ply.register.log") for name in left)
    assert f"kept the registration checkpoint {out.parent / '.reg.ply.register.log'} ({bad_view} of {VIEWS} views" in caplog.text
    bad.write_bytes(good)
    caplog.clear()
    with caplog.at_level("INFO"):
        result = register(scene, cams, copy, out, RegisterOptions(topk=10), show_progress=False)
    assert result.resumed_views == bad_view and f"{bad_view} of 6 views already registered" in caplog.text
    assert sorted(p.name for p in out.parent.iterdir()) == ["reg.ply"]


NEAR_MODES = ["paper", "fit-check-vote-reject", "anchor-reject", "sharp-vote-reject", "solve"]


@pytest.fixture(scope="module")
def inria_plane(room, tmp_path_factory) -> dict[str, bytes]:
    """The numba engine's one-block file of NEAR_MODES at INRIA's near plane (0.2)."""
    from drsplat.defaults import INRIA_NEAR

    return one_block_files(room, tmp_path_factory.mktemp("inria"), NEAR_MODES, near_plane=INRIA_NEAR)


def test_the_near_plane_leaves_out_every_gaussian_nearer_than_it_in_each_view(room):
    """--near-plane 0.2 (INRIA's): a view drops every Gaussian with camera depth under 0.2, as the reference
    rasterizer does at that plane, culled or not; at the default 0.01 the same views hold such Gaussians (hard-tiny's
    floor-level views: 63a measured 72.7 % of one view's weight on them), so the plane decides what is registered."""
    from drsplat.defaults import INRIA_NEAR
    from drsplat.raster import prepare_scene, rasterize_reference
    from drsplat.registration.compute import ViewComputer, ViewJob

    scene, cams, features = room
    geometry = prepare_scene(scene)
    near_ids = 0
    for cull in (True, False):
        computer = ViewComputer(geometry, ViewJob(features, 0, 10, near=INRIA_NEAR, cull=cull))
        default = ViewComputer(geometry, ViewJob(features, 0, 10, cull=cull))
        for cam in cams:
            z = cam.world_to_camera(scene.means.astype(np.float64))[:, 2]
            ids = computer.rasterize(cam).ids.copy()
            want = rasterize_reference(scene, cam, 10, near=INRIA_NEAR)
            np.testing.assert_array_equal(np.sort(ids, axis=2), np.sort(want.ids, axis=2))
            assert not (z[ids[ids >= 0]] < INRIA_NEAR).any()
            seen = default.rasterize(cam).ids
            near_ids += int((z[seen[seen >= 0]] < INRIA_NEAR).sum())
    assert near_ids > 1_000


@pytest.mark.parametrize("engine,block", [("torch", None), ("numba", BLOCK), ("torch", BLOCK)])
@pytest.mark.parametrize("mode", NEAR_MODES)
def test_every_engine_and_plan_writes_the_same_file_at_another_near_plane(room, reference, inria_plane, tmp_path, engine, block, mode):
    """The plane reaches every stage that renders (the view pass, the fit stage's probes, the solve's re-renders, the
    per-view weightings' projections, the culling): the torch engine and blocks write the numba engine's one-block
    file at 0.2, which is not the file at 0.01."""
    from drsplat.defaults import INRIA_NEAR

    scene, cams, features = room
    assert inria_plane[mode] != reference[mode]
    if block is not None and mode_stages(mode).solve:
        return  # refused up front (test_every_engine_and_plan_writes_the_reference_file)
    out = tmp_path / "reg.ply"
    register(scene, cams, features, out, RegisterOptions(topk=10, aggregate=mode, engine=engine, device="cpu", block_size=block,
                                                         near_plane=INRIA_NEAR), show_progress=False)
    assert out.read_bytes() == inria_plane[mode]


def test_a_checkpoint_records_a_near_plane_other_than_the_default(room, caplog):
    """A log made at another plane is not resumed (it names both planes and --near-plane); the default is not recorded, so a log made
    before the option resumes as it was."""
    from drsplat.defaults import INRIA_NEAR, NEAR
    from drsplat.registration.checkpoint import checkpoint_params
    from drsplat.registration.pairlog import changed_params

    scene, cams, features = room
    default = checkpoint_params(scene, cams, features, 10, 0, "paper")
    assert "near_plane" not in default and checkpoint_params(scene, cams, features, 10, 0, "paper", near_plane=NEAR) == default
    inria = checkpoint_params(scene, cams, features, 10, 0, "paper", near_plane=INRIA_NEAR)
    assert inria["near_plane"] == 0.2
    # both values named: `--near-plane auto` decides the plane from the images, so the same command can change it (66a F1)
    assert changed_params(default, inria).startswith("the near plane (0.01 in the checkpoint, 0.2 now: --near-plane, or ")
    assert changed_params(inria, default).startswith("the near plane (0.2 in the checkpoint, 0.01 now:")
    assert "--near-plane auto" in changed_params(inria, default) and changed_params(inria, default).endswith(" changed")


@pytest.mark.parametrize("plane", [0.0, -0.2, float("inf"), float("nan")])
def test_a_near_plane_that_is_no_positive_depth_is_refused_up_front(room, tmp_path, plane):
    scene, cams, features = room
    with pytest.raises(UsageError, match=r"near-plane must be a positive, finite camera depth in scene units, got"):
        register(scene, cams, features, tmp_path / "reg.ply", RegisterOptions(near_plane=plane), show_progress=False)
    assert not (tmp_path / "reg.ply").exists()


@pytest.mark.parametrize("mode", ["fit-check-vote-reject", "solve"])
def test_every_view_a_registration_renders_is_at_its_near_plane(room, tmp_path, monkeypatch, mode):
    """The view pass, the fit stage's probe views and the solve's re-renders each make their own ViewComputer: every
    one of them renders at the registration's plane, and the per-view weightings project at it (round 64c: the fit
    stage's sharp weights were asked at the default)."""
    from drsplat.registration.aggregate import ViewHook
    from drsplat.registration.compute import ViewComputer

    scene, cams, features = room
    planes, weighed = [], []
    made, weights = ViewComputer.__init__, ViewHook.weights
    monkeypatch.setattr(ViewComputer, "__init__", lambda self, geometry, job, *a, **k: (planes.append(job.near), made(self, geometry, job, *a, **k))[1])
    monkeypatch.setattr(ViewHook, "weights", lambda self, geometry, camera, out, mask_ids=None, near=-1.0: (
        weighed.append(near), weights(self, geometry, camera, out, mask_ids, near))[1])
    register(scene, cams, features, tmp_path / "reg.ply", RegisterOptions(topk=10, aggregate=mode, near_plane=0.15), show_progress=False)
    assert len(planes) >= 2 and set(planes) == {0.15}
    assert set(weighed) <= {0.15} and (mode == "solve" or weighed)


def test_the_near_plane_flag_reads_a_depth_or_inria_and_names_both_when_refusing():
    import argparse

    from drsplat.commands.common import near_plane_value

    assert [near_plane_value(t) for t in ("inria", " INRIA ", "0.01", "1e-12", "5")] == [0.2, 0.2, 0.01, 1e-12, 5.0]
    for text in ("abc", "inria2", "", "0", "-0", "-1", "1e-400", "nan", "inf", "1e400"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"\(such as 0\.01 or 0\.2\) or 'inria', got ") as err:
            near_plane_value(text)
        assert str(err.value).endswith(f"got {text!r}")  # as typed: 1e-400 is not "0" (round 65a F4: the words came after it)


def test_register_near_plane_also_reads_auto_and_eval_lerf_does_not(capsys):
    """`register --near-plane auto` decides the plane from the training images (drsplat.frames.near_plane_as_trained);
    `eval lerf` renders at the plane the registered file records, so it takes no 'auto'."""
    import argparse

    from drsplat.cli import main
    from drsplat.commands.common import near_plane_choice

    assert [near_plane_choice(t) for t in ("auto", " AUTO ", "inria", "0.05")] == ["auto", "auto", 0.2, 0.05]
    with pytest.raises(argparse.ArgumentTypeError, match=r"or 'inria' or 'auto', got 'automatic'$"):
        near_plane_choice("automatic")
    for args, said in ((["register", "scene.ply", "--source", "s", "--features", "f", "--out", "o.ply", "--near-plane", "0"], "or 'auto'"),
                       (["eval", "lerf", "--near-plane", "auto", "r.ply", "--source", "s", "--annotations", "a"], "or 'inria', got 'auto'")):
        with pytest.raises(SystemExit) as stop:
            main(args)
        assert stop.value.code == 2 and said in capsys.readouterr().err


def test_a_file_registered_at_another_plane_says_so_and_eval_lerf_renders_there(room, tmp_path):
    """A registration at a plane other than the default writes it into the PLY's header (the default's file is as it was),
    a registration of such a file at another plane does not carry its line over, and `eval lerf` renders at the recorded
    plane unless --near-plane is given (64c F4)."""
    from drsplat.commands.eval import registered_near_plane
    from drsplat.defaults import NEAR
    from drsplat.registration.options import recorded_near_plane

    scene, cams, features = room
    register(scene, cams, features, tmp_path / "inria.ply", RegisterOptions(topk=10, aggregate="paper", near_plane=0.2), show_progress=False)
    registered = load_ply(tmp_path / "inria.ply")
    assert "drsplat.near_plane 0.2" in registered.comments and recorded_near_plane(registered.comments) == 0.2
    assert registered_near_plane(None, registered) == 0.2 and registered_near_plane(0.05, registered) == 0.05
    register(registered, cams, features, tmp_path / "again.ply", RegisterOptions(topk=10, aggregate="paper"), show_progress=False)
    again = load_ply(tmp_path / "again.ply")
    assert not any(c.startswith("drsplat.near_plane") for c in again.comments) and registered_near_plane(None, again) == NEAR
    for line in ("drsplat.near_plane abc", "drsplat.near_plane -1", "drsplat.near_plane nan"):
        assert recorded_near_plane([line]) is None
