"""LangSplat feature files: levels, dtypes, validation, truncation, resampling, manifest."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from drsplat.cameras import Camera
from drsplat.errors import InputError, OutputError
from drsplat.features.format import (
    feat_path,
    is_valid_pair,
    list_stems,
    read_features,
    read_manifest,
    resample_nearest,
    seg_path,
    write_features,
    write_manifest,
)


def langsplat_like(rng: np.random.Generator, h: int = 6, w: int = 8, counts=(3, 2, 4, 1), d: int = 5):
    """Four levels with cumulative ids, as LangSplat's preprocess.py writes them."""
    seg = np.full((len(counts), h, w), -1, np.int64)
    offset = 0
    for level, count in enumerate(counts):
        local = rng.integers(-1, count, size=(h, w))
        local.flat[:count] = np.arange(count)  # every mask appears
        seg[level] = np.where(local >= 0, local + offset, -1)
        offset += count
    feats = rng.normal(size=(offset, d))
    return seg, (feats / np.linalg.norm(feats, axis=1, keepdims=True)).astype(np.float32)  # CLIP's unit embeddings


def test_round_trip_and_levels_index_the_concatenated_array(tmp_path):
    rng = np.random.default_rng(0)
    seg, feats = langsplat_like(rng)
    write_features(tmp_path, "img_001", seg, feats)
    assert list_stems(tmp_path) == ["img_001"]
    assert is_valid_pair(tmp_path, "img_001")
    for level in range(4):
        ids, f = read_features(tmp_path, "img_001", level=level)
        assert ids.dtype == np.int32 and f.dtype == np.float32
        np.testing.assert_array_equal(ids, seg[level])
        np.testing.assert_array_equal(f, feats)
    ids1, _ = read_features(tmp_path, "img_001")
    assert ids1[ids1 >= 0].min() >= 3 and ids1.max() < 5  # level 1 (s) is rows 3..4


@pytest.mark.parametrize("dtype", [np.int8, np.int16, np.int32, np.int64, np.float16, np.float32, np.float64])
def test_any_int_or_float_dtype(tmp_path, dtype):
    rng = np.random.default_rng(1)
    seg, feats = langsplat_like(rng)
    np.save(seg_path(tmp_path, "a"), seg.astype(dtype))
    np.save(feat_path(tmp_path, "a"), feats.astype(np.float16))
    ids, f = read_features(tmp_path, "a", level=2)
    np.testing.assert_array_equal(ids, seg[2])
    np.testing.assert_allclose(f, feats.astype(np.float16).astype(np.float32))


def test_non_cumulative_levels_get_offsets(tmp_path):
    rng = np.random.default_rng(2)
    seg, feats = langsplat_like(rng, counts=(3, 2, 4, 1))
    local = seg.copy()
    for level, offset in enumerate((0, 3, 5, 9)):
        local[level] = np.where(seg[level] >= 0, seg[level] - offset, -1)
    write_features(tmp_path, "b", local, feats)
    for level in range(4):
        np.testing.assert_array_equal(read_features(tmp_path, "b", level=level)[0], seg[level])


def test_single_level_file_serves_any_level(tmp_path):
    seg = np.array([[0, 1], [-1, 1]])
    write_features(tmp_path, "c", seg, np.eye(2, 3, dtype=np.float32))
    np.testing.assert_array_equal(read_features(tmp_path, "c", level=1)[0], seg)


def test_all_zero_embeddings_are_ignored_with_a_warning(tmp_path, caplog):
    """An all-zero row (a placeholder) added its mask's weight to the Gaussians and no direction (round 5)."""
    import logging

    seg = np.zeros((1, 6, 8), np.int32)
    seg[0, :, 4:] = 1
    feats = np.eye(2, 5, dtype=np.float32)
    feats[1] = 0.0
    write_features(tmp_path, "z", seg, feats)
    with caplog.at_level(logging.WARNING):
        ids, got = read_features(tmp_path, "z", level=1)
    assert "1 of 2 embeddings are all zero" in caplog.text
    assert (ids[:, :4] == 0).all() and (ids[:, 4:] == -1).all()
    np.testing.assert_array_equal(got, feats)


