"""Which views a registration uses: cameras paired with LangSplat feature files by image stem.

Owns the pairing rule (camera name == feature stem, in Unicode NFC), the warnings that count what is
skipped, the check of every view's headers before the pass (and D read from them), and loading one
view's mask ids resampled to its camera (a uniform scale only).
"""

from __future__ import annotations

import dataclasses
import logging
import unicodedata
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drsplat.cameras import ASPECT_TOLERANCE, EXIF_TURNS, Camera, exif_orientation, lens_corner_shift, same_aspect
from drsplat.errors import InputError
from drsplat.features.masks.base import LEVELS
from drsplat.features.format import (FEAT_SUFFIX, SEG_SUFFIX, STAMP_JOURNAL, check_feat_layout, check_seg_layout, feat_path, irregular_feature_entries,
                                     list_stems, read_features_report, resample_nearest, seg_path)
from drsplat.utils import npy_header
from drsplat.scene import counted

log = logging.getLogger(__name__)

COARSE_SCALE = 16  # a mask map under 1/16 of its camera's side (one mask pixel for more than 16x16 view pixels) is warned of
COARSE_SIDE = 8  # as is one under 8 pixels a side that is smaller than its camera (the tiny preset's 1/8 map is 16x12: quiet)
ROUNDING_SIDE = 2  # a map side under 2 pixels gets no one-pixel rounding allowance in the aspect check (`map_fits_camera`)


@dataclass
class ViewSelection:
    """views: cameras with features, in camera order; missing: camera names without a feature
    file; unmatched: feature stems without a camera; renamed: (camera name, feature stem) of the
    views paired by another spelling than their camera's name (which the view then takes)."""

    views: list[Camera]
    missing: list[str] = field(default_factory=list)
    unmatched: list[str] = field(default_factory=list)
    renamed: list[tuple[str, str]] = field(default_factory=list)


def name_key(name: str) -> str:
    """A name as cameras and feature files are paired: in Unicode NFC. A folder copied from macOS
    (its file system, or a zip made there) holds names decomposed ("o" + U+0301), Linux tools and
    camera files write them composed ("ó"): two spellings of one name that look the same in every
    message (round 51: 14 of 16 views dropped, both warnings listing identical-looking names)."""
    return unicodedata.normalize("NFC", name)


def stems_by_key(stems: Iterable[str]) -> dict[str, list[str]]:
    """The feature stems grouped by `name_key`: a group of two is two files one name could mean."""
    groups: dict[str, list[str]] = {}
    for stem in stems:
        groups.setdefault(name_key(stem), []).append(stem)
    return groups


def feature_stem(name: str, available: set[str], by_key: dict[str, list[str]] | None = None) -> str | None:
    """The feature stem of the camera image stem `name`: `name` itself, else the name up to its first
    dot, the stem LangSplat's preprocess.py names its files by (`name.split('.')[0]`, as 3DGS names
    its cameras: "frame-000000.color.png" -> frame-000000_s.npy), or None. Each is taken as spelled,
    else the one stem equal to it in Unicode NFC (`name_key`; by_key: `stems_by_key(available)`):
    two stems of that form are two files, and whose is unknown, so neither is taken."""
    by_key = stems_by_key(available) if by_key is None else by_key
    for candidate in dict.fromkeys((name, name.split(".")[0])):
        if candidate in available:
            return candidate
        same = by_key.get(name_key(candidate), [])
        if len(same) == 1:
            return same[0]
    return None


def pair_views(cameras: Sequence[Camera], stems: Sequence[str]) -> ViewSelection:
    """Match cameras to feature files by image stem (`feature_stem`); a view paired by another
    spelling (LangSplat's stem, or the name in another Unicode normalisation) takes the stem as its
    name, by which its files are read."""
    available = set(stems)
    by_key = stems_by_key(available)
    keys = [feature_stem(c.name, available, by_key) for c in cameras]
    shorts = Counter(k for c, k in zip(cameras, keys) if k is not None and k != c.name)
    names = {c.name for c in cameras}
    # a stem that two images cut to (or spell alike), or that another camera is named: whose files they are is unknown, so
    # no other spelling takes them
    keys = [None if k is not None and k != c.name and (shorts[k] > 1 or k in names) else k for c, k in zip(cameras, keys)]
    used = {k for k in keys if k is not None}
    return ViewSelection(
        views=[c if k == c.name else dataclasses.replace(c, name=k) for c, k in zip(cameras, keys) if k is not None],
        missing=[c.name for c, k in zip(cameras, keys) if k is None],
        unmatched=sorted(s for s in stems if s not in used),
        renamed=[(c.name, k) for c, k in zip(cameras, keys) if k is not None and k != c.name],
    )


