"""Feature extraction: per-image masks at four levels and one CLIP embedding per mask (LangSplat).

For each training image: masks (SAM or a weight-free generator, drsplat.features.masks) -> LangSplat's
post-processing (masks_update) -> one crop per mask (the masked bounding box, padded to a square,
resized to the encoder's input size, CLIP-normalised) -> CLIP image embeddings, batched ->
`<stem>_s.npy` (4, H, W) cumulative mask ids and `<stem>_f.npy` (M, D) float32 embeddings,
written atomically by drsplat.features.format. Valid existing pairs are skipped (resumable).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from drsplat.errors import DrsplatError, InputError, WeightsUnavailableError, shown_path
from drsplat.features import format as featurefiles
from drsplat.features.masks import LEVELS, make_generator, MaskSet
from drsplat.features.masks.postprocess import NmsParams, masks_update
from drsplat.features.modelid import (
    DEFAULT_MODEL,
    check_compatible,
    manifest_clip_entry,
    manifest_model_id,
    weights_digest,
)
from drsplat.utils import CancelToken, file_stamp, npy_header, odd_entry_kind, progress
import drsplat
from drsplat.cameras import detect_dataset, image_folder, load_cameras, load_image_sized, unobserved_pixels
from drsplat.features.clip import OPENAI_MEAN, OPENAI_STD, ClipEncoder, use_clip_config
from drsplat.features.masks.sam import SamParams, sam_checkpoint_file_problem
from drsplat.features.weights import sam_checkpoint_unavailable

log = logging.getLogger(__name__)

MAX_HEIGHT = 1080  # LangSplat rescales taller images to 1080 rows


@dataclass
class StageTimes:
    """Seconds spent per stage for one or more images."""

    masks: float = 0.0
    postprocess: float = 0.0
    crop: float = 0.0
    clip: float = 0.0

    def add(self, other: "StageTimes") -> None:
        for k, v in asdict(other).items():
            setattr(self, k, getattr(self, k) + v)

    @property
    def total(self) -> float:
        return self.masks + self.postprocess + self.crop + self.clip


@dataclass
class FeatureReport:
    """What `extract_features` did: stems written and skipped, masks per level, timings; workers:
    the Ray actors that extracted (0 in this process)."""

    written: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    redone: list[str] = field(default_factory=list)
    masks_per_level: list[int] = field(default_factory=lambda: [0] * len(LEVELS))
    nonfinite_embeddings: int = 0
    times: StageTimes = field(default_factory=StageTimes)
    workers: int = 0
    without_masks: list[str] = field(default_factory=list)  # written with no mask at all: registration gets nothing from them
    flat: list[str] = field(default_factory=list)  # images of one colour (blank exports, a fully transparent PNG's RGB)
    upsampled: list[tuple[str, str, float]] = field(default_factory=list)  # (stem, "file WxH to camera WxH", factor) past UPSAMPLE_NOTE
    off_size: list[tuple[str, str]] = field(default_factory=list)  # (stem, "file WxH for camera WxH"): not its size times 2^j
    unobserved: list[tuple[str, float]] = field(default_factory=list)  # (stem, share of its pixels): undistorted views' pixels no photo saw

    def notes(self) -> list[str]:
        """What a user should hear about the images written: those that gave no mask, those of one colour."""
        out = []
        if self.without_masks:
            out.append(f"{len(self.without_masks)} image(s) gave no mask at all ({listed(self.without_masks)}): registration gets nothing "
                       "from them (too few pixels at this --resolution / --max-height, or a blank image?); their feature files hold no "
                       "row, which LangSplat's own training cannot read (it indexes a row for the -1 of every pixel): leave them out "
                       "of a LangSplat run")  # round 96b F1
        if self.flat:
            out.append(f"{len(self.flat)} image(s) are one flat colour ({listed(self.flat)}): their masks and embeddings describe "
                       "nothing of the scene (a blank export, or a transparent image whose colour channels are empty?)")
        if self.upsampled:
            stem, sizes, factor = max(self.upsampled, key=lambda u: u[2])
            out.append(f"{len(self.upsampled)} image file(s) are over {UPSAMPLE_NOTE:g}x narrower than their cameras and were upsampled "
                       f"(the most: {stem}, {sizes}, {factor:.3g}x): their masks and crops hold no more detail than the files "
                       "(thumbnails, a lower-resolution export, or a --resolution above the images' own?)")
        if self.unobserved:
            stem, share = max(self.unobserved, key=lambda u: u[1])
            out.append(f"{len(self.unobserved)} undistorted view(s) hold pixels their photo never saw (the lens maps them outside the "
                       f"file; the most: {stem}, {100 * share:.3g} %): they got no mask, so they lift nothing")
        if self.off_size:
            stem, sizes = self.off_size[0]
            out.append(f"{len(self.off_size)} image file(s) are neither their camera's size nor a power-of-two fraction or multiple "
                       f"of it (as images_2, _4, _8 are, or full-size photos beside their cameras) and were resized to it (the first: {stem}, {sizes}): are they the photos from before "
                       "`colmap image_undistorter`, beside its cameras? Their lens distortion would then never be removed")
        return out


def listed(names: list[str], first: int = 3) -> str:
    """The first few names of a list, and how many more (the CLI's log escapes hidden characters in them)."""
    more = f" and {len(names) - first} more" if len(names) > first else ""
    return ", ".join(names[:first]) + more


UPSAMPLE_NOTE = 1.5  # an image file this many times narrower than its camera is counted as upsampled


def note_image(report: FeatureReport, cam, rgb: np.ndarray, file_size: tuple[int, int]) -> None:
    """Count in `report` an image of one flat colour (every pixel of rgb [H, W, 3], the image at its
    camera's size, the same), an image file (file_size: its stored width, height) over
    UPSAMPLE_NOTE times narrower than its camera, and one of neither its camera's size nor a
    power-of-two fraction or multiple of it (`off_power_of_two`: round 57b, the distorted photos beside the
    cameras of `colmap image_undistorter` were resized to them without a word)."""
    if rgb.size and (rgb == rgb.reshape(-1, rgb.shape[-1])[0]).all():
        report.flat.append(cam.name)
    width, height = file_size
    if width and cam.width > UPSAMPLE_NOTE * width:
        report.upsampled.append((cam.name, f"{width}x{height} to {cam.width}x{cam.height}", cam.width / width))
    if width and off_power_of_two(file_size, cam):
        report.off_size.append((cam.name, f"{width}x{height} for camera {cam.size_text()}"))


def off_power_of_two(file_size: tuple[int, int], cam) -> bool:
    """Whether an image file of file_size (width, height) is neither its camera's size (at the chosen resolution or
    the camera file's own) nor that size times 2^j within a pixel, |j| ≤ OFF_SIZE_POWERS: over 2^j, the downscaled
    copies images_2, _4, _8 and further that 3DGS tools write; times 2^j, full-resolution photos beside the cameras
    of such a copy (round 100c F2: a photo of exactly twice its camera's size was taken for one from before
    `colmap image_undistorter`, whose size differs by a few percent)."""
    own = tuple(cam.unscaled_size) if cam.unscaled_size is not None else (cam.width, cam.height)
    if tuple(file_size) == (cam.width, cam.height):
        return False
    return not any(abs(file_size[0] - own[0] * 2.0**j) <= 1 and abs(file_size[1] - own[1] * 2.0**j) <= 1
                   for j in range(-OFF_SIZE_POWERS, OFF_SIZE_POWERS + 1))


OFF_SIZE_POWERS = 5  # images_32 is the smallest downscaled copy counted as one (and 32x the largest multiple)


def square_pad_box(y0: int, y1: int, x0: int, x1: int) -> tuple[int, int]:
    """Offsets (dy, dx) placing an (y1-y0) x (x1-x0) crop centred in its l x l square, l = max side."""
    h, w = y1 - y0, x1 - x0
    side = max(h, w)
    return (side - h) // 2, (side - w) // 2


def crop_masks(image: np.ndarray, masks: np.ndarray, size: int = 224) -> np.ndarray:
    """LangSplat's crop recipe: one square image per mask.

    image: [H, W, 3] uint8 RGB; masks: [K, H, W] bool. For mask k: pixels outside it are set to
    black, the image is cut to the mask's bounding box (inclusive of its last row/column), the
    cut is centred on a black l x l square (l = its longer side) and resized bilinearly to
    size x size. Returns [K, 3, size, size] float32 RGB in [0, 1] (CLIP normalisation is the
    encoder's job).
    """
    import torch

    k_count = masks.shape[0]
    out = np.zeros((k_count, 3, size, size), np.float32)
    if k_count == 0:
        return out
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # thousands of tiny resizes: thread start-up costs more than it saves
    try:
        _crop_into(out, image, masks, size)
    finally:
        torch.set_num_threads(threads)
    return out


def _crop_into(out: np.ndarray, image: np.ndarray, masks: np.ndarray, size: int) -> None:
    import torch
    import torch.nn.functional as F

    k_count = masks.shape[0]
    rows_any = masks.any(axis=2)
    cols_any = masks.any(axis=1)
    for k in range(k_count):
        ys, xs = np.flatnonzero(rows_any[k]), np.flatnonzero(cols_any[k])
        if ys.size == 0:
            continue
        y0, y1, x0, x1 = ys[0], ys[-1] + 1, xs[0], xs[-1] + 1
        cut = image[y0:y1, x0:x1] * masks[k, y0:y1, x0:x1, None]
        dy, dx = square_pad_box(y0, y1, x0, x1)
        side = max(y1 - y0, x1 - x0)
        square = np.zeros((side, side, 3), np.float32)
        square[dy : dy + (y1 - y0), dx : dx + (x1 - x0)] = cut
        t = torch.from_numpy(square).permute(2, 0, 1)[None]
        out[k] = F.interpolate(t, size=(size, size), mode="bilinear", align_corners=False)[0].numpy() / 255.0


def segmap_from_levels(levels: list[MaskSet]) -> np.ndarray:
    """[L, H, W] int32 mask ids, cumulative across levels, -1 where no mask.

    Within a level masks are painted in order (a later mask overwrites an earlier one, as
    LangSplat's mask2segmap); level j's ids start after all masks of levels 0..j-1.
    """
    h, w = levels[0].masks.shape[1:]
    seg = np.full((len(levels), h, w), -1, np.int32)
    offset = 0
    for j, level in enumerate(levels):
        for k in range(len(level)):
            seg[j][level.masks[k]] = offset + k
        offset += len(level)
    return seg


def extract_image(image: np.ndarray, generator, encoder, nms: NmsParams = NmsParams()) -> tuple[np.ndarray, np.ndarray, StageTimes, list[int]]:
    """Masks and embeddings of one image.

    image: [H, W, 3] uint8 RGB. Returns seg: [4, H, W] int32 cumulative ids, feats: [M, D]
    float32 unit rows (M = masks of all levels), stage times and masks per level.
    """
    times = StageTimes()
    t0 = time.perf_counter()
    levels = generator.generate(image)
    t1 = time.perf_counter()
    levels = masks_update(levels, nms)
    t2 = time.perf_counter()
    all_masks = np.concatenate([lvl.masks for lvl in levels]) if levels else np.zeros((0,) + image.shape[:2], bool)
    crops = crop_masks(image, all_masks, encoder.image_size)
    t3 = time.perf_counter()
    feats = encoder.encode_images(crops) if len(crops) else np.zeros((0, encoder.dim), np.float32)
    t4 = time.perf_counter()
    times.masks, times.postprocess, times.crop, times.clip = t1 - t0, t2 - t1, t3 - t2, t4 - t3
    return segmap_from_levels(levels), feats.astype(np.float32), times, [len(lvl) for lvl in levels]


def feature_cameras(source: str | Path, resolution: float = -1, max_height: int | None = MAX_HEIGHT) -> list:
    """Training cameras at the resolution features are made at: `load_cameras(resolution)`, then
    LangSplat's cap of `max_height` rows (registration resamples id maps to its render size)."""
    cameras = load_cameras(source, resolution=resolution)
    refuse_cameras_without_images(source, cameras)
    if max_height:
        cameras = [c.scaled(max_height / c.height) if c.height > max_height else c for c in cameras]
    return cameras


def refuse_cameras_without_images(source: str | Path, cameras: list) -> None:
    """InputError naming the camera file and the folder its images were looked for in when a camera has no image
    file (`image_path` None): a 3DGS cameras.json with no images/ beside it, as in a training output folder. The
    loader keeps such cameras for `register`, which reads feature files; `features` needs the photographs, and
    said so only after SAM and CLIP were loaded (a probe, round 51: minutes and gigabytes with the real models)."""

    lacking = [c for c in cameras if c.image_path is None]
    if not lacking:
        return
    kind, found = detect_dataset(source)
    count = f"none of its {len(cameras)} cameras has an image" if len(lacking) == len(cameras) else \
        f"{len(lacking)} of its {len(cameras)} cameras {'has' if len(lacking) == 1 else 'have'} no image"
    folder = image_folder(kind, found)
    where = f"{folder}, which does not exist" if not folder.is_dir() else f"{folder}, which holds none of their names"
    advice = (" (3DGS writes cameras.json into its model folder, and the images stay in the dataset folder): give --source the dataset "
              "folder 3DGS trained from (its -s, holding images/)") if kind == "cameras_json" else ""
    raise InputError(found, f"{count} (e.g. {lacking[0].name!r}): the images are looked for in {where}{advice}",
                     field="img_name" if kind == "cameras_json" else None)


def versions() -> dict[str, str]:
    """Versions of the libraries that shape the features."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"drsplat": drsplat.__version__, "numpy": np.__version__}
    for pkg in ("torch", "open_clip_torch", "segment-anything", "scikit-image"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "absent"
    return out


def make_manifest(generator, encoder, nms: NmsParams, resolution: float, max_height: int | None, extra: dict | None = None) -> dict:
    """The manifest.json describing how features were made (read by registration and query)."""
    manifest = {
        "format": "langsplat",
        "levels": list(LEVELS),
        "default_level": 1,
        "mask_generator": generator.name,
        "mask_parameters": generator.parameters(),
        "postprocess": asdict(nms),
        **manifest_clip_entry(encoder.model_name, encoder.pretrained, encoder.checkpoint),
        "dim": int(encoder.dim),
        "crop_size": int(encoder.image_size),
        "resolution": resolution,
        "max_height": max_height,
        "clip_weights": weights_digest(encoder.checkpoint),
        "sam_weights": weights_digest(getattr(generator, "checkpoint", None)),
        "clip_precision": clip_precision(encoder),
        "crop_normalisation": crop_normalisation(encoder),
        "versions": versions(),
    }
    manifest.update(extra or {})
    return manifest


def crop_normalisation(encoder) -> dict | None:
    """{mean, std} the encoder normalises crops with (None for an encoder that does not say): a resume must repeat it."""
    mean, std = getattr(encoder, "mean", None), getattr(encoder, "std", None)
    if mean is None or std is None:
        return None
    return normalisation_entry(mean, std)


def normalisation_entry(mean, std) -> dict:
    """The manifest's form of a crop normalisation (`crop_normalisation`): lists of floats, as JSON stores them."""
    return {"mean": [float(v) for v in mean], "std": [float(v) for v in std]}


def clip_precision(encoder) -> str | None:
    """'float16' or 'float32': the precision CLIP embeds in (float16 on a CUDA device); None when the
    encoder does not say."""
    dtype = getattr(encoder, "dtype", None)
    return None if dtype is None else str(dtype).removeprefix("torch.")


def check_manifest_compatible(features_dir: Path, manifest: dict) -> None:
    """Refuse to add features of another CLIP model or mask generator to an existing folder."""
    old = featurefiles.read_manifest(features_dir)
    if not old:
        if features_dir.is_dir() and featurefiles.list_stems(features_dir):
            raise DrsplatError(f"{features_dir} already holds feature files without a manifest.json; use a new --out folder so features of different origins are not mixed")
        return
    if "mask_generator" not in old and IMAGE_STAMPS not in old and "clip_model_id" not in old and "clip" not in old:
        raise DrsplatError(f"{features_dir / featurefiles.MANIFEST_NAME} is not a drsplat features manifest (it names no mask "
                           "generator or CLIP model): another tool's file; use a new --out folder")
    old_clip = manifest_model_id(old)
    same_weights = bool(old.get("clip_weights")) and old.get("clip_weights") == manifest.get("clip_weights")
    old_model, _, old_tag = old_clip.partition("/")
    new_model, _, new_tag = str(manifest["clip_model_id"]).partition("/")
    renamed = same_weights and old_model == new_model and old_tag.startswith("file:") and new_tag.startswith("file:")
    if not renamed:  # the same file renamed, no tag named, changes its `file:NAME` label only (round 61c: refused)
        check_compatible(old_clip, manifest["clip_model_id"], f"the features already in {features_dir}", "this run's CLIP model")
    if old.get("mask_generator") != manifest["mask_generator"]:
        raise DrsplatError(
            f"{features_dir} holds features made with mask generator {old.get('mask_generator')!r}, this run uses "
            f"{manifest['mask_generator']!r}; use a new --out folder or the same --masks{_no_pair_yet(features_dir)}"
        )
    refuse_unrecorded_normalisation(features_dir, old, manifest)
    for key, flag in RESUME_KEYS.items():
        if key in old and old[key] != json.loads(json.dumps(manifest.get(key))):  # as stored: tuples are lists
            raise DrsplatError(f"{features_dir} holds features made with {key} {old[key]!r}, this run's is {manifest.get(key)!r}: resuming "
                               f"would mix the two in one folder; use a new --out folder or the same {flag}{_no_pair_yet(features_dir)}")
    for key, flag in (("source", "--source"), ("sam_checkpoint", "--sam-checkpoint")):
        if key == "sam_checkpoint" and old.get("sam_weights") and old.get("sam_weights") == manifest.get("sam_weights"):
            continue  # the same weights, moved: their digest (checked above), not their path, says what made the masks, as for CLIP (round 61c)
        check_same_path(features_dir, key, flag, old.get(key), manifest.get(key))
    if old.get("clip_precision") and manifest.get("clip_precision") and old["clip_precision"] != manifest["clip_precision"]:
        log.warning("%s holds features CLIP made in %s, this run's are in %s (CLIP runs in float16 on a CUDA device, float32 on "
                    "the CPU: --device): the two differ in their last bits", shown_path(features_dir), shown_path(old["clip_precision"]),
                    manifest["clip_precision"])  # the stored value as shown: the manifest is a file a user may have edited


def refuse_unrecorded_normalisation(features_dir: Path, old: dict, manifest: dict) -> None:
    """A folder begun before manifests recorded the crop normalisation had its crops normalised with OpenAI's mean and
    std (every checkpoint then): a run normalising otherwise (a SigLIP or MobileCLIP checkpoint now) cannot resume it.
    It did, without a word, and the folder held views of two embeddings (round 62b)."""
    new = manifest.get("crop_normalisation")
    if "crop_normalisation" in old or not new or not featurefiles.list_stems(features_dir):
        return
    if new != normalisation_entry(OPENAI_MEAN, OPENAI_STD):
        raise DrsplatError(f"{features_dir} holds features made before drsplat recorded how crops are normalised (OpenAI's mean "
                           f"and std then), and this run normalises them with mean {new['mean']}, std {new['std']}: resuming would "
                           "mix the two in one folder; use a new --out folder")


def _no_pair_yet(features_dir: Path) -> str:
    """The remedy's tail when the folder holds no feature pair yet (a run stopped in its first image:
    SAM takes minutes an image on a CPU): its manifest alone then refuses other settings, since another
    run may be working there now (the manifest is all that tells them apart); deleting it is safe
    once none is."""
    if featurefiles.list_stems(features_dir):
        return ""
    return (f" (the folder holds no feature file yet, only the manifest of a run stopped before its first: if no `drsplat features` "
            f"is writing there now, delete {featurefiles.MANIFEST_NAME} to start with these settings)")


RESUME_KEYS = {  # manifest entries that change every feature file: a run resuming into the folder must repeat them
    "mask_parameters": "mask flags (--sam-points-per-side, --sam-crop-layers, ...)",
    "postprocess": "mask post-processing",
    "resolution": "--resolution",
    "max_height": "--max-height",
    "clip_weights": "CLIP weights (--clip-checkpoint: compared by the file's contents, whatever its name)",
    "sam_weights": "SAM weights (--sam-checkpoint, or the --sam-model downloaded)",
    "crop_normalisation": "crop normalisation (the weights' tag sets it: --pretrained)",
}


def check_same_path(features_dir: Path, key: str, flag: str, old: str | None, new: str | None) -> None:
    """DrsplatError when a folder's features came from another dataset or SAM checkpoint (manifests
    store them resolved); a warning where an older manifest stored a relative path that resolves
    elsewhere from here."""
    if not old or not new or Path(old).resolve() == Path(new).resolve():
        return
    if key == "source" and same_camera_file(Path(old), Path(new)):  # DATASET and DATASET/transforms.json (round 57c: refused)
        return
    if Path(old).is_absolute():
        raise DrsplatError(f"{features_dir} holds features made with {key} {old}, this run's is {new}: resuming would mix the two "
                           f"under the same names; use a new --out folder or the same {flag}")
    log.warning("%s: its features were made with %s %r (a relative path), which is not %s from here: if that is another "
                "one, use a new --out folder", features_dir, key, old, new)


def same_camera_file(a: Path, b: Path) -> bool:
    """Whether two --source paths name one dataset's camera description (a folder and its transforms.json, sparse/0 and
    its dataset): the files `detect_dataset` finds are the same. False where either is not a dataset now."""
    try:
        return detect_dataset(a)[1].resolve() == detect_dataset(b)[1].resolve()
    except InputError:
        return False


IMAGE_STAMPS = "image_stamps"  # manifest entry: each pair's image and camera as they were when the pair was made (`pair_stamp`)
STAMP_JOURNAL = featurefiles.STAMP_JOURNAL  # a run's stamps, a line per pair as it is written; folded into the manifest at the end


@dataclass
class ImageStamps:
    """Each pair's image as it was when its pair was made (`utils.file_stamp`), so that a later run
    redoes the pairs of edited images. known: stem -> stamp, from the manifest and from the journal
    an unfinished run left beside it (a line per pair as it was written: a run stopped by Ctrl-C, a
    kill or an unreadable image recorded nothing before, and its pairs then passed for those of the
    images as they are now); tracked: whether the folder records stamps at all (a folder drsplat
    made does, from its first manifest on; LangSplat's own do not)."""

    out: Path
    known: dict[str, str]
    tracked: bool

    @classmethod
    def read(cls, out: Path) -> ImageStamps:
        manifest = featurefiles.read_manifest(out) if out.is_dir() else {}
        check_journal(out / STAMP_JOURNAL)
        recorded = manifest.get(IMAGE_STAMPS)
        known = {k: v for k, v in recorded.items() if isinstance(v, str)} if isinstance(recorded, dict) else {}
        return cls(out, {**known, **read_journal(out / STAMP_JOURNAL)}, isinstance(recorded, dict))

    def add(self, stem: str, stamp: str | None) -> None:
        """Record that `stem`'s pair was just written from its image as it was at `stamp` (taken when
        the image was read), in the journal first: a run stopped after this pair keeps the record."""
        if stamp is None:
            return
        self.known[stem] = stamp
        if not self.tracked:  # no manifest will hold them (a library call without one, on a folder that records none)
            return
        # O_NOFOLLOW: a journal replaced by a link since `read` must not append to the file it leads to
        fd = os.open(self.out / STAMP_JOURNAL, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        with os.fdopen(fd, "a", encoding="utf-8") as f:
            f.write(json.dumps({"stem": stem, "stamp": stamp}) + "\n")

    def finish(self, manifest: dict | None, images: int | None = None) -> None:
        """The manifest written with every known stamp (and `images`, the run's count), then the
        journal it now holds removed. manifest None: the folder's own as it is, for a run given none
        (a journal left behind would read as an unfinished run's, `registration.views.select_views`)."""
        base = featurefiles.read_manifest(self.out) if manifest is None else manifest
        counted = {} if images is None else {"images": images}
        featurefiles.write_manifest(self.out, {**base, **counted, IMAGE_STAMPS: self.known})
        (self.out / STAMP_JOURNAL).unlink(missing_ok=True)


def check_journal(path: Path) -> None:
    """InputError unless the stamp journal is absent or a regular file: the run appends to it, and a
    symbolic link would make it append to whatever file the link names (an input of the dataset),
    a FIFO would block the run and a device could be read without end."""
    try:
        kind = odd_entry_kind(path)
    except OSError as exc:
        raise InputError(path, f"the journal of an unfinished features run cannot be read ({exc.strerror})") from None
    if kind is not None:
        raise InputError(path, f"the journal of an unfinished features run (a record per pair written) is {kind}; features "
                               "writes it as a plain file in the --out folder: remove it (its pairs are then made again)")


JOURNAL_LINE_CHARS = 1 << 16  # a journal record is a stem and a stamp: a longer line is no record (read in pieces, skipped)


def read_journal(path: Path) -> dict[str, str]:
    """stem -> stamp of a stamp journal ({} without one); a line that is not a whole record (the last
    one of a run killed while writing it, or one longer than JOURNAL_LINE_CHARS) is skipped: its pair
    has no stamp and is made again. Read a line at a time, so a journal of gigabytes, or one line
    without end, costs no more memory than a record."""
    out: dict[str, str] = {}
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            while line := f.readline(JOURNAL_LINE_CHARS):
                if not line.endswith("\n") and len(line) == JOURNAL_LINE_CHARS:  # an overlong line: skip the rest of it
                    while (rest := f.readline(JOURNAL_LINE_CHARS)) and not rest.endswith("\n"):
                        pass
                    continue
                try:
                    entry = json.loads(line)
                except ValueError:
                    continue
                if isinstance(entry, dict) and isinstance(entry.get("stem"), str) and isinstance(entry.get("stamp"), str):
                    out[entry["stem"]] = entry["stamp"]
    except OSError:
        return {}
    return out


def pair_stamp(cam) -> str | None:
    """The stamp of what a camera's pair is made from: its image file (`utils.file_stamp`; None without one) and,
    after '|', `camera_pixels_key`: the pixels the masks are made on come from both (round 85d F1: a camera file whose
    lens distortion was corrected left every pair of the old lens in place, "skipped 50 already complete")."""
    image = file_stamp(cam.image_path)
    return None if image is None else f"{image}|{camera_pixels_key(cam)}"


def camera_pixels_key(cam) -> str:
    """12 hex digits of what of a camera shapes the image its masks are made on: its size, and, for a lens with
    distortion, the pinhole it is undistorted to (fx, fy, cx, cy), the coefficients and the file's size they describe.
    A pose, or the intrinsics of a camera without distortion (its photo is only resized), change no pixel."""
    import hashlib

    parts: list = [int(cam.width), int(cam.height)]
    if cam.distortion is not None:
        parts += [float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy), np.asarray(cam.distortion, np.float64).tolist(),
                  list(cam.unscaled_size) if cam.unscaled_size is not None else None]
    return hashlib.blake2b(json.dumps(parts).encode(), digest_size=6).hexdigest()


def stale_reason(recorded: str, cam) -> str | None:
    """Why a pair whose recorded stamp is `recorded` is out of date for `cam` ("the image", "the camera"), or None. A
    stamp of a folder written before 2026-12-07 holds the image's part only: its camera is not judged."""
    image, bar, camera = recorded.partition("|")
    if image != file_stamp(cam.image_path):
        return "the image"
    if bar and camera != camera_pixels_key(cam):
        return "the camera (its size, or the lens distortion and the pinhole it is undistorted to)"
    return None


def todo_cameras(cameras: list, out: Path, report: FeatureReport, stamps: ImageStamps | None = None) -> list:
    """The cameras whose feature pair is missing, incomplete, or older than an edit of its image or
    its camera (`stale_reason`) in `out`; complete ones go to report.skipped.
    In a folder that records stamps, a complete pair without one is made again: its image's state
    when it was made is unknown (a pair written just before a run was killed). A skipped pair of a
    folder that records none is stamped with its image as it is now (LangSplat's folders)."""
    todo, seen = [], set()
    for cam in cameras:
        stem = cam.name
        if stem in seen:
            continue
        seen.add(stem)
        if featurefiles.is_valid_pair(out, stem):
            recorded = stamps.known.get(stem) if stamps is not None else None
            if recorded is not None and (why := stale_reason(recorded, cam)) is not None:
                log.warning("%s: %s of %s changed since its features were made; recomputing them", out, why, stem)
            elif recorded is None and stamps is not None and stamps.tracked:
                log.warning("%s: the features of %s were written by a run that stopped before recording their image; recomputing them",
                            out, stem)
            else:
                report.skipped.append(stem)
                if npy_header(featurefiles.feat_path(out, stem))[0][0] == 0:  # said again on a resume (round 96b F3)
                    report.without_masks.append(stem)
                now = pair_stamp(cam) if recorded is None and stamps is not None else None
                if now is not None:
                    stamps.known[stem] = now
                continue
            report.redone.append(stem)
            todo.append(cam)
            continue
        if featurefiles.seg_path(out, stem).exists() or featurefiles.feat_path(out, stem).exists():
            log.warning("%s: incomplete or invalid feature files for %s; recomputing them", out, stem)
            report.redone.append(stem)
        todo.append(cam)
    return todo


def record_result(out: Path, stem: str, seg: np.ndarray, feats: np.ndarray, times: StageTimes, counts: list[int], report: FeatureReport,
                  unseen: np.ndarray | None = None) -> None:
    """Drop non-finite embeddings (counted), give the pixels the photo never saw (`unseen` [H, W] bool,
    `cameras.unobserved_pixels`) no mask, write the pair atomically and account for it in `report`.
    seg and feats may be read-only (a Ray worker's arrays come from the object store): changed in copies then."""
    seg = seg if seg.flags.writeable else seg.copy()  # round 62b: `features --ray` on a distorted dataset, "destination is read-only"
    feats = feats if feats.flags.writeable else feats.copy()
    if unseen is not None and unseen.any():
        seg[:, unseen] = -1
        report.unobserved.append((stem, float(unseen.mean())))
    bad_rows = ~np.isfinite(feats).all(axis=1)
    if bad_rows.any():
        report.nonfinite_embeddings += int(bad_rows.sum())
        log.warning("%s: %d embeddings are not finite; their masks are dropped", stem, int(bad_rows.sum()))
        feats[bad_rows] = 0.0
        seg[np.isin(seg, np.flatnonzero(bad_rows))] = -1
    featurefiles.write_features(out, stem, seg, feats)
    report.written.append(stem)
    if sum(counts) == 0:
        report.without_masks.append(stem)
    report.times.add(times)
    report.masks_per_level = [a + b for a, b in zip(report.masks_per_level, counts)]
    log.debug("%s: %s masks, %.2f s (masks %.2f, post %.2f, crop %.2f, clip %.2f)", stem, counts, times.total, times.masks, times.postprocess, times.crop, times.clip)


@dataclass
class ModelSpec:
    """How to build the mask generator and the CLIP encoder (the `drsplat features` flags), so that
    each Ray worker can load its own copy."""

    masks: str = "sam"
    clip_model: str = DEFAULT_MODEL
    pretrained: str | None = None
    clip_checkpoint: Path | None = None
    sam_checkpoint: Path | None = None
    sam_model: str = "vit_h"
    sam_points_per_side: int = 32
    sam_crop_layers: int = 1
    device: str = "auto"
    batch_size: int = 64
    clip_config: Path | None = None  # an open_clip model config (JSON) for an architecture open_clip does not ship
    nms: NmsParams = field(default_factory=NmsParams)


def sam_weights_missing(spec: ModelSpec) -> DrsplatError | None:
    """Why `spec`'s SAM weights cannot be had, found before anything loads, or None (masks that need none, a
    --sam-checkpoint file, or weights cached or downloadable): a --sam-checkpoint that is no file, or weights neither
    cached nor downloadable (round 105a F2: a wrong --sam-checkpoint was said only after CLIP had loaded)."""
    if spec.masks != "sam":
        return None
    if spec.sam_checkpoint is None:
        return sam_checkpoint_unavailable(spec.sam_model)
    problem = sam_checkpoint_file_problem(Path(spec.sam_checkpoint))
    return None if problem is None else InputError(Path(spec.sam_checkpoint), problem)


def build_models(spec: ModelSpec):
    """(mask generator, CLIP encoder) of `spec`. SAM's weights are looked for (cache, network) before CLIP is built, so
    that a user missing both is told of both in one error (round 104c F1: SAM's absence was said a run later)."""
    use_clip_config(spec.clip_config)
    sam_missing = sam_weights_missing(spec)
    try:
        encoder = ClipEncoder(spec.clip_model, spec.pretrained, spec.clip_checkpoint, spec.device, spec.batch_size)
    except (WeightsUnavailableError, InputError) as clip_missing:  # no weights, or a --clip-checkpoint that is none
        if sam_missing is None:
            raise
        raise WeightsUnavailableError(f"{str(clip_missing).rstrip('.')}; and {sam_missing}") from None
    if sam_missing is not None:
        raise sam_missing
    encoder.require_image_normalisation()  # before any image: SAM takes minutes an image on a CPU
    sam_params = SamParams(points_per_side=spec.sam_points_per_side, crop_n_layers=spec.sam_crop_layers)
    generator = make_generator(spec.masks, spec.sam_checkpoint, spec.sam_model, encoder.device, sam_params)
    return generator, encoder


def extract_features(
    cameras: list,
    out_dir: str | Path,
    generator,
    encoder,
    nms: NmsParams = NmsParams(),
    manifest: dict | None = None,
    *,
    show_progress: bool = True,
    on_progress: Callable[[int, int], None] | None = None,
    cancel: CancelToken | None = None,
) -> FeatureReport:
    """Write `<stem>_s.npy` / `<stem>_f.npy` for every camera's image into `out_dir`.

    Images whose pair already exists and is complete (featurefiles.is_valid_pair) are skipped,
    unless the image was edited since (its size or modification time differs from the stamp the
    manifest recorded when the pair was made); truncated or half-written pairs are redone. Every file is written atomically, so an
    interrupted run (Ctrl-C, cancel) leaves only complete pairs. `manifest` (make_manifest) is
    checked against an existing one (same CLIP model and mask generator) and written first.
    """
    out = Path(out_dir)
    report = FeatureReport()
    stamps = ImageStamps.read(out)
    if manifest is not None:
        check_manifest_compatible(out, manifest)
        out.mkdir(parents=True, exist_ok=True)
        featurefiles.write_manifest(out, {**manifest, IMAGE_STAMPS: stamps.known})  # carried over: an interrupted run keeps them
        stamps.tracked = True
    out.mkdir(parents=True, exist_ok=True)
    todo = {c.name for c in todo_cameras(cameras, out, report, stamps)}
    bar = progress(cameras, desc="features", total=len(cameras), enabled=show_progress, unit="img")
    for i, cam in enumerate(bar):
        if cancel is not None:
            cancel.raise_if_cancelled()
        if cam.name in todo:
            todo.discard(cam.name)
            stamp = pair_stamp(cam)  # the image as it is read, not as it may be by the end of the run
            rgb, file_size = load_image_sized(cam)
            note_image(report, cam, rgb, file_size)
            seg, feats, times, counts = extract_image(rgb, generator, encoder, nms)
            record_result(out, cam.name, seg, feats, times, counts, report, unobserved_pixels(cam, file_size))
            stamps.add(cam.name, stamp)
            if hasattr(bar, "set_postfix"):
                bar.set_postfix(masks=sum(counts), sec=f"{times.total:.2f}")
        if on_progress is not None:
            on_progress(i + 1, len(cameras))
    if manifest is not None:
        stamps.finish(manifest, len(report.written) + len(report.skipped))
    elif stamps.tracked:  # a call without a manifest on a folder that records stamps: its journal goes into the folder's own
        stamps.finish(None)
    return report