def test_tiny_embeddings_are_rescaled_to_unit_length_with_a_warning(tmp_path, caplog):
    """Rows of norm 1e-41 summed in float32 fell into subnormals: directions off by up to 0.87 (1-cos)
    and Gaussians left unassigned without a word (round 5's numerical probe)."""
    import logging

    rng = np.random.default_rng(5)
    seg, feats = langsplat_like(rng, d=16)
    unit = feats / np.linalg.norm(feats, axis=1, keepdims=True)
    write_features(tmp_path, "t", seg, (unit * 1e-30).astype(np.float32))
    with caplog.at_level(logging.WARNING):
        _, got = read_features(tmp_path, "t", level=1)
    assert f"{len(unit)} of {len(unit)} embeddings are not of unit length (norms 1e-30 to 1e-30" in caplog.text
    np.testing.assert_allclose(got, unit, atol=1e-6)


def test_embeddings_below_float32s_smallest_normal_are_ignored_not_rescaled(tmp_path, caplog):
    """Round 30: a row of norm 1e-44 is a few subnormal bits; rescaled, its direction kept cosine 0.61.
    Rows under float32's smallest normal are ignored as all-zero ones are; 1e-37 is still rescaled."""
    import logging

    rng = np.random.default_rng(8)
    seg, feats = langsplat_like(rng, d=16)
    unit = feats / np.linalg.norm(feats, axis=1, keepdims=True)
    rows = (unit * 1e-37).astype(np.float32)
    rows[3] = (unit[3] * 1e-44).astype(np.float32)  # level 1's first mask
    write_features(tmp_path, "s", seg, rows)
    with caplog.at_level(logging.WARNING):
        ids, got = read_features(tmp_path, "s", level=1)
    assert f"1 of {len(unit)} embeddings have a norm below 1.18e-38" in caplog.text
    from drsplat.defaults import MIN_NORM
    from drsplat.lang.lut import MIN_NORM as SCORED_MIN_NORM

    assert MIN_NORM == SCORED_MIN_NORM == np.finfo(np.float32).tiny  # the bar the features and the queries share
    assert (ids[seg[1] == 3] == -1).all() and (ids[seg[1] == 4] == 4).all()
    others = np.arange(len(unit)) != 3
    np.testing.assert_allclose(got[others], unit[others], atol=1e-5)


@pytest.mark.parametrize("scale", [0.5, 2.0, 30.0, 3e35])
def test_embeddings_of_another_length_are_rescaled_and_unit_ones_kept_bit_for_bit(tmp_path, caplog, scale):
    """Round 22: the vote trims a Gaussian's sums by S·μ, μ a unit cluster mean, so mask embeddings of
    norm 0.5 (or raw CLIP features, norm ~10) over-trimmed: `vote-reject` turned features up to 85°
    (cosine 0.08 with the unit run's). Only directions are lifted: any norm off 1 by more than 1e-3 is
    rescaled when read (with one warning); unit rows, float16 ones included, come back as written
    (UNIT_TOLERANCE, 1e-3)."""
    import logging

    rng = np.random.default_rng(7)
    seg, unit = langsplat_like(rng, d=16)
    write_features(tmp_path, "unit", seg, unit)
    write_features(tmp_path, "half", seg, unit.astype(np.float16))
    write_features(tmp_path, "scaled", seg, (unit.astype(np.float64) * scale).astype(np.float32))
    with caplog.at_level(logging.WARNING):
        assert np.array_equal(read_features(tmp_path, "unit", level=1)[1], unit)
        assert np.array_equal(read_features(tmp_path, "half", level=1)[1], unit.astype(np.float16).astype(np.float32))
        assert "unit length" not in caplog.text
        _, got = read_features(tmp_path, "scaled", level=1)
    assert f"{len(unit)} of {len(unit)} embeddings are not of unit length" in caplog.text
    np.testing.assert_allclose(got, unit, atol=1e-6)


