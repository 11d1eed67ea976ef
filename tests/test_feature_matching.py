"""Pairing cameras with feature files and the checks of the mask maps they pair (round 51): Unicode
spellings, macOS AppleDouble files, names differing in case, mask maps far coarser than their camera,
and single-level mask files among files of several levels."""

from __future__ import annotations

import dataclasses
import logging
import shutil
import unicodedata
from pathlib import Path

import numpy as np
import pytest

from drsplat.cameras import Camera, load_cameras, same_aspect
from drsplat.errors import InputError
from drsplat.features.format import list_stems, write_features
from drsplat.registration import RegisterOptions, register_features
from drsplat.registration.driver import prepare_run
from drsplat.registration.views import check_aspect, pair_views, read_feature_headers, select_views, single_level_note, spelling_hint
from drsplat.scene import load_ply

WARN = "drsplat.registration"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """The tiny synthetic dataset (16 views of 128x96, 4-level mask files)."""
    from drsplat.synthetic import write_dataset

    return write_dataset(tmp_path_factory.mktemp("matching") / "ds", "tiny", 0, show_progress=False)


@pytest.fixture(scope="module")
def plain(tiny) -> object:
    """The tiny dataset registered with its own names (`--aggregate paper`)."""
    return register_features(load_ply(tiny / "scene.ply"), load_cameras(tiny), tiny / "features", RegisterOptions(aggregate="paper"),
                             show_progress=False)


def accented(name: str, form: str) -> str:
    """`name` with an accented prefix, in Unicode normal form `form`."""
    return unicodedata.normalize(form, name.replace("orbit", "órbita").replace("inside", "interior_ñ"))


def copy_features(tiny: Path, folder: Path, rename=lambda stem: stem) -> Path:
    """The tiny dataset's feature pairs copied into `folder` under the stems `rename` gives."""
    folder.mkdir()
    for path in (tiny / "features").glob("*.npy"):
        stem, suffix = path.name[:-6], path.name[-6:]
        shutil.copy(path, folder / f"{rename(stem)}{suffix}")
    return folder


def cameras(sizes: list[tuple[int, int]], prefix: str = "v", first: int = 0) -> list[Camera]:
    """Cameras of the given (width, height), each at its own position from `first` on (not copies of one another)."""
    return [Camera(R=np.eye(3), t=np.array([float(first + i), 0.0, 0.0]), fx=float(w), fy=float(w), cx=w / 2, cy=h / 2, width=w, height=h,
                   name=f"{prefix}{i}") for i, (w, h) in enumerate(sizes)]


def write_maps(folder: Path, cams: list[Camera], shapes: list[tuple[int, ...]], seed: int = 0) -> None:
    """A feature pair per camera with a mask map of the given shape ((L, H, W) or (H, W)), 4 masks a level."""
    rng = np.random.default_rng(seed)
    for cam, shape in zip(cams, shapes):
        levels = shape[0] if len(shape) == 3 else 1
        seg = rng.integers(0, 4, size=shape) + (4 * np.arange(levels).reshape((-1, 1, 1)) if len(shape) == 3 else 0)
        feats = rng.normal(size=(4 * levels, 8)).astype(np.float32)
        write_features(folder, cam.name, seg, feats / np.linalg.norm(feats, axis=1, keepdims=True))