def spelling_hint(missing: Sequence[str], unmatched: Sequence[str]) -> str:
    """'; ...' naming a camera without features and a feature stem without a camera that are one name
    ignoring case (images ORBIT_000.JPG, files orbit_000_s.npy: pairing is case-sensitive, as the file
    systems of Linux are), or that spell alike in Unicode NFC but are not paired because several files
    do (`feature_stem`), or two cameras that name one feature file (`pair_views`); '' when there is none."""
    by_key = stems_by_key(unmatched)
    folded: dict[str, list[str]] = {}
    for stem in unmatched:
        folded.setdefault(name_key(stem).casefold(), []).append(stem)
    # the cameras by the key of their name up to its first dot, made once: a scan of `missing` per camera was
    # quadratic (round 54: 20,000 cameras without features spent 52 s here)
    missing_by_key: dict[str, list[str]] = {}
    for m in missing:
        missing_by_key.setdefault(name_key(m.split(".")[0]), []).append(m)
    for name in missing:
        for candidate in dict.fromkeys((name, name.split(".")[0])):
            alike = by_key.get(name_key(candidate), [])
            if len(alike) > 1:
                return (f"; camera {ascii(name)} has {len(alike)} feature files of its name in different Unicode encodings "
                        f"({', '.join(ascii(s + SEG_SUFFIX) for s in alike[:3])}): whose they are is unknown, so none is used")
            others = [m for m in missing_by_key.get(name_key(alike[0]), []) if m != name] if alike else []
            if len(alike) == 1 and others:  # its file is there: two cameras took it (`pair_views`), not a spelling
                return (f"; cameras {ascii(name)} and {ascii(others[0])} both name the feature file "
                        f"{ascii(alike[0] + SEG_SUFFIX)} (by the name up to its first dot, or spelled alike): whose it is is unknown, "
                        "so neither takes it")
            cased = [stem for stem in folded.get(name_key(candidate).casefold(), []) if name_key(stem) != name_key(candidate)]
            if cased:
                return (f"; camera '{name}' and {cased[0]}{SEG_SUFFIX} match ignoring case, but names are paired case-sensitively: "
                        "rename the images or the feature files to one spelling")
    return ""


def _unsaid(*args, **kwargs) -> None:
    """A log call left unsaid (`select_views(quiet=True)`)."""