def test_errors_name_file_and_problem(tmp_path):
    rng = np.random.default_rng(3)
    seg, feats = langsplat_like(rng)
    np.save(seg_path(tmp_path, "d"), seg)
    np.save(feat_path(tmp_path, "d"), feats[:4])
    with pytest.raises(InputError, match=r"d_s\.npy.*out of range.*only 4 embeddings"):
        read_features(tmp_path, "d", level=1)
    with pytest.raises(InputError, match=r"level 7 requested.*4 levels"):
        read_features(tmp_path, "d", level=7)
    np.save(feat_path(tmp_path, "d"), feats[:, :, None])
    with pytest.raises(InputError, match=r"d_f\.npy.*shape"):
        read_features(tmp_path, "d")
    with pytest.raises(InputError, match=r"e_s\.npy.*missing"):
        read_features(tmp_path, "e")
    np.save(seg_path(tmp_path, "f"), seg.astype(np.float32) + 0.25)
    np.save(feat_path(tmp_path, "f"), feats)
    with pytest.raises(InputError, match="not whole numbers"):
        read_features(tmp_path, "f")


def test_nonfinite_embeddings_are_counted(tmp_path):
    rng = np.random.default_rng(4)
    seg, feats = langsplat_like(rng)
    feats[3, 0] = np.nan
    feats[4, 2] = np.inf
    write_features(tmp_path, "g", seg, feats)
    with pytest.raises(InputError, match=r"g_f\.npy.*2 of 10 embeddings contain non-finite"):
        read_features(tmp_path, "g")
    ids, f = read_features(tmp_path, "g", level=1, drop_nonfinite=True)
    assert np.isfinite(f).all()
    assert (ids == -1).all()  # level 1 used exactly rows 3 and 4


def test_truncated_and_corrupt_files_are_detected(tmp_path):
    rng = np.random.default_rng(5)
    seg, feats = langsplat_like(rng, h=40, w=50)
    write_features(tmp_path, "h", seg, feats)
    assert is_valid_pair(tmp_path, "h")
    data = feat_path(tmp_path, "h").read_bytes()
    feat_path(tmp_path, "h").write_bytes(data[: len(data) - 7])
    assert not is_valid_pair(tmp_path, "h")
    with pytest.raises(InputError, match="truncated"):
        read_features(tmp_path, "h")
    feat_path(tmp_path, "h").write_bytes(b"not numpy at all")
    assert not is_valid_pair(tmp_path, "h")
    with pytest.raises(InputError, match="not a readable .npy"):
        read_features(tmp_path, "h")
    feat_path(tmp_path, "h").unlink()
    assert not is_valid_pair(tmp_path, "h")


def test_resample_nearest_matches_scaled_intrinsics():
    """A point projected by a camera and by camera.scaled() lands on the same mask."""
    rng = np.random.default_rng(6)
    src = rng.integers(-1, 50, size=(48, 64)).astype(np.int32)
    cam_src = Camera(R=np.eye(3), t=np.zeros(3), fx=60.0, fy=60.0, cx=31.0, cy=25.0, width=64, height=48)
    for factor in (2.0, 0.5, 1.5, 0.75):
        cam_dst = cam_src.scaled(factor)
        dst = resample_nearest(src, cam_dst.width, cam_dst.height)
        assert dst.shape == (cam_dst.height, cam_dst.width)
        # destination pixel centres, expressed in source pixel coordinates, fall in the sampled pixel
        ys, xs = np.mgrid[0 : cam_dst.height, 0 : cam_dst.width]
        sx, sy = (xs + 0.5) * 64 / cam_dst.width, (ys + 0.5) * 48 / cam_dst.height
        np.testing.assert_array_equal(dst, src[np.floor(sy).astype(int), np.floor(sx).astype(int)])
        # a world point projects to corresponding pixels in both cameras
        pts = np.c_[rng.uniform(-0.4, 0.4, (200, 2)), np.ones(200)]
        uv_s, _ = cam_src.project(pts)
        uv_d, _ = cam_dst.project(pts)
        np.testing.assert_allclose(uv_d / factor, uv_s, atol=1e-3 * max(1, 1 / factor) + 0.05)
    assert resample_nearest(src, 64, 48) is src
    up = resample_nearest(src, 128, 96)
    np.testing.assert_array_equal(up[::2, ::2], src)
    np.testing.assert_array_equal(resample_nearest(up, 64, 48), src)