def warnings_of(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


# F2: image names composed (NFC, as Linux writes them), feature files decomposed (NFD, a folder copied from macOS)

def test_feature_files_named_in_nfd_pair_with_cameras_named_in_nfc_and_register_the_same(tiny, plain, tmp_path, caplog):
    """Round 51: 14 of 16 views were dropped (seg mIoU 0.96 -> 0.21), both warnings listing names that looked the same;
    the names are paired in NFC, and the registration is the one of plain names, bit for bit."""
    feats = copy_features(tiny, tmp_path / "features", lambda stem: accented(stem, "NFD"))
    cams = [dataclasses.replace(c, name=accented(c.name, "NFC")) for c in load_cameras(tiny)]
    assert sum(c.name != accented(c.name, "NFD") for c in cams) == 16  # every name differs in its bytes
    with caplog.at_level(logging.INFO, logger=WARN):
        result = register_features(load_ply(tiny / "scene.ply"), cams, feats, RegisterOptions(aggregate="paper"), show_progress=False)
    assert result.num_views == 16 and not result.missing_features and not result.unmatched_features
    assert np.array_equal(result.features, plain.features) and np.array_equal(result.weights, plain.weights)
    assert not warnings_of(caplog)
    assert "16 cameras matched their feature files only in Unicode NFC" in caplog.text


def test_two_feature_files_of_one_name_in_nfc_pair_with_neither_and_are_named(tmp_path, caplog):
    """Two files whose names differ only in how their accents are encoded are two files: which one a camera means is
    unknown, so it keeps no features (as before), and the warning now says why, with the names escaped."""
    nfc = "\u1ec7_0"  # e with circumflex and dot below, composed
    spellings = ["\u00ea\u0323_0", "e\u0323\u0302_0"]  # both are it in NFC, neither is NFC
    assert all(unicodedata.normalize("NFC", s) == nfc and s != nfc for s in spellings)
    cams = cameras([(40, 30)] * 3)
    named = [dataclasses.replace(cams[0], name=nfc), cams[1], cams[2]]
    write_maps(tmp_path, [dataclasses.replace(cams[0], name=s) for s in spellings] + cams[1:], [(4, 30, 40)] * 4)
    assert pair_views(named, spellings + ["v1", "v2"]).missing == [nfc]
    with caplog.at_level(logging.WARNING, logger=WARN):
        sel = select_views(named, tmp_path)
    assert [c.name for c in sel.views] == ["v1", "v2"]
    assert "has 2 feature files of its name in different Unicode encodings" in caplog.text and ascii(spellings[0] + "_s.npy") in caplog.text


def test_mask_files_of_another_number_of_levels_than_langsplats_four_are_warned_of(tiny, tmp_path, caplog):
    """Round 100c F1: a folder of 3-level files registered its second level (m of s, m, l) as LangSplat's 's', and a
    folder mixing 3- and 4-level files one view's s masks beside another's m, without a word. `--level` picks each
    file's level by index, which is said, once, whenever the files of several levels are not all of four."""
    scene, options = load_ply(tiny / "scene.ply"), RegisterOptions(aggregate="paper", level=1)
    four = cameras([(40, 30)] * 3)
    write_maps(tmp_path, four, [(4, 30, 40)] * 3)
    with caplog.at_level(logging.WARNING, logger=WARN):
        prepare_run(scene, four, tmp_path / ".", options)
    assert not warnings_of(caplog)
    three = cameras([(40, 30)] * 2, prefix="t", first=3)
    write_maps(tmp_path, three, [(3, 30, 40)] * 2, seed=1)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=WARN):
        prepare_run(scene, four + three, tmp_path, options)
    said = warnings_of(caplog)
    # round 104a F3: the files of the layout fewer views have are named (with 1 odd view of 1,000, none was)
    assert said == ["the views' mask files have different numbers of levels (2 views 3: t0_s.npy, t1_s.npy; 3 views 4): level 1 is each file's level 1 by "
                    "index, a different mask scale in files of another layout (LangSplat's 's' only in files of 4 levels); remake the "
                    "features so every view has the same levels"], said
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=WARN):
        prepare_run(scene, three, tmp_path, options)
    said = [m for m in warnings_of(caplog) if "match no camera" not in m]  # the four-level files left in the folder are named too
    assert said == ["the mask files of 2 views have 3 levels, not LangSplat's 4 (default, s, m, l): level 1 is read as each file's level 1 "
                    "by index, whatever mask scale it holds there (LangSplat's 's' only in files of 4 levels)"], said
    write_maps(tmp_path, three, [(30, 40)] * 2, seed=2)  # single-level files beside four-level ones are single_level_note's
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger=WARN):
        prepare_run(scene, four + three, tmp_path, options)
    assert len(warnings_of(caplog)) == 1 and "have one level" in warnings_of(caplog)[0]


# F3: mask maps far coarser than their camera

def test_mask_maps_far_coarser_than_their_camera_are_warned_of_once_and_halves_to_eighths_are_not(tiny, tmp_path, caplog):
    """Round 51: 4x3 maps for 256x192 cameras were resampled without a word (seg mIoU 0.96 -> 0.28); maps of 1/2, 1/4
    and 1/8 (0.98, 0.95, 0.89) stay quiet, as does 1/8 of the tiny preset's 128x96 (16x12). The sizes come from the one
    pass over the headers that registration makes anyway (`read_feature_headers`), not from a pass of their own."""
    scene, options = load_ply(tiny / "scene.ply"), RegisterOptions(aggregate="paper", level=0)  # level 0: no single-level note
    quiet = cameras([(256, 192)] * 4 + [(128, 96)])
    write_maps(tmp_path, quiet, [(4, 192, 256), (4, 96, 128), (4, 48, 64), (4, 24, 32), (4, 12, 16)])
    with caplog.at_level(logging.WARNING, logger=WARN):
        prepare_run(scene, quiet, tmp_path, options)
    assert not warnings_of(caplog)
    coarse = cameras([(256, 192)] * 3, prefix="c", first=5)
    write_maps(tmp_path, coarse, [(4, 3, 4), (3, 4), (4, 12, 16)])
    with caplog.at_level(logging.WARNING, logger=WARN):
        assert len(prepare_run(scene, quiet + coarse, tmp_path, options).headers.coarse) == 2
    said = warnings_of(caplog)
    assert len(said) == 1 and said[0].startswith("2 of 8 views' mask maps are far coarser than their cameras (e.g. c0_s.npy: field 'shape': "
                                                 "mask map 4x3 for a 256x192 camera, each mask pixel covering 64x64 view pixels)")