def select_views(cameras: Sequence[Camera], features_dir: Path, quiet: bool = False) -> ViewSelection:
    """`pair_views` on the feature folder, with the warnings and the error when nothing matches. quiet: the
    warnings and notes left unsaid, for a check whose run selects the views again and says them then."""
    warning, info = (_unsaid, _unsaid) if quiet else (log.warning, log.info)
    stems = list_stems(features_dir)
    irregular = irregular_feature_entries(features_dir)
    if irregular:
        warning("%s of %s named like feature files %s (a folder, a device, a broken link) and %s skipped: %s",
                counted(len(irregular), "entry", "entries"), features_dir, "is not a regular file" if len(irregular) == 1 else "are not regular files",
                "is" if len(irregular) == 1 else "are", ", ".join(irregular[:3]))
    halves = sorted(set(stems) ^ set(list_stems(features_dir, FEAT_SUFFIX)))
    if halves:  # a pair cut short by an interrupted copy, or a file deleted: skipped like a missing pair, and said
        one = len(halves) == 1
        warning("%s in %s %s incomplete (a %s without its %s, or the reverse) and skipped (e.g. %s); rerun `drsplat features` to "
                "complete %s", counted(len(halves), "feature pair", "feature pairs"), features_dir, "is" if one else "are", SEG_SUFFIX,
                FEAT_SUFFIX, ", ".join(halves[:3]), "it" if one else "them")
        stems = [stem for stem in stems if stem not in set(halves)]
    if not stems:
        raise InputError(features_dir, "no LangSplat feature files (<stem>_s.npy + <stem>_f.npy) in this folder")
    sel = pair_views(cameras, stems)
    hint = spelling_hint(sel.missing, sel.unmatched)
    unpaired = [name for name in sel.missing if name not in halves and name.split(".")[0] not in halves]  # the halves are said above
    if unpaired:
        warning("%d of %d cameras %s no feature file in %s and %s skipped (e.g. %s)%s", len(unpaired), len(cameras),
                "has" if len(unpaired) == 1 else "have", features_dir, "is" if len(unpaired) == 1 else "are", ", ".join(unpaired[:3]), hint)
    if (features_dir / STAMP_JOURNAL).exists():  # `features` folds its journal into the manifest when it finishes
        warning("%s holds the journal of a `drsplat features` run that has not finished (%s): it is still writing or was stopped, "
                "so views may be missing; rerun `drsplat features` into the folder to finish it, then register", features_dir, STAMP_JOURNAL)
    renamed = [stem for name, stem in sel.renamed if name_key(stem) != name_key(name)]
    if renamed:
        info("%s feature files by the image name up to its first dot, as LangSplat names them (e.g. %s)",
             counted(len(renamed), "camera matched its", "cameras matched their"), ", ".join(renamed[:3]))
    respelled = [(name, stem) for name, stem in sel.renamed if stem not in (name, name.split(".")[0])]
    if respelled:
        info("%s feature files only in Unicode NFC, the names' accents being encoded differently (e.g. camera "
             "%s, file %s), as in a folder copied from macOS", counted(len(respelled), "camera matched its", "cameras matched their"), ascii(respelled[0][0]), ascii(respelled[0][1] + SEG_SUFFIX))
    if sel.unmatched:
        warning("%s in %s %s (e.g. %s)", counted(len(sel.unmatched), "feature file", "feature files"), features_dir,
                "matches no camera and is ignored" if len(sel.unmatched) == 1 else "match no camera and are ignored", ", ".join(sel.unmatched[:3]))
    duplicates = len(sel.views) - len({c.name for c in sel.views})
    if duplicates:
        warning("%s an image name with another camera; each uses that image's features", counted(duplicates, "camera shares", "cameras share"))
    copies = same_camera_copies(sel.views)
    if copies:
        warning("%s the very pose, intrinsics and size of another view (e.g. %s and %s): each counts as a view of its "
                "own, so what a copied view's masks say counts twice in the cross-view check; drop the copies from the "
                "dataset if they are one photo", counted(len(copies), "view has", "views have"), copies[0][0], copies[0][1])
    if not sel.views:
        raise InputError(
            features_dir,
            f"no feature file matches a camera image stem (cameras: {', '.join(c.name for c in cameras[:3])}...; "
            f"features: {', '.join(stems[:3])}...){hint}",
        )
    return sel


def far_coarser(w: int, h: int, cam: Camera) -> bool:
    """True when a w x h mask map is far coarser than camera `cam`: smaller than it, and under
    1/COARSE_SCALE of its width or height, or under COARSE_SIDE pixels a side. Maps of 1/2, 1/4 and
    1/8 of the camera register well (round 51, 256x192 views: seg mIoU 0.98, 0.95, 0.89 against 0.96
    at full size), one of 1/64 does not (0.28): each of its pixels stands for 64x64 view pixels."""
    if w >= cam.width and h >= cam.height:
        return False
    return w * COARSE_SCALE < cam.width or h * COARSE_SCALE < cam.height or min(w, h) < COARSE_SIDE


def far_coarser_note(coarse: Sequence[CoarseMap], views: int) -> str | None:
    """The warning, or None, for the mask maps far coarser than their cameras (`far_coarser`) among
    `views` views: they are resampled to the camera like any smaller map, and the masks of a 4x3 map
    for a 256x192 camera lost most of what they said (round 51: seg mIoU 0.96 -> 0.28, without a word)."""
    if not coarse:
        return None
    first = coarse[0]
    return (f"{len(coarse)} of {views} views' mask maps are far coarser than their cameras (e.g. {first.file}: field 'shape': mask map "
            f"{first.width}x{first.height} for a {first.camera_width}x{first.camera_height} camera, each mask pixel covering "
            f"{first.camera_width / first.width:.3g}x{first.camera_height / first.height:.3g} view pixels): their masks are resampled to "
            f"the camera and lose their shapes; make the masks at the camera's size, or at least 1/{COARSE_SCALE} of it")