def test_resample_nearest_takes_the_pixel_after_an_edge_a_centre_falls_on():
    """Round 22: (x + 0.5) * (W / width) in float64 fell one column short where the centre lies
    exactly on a source edge: 2 -> 49 columns, x = 24 ((24.5) * 2 / 49 = 1 exactly) took column 0."""
    from fractions import Fraction

    from drsplat.features.format import source_pixels

    src = np.arange(2, dtype=np.int32)[None, :].repeat(3, 0)
    assert resample_nearest(src, 49, 3)[0, 24] == 1
    assert source_pixels(195, 100)[58] == 30
    for size, source in ((49, 2), (195, 100), (1300, 700), (700, 1300), (37, 1), (1, 37), (97, 89)):
        exact = [int(Fraction(2 * x + 1, 2) * source // size) for x in range(size)]  # ⌊(x + ½)·W/width⌋ in exact rationals
        assert source_pixels(size, source).tolist() == [min(e, source - 1) for e in exact], (size, source)


def test_mask_maps_of_another_aspect_ratio_are_refused_not_stretched(tmp_path):
    """Uniform scales (half resolution, odd sizes rounded down) are resampled; a transposed or cropped
    map is one error naming the _s.npy file and both sizes (was: stretched silently)."""
    from drsplat.registration.views import load_view_features

    rng = np.random.default_rng(7)
    cam = Camera(R=np.eye(3), t=np.zeros(3), fx=60.0, fy=60.0, cx=50.0, cy=37.0, width=101, height=75, name="a")
    feats = rng.normal(size=(4, 3)).astype(np.float32)
    for h, w in ((75, 101), (37, 50), (18, 25), (150, 202), (2, 3)):
        write_features(tmp_path, "a", rng.integers(-1, 4, size=(h, w)), feats)
        assert load_view_features(tmp_path, cam, 0)[0].shape == (75, 101)
    for h, w in ((101, 75), (75, 90), (60, 101), (18, 30)):
        write_features(tmp_path, "a", rng.integers(-1, 4, size=(h, w)), feats)
        with pytest.raises(InputError, match=rf"a_s.npy: field 'shape': mask map is {w}x{h} .* camera 'a' is 101x75"):
            load_view_features(tmp_path, cam, 0)


def test_bool_mask_maps_are_refused(tmp_path):
    """Was: False read as mask 0, True as mask 1."""
    np.save(seg_path(tmp_path, "a"), np.ones((6, 8), bool))
    np.save(feat_path(tmp_path, "a"), np.ones((2, 3), np.float32))
    with pytest.raises(InputError, match="a_s.npy: field 'dtype': mask ids have dtype bool, expected integers or floats"):
        read_features(tmp_path, "a")


def test_manifest_round_trip_and_errors(tmp_path):
    assert read_manifest(tmp_path) == {}
    manifest = {"mask_generator": "oracle", "clip": {"model": "ViT-B-16", "pretrained": "laion2b_s34b_b88k"}, "params": {"levels": 4}}
    write_manifest(tmp_path, manifest)
    assert read_manifest(tmp_path) == manifest
    (tmp_path / "manifest.json").write_text("{broken")
    with pytest.raises(InputError, match="manifest.json.*not valid JSON"):
        read_manifest(tmp_path)


def test_feature_headers_are_checked_up_front_and_missing_files_left_to_their_reader_on_ray(tmp_path):
    """read_feature_headers gives D and the mask counts; a missing view file is an error here, and with missing_ok (on
    Ray, where a worker reads it) skipped, unless no view is left to give D."""
    from drsplat.registration.views import read_feature_headers

    rng = np.random.default_rng(8)
    cams = [Camera(R=np.eye(3), t=np.zeros(3), fx=60.0, fy=60.0, cx=20.0, cy=15.0, width=40, height=30, name=f"v{i}") for i in range(3)]
    for cam in cams:
        write_features(tmp_path, cam.name, rng.integers(-1, 4, size=(4, 15, 20)), rng.normal(size=(4, 7)).astype(np.float32))
    headers = read_feature_headers(tmp_path, cams, 1)
    assert (headers.dim, headers.max_masks, headers.total_masks) == (7, 4, 12)
    with pytest.raises(InputError, match="v0_s.npy: field 'shape': level 4 requested but the file has 4 levels"):
        read_feature_headers(tmp_path, cams, 4)
    feat_path(tmp_path, "v0").unlink()
    with pytest.raises(InputError, match="v0_f.npy: file not found"):
        read_feature_headers(tmp_path, cams, 1)
    assert read_feature_headers(tmp_path, cams, 1, missing_ok=True).dim == 7
    with pytest.raises(InputError, match="v0_f.npy: file not found"):
        read_feature_headers(tmp_path, cams[:1], 1, missing_ok=True)


@pytest.mark.parametrize("field", ["clip_model_id", "clip.model", "clip.pretrained", "clip"])
def test_a_manifest_clip_model_with_a_control_character_is_refused_naming_the_field(tmp_path, field):
    """Was: register copied `clip_model_id` = "x<ESC>[2J<LF>ERROR: forged" into the registered PLY's
    header (exit 0), and query then refused that PLY as altered. Now reading the manifest refuses
    it, naming manifest.json and the field, in one line that carries no control character itself."""
    manifest = {"mask_generator": "oracle", "clip_model_id": "ViT-B-16/laion2b_s34b_b88k",
                "clip": {"model": "ViT-B-16", "pretrained": "laion2b_s34b_b88k"}}
    write_manifest(tmp_path, manifest)
    assert read_manifest(tmp_path) == manifest
    forged = "x\u001b[2J\nERROR: forged"
    if field == "clip":
        manifest["clip"] = forged
    elif "." in field:
        manifest["clip"][field.split(".")[1]] = forged
    else:
        manifest[field] = forged
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError) as caught:
        read_manifest(tmp_path)
    message = str(caught.value)
    assert f"manifest.json: field '{field}'" in message and "control character (U+001B)" in message
    assert "\x1b" not in message and "\n" not in message
    elsewhere = tmp_path / "other"  # `features --clip-checkpoint W --pretrained TAG` takes any TAG: its writer refuses it too
    with pytest.raises(OutputError, match=rf"cannot write .*manifest\.json: field '{field}': .* holds a control character \(U\+001B\)"):
        write_manifest(elsewhere, manifest)
    assert not elsewhere.exists()


@pytest.mark.parametrize("forged, words", [("oracle\u2028ERROR: forged", "line separator character (U+2028)"),
                                           ("oracle\u2029x", "paragraph separator character (U+2029)"),
                                           ("V" * 100_000, "100,000 characters long")])
def test_a_manifest_clip_model_a_log_would_split_or_that_is_huge_is_refused(tmp_path, forged, words):
    """Was (a second probe, 2026-12-01): U+2028 in `clip_model_id` reached the registered PLY's header
    and `info`'s output raw (log viewers break the line there: a forged second line), and a
    100,000-character id was accepted and printed whole. Now both are refused by the manifest's reader."""
    (tmp_path / "manifest.json").write_text(json.dumps({"mask_generator": "oracle", "clip_model_id": forged}))
    with pytest.raises(InputError) as caught:
        read_manifest(tmp_path)
    message = str(caught.value)
    assert "field 'clip_model_id'" in message and words in message and len(message) < 600, message
    assert "\u2028" not in message and "\u2029" not in message


def test_a_manifest_that_is_a_link_to_nothing_is_an_error_not_no_manifest(tmp_path):
    """Was: a dangling manifest.json link passed for "no manifest" (exit 0, the CLIP model then
    'unknown'); a link to nothing says so now."""
    (tmp_path / "manifest.json").symlink_to(tmp_path / "gone.json")
    with pytest.raises(InputError, match=r"manifest\.json: is a symbolic link to nothing"):
        read_manifest(tmp_path)
    assert read_manifest(tmp_path / "none") == {}


def test_float_mask_ids_beyond_int64_name_the_stored_value_without_a_numpy_warning(tmp_path):
    """Was: 1e300 ids gave numpy's 'invalid value encountered in cast' and then 'mask ids must be >= -1,
    found -9223372036854775808', a value the file does not hold. Now one error with the real value."""
    rng = np.random.default_rng(9)
    seg, feats = langsplat_like(rng)
    np.save(feat_path(tmp_path, "o"), feats)
    huge = seg.astype(np.float64)
    huge[1, :2, :5] = 1e300
    np.save(seg_path(tmp_path, "o"), huge)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match=r"o_s\.npy: 10 mask ids are beyond any embedding row \(largest 1e\+300\)"):
            read_features(tmp_path, "o", level=1)
        huge[1, :2, :5] = -1e300
        np.save(seg_path(tmp_path, "o"), huge)
        with pytest.raises(InputError, match=r"o_s\.npy: mask ids must be >= -1, found -1e\+300"):
            read_features(tmp_path, "o", level=1)
        half = seg.astype(np.float16)
        half[0, 0, 0] = np.finfo(np.float16).max  # whole, but no row: the usual message, without an overflow warning on the way
        np.save(seg_path(tmp_path, "o"), half)
        with pytest.raises(InputError, match=r"o_s\.npy: mask id 65504 at level 0 is out of range"):
            read_features(tmp_path, "o", level=0)
        wide = seg.astype(np.longdouble)  # a second probe: 2^63 - 1 held exactly, which float() rounds up to 2^63
        wide[0, 0, 0] = np.longdouble(2) ** 63 - 1
        np.save(seg_path(tmp_path, "o"), wide)
        with pytest.raises(InputError, match=r"o_s\.npy: mask id 9223372036854775807 at level 0 is out of range"):
            read_features(tmp_path, "o", level=0)
        np.save(seg_path(tmp_path, "o"), seg.astype(np.float64))
        np.testing.assert_array_equal(read_features(tmp_path, "o", level=1)[0], seg[1])