def test_a_mask_map_of_one_pixel_a_side_is_held_to_its_cameras_aspect(tmp_path):
    """Round 51: a 1x1 map passed the aspect check of a 256x192 camera (1.0 against 1.333) by its one-pixel rounding
    allowance, which for a 1-pixel side covers nearly any aspect; such a map is now refused, naming why. Kept: a 1x1 map
    of a square camera, 100x1 of a 1000x10 strip, 4x3 of 256x192, 25x18 and 3x2 of 101x75 (rounding), a map larger
    than its camera."""
    cam = cameras([(256, 192)])[0]
    for w, h in [(1, 1), (2, 1), (1, 2), (3, 1)]:
        with pytest.raises(InputError, match=rf"v0_s.npy: field 'shape': mask map is {w}x{h} .*camera 'v0' is 256x192.*"
                                             r"a side cannot show its aspect, so no rounding excuses it"):
            check_aspect(tmp_path / "v0_s.npy", w, h, cam)
    for (w, h), (width, height) in [((1, 1), (64, 64)), ((100, 1), (1000, 10)), ((4, 3), (256, 192)), ((25, 18), (101, 75)),
                                    ((3, 2), (101, 75)), ((512, 384), (256, 192)), ((2, 1), (2, 1))]:
        check_aspect(tmp_path / "v_s.npy", w, h, cameras([(width, height)])[0])


def test_a_map_whose_sides_are_each_a_whole_pixel_off_the_other_way_is_another_aspect(tmp_path):
    """Round 52: 5x2 passed for a 256x192 camera (2.5 against 1.333): the rounding allowance took |w - s·width| <= 1 on
    each side, and s = 1/64 gives 4x3, one pixel off either side in opposite directions. Rounding, floor and ceil move a side
    by less than a pixel, so the allowance is strict; every such downscale of 200,000 random sizes and scales still passes."""
    with pytest.raises(InputError, match=r"v0_s.npy: field 'shape': mask map is 5x2 .*aspect ratios 2.5 and 1.333 differ"):
        check_aspect(tmp_path / "v0_s.npy", 5, 2, cameras([(256, 192)])[0])
    rng = np.random.default_rng(0)
    sizes = rng.integers(1, 5000, size=(200_000, 2))
    scales = np.exp(rng.uniform(np.log(1e-3), np.log(4.0), size=200_000))
    rules = [np.floor, np.ceil, np.round]
    for (width, height), scale, (rx, ry) in zip(sizes, scales, rng.integers(0, 3, size=(200_000, 2))):
        w, h = max(1, int(rules[rx](scale * width))), max(1, int(rules[ry](scale * height)))
        assert same_aspect(w, h, int(width), int(height)), (w, h, width, height, scale)


# F4: a single-level mask file among files of several levels

def test_single_level_files_among_four_level_ones_are_warned_of_when_a_level_past_0_is_asked(tmp_path, caplog):
    """Round 51: a (1, H, W) or (H, W) file served `--level 3` beside 4-level files without a word (a (3, H, W) one is
    refused); it is named, once, for levels 1-3, not for level 0, and not in a folder of single-level files."""
    cams = cameras([(40, 30)] * 6)
    write_maps(tmp_path, cams, [(4, 30, 40)] * 5 + [(1, 30, 40)])
    levels = read_feature_headers(tmp_path, cams, 3).levels
    assert single_level_note(levels, 3) == ("v5_s.npy has one level; the other 5 views have 4: it is used as level 3, a mask scale of its "
                                            "own beside the others' (remake its features with all levels, or register those with one)")
    assert single_level_note(levels, 0) is None
    write_maps(tmp_path, cams[3:], [(30, 40), (30, 40), (1, 30, 40)], seed=1)  # as many single- as multi-level files
    assert single_level_note(read_feature_headers(tmp_path, cams, 1).levels, 1).startswith(
        "3 views' mask files have one level (v3_s.npy, v4_s.npy, v5_s.npy); the other 3 views have 4: their one level is used as level 1")
    write_maps(tmp_path, cams, [(30, 40)] * 6, seed=2)
    assert single_level_note(read_feature_headers(tmp_path, cams, 3).levels, 3) is None