def same_camera_copies(views: Sequence[Camera]) -> list[tuple[str, str]]:
    """(earlier view's name, later view's name) for every view whose R, t, intrinsics and size equal
    an earlier view's bit for bit: a dataset listing one photo twice (round 41: the cross-view check
    took a copied view's votes as a second view's and kept a mislabelled mask it had dropped)."""
    first: dict[tuple, str] = {}
    copies = []
    for c in views:
        key = c.exact_key()
        if key in first:
            copies.append((first[key], c.name))
        else:
            first[key] = c.name
    return copies


def warn_if_distorted_without_manifest(views: Sequence[Camera], manifest: dict, features_dir: Path) -> None:
    """One warning when views have lens distortion and the features folder has no drsplat manifest.

    `drsplat features` undistorts the photos before segmenting them, so its masks lie on the pinhole
    camera's pixels, which registration projects through. A folder without a manifest holds another
    tool's features (LangSplat's preprocess segments the photos as stored): their masks are off by the
    lens's shift, most at the corners (`lens_corner_shift`)."""
    distorted = [c for c in views if c.distortion is not None]
    if manifest or not distorted:
        return
    worst = max(distorted, key=lens_corner_shift)
    log.warning("%d of %d views have lens distortion and %s has no drsplat manifest: features made by another tool (LangSplat's "
                "preprocess) are masks of the distorted photos, but registration projects through the undistorted pinhole camera, so "
                "masks land up to %.1f px off at the corners (%s); undistort the images before segmenting them, or make the features with "
                "`drsplat features`, which does", len(distorted), len(views), features_dir, lens_corner_shift(worst), worst.name)


def warn_if_turned_without_manifest(views: Sequence[Camera], manifest: dict, features_dir: Path) -> None:
    """One warning when views' photos carry an EXIF orientation other than upright and the features
    folder has no drsplat manifest.

    3DGS, COLMAP and registration read a photo's pixels as stored; LangSplat's preprocess reads them
    with cv2.imread, which applies the orientation, so its masks of a photo marked as turned 180°
    are upside down against the camera, with the very same shape (no size check can see it; one
    turned by 90° has its sides swapped, which the header check refuses). `drsplat features` reads
    the pixels as stored. Only the files' headers are read."""
    if manifest:
        return
    turned = [(c, orientation) for c in views if (orientation := exif_orientation(c.image_path)) != 1]
    if not turned:
        return
    camera, orientation = turned[0]
    log.warning("%d of %d views' photos carry an EXIF orientation (%s: %s) and %s has no drsplat manifest: features made by another "
                "tool that reads photos with OpenCV (LangSplat's preprocess) are masks of the photos as the tag shows them, while "
                "registration projects onto the pixels as stored, so its masks lie %s against the cameras; store the pixels upright "
                "(e.g. `mogrify -auto-orient`) and rebuild the cameras from them, or make the features with `drsplat features`",
                len(turned), len(views), camera.name, EXIF_TURNS[orientation], features_dir, EXIF_TURNS[orientation])


@dataclass(frozen=True)
class CoarseMap:
    """A view's mask map far coarser than its camera (`far_coarser`): the file's name and both sizes."""

    file: str
    width: int
    height: int
    camera_width: int
    camera_height: int


@dataclass
class FeatureHeaders:
    """What the views' feature-file headers say: dim, D of the embeddings; max_masks, the most masks
    (rows of embeddings) one view has; total_masks, their sum over the views read."""

    dim: int
    max_masks: int
    total_masks: int
    levels: dict[str, int] = field(default_factory=dict)  # mask-id file name -> its levels (`single_level_note`)
    coarse: list[CoarseMap] = field(default_factory=list)  # the maps far coarser than their camera (`far_coarser_note`)