def test_huge_ids_of_overlapping_levels_are_refused_not_wrapped_into_valid_rows(tmp_path):
    """Was: with a level-0 id of 2^63 - 1, the int64 offset of the next (restarting) level wrapped,
    and its ids 2^62 + 5 and 0 came back as rows 5 and 0 (exit 0, wrong masks). Now one error naming
    the stored id and the offset."""
    seg = np.full((2, 4, 4), -1, np.int64)
    seg[0, 0, 0] = 2**63 - 1
    seg[1, 0, 0] = 2**62 + 5
    seg[1, 1, 1] = 0
    np.save(seg_path(tmp_path, "w"), seg)
    np.save(feat_path(tmp_path, "w"), np.eye(8, 4, dtype=np.float32))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # since round 85d F5 any level's id past the embeddings is refused first, whichever level is read
        with pytest.raises(InputError, match=rf"w_s\.npy: mask id {2**63 - 1} at level 0 is out of range"):
            read_features(tmp_path, "w", level=1)
    seg[0, 0, 0], seg[1, 0, 0] = 3, 5  # restarting levels: level 1's id 5 is row 4 + 5, past the 8
    np.save(seg_path(tmp_path, "w"), seg)
    with pytest.raises(InputError, match=r"w_s\.npy: mask id 5 at level 1 \(9 once offset by the 4 ids of the levels before it\) is out of range"):
        read_features(tmp_path, "w", level=1)


