"""The paper's ablations, reproduced on synthetic scenes with exact ground truth (`drsplat eval ablate`).

    topk        top-k ∈ {1, 5, 10, 20, 40, 64}: localisation / segmentation mIoU, pruned ratio, registration time
    pq          PQ sub-vectors M ∈ {32, 64, 128, 256} (and exact float16): mIoU, bytes per Gaussian, query time
    robustness  mislabelled-mask fraction and embedding noise against mIoU
    metrics     volume-aware vs count vs voxel IoU across scenes and settings (the paper's Fig. S3)
    aggregate   aggregation modes (drsplat.registration.aggregate) x top-k on the hard room presets: seg / loc mIoU
                (volume and count; labelled-only and with unlabelled Gaussians as false positives),
                floaters kept, labelled coverage, time per view
    resolution  the views registered at 1/r of their size (`register --resolution r`), r ∈ {1, 2, 4}: what it
                costs in seg / loc mIoU and coverage against what it saves in time per view

Every ablation prints a Markdown table, and writes `<out-dir>/ablation_<name>.png` (plot) and
`<out-dir>/ablation_<name>.json` (the numbers). Synthetic datasets are cached in
`<out-dir>/datasets/` so reruns only repeat the registration. The mIoU columns use the
volume-aware weighting unless said otherwise; localisation uses the grid-searched global τ.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drsplat.utils import CancelToken, atomic_path, cancel_on_signals, check_outputs_writable, json_text
from drsplat.defaults import AGGREGATE_MODES, DEFAULT_AGGREGATE, DEFAULT_TOPK, ORACLE_LABEL_NAMES, ORACLE_TEXT_EMBEDDINGS
from drsplat.cameras import RESOLUTION_DIVISORS, load_cameras, scale_cameras
from drsplat.errors import DrsplatError, InputError, UsageError, shown_path
from drsplat.eval.datasets import load_gt_labels, load_label_names
from drsplat.eval.metrics import argmax_labels, evaluate_scene, scene_weights, segmentation_iou
from drsplat.lang import build_field
from drsplat.registration import RegisterOptions, register_features
from drsplat.scene import load_ply
from drsplat.features.format import FEATURE_FILE_PATTERNS, read_manifest
from drsplat.commands.common import int_range, refuse_repeats, seed_int
from drsplat.defaults import MAX_TOPK
from drsplat.synthetic import MASK_SOURCES, MAX_WIDTH, MIN_WIDTH, PRESETS, WRONG_LABELS, segmenter_corruption_error, write_dataset

log = logging.getLogger(__name__)

ABLATIONS = ("topk", "pq", "robustness", "metrics", "aggregate", "resolution")
AGGREGATE_PRESETS = ("hard-silhouette", "hard-thin", "hard-small", "hard-grazing", "hard-lowres", "hard-noisy", "hard-room")
AGGREGATE_TOPK = (10, 40)
# oracle corruptions of the aggregate ablation: name -> (mislabelled-mask fraction, boundary jitter in
# pixels, merged-mask fraction, split-mask fraction); "own" is each preset's default (hard-noisy 10% +
# 2 px, hard-room 1 px, others clean); "jitter2" is "mislabel10" without its mislabels: the room that
# isolates what the mislabels cost; "merge10" / "merge20": under-segmentation, a share of the instance
# masks swallowed by the neighbour each touches most (drsplat.synthetic.merged_instances); "split10" /
# "split20": over-segmentation, a share cut in two parts embedded as parts of their object
# (drsplat.synthetic.split_instances); the clean room otherwise
CORRUPTIONS = {"own": (None, None, 0.0, 0.0), "clean": (0.0, 0, 0.0, 0.0), "mislabel10": (0.1, 2, 0.0, 0.0), "mislabel20": (0.2, 0, 0.0, 0.0),
               "jitter2": (0.0, 2, 0.0, 0.0), "merge10": (0.0, 0, 0.1, 0.0), "merge20": (0.0, 0, 0.2, 0.0), "split10": (0.0, 0, 0.0, 0.1),
               "split20": (0.0, 0, 0.0, 0.2)}
# the room each corruption is measured against: the same masks without that corruption
CORRUPTION_REFERENCE = {"mislabel10": "jitter2", "mislabel20": "clean", "jitter2": "clean", "merge10": "clean", "merge20": "clean",
                        "split10": "clean", "split20": "clean"}
TOPK_VALUES = (1, 5, 10, 20, 40, 64)
RESOLUTION_VALUES = (1, 2, 4)  # 3DGS's -r (drsplat.cameras.RESOLUTION_DIVISORS): the views' size divided by r
PQ_VALUES = (32, 64, 128, 256)
MISLABEL_VALUES = (0.0, 0.1, 0.2, 0.3, 0.5)
NOISE_VALUES = (0.15, 0.5, 1.0, 2.0, 4.0, 8.0)
DEFAULT_NOISE = 0.15


@dataclass
class Dataset:
    """A synthetic dataset on disk and what the ablations need of it."""

    path: Path
    scene: object
    cameras: list
    gt: np.ndarray
    names: list[str]
    text: np.ndarray


@dataclass
class AblationResult:
    name: str
    columns: list[str]
    rows: list[list]
    notes: list[str] = field(default_factory=list)
    extra: dict = field(default_factory=dict)

    def markdown(self) -> str:
        def fmt(v):
            if isinstance(v, float):
                return f"{v:.3f}" if abs(v) < 1000 else f"{v:.0f}"
            return str(v)

        lines = ["| " + " | ".join(self.columns) + " |", "|" + "|".join("---:" for _ in self.columns) + "|"]
        lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in self.rows]
        return "\n".join(lines + [f"\n{n}" for n in self.notes])

    def to_dict(self) -> dict:
        return {"name": self.name, "columns": self.columns, "rows": self.rows, "notes": self.notes, **self.extra}


def dataset(root: Path, preset: str, seed: int, mislabel: float = 0.0, noise: float = DEFAULT_NOISE, mask_source: str | None = None,
            jitter: int | None = None, merge: float = 0.0, width: int | None = None, split: float = 0.0) -> Dataset:
    """Write (once) and load a synthetic dataset with the given oracle corruption (mask_source:
    override the preset's oracle mask source, "render", "geometry" or "segmenter"; jitter: the masks' boundary
    jitter in pixels, None the preset's; merge: the share of instance masks merged into a
    neighbour's; split: the share cut in two parts; width: the views' width in pixels, None the
    preset's; drsplat.synthetic)."""
    path = root / (f"{preset}-s{seed}-m{mislabel:g}-n{noise:g}" + (f"-{mask_source}" if mask_source else "")
                   + (f"-j{jitter}" if jitter is not None else "") + (f"-u{merge:g}" if merge > 0 else "")
                   + (f"-p{split:g}" if split > 0 else "") + (f"-w{width}" if width is not None else ""))
    def write() -> None:
        write_dataset(path, preset, seed, mislabel_fraction=mislabel, noise=noise, mask_source=mask_source, jitter=jitter,
                      merge_fraction=merge, split_fraction=split, width=width, show_progress=False)

    if not (path / "scene.ply").exists() or (mislabel > 0 and _stale_wrong_labels(path)):
        write()
        return load_cached(path, PRESETS[preset].dim)
    try:
        return load_cached(path, PRESETS[preset].dim)
    except DrsplatError as exc:  # a damaged cache is ours to rebuild; one that fails again is reported by the second load
        log.warning("cached dataset %s fails a check (%s); written again", path, exc)
        write()
        return load_cached(path, PRESETS[preset].dim)


def load_cached(path: Path, dim: int) -> Dataset:
    """A cached synthetic dataset read through the checked loaders of `drsplat eval iou` (labels in range
    and one per Gaussian, names, finite unit text embeddings of `dim` columns, one per name), so a
    damaged cache raises one InputError naming the file instead of changing the numbers silently."""
    from drsplat.query import load_query_embeddings  # here: the same checks as `eval iou --text-embeddings`, without query's stack at import

    scene = load_ply(path / "scene.ply")
    names = load_label_names(path / ORACLE_LABEL_NAMES)
    text = load_query_embeddings(path / ORACLE_TEXT_EMBEDDINGS, dim)
    if text.shape[0] != len(names):
        raise InputError(path / ORACLE_TEXT_EMBEDDINGS, f"{text.shape[0]} embeddings for the {len(names)} label names of {ORACLE_LABEL_NAMES}")
    gt = load_gt_labels(path / "gt" / "labels.npy", scene.num_gaussians, len(names))
    return Dataset(path, scene, load_cameras(path), gt, names, text)


def _stale_wrong_labels(path: Path) -> bool:
    """True for a cached mislabelled dataset written before its wrong labels had a random stream of
    their own (drsplat.synthetic.WRONG_LABEL_STREAM): its masks differ from the same room without
    mislabels, so it is written again (logged)."""
    stale = read_manifest(path / "features").get("params", {}).get("wrong_labels") != WRONG_LABELS
    if stale:
        log.info("%s: made before the mislabels had a random stream of their own; written again", path)
    return stale


def register(ds: Dataset, topk: int = DEFAULT_TOPK, collect: bool = False, aggregate: str = "paper", resolution: int = 1,
             cancel: CancelToken | None = None):
    """Register `ds` (resolution r: its views at 1/r of their size, `scale_cameras`, the feature maps
    resampled to them, as `register --resolution r` does); cancel: stops it between views."""
    return register_features(ds.scene, scale_cameras(ds.cameras, resolution), ds.path / "features", RegisterOptions(topk=topk, aggregate=aggregate), show_progress=False,
                             collect_embeddings=collect, cancel=cancel)


def evaluate(ds: Dataset, scores: np.ndarray, assigned: np.ndarray, weightings=("volume",), voxel_resolution: int = 64) -> dict:
    """{(task, weighting): IoUReport} for one scored scene (unassigned Gaussians never selected)."""
    reps = evaluate_scene(ds.scene, scores, ds.gt, ds.names, ("loc", "seg"), weightings, voxel_resolution=voxel_resolution, assigned=assigned)
    return {(r.task, r.weighting): r for r in reps}


def exact_scores(ds: Dataset, result) -> tuple[np.ndarray, object]:
    field = build_field(result.features, result.weights)
    return field.scores(ds.text), field


def _check(cancel: CancelToken | None) -> None:
    if cancel is not None:
        cancel.raise_if_cancelled()


# ---------------------------------------------------------------------------------------------- ablations


def ablate_topk(root: Path, preset: str, seeds: list[int], values=TOPK_VALUES, cancel: CancelToken | None = None) -> AblationResult:
    register(dataset(root, preset, seeds[0]), int(values[0]), cancel=cancel)  # warm-up: compiled kernels load once, not inside the timings
    rows = []
    for k in values:
        per = []
        for seed in seeds:
            _check(cancel)
            ds = dataset(root, preset, seed)
            res = register(ds, k, cancel=cancel)
            scores, _ = exact_scores(ds, res)
            reps = evaluate(ds, scores, res.weights > 0)
            per.append((reps["loc", "volume"].miou, reps["seg", "volume"].miou, 1.0 - res.num_assigned / ds.scene.num_gaussians, res.seconds))
        loc, seg, pruned, secs = np.mean(per, axis=0)
        rows.append([int(k), float(loc), float(seg), float(pruned), float(secs)])
        log.info("top-k %d: loc %.3f seg %.3f pruned %.3f %.2f s", k, loc, seg, pruned, secs)
    return AblationResult("topk", ["top-k", "loc mIoU", "seg mIoU", "pruned ratio", "registration s"], rows,
                          [f"preset {preset}, seeds {seeds}; mean over seeds; registration time of the whole scene (raster + accumulate)."])


def ablate_pq(root: Path, preset: str, seeds: list[int], values=PQ_VALUES, repeats: int = 9, cancel: CancelToken | None = None) -> AblationResult:
    table: dict[str, list] = {}
    sizes = []
    for seed in seeds:
        _check(cancel)
        ds = dataset(root, preset, seed)
        sizes.append(f"{ds.scene.num_gaussians:,}")
        res = register(ds, 40, collect=True, cancel=cancel)
        for m in (None,) + tuple(values):
            _check(cancel)
            if m is not None and ds.text.shape[1] % m:
                log.warning("skipping M=%d: it does not divide D=%d", m, ds.text.shape[1])
                continue
            field_ = build_field(res.features, res.weights) if m is None else build_field(res.features, res.weights, codebook="scene", m=m,
                                                                                        train_embeddings=res.mask_embeddings, seed=seed)
            field_.scores(ds.text)  # warm-up: compiled kernels load once
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                scores = field_.scores(ds.text)
                times.append(time.perf_counter() - t0)
            reps = evaluate(ds, scores, res.weights > 0)
            key = "exact fp16" if m is None else str(m)
            table.setdefault(key, []).append((reps["loc", "volume"].miou, reps["seg", "volume"].miou, field_.bytes_per_gaussian(),
                                              1e3 * float(np.median(times))))
    rows = []
    for key, per in table.items():
        loc, seg, nbytes, ms = np.mean(per, axis=0)
        rows.append([key, float(loc), float(seg), int(nbytes), float(ms)])
    return AblationResult("pq", ["PQ sub-vectors", "loc mIoU", "seg mIoU", "bytes/Gaussian", f"query ms ({len(ds.names)} queries)"], rows,
                          [f"preset {preset} ({' / '.join(sizes)} Gaussians), seeds {seeds}; codebook trained per scene on its mask embeddings; "
                           f"query time = median of {repeats} scorings of all labels after a warm-up."])


def ablate_robustness(root: Path, preset: str, seeds: list[int], mislabels=MISLABEL_VALUES, noises=NOISE_VALUES,
                      cancel: CancelToken | None = None) -> AblationResult:
    settings = [("mislabel", m, m, DEFAULT_NOISE) for m in mislabels] + [("noise", n, 0.0, n) for n in noises if n != DEFAULT_NOISE]
    rows = []
    for kind, value, mis, noise in settings:
        per = []
        for seed in seeds:
            _check(cancel)
            ds = dataset(root, preset, seed, mis, noise)
            res = register(ds, 40, cancel=cancel)
            scores, _ = exact_scores(ds, res)
            reps = evaluate(ds, scores, res.weights > 0, ("volume", "count"))
            per.append((reps["loc", "volume"].miou, reps["seg", "volume"].miou, reps["loc", "count"].miou, reps["seg", "count"].miou))
        rows.append([kind, float(value), *map(float, np.mean(per, axis=0))])
        log.info("%s %.2f: %s", kind, value, rows[-1][2:])
    return AblationResult("robustness", ["corruption", "value", "loc mIoU (vol)", "seg mIoU (vol)", "loc mIoU (count)", "seg mIoU (count)"], rows,
                          [f"preset {preset}, seeds {seeds}. mislabel: share of oracle masks given another label's embedding "
                           f"(noise {DEFAULT_NOISE}); noise: norm of the oracle embedding noise, against a label component of norm 0.8 (no mislabels)."])


def ablate_metrics(root: Path, preset: str, seeds: list[int], cancel: CancelToken | None = None, voxel_resolution: int = 64) -> AblationResult:
    """Per-label IoU under the three weightings across scenes and settings, and their correlations."""
    settings = [("clean k=40", 0.0, DEFAULT_NOISE, 40), ("clean k=1", 0.0, DEFAULT_NOISE, 1),
                ("mislabel 0.3", 0.3, DEFAULT_NOISE, 40), ("noise 1.0", 0.0, 1.0, 40)]
    points: dict[str, dict[str, list[float]]] = {"loc": {w: [] for w in ("volume", "count", "voxel")},
                                                 "seg": {w: [] for w in ("volume", "count", "voxel")}}
    rows = []
    for seed in seeds:
        for name, mis, noise, k in settings:
            _check(cancel)
            ds = dataset(root, preset, seed, mis, noise)
            res = register(ds, k, cancel=cancel)
            scores, _ = exact_scores(ds, res)
            reps = evaluate(ds, scores, res.weights > 0, ("volume", "count", "voxel"), voxel_resolution)
            for task in ("loc", "seg"):
                valid = reps[task, "volume"].valid & reps[task, "count"].valid & reps[task, "voxel"].valid
                for w in ("volume", "count", "voxel"):
                    points[task][w].extend(reps[task, w].iou[valid].tolist())
            rows.append([f"seed {seed}, {name}", *(float(reps[t, w].miou) for t in ("loc", "seg") for w in ("volume", "count", "voxel"))])
    corr = {}
    for task in ("loc", "seg"):
        v = {w: np.asarray(points[task][w]) for w in points[task]}
        corr[task] = {f"{a}~{b}": (_pearson(v[a], v[b]), _spearman(v[a], v[b])) for a, b in (("voxel", "volume"), ("voxel", "count"), ("volume", "count"))}
    notes = [f"preset {preset}, seeds {seeds}; per-label IoU pairs pooled over scenes and settings ({len(points['loc']['volume'])} loc, "
             f"{len(points['seg']['volume'])} seg). Correlations (Pearson r / Spearman rho):"]
    for task in ("loc", "seg"):
        notes.append(f"{task}: " + ", ".join(f"{k} r={p:.3f} rho={s:.3f}" for k, (p, s) in corr[task].items()))
    return AblationResult("metrics", ["scene / setting", "loc vol", "loc count", "loc voxel", "seg vol", "seg count", "seg voxel"], rows, notes,
                          {"points": points, "correlation": {t: {k: list(v) for k, v in c.items()} for t, c in corr.items()}})


AGGREGATE_COLUMNS = ["preset", "mode", "top-k", "seg mIoU vol", "seg mIoU vol +unl", "seg mIoU count", "seg mIoU count +unl",
                     "loc mIoU vol", "loc mIoU vol lab", "loc mIoU count", "floaters kept", "labelled coverage", "ms/view"]


def aggregate_metrics(ds: Dataset, result) -> list[float]:
    """The aggregate ablation's numbers for one registration (AGGREGATE_COLUMNS[3:]).

    "+unl": segmentation with unlabelled Gaussians kept: an assigned unlabelled Gaussian is a false
    positive of the label it takes (unassigned ones predict nothing). "lab": localisation on the
    labelled Gaussians only (the plain loc column counts selected unlabelled ones as false
    positives). floaters kept: share of unlabelled Gaussians assigned; labelled coverage: share of
    labelled Gaussians assigned.
    """
    scores, _ = exact_scores(ds, result)
    assigned = result.weights > 0
    reps = evaluate(ds, scores, assigned, ("volume", "count"))
    labelled = ds.gt >= 0
    lab_ds = Dataset(ds.path, ds.scene.subset(labelled), ds.cameras, ds.gt[labelled], ds.names, ds.text)
    lab = evaluate(lab_ds, scores[labelled], assigned[labelled], ("volume",))
    pred = np.where(assigned, argmax_labels(scores), -1)
    with_unl = {}
    for weighting in ("volume", "count"):
        w, _ = scene_weights(ds.scene, weighting)
        iou, _ = segmentation_iou(pred, ds.gt, w, len(ds.names), ignore_unlabelled=False)
        with_unl[weighting] = float(np.nanmean(iou))
    return [float(reps["seg", "volume"].miou), with_unl["volume"], float(reps["seg", "count"].miou), with_unl["count"],
            float(reps["loc", "volume"].miou), float(lab["loc", "volume"].miou), float(reps["loc", "count"].miou),
            float(assigned[~labelled].mean()) if (~labelled).any() else 0.0, float(assigned[labelled].mean()),
            1e3 * result.seconds / max(result.num_views, 1)]


def _corrupted(root: Path, preset: str, seed: int, mask_source: str | None, corruption: str) -> Dataset:
    mislabel, jitter, merge, split = CORRUPTIONS[corruption]
    return dataset(root, preset, seed, PRESETS[preset].mislabel if mislabel is None else mislabel, mask_source=mask_source, jitter=jitter,
                   merge=merge, split=split)


def ablate_aggregate(root: Path, presets=AGGREGATE_PRESETS, seeds: list[int] = (0,), modes=None, topks=AGGREGATE_TOPK,
                     cancel: CancelToken | None = None, mask_source: str | None = None, mask_sources=None,
                     corruptions=("own",)) -> AblationResult:
    """Every aggregation mode x top-k on every hard preset, mean over seeds (AGGREGATE_COLUMNS).
    mask_source: every preset's oracle masks from this source (None: each preset's own);
    mask_sources: several of them (rows then name "preset source corruption"); corruptions: keys
    of CORRUPTIONS (several: rows name them)."""
    modes = tuple(modes or AGGREGATE_MODES)
    sources = tuple(mask_sources) if mask_sources else (mask_source,)
    named = len(sources) > 1 or tuple(corruptions) != ("own",)
    first = _corrupted(root, presets[0], seeds[0], sources[0], corruptions[0])
    for k in topks:  # warm-up: compiled kernels load once, not inside the timings
        for mode in modes:
            register(first, int(k), aggregate=mode, cancel=cancel)
    rows = []
    for preset in presets:
        for source in sources:
            for corruption in corruptions:
                name = f"{preset} {source or 'own'} {corruption}" if named else preset
                for k in topks:
                    for mode in modes:
                        per = []
                        for seed in seeds:
                            _check(cancel)
                            ds = _corrupted(root, preset, seed, source, corruption)
                            per.append(aggregate_metrics(ds, register(ds, int(k), aggregate=mode, cancel=cancel)))
                        rows.append([name, mode, int(k), *map(float, np.mean(per, axis=0))])
                        log.info("%s k=%d %s: %s", name, k, mode, " ".join(f"{v:.3f}" for v in rows[-1][3:]))
    own_source = "each preset's own (geometry for hard-silhouette, render otherwise)"
    masks = ", ".join(f"{s} (every preset)" if s else own_source for s in sources)
    own_corruption = "each preset's default oracle corruption (hard-noisy: 10% mislabelled masks, 2 px jitter; hard-room: 1 px jitter)"
    kinds = ", ".join(own_corruption if c == "own" else c for c in corruptions)
    notes = [f"presets {', '.join(presets)}; seeds {list(seeds)} (mean); oracle masks: {masks}; corruptions: {kinds}. "
             "vol = volume-aware, count = OpenGaussian's; "
             "+unl = unlabelled Gaussians that stay assigned count as false positives; lab = labelled Gaussians only; "
             "ms/view = whole registration time / views."]
    return AblationResult("aggregate", list(AGGREGATE_COLUMNS), rows, notes)


RESOLUTION_COLUMNS = ["resolution", "mode", "views", "seg mIoU vol", "seg mIoU vol +unl", "loc mIoU vol", "labelled coverage",
                      "ms/view", "speed-up"]


def ablate_resolution(root: Path, preset: str, seeds: list[int], values=RESOLUTION_VALUES, modes=("paper", DEFAULT_AGGREGATE),
                      width: int | None = None, mask_source: str | None = None, cancel: CancelToken | None = None) -> AblationResult:
    """What registering the views at 1/r of their size costs and saves (3DGS's -r; `register
    --resolution r`). The feature maps stay full size and are resampled to the smaller views (nearest
    neighbour, drsplat.registration.views), so only the rasterized pixels change: about r² fewer.

    Per r and mode (RESOLUTION_COLUMNS): labelled seg mIoU vol, the same with unlabelled Gaussians as
    false positives, loc mIoU vol and labelled coverage, mean over seeds; ms per view of the whole
    registration, median over seeds; speed-up = the first r's ms per view / this r's, same mode.
    width: the synthetic views' width before scaling (None: the preset's); mask_source: the oracle
    masks' source (None: the preset's). With "render" masks the full-size masks follow the
    full-size footprints, so smaller views also see masks sharper than their own footprints (what
    "geometry" masks, true silhouettes, are at every size)."""
    first = dataset(root, preset, seeds[0], mask_source=mask_source, width=width)
    for mode in modes:  # warm-up: compiled kernels load once, not inside the timings
        register(first, aggregate=mode, cancel=cancel)
    rows, base = [], {}
    for r in values:
        for mode in modes:
            per, ms = [], []
            for seed in seeds:
                _check(cancel)
                ds = dataset(root, preset, seed, mask_source=mask_source, width=width)
                m = aggregate_metrics(ds, register(ds, aggregate=mode, resolution=int(r), cancel=cancel))
                per.append([m[0], m[1], m[4], m[8]])
                ms.append(m[9])
            cam = scale_cameras(first.cameras[:1], int(r))[0]
            speed = float(np.median(ms))
            base.setdefault(mode, speed)
            rows.append([int(r), mode, f"{cam.width}x{cam.height}", *map(float, np.mean(per, axis=0)), speed, base[mode] / speed])
            log.info("resolution %d %s: %s", r, mode, " ".join(f"{v:.3f}" for v in rows[-1][3:]))
    notes = [f"preset {preset} at {first.cameras[0].width}x{first.cameras[0].height}, {len(first.cameras)} views, "
             f"{mask_source or 'its own'} oracle masks; seeds {list(seeds)} "
             "(mean; ms/view: median); feature maps at full size, resampled to the views; speed-up against the first resolution "
             "of the same mode."]
    return AblationResult("resolution", list(RESOLUTION_COLUMNS), rows, notes)


def time_aggregate_modes(ds: Dataset, modes, topk: int = DEFAULT_TOPK, repeats: int = 5, cancel: CancelToken | None = None) -> dict[str, float]:
    """{mode: median ms per view} over `repeats` registrations of `ds`, modes interleaved within each
    repeat so that a busy machine slows every mode alike (the ablation's single-run ms/view is noisier)."""
    times: dict[str, list[float]] = {m: [] for m in modes}
    for _ in range(repeats):
        for mode in modes:
            _check(cancel)
            res = register(ds, topk, aggregate=mode, cancel=cancel)
            times[mode].append(1e3 * res.seconds / max(res.num_views, 1))
    return {m: float(np.median(t)) for m, t in times.items()}


def aggregate_summary(result: AblationResult, baseline: str = "paper", topk: int = DEFAULT_TOPK) -> str:
    """Markdown table per mode at one top-k: per preset seg mIoU vol minus the baseline's, the
    smallest gain over presets, floaters kept and time relative to the baseline."""
    cols = result.columns
    seg, fl, cov, ms = (cols.index(c) for c in ("seg mIoU vol", "floaters kept", "labelled coverage", "ms/view"))
    rows = [r for r in result.rows if r[2] == topk]
    presets = list(dict.fromkeys(r[0] for r in rows))
    modes = list(dict.fromkeys(r[1] for r in rows))
    get = {(r[0], r[1]): r for r in rows}
    lines = ["| mode | " + " | ".join(f"Δseg {p}" for p in presets) + " | min Δseg | floaters kept | labelled coverage | time vs paper |",
             "|---|" + "---:|" * (len(presets) + 4)]
    for mode in modes:
        d = [get[p, mode][seg] - get[p, baseline][seg] for p in presets]
        fk = np.mean([get[p, mode][fl] for p in presets])
        cv = min(get[p, mode][cov] for p in presets)
        speed = np.mean([get[p, mode][ms] / get[p, baseline][ms] for p in presets])
        lines.append(f"| {mode} | " + " | ".join(f"{x:+.3f}" for x in d) + f" | {min(d):+.3f} | {fk:.3f} | {cv:.3f} | {speed:.2f}x |")
    return "\n".join(lines)


def corruption_costs(result: AblationResult, topk: int = DEFAULT_TOPK) -> str:
    """Markdown table of what each corruption costs each mode: labelled seg mIoU vol of the room
    without it (CORRUPTION_REFERENCE, same masks otherwise) minus the corrupted room's, mean over the
    presets and the worst preset, per mask source; "" when the rows hold no corruption with its
    reference (rows named "preset source corruption")."""
    seg = result.columns.index("seg mIoU vol")
    get = {}
    for r in result.rows:
        parts = r[0].split(" ")
        if r[2] == topk and len(parts) == 3:
            get[tuple(parts), r[1]] = r[seg]
    names = list(dict.fromkeys(key for key, _ in get))  # in row order
    presets = list(dict.fromkeys(p for p, _, _ in names))
    sources = list(dict.fromkeys(s for _, s, _ in names))
    pairs = [(src, c, ref) for src in sources for c, ref in CORRUPTION_REFERENCE.items()
             if all((p, src, c) in names and (p, src, ref) in names for p in presets)]
    if not pairs:
        return ""
    modes = list(dict.fromkeys(m for _, m in get))
    lines = ["What each corruption costs (labelled seg mIoU vol of the same room without it, minus the corrupted room's; "
             "mean over the presets, worst preset in brackets):", "",
             "| mode | " + " | ".join(f"{src} {c} (vs {ref})" for src, c, ref in pairs) + " |", "|---|" + "---:|" * len(pairs)]
    for mode in modes:
        cells = []
        for src, c, ref in pairs:
            cost = np.array([get[(p, src, ref), mode] - get[(p, src, c), mode] for p in presets])
            worst = int(np.argmax(cost))
            cells.append(f"{cost.mean():.3f} ({cost[worst]:.3f} {presets[worst]})")
        lines.append(f"| {mode} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    if len(a) < 2 or a.std() == 0 or b.std() == 0:
        return float("nan")
    return float(np.corrcoef(a, b)[0, 1])


def _spearman(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import rankdata

    return _pearson(rankdata(a), rankdata(b)) if len(a) >= 2 else float("nan")


# ---------------------------------------------------------------------------------------------- plots


def plot(result: AblationResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if result.name == "aggregate":
        fig = _plot_aggregate(result, plt)
    elif result.name == "resolution":
        fig, axes = plt.subplots(1, 2, figsize=(10, 4))
        cols = result.columns
        for i, mode in enumerate(dict.fromkeys(r[1] for r in result.rows)):
            rows = [r for r in result.rows if r[1] == mode]
            for ax, metric in zip(axes, ("seg mIoU vol", "loc mIoU vol")):
                xs, ys = [r[cols.index("ms/view")] for r in rows], [r[cols.index(metric)] for r in rows]
                ax.plot(xs, ys, marker="o", color=f"C{i}", label=mode)
                for r, x, y in zip(rows, xs, ys):
                    ax.annotate(f"1/{r[0]} ({r[2]})", (x, y), fontsize=7, xytext=(4, 2), textcoords="offset points")
                ax.set(xlabel="ms per view", ylabel=metric, title=f"speed against error: {metric}")
        axes[0].legend(fontsize=7)
    elif result.name == "metrics":
        fig, axes = plt.subplots(2, 2, figsize=(9, 8))
        for r, task in enumerate(("loc", "seg")):
            pts = result.extra["points"][task]
            for c, other in enumerate(("volume", "count")):
                ax = axes[r, c]
                ax.scatter(pts["voxel"], pts[other], s=10, alpha=0.6)
                ax.plot([0, 1], [0, 1], "k--", lw=0.8)
                p, s = result.extra["correlation"][task][f"voxel~{other}"]
                ax.set(xlabel="voxel IoU", ylabel=f"{other} IoU", title=f"{task}: r={p:.2f}, rho={s:.2f}", xlim=(0, 1), ylim=(0, 1))
    elif result.name == "robustness":
        groups = sorted({row[0] for row in result.rows})
        fig, axes = plt.subplots(1, len(groups), figsize=(5 * len(groups), 4))
        for ax, g in zip(np.atleast_1d(axes), groups):
            rows = [row for row in result.rows if row[0] == g]
            for i, col in enumerate(result.columns[2:], start=2):
                ax.plot([row[1] for row in rows], [row[i] for row in rows], marker="o", label=col)
            ax.set(xlabel=f"{g} level", ylabel="mIoU", ylim=(0, 1), title=g)
            ax.legend(fontsize=7)
    else:
        cols = result.columns
        metric_cols = [i for i, c in enumerate(cols) if "mIoU" in c]
        other_cols = [i for i, c in enumerate(cols) if "mIoU" not in c and i >= 1]
        fig, axes = plt.subplots(1, 1 + len(other_cols), figsize=(4.5 * (1 + len(other_cols)), 4))
        axes = np.atleast_1d(axes)
        xs = np.arange(len(result.rows))
        for i in metric_cols:
            axes[0].plot(xs, [row[i] for row in result.rows], marker="o", label=cols[i])
        for ax, i in zip(axes[1:], other_cols):
            ax.plot(xs, [row[i] for row in result.rows], marker="o")
            ax.set(xlabel=cols[0], ylabel=cols[i])
        for ax in axes:
            ax.set_xticks(xs, [str(row[0]) for row in result.rows])
        axes[0].set(xlabel=cols[0], ylabel="mIoU", ylim=(0, 1))
        axes[0].legend(fontsize=7)
    fig.suptitle(f"drsplat ablation: {result.name}")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def _plot_aggregate(result: AblationResult, plt):
    """At the largest top-k: seg mIoU vol (labelled only, and with unlabelled Gaussians as false
    positives) per mode, averaged over the presets of each mask source and corruption (the rows'
    labels after the preset name; one group when there are none); floaters kept per mode; and speed
    against error: the mean labelled seg mIoU over every row against the time per view relative
    to the first mode (the interleaved timing when there is one, else the rows' ms/view)."""
    cols = result.columns
    k = max(r[2] for r in result.rows)
    rows = [r for r in result.rows if r[2] == k]
    modes = list(dict.fromkeys(r[1] for r in rows))

    def group(label: str) -> str:
        return label.split(" ", 1)[1] if " " in label else "all"

    groups = list(dict.fromkeys(group(r[0]) for r in rows))
    fig, axes = plt.subplots(1, 4, figsize=(20, 4.5), gridspec_kw={"width_ratios": [3, 3, 1.2, 1.6]})
    width = 0.8 / len(modes)
    xs = np.arange(len(groups))
    for ax, metric in zip(axes[:2], ("seg mIoU vol", "seg mIoU vol +unl")):
        c = cols.index(metric)
        means = {(g, m): np.mean([r[c] for r in rows if r[1] == m and group(r[0]) == g]) for g in groups for m in modes}
        for i, mode in enumerate(modes):
            ax.bar(xs + i * width, [means[g, mode] for g in groups], width, label=mode)
        ax.set(ylim=(max(0.0, min(means.values()) - 0.05), 1.0), ylabel=metric, title=f"{metric}, top-k {k}, mean over presets")
        ax.set_xticks(xs + 0.4 - width / 2, groups, fontsize=8)
    axes[0].legend(fontsize=7, ncol=2)
    floaters = cols.index("floaters kept")
    axes[2].bar(np.arange(len(modes)), [np.mean([r[floaters] for r in rows if r[1] == m]) for m in modes], color="C0")
    axes[2].set_xticks(np.arange(len(modes)), modes, rotation=45, ha="right", fontsize=8)
    axes[2].set(title="unlabelled kept (mean)")
    timing = result.extra.get("timing", {}).get("ms_per_view", {})
    ms = {m: timing.get(m, np.mean([r[cols.index("ms/view")] for r in rows if r[1] == m])) for m in modes}
    seg = cols.index("seg mIoU vol")
    for i, mode in enumerate(modes):
        x, y = ms[mode] / ms[modes[0]], np.mean([r[seg] for r in rows if r[1] == mode])
        axes[3].scatter([x], [y], color=f"C{i}", s=40)
        axes[3].annotate(mode, (x, y), fontsize=7, xytext=(4, 2), textcoords="offset points")
    axes[3].set(xlabel=f"time per view vs {modes[0]}", ylabel="labelled seg mIoU vol (mean of all rows)", title="speed against error")
    return fig


# ---------------------------------------------------------------------------------------------- CLI


MAX_REPEATS = 1000  # aggregate's interleaved timing runs: each repeat registers the scene once per mode
# the flags each ablation reads besides --preset, --seeds and --out-dir; any other one given is a usage
# error (silently ignoring it would report numbers for settings the user did not ask for)
ABLATION_FLAGS = {"topk": ("values",), "pq": ("values",), "robustness": (), "metrics": (),
                  "aggregate": ("modes", "mask_source", "corruptions", "repeats", "values"),
                  "resolution": ("modes", "mask_source", "width", "values")}


def add_ablate_parser(sub) -> None:
    p = sub.add_parser("ablate", help="reproduce the paper's ablations on synthetic scenes (tables + PNG plots)",
                       description=__doc__.split("\n\n")[0].rstrip(".") + "; see docs/evaluation.md.")
    p.add_argument("ablation", choices=ABLATIONS)
    p.add_argument("--preset", default=None, metavar="NAME[,NAME]",
                   help="synthetic preset (default tiny); for 'aggregate' a comma-separated list (default: every hard-* room but hard-tiny)")
    p.add_argument("--modes", default=None, metavar="M,M", help="aggregate, resolution: the aggregation modes to compare (default: all of them for aggregate; paper "
                        "and the default mode for resolution)")
    p.add_argument("--mask-source", default=None, metavar="SRC[,SRC]",
                   help="aggregate, resolution: oracle masks of every preset from the rendered Gaussians' vote (render), ray-cast true silhouettes "
                        "(geometry) or a segmenter's superpixels (segmenter: with corruptions without jitter, e.g. clean or "
                        "mislabel20); for aggregate a comma-separated list compares them (default: each preset's own)")
    p.add_argument("--corruptions", default=None, metavar="C[,C]",
                   help=f"aggregate: oracle corruptions to compare ({', '.join(CORRUPTIONS)}; default: each preset's own)")
    p.add_argument("--repeats", type=int_range(1, MAX_REPEATS), default=None,
                   help="aggregate: interleaved timing runs per mode on the last preset (default: 5)")
    p.add_argument("--seeds", default="0", metavar="S,S", help="comma-separated scene seeds (results are averaged)")
    p.add_argument("--values", default=None, metavar="V,V", help="override the swept values (top-k, PQ sub-vectors or resolution divisors)")
    p.add_argument("--width", type=int_range(MIN_WIDTH, MAX_WIDTH), default=None, metavar="PIXELS",
                   help="resolution: render the synthetic views this wide before dividing them (default: the preset's)")
    p.add_argument("--out-dir", type=Path, default=Path(DEFAULT_ABLATION_DIR), metavar="DIR",
                   help=f"where the PNG, JSON and cached datasets go (default: {DEFAULT_ABLATION_DIR} in the working folder; "
                        "a rerun there reuses its datasets)")
    p.set_defaults(func=run_ablate)


def _list(flag: str, text: str) -> list[str]:
    """The comma-separated entries of `flag`, stripped; UsageError for an empty one, none at all, or one given twice."""
    items = [t.strip() for t in text.split(",")]
    if not any(items):
        raise UsageError(f"{flag} {text!r} gives no value; expected a comma-separated list")
    if not all(items):
        raise UsageError(f"{flag} {text!r}: an entry is empty (two commas in a row, or one at an end)")
    refuse_repeats(flag, items)  # a mode or preset run twice costs twice the time
    return items


def _int_list(flag: str, text: str, parse) -> list[int]:
    """`_list` of integers through an argparse validator (`int_range`), each once; UsageError naming the flag."""
    values = []
    for item in _list(flag, text):
        try:
            values.append(parse(item))
        except argparse.ArgumentTypeError as exc:
            raise UsageError(f"{flag}: {exc}") from None
    refuse_repeats(flag, values, str)  # "1,01" is one value twice
    return values


def _modes(text: str | None, default: tuple[str, ...]) -> tuple[str, ...]:
    """--modes as a tuple (`default` when not given); UsageError naming any unknown mode."""
    modes = tuple(_list("--modes", text)) if text is not None else default
    bad = [m for m in modes if m not in AGGREGATE_MODES]
    if bad:
        raise UsageError(f"--modes: unknown mode {', '.join(map(repr, bad))} (modes: {', '.join(AGGREGATE_MODES)})")
    return modes


def _presets(text: str | None, several: bool) -> tuple[str, ...]:
    presets = tuple(_list("--preset", text)) if text is not None else (AGGREGATE_PRESETS if several else ("tiny",))
    bad = [p for p in presets if p not in PRESETS]
    if bad:
        raise UsageError(f"--preset: unknown preset {', '.join(map(repr, bad))} (presets: {', '.join(PRESETS)})")
    if not several and len(presets) > 1:
        raise UsageError(f"--preset {text!r}: this ablation takes one preset (only aggregate compares several)")
    return presets


@dataclass
class AblateSettings:
    """run_ablate's flags, every one checked before any work."""

    presets: tuple[str, ...]
    seeds: list[int]
    values: list[int] | None
    modes: tuple[str, ...] = ()
    sources: tuple[str | None, ...] = (None,)
    corruptions: tuple[str, ...] = ("own",)
    repeats: int = 5


def ablate_settings(args: argparse.Namespace) -> AblateSettings:
    """Every flag of `eval ablate` checked up front (UsageError, exit 2): flags the ablation does not
    read, seeds, presets, swept values, modes, mask sources, corruptions."""
    given = {"modes": args.modes, "mask_source": args.mask_source, "corruptions": args.corruptions, "repeats": args.repeats,
             "values": args.values, "width": args.width}
    unused = [f"--{k.replace('_', '-')}" for k, v in given.items() if v is not None and k not in ABLATION_FLAGS[args.ablation]]
    if unused:
        raise UsageError(f"{', '.join(unused)} {'does' if len(unused) == 1 else 'do'} not apply to the {args.ablation} ablation")
    several = args.ablation == "aggregate"
    presets = _presets(args.preset, several)
    seeds = _int_list("--seeds", args.seeds, seed_int)
    values = None if args.values is None else _int_list("--values", args.values, _value_parser(args.ablation, presets))
    settings = AblateSettings(presets, seeds, values)
    if args.ablation == "aggregate":
        modes = _modes(args.modes, AGGREGATE_MODES)
        settings.modes = modes if "paper" in modes else ("paper",) + modes  # the baseline of the summary
        settings.sources = tuple(_list("--mask-source", args.mask_source)) if args.mask_source is not None else (None,)
        settings.corruptions = tuple(_list("--corruptions", args.corruptions)) if args.corruptions is not None else ("own",)
        bad = [s for s in settings.sources if s is not None and s not in MASK_SOURCES]
        if bad:
            raise UsageError(f"--mask-source: unknown {', '.join(map(repr, bad))} (mask sources: {', '.join(MASK_SOURCES)})")
        bad = [c for c in settings.corruptions if c not in CORRUPTIONS]
        if bad:
            raise UsageError(f"--corruptions: unknown {', '.join(map(repr, bad))} (corruptions: {', '.join(CORRUPTIONS)})")
        refused = ([c for c in settings.corruptions if segmenter_corruption_error("segmenter", *CORRUPTIONS[c][1:])]
                   if "segmenter" in settings.sources else [])
        if refused:
            raise UsageError(f"--mask-source segmenter takes corruptions without jitter, merges or splits (the oracle's models of a "
                             f"segmenter's errors), not {', '.join(refused)}; e.g. clean, mislabel20")
        settings.repeats = 5 if args.repeats is None else args.repeats
    elif args.ablation == "resolution":
        settings.modes = _modes(args.modes, ("paper", DEFAULT_AGGREGATE))
        if args.mask_source is not None and args.mask_source not in MASK_SOURCES:
            raise UsageError(f"--mask-source: resolution takes one mask source ({', '.join(MASK_SOURCES)}), not {args.mask_source!r}")
        settings.sources = (args.mask_source,)
    return settings


def _value_parser(ablation: str, presets: tuple[str, ...]):
    """The argparse-style validator of one --values entry of `ablation`."""
    if ablation == "resolution":
        def divisor(text: str) -> int:
            value = int_range()(text)
            if value not in RESOLUTION_DIVISORS:
                raise argparse.ArgumentTypeError(f"{value} is not a resolution divisor (3DGS's -r: {', '.join(map(str, RESOLUTION_DIVISORS))})")
            return value
        return divisor
    if ablation == "pq":
        dim = PRESETS[presets[0]].dim

        def sub_vectors(text: str) -> int:
            value = int_range(1, dim)(text)
            if dim % value:
                raise argparse.ArgumentTypeError(f"{value} sub-vectors do not divide the {dim}-D embeddings of preset {presets[0]}")
            return value
        return sub_vectors
    return int_range(1, MAX_TOPK)


def _holds_feature_files(folder: Path) -> bool:
    """Whether `folder` holds a file named like a LangSplat feature file or drsplat's features manifest."""
    return any(next(folder.glob(pattern), None) is not None for pattern in FEATURE_FILE_PATTERNS)


DEFAULT_ABLATION_DIR = "ablations"  # the docs quote ablation commands without --out-dir (round 61d: they exited 2 as written)


def ablation_outputs(out_dir: Path, name: str) -> tuple[Path, Path]:
    """(PNG, JSON) an ablation writes, probed before the work (`check_output_writable`): a folder in
    their place or a read-only OUT_DIR would otherwise be found after minutes of registrations."""
    png, doc = out_dir / f"ablation_{name}.png", out_dir / f"ablation_{name}.json"
    if out_dir.exists() and not out_dir.is_dir():
        raise UsageError(f"--out-dir {shown_path(out_dir)}: is a file, not a folder")
    if out_dir.is_dir() and _holds_feature_files(out_dir):  # its datasets/ tree and plots would mix with a features folder (round 54)
        raise UsageError(f"--out-dir {shown_path(out_dir)}: holds LangSplat feature files (a features folder); give a folder of its own")
    check_outputs_writable(png, doc)
    return png, doc


def run_ablate(args: argparse.Namespace) -> int:
    settings = ablate_settings(args)
    png, doc = ablation_outputs(args.out_dir, args.ablation)
    token = CancelToken()
    with cancel_on_signals(token, "the current registration"):
        result = _run(args, settings, token)
    plot(result, png)
    with atomic_path(doc) as tmp:
        tmp.write_text(json_text(result.to_dict()) + "\n")
    log.info("wrote %s and %s", shown_path(png), shown_path(doc))
    return 0


def _run(args: argparse.Namespace, st: AblateSettings, cancel: CancelToken) -> AblationResult:
    """The ablation asked for, its table printed; Cancelled at the next check after Ctrl-C."""
    root = args.out_dir / "datasets"
    preset, seeds, values = st.presets[0], st.seeds, st.values
    if args.ablation == "aggregate":
        presets, modes, sources, corruptions = st.presets, st.modes, st.sources, st.corruptions
        result = ablate_aggregate(root, presets, seeds, modes, values or AGGREGATE_TOPK, cancel=cancel, mask_sources=sources,
                                  corruptions=corruptions)
        k = max(values or AGGREGATE_TOPK)
        timed = _corrupted(root, presets[-1], seeds[0], sources[0], corruptions[0])
        speed = time_aggregate_modes(timed, modes, k, st.repeats, cancel=cancel)
        result.extra["timing"] = {"preset": presets[-1], "seed": seeds[0], "topk": k, "repeats": st.repeats, "ms_per_view": speed}
        costs = corruption_costs(result, topk=k)
        lines = [result.markdown(), "", aggregate_summary(result, topk=k), "", *([costs, ""] if costs else []),
                 f"Time per view on {presets[-1]} (seed {seeds[0]}, {timed.scene.num_gaussians} Gaussians, "
                 f"{timed.cameras[0].width}x{timed.cameras[0].height}, top-k {k}), median of {st.repeats} interleaved runs:", "",
                 "| mode | ms/view | vs paper |", "|---|---:|---:|"]
        lines += [f"| {mode} | {ms:.1f} | {ms / speed['paper']:.2f}x |" for mode, ms in speed.items()]
        print("\n".join(lines))  # noqa: T201 - the tables the user asked for
        return result
    if args.ablation == "resolution":
        result = ablate_resolution(root, preset, seeds, values or RESOLUTION_VALUES, st.modes, width=args.width, mask_source=st.sources[0],
                                   cancel=cancel)
    elif args.ablation == "topk":
        result = ablate_topk(root, preset, seeds, values or TOPK_VALUES, cancel=cancel)
    elif args.ablation == "pq":
        result = ablate_pq(root, preset, seeds, values or PQ_VALUES, cancel=cancel)
    elif args.ablation == "robustness":
        result = ablate_robustness(root, preset, seeds, cancel=cancel)
    else:
        result = ablate_metrics(root, preset, seeds, cancel=cancel)
    print(result.markdown())  # noqa: T201 - the table the user asked for
    return result