def read_feature_headers(features_dir: Path, views: Sequence[Camera], level: int, missing_ok: bool = False) -> FeatureHeaders:
    """The views' FeatureHeaders, after every view's two headers are checked (nothing loaded).

    Before any view is rendered, so that a bad file stops a registration at once rather than hours
    into it: each file's layout is the format's (`check_seg_layout`, `check_feat_layout`, the rules
    the read path applies), the mask map's H x W a uniform scale of the camera's (`same_aspect`),
    and every D the first view's. `npy_header` has already held each shape against its file's size.
    What a header cannot tell (ids past M, non-finite values) is found when the view is read.
    About 0.1 ms a view. missing_ok: a view whose file is not here is left to the process that
    reads it (on Ray, a worker node: the driver need not hold every view's files), as long as one
    view gives D.
    """
    dim, first, max_masks, total_masks = 0, None, 0, 0
    dims: dict[int, list[Path]] = {}  # D -> the embedding files of that D
    levels: dict[str, int] = {}  # mask-id file name -> its levels
    coarse: list[CoarseMap] = []
    for cam in views:
        spath, fpath = seg_path(features_dir, cam.name), feat_path(features_dir, cam.name)
        if missing_ok and not (spath.is_file() and fpath.is_file()):
            continue
        s_shape, s_dtype, _ = npy_header(spath)
        check_seg_layout(spath, s_shape, s_dtype, level)
        levels[spath.name] = int(s_shape[0]) if len(s_shape) == 3 else 1
        check_aspect(spath, s_shape[-1], s_shape[-2], cam)
        if far_coarser(s_shape[-1], s_shape[-2], cam):
            coarse.append(CoarseMap(spath.name, int(s_shape[-1]), int(s_shape[-2]), cam.width, cam.height))
        f_shape, f_dtype, _ = npy_header(fpath)
        check_feat_layout(fpath, f_shape, f_dtype)
        max_masks, total_masks = max(max_masks, int(f_shape[0])), total_masks + int(f_shape[0])
        dims.setdefault(int(f_shape[1]), []).append(fpath)
        if first is None:
            dim, first = int(f_shape[1]), fpath
    if len(dims) > 1:  # the files of the fewest views are the odd ones (a transposed file, another model's), not the first view's D
        common = max(dims, key=lambda d: len(dims[d]))
        odd = min((d for d in dims if d != common), key=lambda d: len(dims[d]))
        fpath = dims[odd][0]
        raise InputError(fpath, f"embeddings are {odd}-D but {dims[common][0].name} has {common}-D ones (as have {len(dims[common])} of the "
                                f"{sum(map(len, dims.values()))} views): one registration reads one model's features (a folder mixing two CLIP "
                                "models, or an embedding file stored transposed?)", field="shape")
    if first is None and views:  # every view's files missing here
        npy_header(feat_path(features_dir, views[0].name))  # the error naming the first view's file
    return FeatureHeaders(dim, max_masks, total_masks, levels, coarse)


def single_level_note(levels: dict[str, int], level: int) -> str | None:
    """The warning, or None, for mask-id files (name -> levels) that mix one level with several when
    `level` is not 0.

    A single-level file serves every level (`check_seg_layout`): right in a folder of single-level
    files, but beside files of 4 levels it is one scale of masks standing in for level `level` of
    the others (round 51: a view's level-1 masks served `--level 3` without a word, while a file of
    3 levels was refused). At level 0 its one level is the level asked for."""
    single = sorted(name for name, count in levels.items() if count == 1)
    multi = Counter(count for count in levels.values() if count > 1)
    if level == 0 or not single or not multi:
        return None
    counts = sorted(multi)
    several = str(counts[0]) if len(counts) == 1 else f"{counts[0]} to {counts[-1]}"
    if len(single) == 1:
        return (f"{single[0]} has one level; the other {multi.total()} views have {several}: it is used as level {level}, a mask "
                "scale of its own beside the others' (remake its features with all levels, or register those with one)")
    return (f"{len(single)} views' mask files have one level ({', '.join(single[:3])}{', ...' if len(single) > 3 else ''}); the other "
            f"{multi.total()} views have {several}: their one level is used as level {level}, a mask scale of its own beside the "
            "others' (remake their features with all levels, or register those with one)")