@pytest.mark.parametrize("bad_level", [0, 3])
def test_an_id_past_the_embeddings_at_a_level_not_read_is_refused_naming_it(tmp_path, bad_level):
    """Round 85d F5: level 0's ids all 999 (24 embeddings) made the levels' ranges overlap, and reading level 1 blamed
    its valid id 11 ("1011 once offset"); a 999 at level 3 passed without a word. An id ≥ M is no row in either reading
    of the levels: refused first, naming its level."""
    seg = np.full((4, 4, 4), -1, np.int64)
    for lvl in range(4):
        seg[lvl, lvl, :] = [6 * lvl, 6 * lvl + 1, 6 * lvl + 2, 6 * lvl + 5]  # cumulative ids, 6 masks a level
    seg[bad_level, seg[bad_level] >= 0] = 999
    np.save(seg_path(tmp_path, "v"), seg)
    np.save(feat_path(tmp_path, "v"), np.eye(24, 8, dtype=np.float32) + 0.1)
    with pytest.raises(InputError, match=rf"v_s\.npy: mask id 999 at level {bad_level} is out of range: v_f\.npy has only 24 embeddings"):
        read_features(tmp_path, "v", level=1)


def test_embeddings_of_another_dimension_name_the_odd_file_not_the_first_view(tmp_path):
    """Round 39: with the first view's embeddings stored transposed, the error blamed the second view's good file
    ("orbit_001_f.npy: embeddings are 512-D but orbit_000_f.npy has 32-D ones"); the file of the fewest views is named."""
    from drsplat.registration.views import read_feature_headers

    rng = np.random.default_rng(9)
    cams = [Camera(R=np.eye(3), t=np.zeros(3), fx=60.0, fy=60.0, cx=20.0, cy=15.0, width=40, height=30, name=f"v{i}") for i in range(4)]
    for cam in cams:
        write_features(tmp_path, cam.name, rng.integers(-1, 6, size=(4, 15, 20)), rng.normal(size=(6, 16)).astype(np.float32))
    np.save(feat_path(tmp_path, "v0"), np.load(feat_path(tmp_path, "v0")).T.copy())  # 16 x 6: stored transposed
    with pytest.raises(InputError, match=r"v0_f.npy: field 'shape': embeddings are 6-D but v1_f.npy has 16-D ones \(as have 3 of the 4 "
                                         r"views\).*stored transposed"):
        read_feature_headers(tmp_path, cams, 1)