def test_a_single_level_file_among_four_level_ones_is_warned_of_once_by_a_default_registration(tiny, tmp_path, caplog):
    """The fit stage re-checks its probe views' headers in pairs: the warning is still said once, with one
    single-level file among 15 and with 8 among 16 (a probe pair of one and one is then likely)."""
    cams = load_cameras(tiny)
    for count in (1, 8):
        feats = copy_features(tiny, tmp_path / f"features{count}")
        for cam in cams[3:3 + count]:
            np.save(feats / f"{cam.name}_s.npy", np.load(feats / f"{cam.name}_s.npy")[1:2])
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger=WARN):
            register_features(load_ply(tiny / "scene.ply"), cams, feats, RegisterOptions(level=3), show_progress=False)
        said = [m for m in warnings_of(caplog) if "one level" in m]
        assert len(said) == 1 and f"the other {16 - count} views have 4" in said[0], said


# N4, N5: a folder copied from a Mac; names that differ in case

def test_apple_double_files_and_ds_store_are_no_feature_files(tiny, tmp_path, caplog):
    """Round 51: a folder copied from a Mac to an exFAT disk holds `._<name>` beside every file (its resource fork) and a
    .DS_Store; they were counted as feature files without a camera. They are passed over without a word."""
    feats = copy_features(tiny, tmp_path / "features")
    for path in list(feats.glob("*.npy")):
        (feats / f"._{path.name}").write_bytes(b"\x00\x05\x16\x07" + bytes(4092))
    (feats / ".DS_Store").write_bytes(bytes(6148))
    assert list_stems(feats) == list_stems(tiny / "features")
    with caplog.at_level(logging.WARNING, logger=WARN):
        sel = select_views(load_cameras(tiny), feats)
    assert len(sel.views) == 16 and not sel.unmatched and not warnings_of(caplog)


def test_cameras_and_feature_files_that_match_ignoring_case_are_said_to(tiny, tmp_path):
    """Round 51: images ORBIT_000.JPG, features orbit_000_*.npy: the refusal listed both sides; it now says they match
    ignoring case."""
    cams = [dataclasses.replace(c, name=c.name.upper()) for c in load_cameras(tiny)]
    with pytest.raises(InputError, match=r"no feature file matches a camera image stem .*; camera 'ORBIT_000' and orbit_000_s.npy match "
                                         r"ignoring case, but names are paired case-sensitively"):
        select_views(cams, tiny / "features")


def test_two_cameras_naming_one_feature_file_are_said_to_and_not_as_a_case_mismatch():
    """Round 52: cameras frame-0.color and frame-0.depth both cut to LangSplat's stem frame-0 and are
    rightly left unpaired, but the warning said they "match ignoring case", though nothing differed
    in case; it now says two cameras name the file. A real case-only mismatch keeps its hint."""
    sel = pair_views(cameras([(8, 6)] * 2, prefix="frame-0."), ["frame-0"])
    assert not sel.views and sel.unmatched == ["frame-0"]
    hint = spelling_hint(sel.missing, sel.unmatched)
    assert "both name the feature file 'frame-0_s.npy'" in hint and "ignoring case" not in hint, hint
    sel = pair_views(cameras([(8, 6)], prefix="ORBIT_"), ["orbit_0"])
    assert "camera 'ORBIT_0' and orbit_0_s.npy match ignoring case" in spelling_hint(sel.missing, sel.unmatched)


def test_on_a_tie_of_layouts_the_files_not_of_langsplats_four_levels_are_named():
    """Round 105a: two 3-level and two 4-level files named LangSplat's own 4-level files as the odd ones."""
    from drsplat.registration.views import level_count_note

    note = level_count_note({"a_s.npy": 3, "b_s.npy": 3, "c_s.npy": 4, "d_s.npy": 4}, 1)
    assert "(2 views 3: a_s.npy, b_s.npy; 2 views 4)" in note, note
    note = level_count_note({"a_s.npy": 3, "b_s.npy": 5, "c_s.npy": 5}, 1)  # no 4: the layout more views have
    assert "(1 view 3: a_s.npy; 2 views 5)" in note, note