def level_count_note(levels: dict[str, int], level: int) -> str | None:
    """The warning, or None, for mask-id files (name -> levels) of several levels whose layout is not
    LangSplat's four (default, s, m, l), or not one layout in every view: `level` picks each file's
    level of that index, which is LangSplat's scale of that name only in its four-level layout (round
    100c F1: a folder of 3-level files, read as s, m, l, gave its m masks for the default level s,
    and a folder mixing 3 and 4 levels one view's s masks beside another's m, without a word).
    Single-level files are `single_level_note`'s."""
    multi = Counter(count for count in levels.values() if count > 1)
    if not multi or set(multi) == {len(LEVELS)}:
        return None
    named = f" (LangSplat's '{LEVELS[level]}' only in files of {len(LEVELS)} levels)" if level < len(LEVELS) else ""
    if len(multi) == 1:
        (count, views), = multi.items()
        return (f"the mask files of {counted(views, 'view', 'views')} have {count} levels, not LangSplat's {len(LEVELS)} ({', '.join(LEVELS)}): "
                f"level {level} is read as each file's level {level} by index, whatever mask scale it holds there{named}")
    # the layout most views have (LangSplat's on a tie); the others' files are named (round 104a F3)
    usual = max(sorted(multi), key=lambda count: (multi[count], count == len(LEVELS)))

    def layout(count: int, views: int) -> str:
        if count == usual:
            return f"{counted(views, 'view', 'views')} {count}"
        files = sorted(name for name, c in levels.items() if c == count)
        return f"{counted(views, 'view', 'views')} {count}: {', '.join(files[:3])}{', ...' if len(files) > 3 else ''}"

    layouts = "; ".join(layout(count, views) for count, views in sorted(multi.items()))
    return (f"the views' mask files have different numbers of levels ({layouts}): level {level} is each file's level {level} by index, "
            f"a different mask scale in files of another layout{named}; remake the features so every view has the same levels")


def check_aspect(path: Path, w: int, h: int, cam: Camera) -> None:
    """InputError unless a w x h mask map (from `path`) is camera `cam`'s image uniformly scaled (`map_fits_camera`)."""
    if not map_fits_camera(w, h, cam.width, cam.height):
        tiny = "; a map of 1 pixel a side cannot show its aspect, so no rounding excuses it" \
            if same_aspect(w, h, cam.width, cam.height) else " (a transposed or cropped map?)"
        raise InputError(path, f"mask map is {w}x{h} (width x height) but camera '{cam.name}' is {cam.width}x{cam.height}: "
                               f"aspect ratios {w / h:.4g} and {cam.width / cam.height:.4g} differ{tiny}; "
                               "only a uniform scale of the camera size is resampled", field="shape")


def map_fits_camera(w: int, h: int, width: int, height: int) -> bool:
    """True if a w x h mask map is the width x height camera image uniformly scaled: `same_aspect`, except
    that a map smaller than its camera with a side of 1 pixel (under ROUNDING_SIDE) must match within
    ASPECT_TOLERANCE. same_aspect allows a pixel of rounding per side, which for a 1-pixel side is a
    scale anywhere in (0, 2/size], so nearly any aspect (round 51: a 1x1 map passed for a 256x192
    camera, 1.0 against 1.333). A 2-pixel side keeps the allowance: 3x2 is 101x75 rounded, and is
    warned of as far coarser than its camera (`far_coarser`)."""
    if min(w, h) < ROUNDING_SIDE and (w < width or h < height):
        return abs((w / h) / (width / height) - 1.0) <= ASPECT_TOLERANCE
    return same_aspect(w, h, width, height)


def load_view_features(features_dir: Path, cam: Camera, level: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(mask ids [H, W] resampled to the camera size, feats [M, D] float32, masks dropped as non-finite).

    A mask map of another aspect ratio than the camera's is an error, not stretched: it is a
    transposed, cropped or foreign map (a uniform scale, e.g. half resolution, is resampled).
    """
    mask_ids, feats, nonfinite = read_features_report(features_dir, cam.name, level, drop_nonfinite=True)
    h, w = mask_ids.shape
    check_aspect(seg_path(features_dir, cam.name), w, h, cam)
    return resample_nearest(mask_ids, cam.width, cam.height), feats, nonfinite


def used_masks(mask_ids: np.ndarray) -> np.ndarray:
    """The mask ids that occur in a view's mask image (ViewPairs.used), ascending: [U] int32 from
    mask_ids [H, W] (negative: no mask); `np.unique(mask_ids[mask_ids >= 0])`, the reference. Not
    ViewPairs.present_masks, the masks that reached a Gaussian.

    Counted with a bincount over the pixels rather than sorted: the sort took ~6 ms of host time
    per 640x480 view on the H100 machine's slower cores, time in which the GPU waited (2026-11-27),
    the bincount a quarter of that. Ids past 4x the pixel count take the sort (the count table would
    outgrow the image).
    """
    flat = mask_ids.ravel()
    top = int(flat.max()) if flat.size else -1
    if top < 0:
        return np.zeros(0, np.int32)
    if top > 4 * flat.size:
        return np.unique(flat[flat >= 0]).astype(np.int32)
    return np.flatnonzero(np.bincount(flat[flat >= 0])).astype(np.int32)