def test_a_pair_whose_other_file_is_write_protected_is_left_whole(tmp_path):
    """Round 60c: with img_s.npy write-protected, writing the pair replaced img_f.npy first and then refused img_s.npy: a
    new _f beside an old _s, which `is_valid_pair` accepts when their row counts agree. Both are checked before either."""
    from drsplat.errors import OutputError

    rng = np.random.default_rng(0)
    seg, feats = langsplat_like(rng)
    write_features(tmp_path, "img", seg, feats)
    before = {p.name: p.read_bytes() for p in tmp_path.glob("img_*.npy")}
    (tmp_path / "img_s.npy").chmod(0o444)
    try:
        with pytest.raises(OutputError, match=r"img_s.npy: exists and is write-protected"):
            write_features(tmp_path, "img", seg, feats * 0 + feats[::-1])
    finally:
        (tmp_path / "img_s.npy").chmod(0o644)
    assert {p.name: p.read_bytes() for p in tmp_path.glob("img_*.npy")} == before



def test_levels_restarting_at_0_whose_counts_miss_an_embedding_are_refused_not_shifted(tmp_path):
    """Round 63a: in a file whose level ids restart at 0, level 0's last mask (id 9 of 10) covered no pixel, so
    level 0 was read as 9 masks and level 1's ids 0..4 as rows 9..13 instead of 10..14: every level-1 pixel got
    the embedding of the mask before its own, silently. Now one error naming the counts; when they add up to the
    embeddings, the levels are read as before."""
    seg = np.full((2, 6, 10), -1, np.int32)
    seg[0] = np.arange(60).reshape(6, 10) % 9  # masks 0..8 of level 0's 10
    seg[1] = np.arange(60).reshape(6, 10) % 5
    np.save(seg_path(tmp_path, "x"), seg)
    np.save(feat_path(tmp_path, "x"), np.eye(16, dtype=np.float32)[:15])
    with pytest.raises(InputError, match=r"x_s\.npy: its 2 levels' mask ids each start at 0.*\(9 \+ 5 = 14\); but x_f\.npy holds 15 "
                                         r"embeddings.*which rows are level 1's cannot be told"):
        read_features(tmp_path, "x", level=1)
    np.testing.assert_array_equal(read_features(tmp_path, "x", level=0)[0], seg[0])  # level 0 needs no offset
    np.save(feat_path(tmp_path, "x"), np.eye(16, dtype=np.float32)[:14])
    ids, feats = read_features(tmp_path, "x", level=1)
    np.testing.assert_array_equal(ids, seg[1] + 9)
