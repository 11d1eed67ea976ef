"""A scene and its cameras in one frame.

Some trainers move the world before they train, and write the scene in the moved frame while the
dataset's cameras stay where the capture put them. Registration then renders every view of a scene
it cannot see. Two such moves are undone:

- nerfstudio's splatfacto writes its move to `dataparser_transforms.json`;
  `drsplat.cameras.load_cameras` reads it when it lies beside the cameras, and
  `cameras_in_scene_frame` finds it in the run folder of a splatfacto checkpoint given as the scene.
- gsplat's `simple_trainer` (`normalize_world_space`, on by default) writes its move nowhere, but
  the move is a function of the COLMAP model alone, so it is computed here again
  (`gsplat_normalizations`), and the cameras are moved when the scene fits them only there
  (`cameras_in_scene_frame`).

gsplat's normalisation of cameras with rotations R_v (camera to world, OpenCV axes) and centres
c_v, and sparse points p_k (float32), as a similarity x' = T x:

1. Up and scale (T₁). u = normalize(mean_v R_v·(0, −1, 0)), the cameras' mean up direction. A
   rotation A takes u to (0, −1, 0) (Rodrigues about u × (0, −1, 0); a reflection of x when u is
   exactly (0, 1, 0)). With the cameras' forward axes f_v = A R_v·(0, 0, 1) and centres
   a_v = A c_v, each optical axis's closest point to the origin is a_v − (f_v·a_v) f_v; the
   translation is d = −(their per-coordinate median), and the scale s = 1 / median_v |a_v + d|.
   T₁ = s·[A | d].
2. Principal axes (T₂), of the moved points q_k = T₁ p_k: the eigenvectors of their covariance,
   largest eigenvalue first (so z is the flattest direction), the first negated when their
   determinant is negative, as the rows of a rotation B about their per-coordinate median m:
   T₂ = [B | −B m].
3. Upside down (T₃, gsplat releases since its "upside-down fix"): when the median z of T₂ q_k is
   above their mean z, T₃ = diag(1, −1, −1) turns the world over.

Releases differ in step 3, so the candidates are T₂T₁ and, where step 3 applies, T₃T₂T₁. Which
frame the scene is in is read from the sparse points, since a 3DGS scene grows from them (gsplat
seeds its Gaussians there): in its own frame they lie on its Gaussians. A candidate is taken when
the median distance from the points it moves to the nearest Gaussian centre is FRAME_FIT_GAIN times
smaller than from the points as given, and at most FRAME_FIT_MAX of the scene's size (any move that
shrinks a model lying far from the scene brings its points nearer), and the Gaussians' median
distance to the nearest moved point at most FRAME_COVER_MAX of it (points of another model, heaped
by the move onto one part of the scene: 3 points, or points 1e8 away that float32 rounds onto a
few spots, were taken before, round 23). The share of the scene the views see is no such test: a
scene near the origin and a few units across is still mostly in view after gsplat's move, and then
registers wrong (tiny, seed 1: over half of its centres inside some view as given). A model without
sparse points is left as it is (gsplat's parser cannot have read it).

gsplat's `pose_opt` also refines each training camera while it trains (CameraOptModule): row r of
its checkpoint's `pose_adjust.embeds.weight` [T, 9] = (dx, d6) turns camera-to-world C into

    C·[R_d | dx],   R_d = rotation_6d_to_matrix(d6 + (1, 0, 0, 0, 1, 0))

in the frame it trained in, where r counts its training images: the model's images in name order,
less every `test_every`-th (position i with i mod test_every = 0, held out for evaluation; 8 unless
the run's cfg.yml says otherwise). The scene fits the refined cameras, so `cameras_in_scene_frame`
refines them too (`with_pose_refinements`).

Trainers also differ in the principal point. gsplat and nerfstudio project with each camera's cx, cy;
INRIA's gaussian-splatting (and the LangSplat / Dr. Splat code built on it) keeps only a COLMAP
camera's two fields of view and projects about the image centre. A scene trained so, registered
with a calibrated principal point 1.35 % of the width off-centre (fox's), is registered shifted by
that much in every view (seg mIoU 0.730 against 0.950 on a probe, round 54).
`cameras_with_principal_point` tells the two apart by which reading the scene re-renders its
training images under.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from drsplat.cameras import (DATAPARSER_TRANSFORMS, AppliedMove, Camera, applied_move, dataparser_transforms_path, dataset_in_trained_frame,
                             detect_dataset, folder_prefixes, in_trained_frame, load_image, off_size_factors, qvec_to_rotmat, run_orientation,
                             read_colmap_model, read_dataparser_transform)
from drsplat.defaults import DEFAULT_NEAR_PLANE, DEFAULT_PRINCIPAL_POINT, INRIA_NEAR, NEAR, PRINCIPAL_POINTS
from drsplat.errors import InputError
from drsplat.raster import faint_share, median_seen_depth, near_band, prepare_scene, rasterize, share_in_some_view
from drsplat.scene import counted
from drsplat.utils import CancelToken, real_number, spread_rows

log = logging.getLogger(__name__)

FRAME_SAMPLE = 20_000  # sparse points the frame decision measures (and 10x as many Gaussian centres it measures them against)
FRAME_FIT_GAIN = 4.0  # a move is taken when the sparse points lie this many times nearer the scene there than as given
FRAME_FIT_MAX = 0.05  # ... and on the scene there: their median distance to it at most this share of its size (any move that shrinks a far model nears it)
FRAME_COVER_MAX = 0.1  # ... and the scene on them: the Gaussians' median distance to the nearest point at most this share (points heaped on a part of it)
SPLATFACTO_FRAME = ("nerfstudio's splatfacto exports in its dataparser frame: put the run's dataparser_transforms.json beside the "
                    "dataset's cameras, in place of any other run's")  # the remedy both frame warnings give (round 57a: it is there already when a wrong one is)
LOW_SEEN_FRACTION = 0.5  # below this share of the Gaussians' centres inside some view, a scene is most likely in another frame than its cameras (`frame_hint`)
CAMERA_UP = np.array([0.0, -1.0, 0.0])  # OpenCV camera axes: y points down
CAMERA_FORWARD = np.array([0.0, 0.0, 1.0])
GSPLAT_TEST_EVERY = 8  # gsplat's default: every 8th image (in name order) is held out of training
GSPLAT_CONFIG = "cfg.yml"  # simple_trainer's dump of its settings, in its result_dir (its checkpoints: result_dir/ckpts/)
UNREADABLE = "(unreadable)"  # `gsplat_run_settings`' key for a cfg.yml it could not read (no YAML key has this form)
GSPLAT_CONFIG_BYTES = 1 << 20  # what is read of it (gsplat's is a few kB; test_every sits among its first lines)
IDENTITY_6D = np.array([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])  # the 6-D form of no rotation
REFINED_COMMENT = "drsplat cameras refined by the gsplat pose_opt of "  # + the checkpoint: a registered PLY's header (`refinement_comment`)


@dataclass(frozen=True)
class FrameMove:
    """A similarity x' = s·(R x + t) from the cameras' frame to a trainer's. name: which trainer's
    move it is, in words; matrix: [4, 4] the same move as a matrix, [s·R | s·t]."""

    name: str
    matrix: np.ndarray

    @property
    def scale(self) -> float:
        """s, the length of the 3x3 part's rows (R may be a reflection: gsplat's T₁ for cameras whose up is +y)."""
        return float(np.linalg.norm(self.matrix[0, :3]))

    @property
    def rotation(self) -> np.ndarray:
        return self.matrix[:3, :3] / self.scale

    @property
    def translation(self) -> np.ndarray:
        return self.matrix[:3, 3] / self.scale

    def cameras(self, cameras: Sequence[Camera]) -> list[Camera]:
        """`cameras` moved into the trainer's frame (`cameras.in_trained_frame`)."""
        rotation, translation, scale = self.rotation, self.translation, self.scale
        return [in_trained_frame(c, rotation, translation, scale) for c in cameras]


def up_and_scale(camtoworlds: np.ndarray) -> np.ndarray:
    """T₁ [4, 4] of gsplat's normalisation (module docstring, step 1). camtoworlds: [V, 4, 4] OpenCV."""
    rot, centres = camtoworlds[:, :3, :3], camtoworlds[:, :3, 3]
    up = (rot @ CAMERA_UP).mean(axis=0)
    up /= np.linalg.norm(up)
    cos = float(up @ CAMERA_UP)
    k = np.cross(up, CAMERA_UP)
    skew = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    align = np.eye(3) + skew + skew @ skew / (1.0 + cos) if cos > -1.0 else np.diag([-1.0, 1.0, 1.0])
    forward = (align @ rot) @ CAMERA_FORWARD
    moved = centres @ align.T
    closest = moved - np.sum(forward * moved, axis=-1, keepdims=True) * forward
    shift = -np.median(closest, axis=0)
    scale = 1.0 / np.median(np.linalg.norm(moved + shift, axis=-1))
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = scale * align, scale * shift
    return out


def principal_axes(points: np.ndarray) -> np.ndarray:
    """T₂ [4, 4] of gsplat's normalisation (module docstring, step 2). points: [P, 3], P ≥ 2."""
    centre = np.median(points, axis=0)
    values, vectors = np.linalg.eigh(np.cov(points - centre, rowvar=False))
    vectors = vectors[:, np.argsort(values)[::-1]]
    if np.linalg.det(vectors) < 0:
        vectors[:, 0] *= -1.0
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = vectors.T, -vectors.T @ centre
    return out


def move_points(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[P, 3] float64: matrix [4, 4] applied to points [P, 3]."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def gsplat_normalizations(camtoworlds: np.ndarray, points: np.ndarray) -> list[FrameMove]:
    """The frames gsplat's simple_trainer may have trained in, for its COLMAP model: camtoworlds [V, 4, 4]
    (every image of the model, OpenCV), points [P, 3] its sparse points (P ≥ 3; gsplat's Parser
    always has them: they also seed its Gaussians). Moves that are not finite (a non-finite point, or
    cameras all at one place looking one way: gsplat's own training would be NaN there too) are left out."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        first = up_and_scale(np.asarray(camtoworlds, np.float64))
        moved = move_points(first, np.asarray(points, np.float32))  # gsplat holds the points in float32
        if not (np.isfinite(first).all() and np.isfinite(moved).all()):
            return []
        second = principal_axes(moved) @ first
        found = [FrameMove("gsplat's normalised world", second)]
        heights = move_points(second, np.asarray(points, np.float32))[:, 2]
        if np.median(heights) > np.mean(heights):
            found.append(FrameMove("gsplat's normalised world, turned upright", np.diag([1.0, -1.0, -1.0, 1.0]) @ second))
    return [m for m in found if np.isfinite(m.matrix).all() and m.scale > 0]


@dataclass
class ColmapEvidence:
    """What a COLMAP dataset tells of the frame it was trained in: camtoworlds [V, 4, 4] (every image
    of the model, OpenCV) and points [P, 3] its sparse points (P ≥ 3)."""

    camtoworlds: np.ndarray
    points: np.ndarray

    def moves(self) -> list[FrameMove]:
        return gsplat_normalizations(self.camtoworlds, self.points)


def colmap_evidence(source: str | Path) -> ColmapEvidence | None:
    """The ColmapEvidence of dataset `source`; None for another camera format, a model without images
    or without 3 sparse points (gsplat cannot have trained on it), or cameras nerfstudio's dataparser
    transform moved already."""
    try:
        kind, found = detect_dataset(source)
    except InputError:
        return None
    if kind != "colmap" or dataparser_transforms_path(source) is not None:
        return None
    model = read_colmap_model(found)
    if not model.images or len(model.points) < 3:
        return None
    worldtocams = np.tile(np.eye(4), (len(model.images), 1, 1))
    for m, image in zip(worldtocams, model.images.values()):
        m[:3, :3], m[:3, 3] = qvec_to_rotmat(np.asarray(image.qvec, np.float64)), image.tvec
    return ColmapEvidence(np.linalg.inv(worldtocams), np.array(list(model.points.values()), np.float64))


def point_misfit(tree: cKDTree, spread: float, points: np.ndarray) -> float:
    """median_k |p_k − nearest point of the tree| / spread: how far points [P, 3] lie from the tree's
    points, in units of the scene's size. Sparse points against the scene's centres: a 3DGS scene
    grows from its sparse points, so in its own frame they lie on it, about the spacing of its
    Gaussians apart; the centres against the points: how well the points cover the scene."""
    distances, _ = tree.query(points, k=1, workers=-1)
    return float(np.median(distances) / spread)


def scene_sample(means: np.ndarray) -> tuple[np.ndarray, float] | None:
    """(up to FRAME_SAMPLE·10 of the finite centres means [N, 3], their spread: the median distance from
    their median), or None without two finite centres or with no spread."""
    finite = np.asarray(means, np.float64)
    finite = finite[np.isfinite(finite).all(axis=1)]
    finite = spread_rows(finite, 10 * FRAME_SAMPLE)
    if len(finite) < 2:
        return None
    spread = float(np.median(np.linalg.norm(finite - np.median(finite, axis=0), axis=1)))
    return (finite, spread) if spread > 0 else None


def best_move(means: np.ndarray, evidence: ColmapEvidence) -> tuple[FrameMove, str] | None:
    """The move of evidence.moves() the scene of centres means [N, 3] was trained in, with why, or
    None for the cameras' own frame: the move under which the sparse points lie on the scene and the
    scene on them, each within its bar of the scene's size (FRAME_FIT_MAX, FRAME_COVER_MAX), and the
    points FRAME_FIT_GAIN times nearer it than as given (`point_misfit` both ways)."""
    moves = evidence.moves()  # none when gsplat could not have normalised this model (a non-finite point)
    sample = scene_sample(means) if moves else None
    if sample is None:
        return None
    centres, spread = sample
    tree = cKDTree(centres)
    points = spread_rows(evidence.points, FRAME_SAMPLE)
    given = point_misfit(tree, spread, points)
    misfits = [point_misfit(tree, spread, move_points(m.matrix, points)) for m in moves]
    k = int(np.argmin(misfits))
    if not (misfits[k] * FRAME_FIT_GAIN < given and misfits[k] <= FRAME_FIT_MAX):
        return None
    cover = point_misfit(cKDTree(move_points(moves[k].matrix, points)), spread, spread_rows(centres, FRAME_SAMPLE))
    if not cover <= FRAME_COVER_MAX:  # points of another model that the move heaps onto one part of the scene
        return None
    return moves[k], (f"the COLMAP model's sparse points lie {given:.3g} scene sizes from its Gaussians as given and {misfits[k]:.3g} "
                      f"there, where its Gaussians lie {cover:.3g} from them")


def run_dataparser_transform(scene_path: str | Path) -> Path | None:
    """The dataparser_transforms.json of the nerfstudio run a checkpoint belongs to, if it is there:
    ns-train saves outputs/<experiment>/<method>/<timestamp>/ with config.yml and that file beside
    nerfstudio_models/step-<step>.ckpt, so it lies two folders above the checkpoint."""
    path = Path(scene_path).absolute()  # "step-1.ckpt" given from inside nerfstudio_models: its run folder is not "."'s parent
    if path.suffix.lower() != ".ckpt":
        return None
    found = path.parent.parent / DATAPARSER_TRANSFORMS
    return found if found.is_file() else None


def cameras_in_scene_frame(means: np.ndarray, cameras: list[Camera], source: str | Path, what: str = "the scene",
                           scene_path: str | Path | None = None, refinements: np.ndarray | None = None) -> list[Camera]:
    """`cameras` (from dataset `source`) in the frame their scene was trained in, with one warning
    that names the move (`what`: the scene, as the warning calls it); else `cameras` themselves:
    - a nerfstudio checkpoint (scene_path) whose run folder holds dataparser_transforms.json, when no
      such file lies beside the cameras (`cameras.load_cameras` applies that one): its move;
    - else gsplat's normalised world, when `best_move` finds the scene of centres means [N, 3] in it;
    - then, for a gsplat checkpoint trained with pose_opt, its camera refinements (`with_pose_refinements`;
      refinements: its load report's `camera_refinements`, read with the scene)."""
    run = run_dataparser_transform(scene_path) if scene_path is not None and dataparser_transforms_path(source) is None else None
    if run is not None:
        moved, scale, undone = dataset_in_trained_frame(run, *detect_dataset(source), cameras)  # as the file beside the cameras is read
        log.warning("%s was trained by nerfstudio in the frame of its run's %s: the %d cameras of %s are moved there (scale %.6g%s)",
                    what, run, len(cameras), source, scale, f"; after undoing {undone}, which the run's file includes" if undone else "")
        return moved
    evidence = colmap_evidence(source)
    found = best_move(means, evidence) if evidence is not None and len(means) else None
    if found is not None:
        move, why = found
        log.warning("%s is in %s, not in the frame of the cameras of %s (%s; gsplat's simple_trainer trains there unless "
                    "normalize_world_space is off): the %d cameras are moved there (scale %.6g)", what, move.name, source, why,
                    len(cameras), move.scale)
        cameras = move.cameras(cameras)
    return with_pose_refinements(cameras, source, scene_path, refinements, what) if scene_path is not None else cameras


def rotation_6d_to_matrix(d6: np.ndarray) -> np.ndarray:
    """[..., 3, 3] the rotations of 6-D representations d6 [..., 6] (Zhou et al. 2019; gsplat's
    examples/utils.py): Gram-Schmidt on a₁ = d6[:3], a₂ = d6[3:],

        b₁ = a₁ / |a₁|,   b₂ = normalize(a₂ − (b₁·a₂) b₁),   b₃ = b₁ × b₂,

    the rows of the matrix (normalize divides by max(|x|, 1e-12), as torch's F.normalize)."""
    def normalize(x: np.ndarray) -> np.ndarray:
        return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)

    a1, a2 = d6[..., :3], d6[..., 3:]
    b1 = normalize(a1)
    b2 = normalize(a2 - np.sum(b1 * a2, axis=-1, keepdims=True) * b1)
    return np.stack([b1, b2, np.cross(b1, b2)], axis=-2)


def pose_refined(camera: Camera, delta: np.ndarray) -> Camera:
    """`camera` refined by delta [9] = (dx [3], d6 [6]), one row of gsplat's CameraOptModule: its
    camera-to-world C becomes C·[R_d | dx], R_d = rotation_6d_to_matrix(d6 + IDENTITY_6D), so
    world-to-camera R' = R_dᵀ R and t' = R_dᵀ (t − dx) (the centre moves by dx along the camera's axes)."""
    turn = rotation_6d_to_matrix(np.asarray(delta[3:], np.float64) + IDENTITY_6D)
    r, t = np.asarray(camera.R, np.float64), np.asarray(camera.t, np.float64)
    return dataclasses.replace(camera, R=turn.T @ r, t=turn.T @ (t - np.asarray(delta[:3], np.float64)))


def training_names(names: Sequence[str], test_every: int) -> list[str]:
    """gsplat's training images in order (its Dataset "train" split): `names` (the COLMAP model's image
    names) sorted, less those at positions i with i mod test_every = 0."""
    ordered = sorted(names)
    return [name for i, name in enumerate(ordered) if i % test_every != 0]


def gsplat_run_settings(scene_path: str | Path) -> tuple[dict[str, str], Path | None]:
    """The top-level `key: value` lines of the cfg.yml of the gsplat run checkpoint `scene_path`
    belongs to (result_dir/ckpts/ckpt_<step>_rank<r>.pt: two folders up) and its path; ({}, None)
    without one; {UNREADABLE: why} when it cannot be read. Read as lines, not as YAML: gsplat dumps
    its strategy objects with Python tags."""
    found = Path(scene_path).absolute().parent.parent / GSPLAT_CONFIG  # absolute: "ckpt.pt" given from inside ckpts/
    if not found.is_file():
        return {}, None
    try:
        with open(found, "rb") as f:
            raw = f.read(GSPLAT_CONFIG_BYTES)
    except OSError as exc:
        return {UNREADABLE: exc.strerror or type(exc).__name__}, found
    encoding = "utf-16" if raw[:2] in (b"\xff\xfe", b"\xfe\xff") else "utf-8-sig"  # a BOM: an editor's (or PowerShell's) copy
    text = raw.decode(encoding, errors="replace")
    lines = re.split(r"\r\n|\r|\n", text)
    return {m.group(1): m.group(2).strip() for line in lines if (m := re.fullmatch(r"([A-Za-z_]\w*):[ \t]*(.*)", line))}, found


def _test_every(settings: dict[str, str], config: Path | None) -> tuple[int | None, str]:
    """(the run's test_every, where it came from); None with why when cfg.yml gives no usable one."""
    if config is None:
        return GSPLAT_TEST_EVERY, f"gsplat's default test_every {GSPLAT_TEST_EVERY} (no {GSPLAT_CONFIG} two folders above the checkpoint)"
    if UNREADABLE in settings:
        return None, f"{config} cannot be read ({settings[UNREADABLE]})"
    if "test_every" not in settings:  # gsplat dumps every setting: a file without it is not (all of) its cfg.yml
        return None, f"{config} gives no test_every (not gsplat's settings, or cut short)"
    value = settings["test_every"]
    if not re.fullmatch(r"\d{1,9}", value) or int(value) < 1:
        return None, f"{config} gives test_every {value!r}, not a positive whole number"
    return int(value), f"test_every {int(value)} from {config}"


def with_pose_refinements(cameras: list[Camera], source: str | Path, scene_path: str | Path, deltas: np.ndarray | None,
                          what: str = "the scene") -> list[Camera]:
    """`cameras` (dataset `source`, in the frame the scene trained in) refined as the gsplat checkpoint
    `scene_path` refined them while training (`pose_opt`; module docstring): deltas [T, 9] its
    refinements as its load report holds them (`LoadReport.camera_refinements`), None without. One
    warning says so; `cameras` themselves when there are none. The refinements are left out, with a
    warning that says why, when they cannot be matched to the cameras (`_unmatched`). A camera whose
    row is not finite, whose 6-D offset gives no rotation, or whose shift is longer than the whole
    rig's reach (no refinement of a trained pose moves it so far) keeps its pose (counted in the warning)."""
    if deltas is None:
        return cameras
    settings, config = gsplat_run_settings(scene_path)
    test_every, told = _test_every(settings, config)
    names = _colmap_image_names(source)
    train = training_names(names, test_every) if names is not None and test_every is not None else None
    why = _unmatched(deltas, settings, config, test_every, told, names, train, source)
    if why:
        log.warning("%s holds %s camera refinements (gsplat's pose_opt), not applied: %s", what, f"{len(deltas):,}", why)
        return cameras
    prefixes = folder_prefixes(names) or {}  # the views' names as the reader gives them (round 58a: a rig's matched no row)
    row_of = {prefixes.get(name, "") + Path(name).stem: r for r, name in enumerate(train)}
    centres = np.array([np.asarray(c.center, np.float64) for c in cameras]) if cameras else np.zeros((0, 3))
    reach = float(np.max(np.linalg.norm(centres - centres.mean(axis=0), axis=1))) if len(centres) > 1 else np.inf
    with np.errstate(invalid="ignore", over="ignore"):
        turns = rotation_6d_to_matrix(deltas[:, 3:] + IDENTITY_6D)
        usable = (np.isfinite(deltas).all(axis=1) & (np.abs(np.linalg.det(turns) - 1.0) < 1e-6)  # a 6-D offset of -identity has no rotation
                  & ~(np.linalg.norm(deltas[:, :3], axis=1) > (reach if reach > 0 else np.inf)))
    out, refined, shifts = [], 0, []
    for camera in cameras:
        r = row_of.get(camera.name)
        if r is None or not usable[r]:
            out.append(camera)
            continue
        out.append(pose_refined(camera, deltas[r]))
        refined += 1
        shifts.append(float(np.linalg.norm(deltas[r, :3])))
    bad = int(np.count_nonzero(~usable))
    log.warning("%s was trained with refined camera poses (gsplat's pose_opt): %d of the %d cameras of %s take its refinements "
                "(%s; largest shift %.3g scene units)%s", what, refined, len(cameras), source, told, max(shifts, default=0.0),
                f"; {bad} refinements not finite, of no rotation or shifting a camera beyond the rig's reach ({reach:.3g}), not applied"
                if bad else "")
    return out


def refinement_comment(scene_path: str | Path) -> str | None:
    """The PLY header comment a registration writes when its scene, the gsplat checkpoint `scene_path`,
    holds camera refinements, so that evaluating the registered scene decides on them as the
    registration did (`refined_by`); None for a path a header line cannot hold (a line break in it)."""
    text = f"{REFINED_COMMENT}{Path(scene_path).absolute()}"
    return None if "\n" in text or "\r" in text else text


def refined_by(comments: Sequence[str]) -> Path | None:
    """The checkpoint whose camera refinements a registered scene was registered with (its
    `refinement_comment`), or None."""
    found = next((c for c in comments if c.startswith(REFINED_COMMENT)), None)
    return Path(found[len(REFINED_COMMENT):]) if found is not None else None


def _unmatched(deltas: np.ndarray, settings: dict[str, str], config: Path | None, test_every: int | None, told: str,
               names: list[str] | None, train: list[str] | None, source: str | Path) -> str:
    """Why refinements deltas [T, 9] cannot be matched to the cameras of `source` (its COLMAP model's
    image names, None for another format; train: `training_names` of them), or "": cfg.yml's test_every unusable (`told` why), a run
    its cfg.yml says did not refine poses or read no COLMAP model, one that perturbed its cameras
    (pose_noise > 0: the perturbation is not saved), or a count that is not the model's training images'."""
    if test_every is None:
        return told
    if settings.get("pose_opt", "true").lower() in ("false", "no", "off"):
        return f"{config} says pose_opt: {settings['pose_opt']} (a checkpoint of another run?)"
    if settings.get("data_type", "colmap").strip("'\"") != "colmap":
        return f"{config} says data_type: {settings['data_type']}, and only a COLMAP dataset's training order is known"
    if names is None:
        return f"gsplat numbers them by a COLMAP model's images, and {source} is none"
    noise = settings.get("pose_noise", "0")
    try:
        perturbed = not float(noise) <= 0.0  # gsplat perturbs when pose_noise > 0; NaN or unreadable: assume it did
    except ValueError:
        perturbed = True
    if perturbed:
        return f"the run perturbed its cameras (pose_noise {noise} in {config}), and the perturbation is not saved"
    if len(train) != len(deltas):
        return (f"the COLMAP model of {source} has {len(train)} training images ({len(names)} images, every {test_every}-th held out: "
                f"{told})")
    return ""


def _colmap_image_names(source: str | Path) -> list[str] | None:
    """The image names of dataset `source`'s COLMAP model, or None for another camera format."""
    try:
        kind, found = detect_dataset(source)
    except InputError:
        return None
    if kind != "colmap":
        return None
    return [image.name for image in read_colmap_model(found).images.values()]


def frame_hint(means: np.ndarray, cameras: Sequence[Camera], near: float = NEAR) -> str:
    """'; only k% of the Gaussians' centres lie inside any view: ...' when fewer than LOW_SEEN_FRACTION
    of them do (`raster.share_in_some_view`), with where a scene in another frame than its cameras
    comes from; "" otherwise (the registration's warnings and errors end with it)."""
    seen = share_in_some_view(means, cameras, near=near)
    if seen >= LOW_SEEN_FRACTION:
        return ""
    return (f"; only {100 * seen:.0f}% of the Gaussians' centres lie inside any view: the scene may be in another frame than its "
            f"cameras ({SPLATFACTO_FRAME}, and drsplat moves the cameras there; gsplat's simple_trainer normalises the world unless normalize_world_space "
            "is off: `drsplat register` moves a COLMAP dataset's cameras there itself, from the model's images and sparse points, "
            "which must be those gsplat was trained on): give the cameras of the scene's frame")


PHOTO_CHECK_VIEWS = 4  # views re-rendered by `warn_if_scene_misses_its_images`, spread over the training order
PHOTO_CHECK_WIDTH = 96  # px: the longer side they are compared at (a frame mismatch shows at any size; this keeps it a few ms)
PHOTO_CHECK_SAMPLE = 1_000_000  # Gaussians rendered at most: a spread subset of a larger scene shows the same picture, sparser
# ... but only so much sparser: flowers (542k) in its own frame correlated 0.98 whole, 0.77 on a fifth of it, 0.45 on
# a 27th (round 52), so a scene over this many times the sample is not checked (a false alarm at 25M otherwise)
PHOTO_CHECK_MAX_THINNING = 4
PHOTO_SUPERSAMPLE = 4  # render samples per compared pixel, a side (`supersampled_render`)
FLAT_GREY = 1e-6  # grey-level spread under which an image is flat (8-bit steps are 4e-3)
PHOTO_MIN_PIXELS = 100  # covered pixels a view needs to count
# median correlation under which the scene does not show its own training images: its own frame gave
# 0.91-1.00 on every synthetic room preset (2 seeds), 0.86 on city (whose images show one room
# each), 0.98 on flowers.ply against its own 640x480 renders; moves of it 0.0-0.80 (a room turned
# half round about its up axis looks much like itself; turned about another axis, shrunk, shifted,
# flipped: mostly under 0.55)
PHOTO_MATCH_MIN = 0.6


def grey_correlation(render: np.ndarray, image: np.ndarray, covered: np.ndarray) -> float:
    """Pearson correlation ρ of two images' grey levels over the pixels `covered`.

    render, image: [H, W, 3] in [0, 1]; covered: [H, W] bool. With g = (R + G + B) / 3,

        ρ = Σ (r − r̄)(g − ḡ) / √(Σ (r − r̄)² · Σ (g − ḡ)²)    over covered pixels,

    invariant to a gain and an offset of either image (a trainer's exposure or appearance
    compensation keeps ρ high), NaN when either is flat over them.
    """
    r = render[covered].mean(axis=1, dtype=np.float64)
    g = image[covered].mean(axis=1, dtype=np.float64)
    if r.size < 2 or r.std() < FLAT_GREY or g.std() < FLAT_GREY:  # rounding, not a picture: no correlation to speak of
        return float("nan")
    r, g = r - r.mean(), g - g.mean()
    return float(np.dot(r, g) / np.sqrt(np.dot(r, r) * np.dot(g, g)))


def over_fitted_background(rgb: np.ndarray, alpha: np.ndarray, image: np.ndarray) -> np.ndarray:
    """A render over black, rgb [H, W, 3] with alpha [H, W], put over the background colour that
    explains image [H, W, 3] best, with t = 1 − α, per channel by least squares over all pixels:

        I ≈ a·C + b·t + c,   C' = C + t·b / a   (C alone where a ≤ 0),

    since trainers composite over a background of their own (white for NeRF-synthetic captures,
    a random or learned one) and the scene's partly transparent pixels show it, while a photo's
    exposure and white balance (a, c) differ from the render's: fitting b without them took a
    darker photo for a darker background and misjudged a scene in its own frame (round 52)."""
    t = 1.0 - alpha.astype(np.float64).ravel()
    out = rgb.astype(np.float64)
    if not np.any(t > 0):
        return out
    for ch in range(3):
        design = np.stack([out[..., ch].ravel(), t, np.ones_like(t)], axis=1)
        (a, b, _), *_ = np.linalg.lstsq(design, image[..., ch].astype(np.float64).ravel(), rcond=None)
        if a > 0:
            out[..., ch] += (b / a) * t.reshape(alpha.shape)
    return out


def supersampled_render(prepared, camera: Camera, factor: int, near: float = NEAR) -> tuple[np.ndarray, np.ndarray]:
    """(rgb [H, W, 3], alpha [H, W]) of the camera's view over black, each pixel the mean of a
    factor x factor block of a render `factor` times the size: a photo's pixel averages its
    footprint, and a dense scene's sub-pixel Gaussians rendered at one sample a pixel alias (a real
    scene, flowers at 96 px: correlation 0.62 with its own 640 px renders, 0.94 at 320 px). near: the
    near plane (a capture registered at another plane is checked at it: round 64c)."""
    big = camera.scaled(factor)
    raster = rasterize(prepared, big, 1, with_rgb=True, near=near)
    h, w = camera.height, camera.width
    rgb = raster.rgb[: h * factor, : w * factor].reshape(h, factor, w, factor, 3).mean(axis=(1, 3))
    alpha = raster.alpha[: h * factor, : w * factor].reshape(h, factor, w, factor).mean(axis=(1, 3))
    return rgb, alpha


def photo_scene(scene, sample: int = PHOTO_CHECK_SAMPLE):
    """The prepared scene `photo_agreement` renders: `scene`, or over `sample` Gaussians a subset spread over the file."""
    subset = scene if scene.num_gaussians <= sample else scene.subset(spread_rows(np.arange(scene.num_gaussians), sample))
    return prepare_scene(subset, warn=False)  # a sample for a check: the registration's own render says what it leaves out


def view_picture(camera: Camera, width: int, pictures: dict, skipped: Counter) -> tuple[Camera, np.ndarray | None]:
    """(the camera at `width` px on its longer side, its training image at that size [H, W, 3] float32 in [0, 1], or
    None when it cannot be used: why is counted in `skipped`). pictures: the images read so far, by file and size (or
    why one could not be used), so that each is decoded once."""
    # at the camera file's own size, not a --resolution's: a view of a few pixels aliases its render (round 52)
    full = camera if camera.unscaled_size is None else camera.scaled(camera.unscaled_size[0] / camera.width)
    small = full.scaled(min(1.0, width / max(full.width, full.height)))  # the longer side: a 10 x 100000 camera is no 96 x 960000 render
    if small.width * small.height < PHOTO_MIN_PIXELS:  # no render of it could cover enough to count: not "shows nothing" (round 104b F1)
        skipped[TOO_SMALL_VIEW] += 1
        return small, None
    key = (camera.image_path, small.width, small.height)
    if key not in pictures:
        try:
            pictures[key] = load_image(small).astype(np.float32) / 255.0  # resized from the file with a filter that averages
        except InputError as exc:  # the registration does not need the image: an unusable one only leaves this view out
            pictures[key] = OTHER_ASPECT_IMAGE if exc.field == "size" else UNREADABLE_IMAGE  # (round 57a: both were "could not be read")
    picture = pictures[key]
    if isinstance(picture, str):
        skipped[picture] += 1
        return small, None
    return small, picture


def photo_agreement(scene, cameras: Sequence[Camera], views: int = PHOTO_CHECK_VIEWS, width: int = PHOTO_CHECK_WIDTH,
                    sample: int = PHOTO_CHECK_SAMPLE, supersample: int = PHOTO_SUPERSAMPLE, prepared=None,
                    pictures: dict | None = None, skipped: Counter | None = None, near: float = NEAR) -> dict[str, float]:
    """How well the scene re-renders its training images: camera name -> `grey_correlation` of the
    scene's render (black background) and the camera's image, both `width` px on their longer side, over the pixels
    the render covers (α ≥ ½), for up to `views` cameras with an image file, spread over the list.

    A 3DGS scene is fitted to exactly these images, so in its cameras' frame ρ is near 1; in
    another frame (moved, turned, scaled) its render shows other things where the image has its
    own, and ρ is near 0. Views whose image is no regular file or cannot be read, or where the render covers under
    PHOTO_MIN_PIXELS pixels, are left out (no picture to compare). scene: a GaussianScene of N
    Gaussians; over `sample`, a subset spread over the file is rendered. prepared: that subset's
    `photo_scene`, when the caller renders it more than once. pictures: the images read so far, by
    file and size (or why one could not be used), for a caller that compares readings of the same cameras (each image is decoded
    once: round 56b, 6400x4800 JPEGs were decoded twice); skipped: counts why views were left out.
    """
    for label, value in (("views", views), ("width", width), ("sample", sample), ("supersample", supersample)):
        if value < 1:
            raise ValueError(f"photo_agreement: {label} must be at least 1, got {value}")
    pictures = {} if pictures is None else pictures
    skipped = Counter() if skipped is None else skipped
    with_images = [c for c in cameras if c.image_path is not None and c.image_path.is_file()]  # a named pipe would block the open
    skipped[NO_IMAGE_FILE] += len(cameras) - len(with_images)
    if scene.num_gaussians == 0:
        skipped[EMPTY_SCENE] += len(with_images)
    if not with_images or scene.num_gaussians == 0:
        return {}
    picked = [with_images[i] for i in spread_rows(np.arange(len(with_images)), views)]
    prepared = photo_scene(scene, sample) if prepared is None else prepared
    out: dict[str, float] = {}
    for camera in picked:
        small, picture = view_picture(camera, width, pictures, skipped)
        if picture is None:
            continue
        rgb, alpha = supersampled_render(prepared, small, supersample, near)
        covered = alpha >= 0.5
        if np.count_nonzero(covered) < PHOTO_MIN_PIXELS:
            skipped[LITTLE_COVERED] += 1
            continue
        rho = grey_correlation(over_fitted_background(rgb, alpha, picture), picture, covered)
        if np.isfinite(rho):
            out[camera.name] = rho
        else:
            skipped[FLAT_PICTURE] += 1
    return out


NO_IMAGE_FILE = "with no image file"  # why `photo_agreement` left views out (its `skipped` counts), in words
UNREADABLE_IMAGE = "whose image could not be read"
OTHER_ASPECT_IMAGE = "whose image has another aspect ratio than its camera (another dataset's images, or rotated photos?)"
LITTLE_COVERED = f"where the render covers under {PHOTO_MIN_PIXELS} pixels"
TOO_SMALL_VIEW = f"of under {PHOTO_MIN_PIXELS} pixels at the check's {PHOTO_CHECK_WIDTH} px on the longer side, too few to compare"
FLAT_PICTURE = "where the image or the render is one flat grey"
EMPTY_SCENE = "of a scene with no Gaussians to render"
NOT_ITS_IMAGE = f"whose render correlates under {PHOTO_MATCH_MIN} with its image"


def skipped_views(skipped: Counter) -> str:
    """`photo_agreement`'s skipped counts in words: "3 views whose image could not be read, 1 view with no image file"."""
    return ", ".join(f"{counted(n, 'view', 'views')} {why}" for why, n in skipped.items() if n) or "no view was left out"


PRINCIPAL_POINT_VIEWS = 8  # views `cameras_with_principal_point` renders under each reading
PRINCIPAL_POINT_MIN_SHIFT = 1e-3  # of the longer side: principal points nearer their centres are taken as given (0.1 px at the check's 96 px)
# median gain of grey correlation that decides for the centres. Round 55a, 360 decisions on tiny, small, hard-room and
# demo (seeds 0-2): a scene trained with the file's principal points kept them in every case; one trained about the
# centres was found in every case from 1 % of the width off, and in some at 0.2-0.5 % (a sub-pixel shift: the
# renders' own half-pixel biases are as large there)
PRINCIPAL_POINT_MARGIN = 2e-3


def cameras_as_trained(scene, cameras: Sequence[Camera], source: str | Path, principal_point: str = DEFAULT_PRINCIPAL_POINT,
                       what: str = "the scene", scene_path: str | Path | None = None,
                       refinements: np.ndarray | None = None, cancel: CancelToken | None = None, near: float = NEAR) -> list[Camera]:
    """`cameras` of dataset `source` as their scene (a GaussianScene) was trained with them: moved into
    its frame (`cameras_in_scene_frame`), the readings a nerfstudio run leaves open decided
    (`cameras_of_nerfstudio_run`), then with its principal points (`cameras_with_principal_point`,
    `principal_point` its choice). Each step renders views of the scene when it must decide; `cancel`
    (the viewer's, when another check replaces this one) is honoured between them (Cancelled). near: the
    plane the renders are drawn at (the registration's `--near-plane`)."""
    cameras = cameras_in_trained_frame(scene, cameras, source, what=what, scene_path=scene_path, refinements=refinements, cancel=cancel,
                                       near=near)
    return cameras_with_principal_point(scene, cameras, principal_point, what=what, source=source, near=near)


def cameras_in_trained_frame(scene, cameras: Sequence[Camera], source: str | Path, what: str = "the scene",
                             scene_path: str | Path | None = None, refinements: np.ndarray | None = None,
                             cancel: CancelToken | None = None, near: float = NEAR) -> list[Camera]:
    """`cameras_as_trained` up to the principal points: moved into the scene's frame and a nerfstudio run's open
    readings decided (Cancelled between the steps when `cancel` is)."""
    stop = cancel.raise_if_cancelled if cancel is not None else (lambda: None)
    cameras = cameras_in_scene_frame(scene.means, list(cameras), source, what=what, scene_path=scene_path, refinements=refinements)
    stop()
    run = nerfstudio_run_file(source, scene_path)
    if run is not None:
        cameras = cameras_of_nerfstudio_run(scene, cameras, *run, what=what, near=near)
        stop()
    return cameras


def given_near_plane(near_plane: float | str) -> float:
    """A near plane given as a number: a positive, finite depth in scene units, else one ValueError (round 67a F8: the
    Python API rendered principal-point views at -1, 0, NaN or inf, and "inria" was "could not convert string to float";
    the command line's own parser names its words)."""
    plane = real_number(near_plane)
    if not (math.isfinite(plane) and plane > 0):
        raise ValueError(f"near_plane: expected \"auto\" or a positive, finite camera depth in scene units (0.01: gsplat's, 0.2: "
                         f"INRIA's), got {near_plane!r}")
    return plane


def cameras_and_plane_as_trained(scene, cameras: Sequence[Camera], source: str | Path, principal_point: str = DEFAULT_PRINCIPAL_POINT,
                                 near_plane: float | str = DEFAULT_NEAR_PLANE, what: str = "the scene",
                                 scene_path: str | Path | None = None, refinements: np.ndarray | None = None,
                                 cancel: CancelToken | None = None,
                                 before_deciding: Callable[[list[Camera]], None] | None = None) -> tuple[list[Camera], float]:
    """(`cameras_as_trained`'s cameras, the near plane): near_plane a depth, or "auto", decided by `near_plane_as_trained`
    once the cameras are in the scene's frame and before their principal points, which are then decided at that plane.
    INRIA's rasterizer both draws from 0.2 and centres the principal points: decided at 0.01 first, the Gaussians it never
    drew covered the principal-point renders of a scene with floaters before every camera, which kept the file's points
    and registered other bytes than `--near-plane inria` (round 66a F3). A camera file whose off-centre principal points
    the scene was not trained with is itself a sign of INRIA's training, so the plane is decided with them as given.
    before_deciding: called with the cameras in the scene's frame before the plane is decided (a registration's refusals
    that need no render)."""
    decided = near_plane == "auto"
    plane = NEAR if decided else given_near_plane(near_plane)
    framed = cameras_in_trained_frame(scene, cameras, source, what=what, scene_path=scene_path, refinements=refinements, cancel=cancel,
                                      near=plane)
    if before_deciding is not None:
        before_deciding(framed)
    if decided:
        plane = near_plane_as_trained(scene, framed, what=what)
        if cancel is not None:
            cancel.raise_if_cancelled()
    return cameras_with_principal_point(scene, framed, principal_point, what=what, source=source, near=plane), plane


def nerfstudio_run_file(source: str | Path, scene_path: str | Path | None = None) -> tuple[Path, AppliedMove] | None:
    """(the dataparser_transforms.json the cameras of dataset `source` were moved by: the one beside them, else the run's of a
    nerfstudio checkpoint `scene_path`; what the dataset's transforms.json says its poses carry, `applied_move`), or None."""
    path = dataparser_transforms_path(source)
    if path is None and scene_path is not None:
        path = run_dataparser_transform(scene_path)
    if path is None:
        return None
    kind, found = detect_dataset(source)
    return path, (applied_move(found) if kind == "transforms" else AppliedMove())


HALF_TURN_X = np.diag([1.0, -1.0, -1.0])  # nerfstudio's PCA up-flip: a half turn about x
READING_MARGIN = 0.02  # median gain of grey correlation that decides for another reading of a nerfstudio run (they see other sides of a scene)
READING_VIEWS = 8  # views `cameras_of_nerfstudio_run` renders under each reading


def without_implied_move(cameras: Sequence[Camera], path: Path, applied: AppliedMove) -> list[Camera]:
    """`cameras`, moved by the dataparser file `path` after undoing the applied_transform A nerfstudio takes for a
    transforms.json without one beside a colmap/sparse/0 folder (`applied_move`), as they would be without undoing it.

    With the file's (R, t, s) and A's rotation R_A, the undone reading puts x at x'_U = s·(R R_Aᵀ x + t), the other
    at x'_N = s·(R x + t), so

        x'_N = Q x'_U + s·(I − Q) t,   Q = R R_A Rᵀ."""
    rotation, translation, scale = read_dataparser_transform(path)
    scale = scale / applied.scale
    q = rotation @ applied.rotation @ rotation.T
    offset = scale * (translation - q @ translation)
    return [in_trained_frame(c, q, offset, 1.0) for c in cameras]


def half_turned(cameras: Sequence[Camera]) -> list[Camera]:
    """`cameras` turned half round about x, F = diag(1, −1, −1): world-to-camera R·F, t (`in_trained_frame` with R = F)."""
    return [in_trained_frame(c, HALF_TURN_X, np.zeros(3), 1.0) for c in cameras]


def cameras_of_nerfstudio_run(scene, cameras: Sequence[Camera], path: Path, applied: AppliedMove, what: str = "the scene",
                              near: float = NEAR) -> list[Camera]:
    """`cameras`, moved by nerfstudio's dataparser file `path` (`applied`: what the dataset's transforms.json
    carries), in the frame the run trained in, where its files leave two things open:

    - the applied_transform A nerfstudio takes itself for a transforms.json without one beside a colmap/sparse/0
      folder (`applied.implied`) is in the saved transform only when ns-train's --data was the dataset folder,
      where it looks for that folder; given the transforms.json itself it saves T without A (round 56b: the
      cameras landed turned by A's half turn about (1, 1, 0), seg mIoU 0.211 against 0.950, without a word);
      the cameras come undone (`without_implied_move` is the other reading);
    - a run oriented by PCA (`cameras.run_orientation`, or a run whose orientation nothing beside the file says: a
      user who copies only dataparser_transforms.json, as the docs ask, leaves config.yml behind; round 57a): when
      PCA's up-flip fires, nerfstudio turns its poses half round about x and the saved transform misses that turn
      (v1.1.4 and earlier flip the poses only, v1.1.5 the saved transform only; `half_turned` is the other reading).

    Which applies is in no file, so every combination is rendered together (`best_reading`; deciding one at a
    time could compare two wrong readings: round 56c) and the best taken, with one warning, when it matches the
    images by READING_MARGIN more than the cameras as moved; a warning too when none looks like the images."""
    cameras = list(cameras)
    implied = (f"without {applied.what} (ns-train, given the transforms.json and not its folder, finds no colmap folder "
               "under it and saves no such move)")
    turn = "turned half round about x (PCA's up-flip, which the saved transform misses)"
    readings: list[tuple[str, str, list[Camera]]] = [("saved", "as the saved transform gives them", cameras)]
    if applied.implied:
        readings.append(("without A", implied, without_implied_move(cameras, path, applied)))
    oriented = run_orientation(path, applied.orientation)
    if oriented is None or oriented[0] == "pca":  # PCA said, or nothing says (no config.yml beside an exported run's file: round 57a)
        if oriented is None:
            turn += ", if the run was oriented by PCA: no config.yml beside the file says how"
        readings += [(f"{label}, turned" if i else "turned", f"{words}, and {turn}" if i else turn, half_turned(c))
                     for i, (label, words, c) in enumerate(readings)]
    if len(readings) == 1:
        return cameras
    chosen, scores = best_reading(scene, [c for _, _, c in readings], READING_MARGIN, READING_VIEWS, near)
    said = ", ".join(f"{label} {score:.3f}" for (label, _, _), score in zip(readings, scores.medians))
    if not scores.views:
        log.warning("%s leaves open how %s was trained (%s), and no training image could be compared with its renders to tell "
                    "(%s): the cameras are used as the saved transform gives them", path, what,
                    "; or ".join(words for _, words, _ in readings[1:]), scores.left_out)
        return cameras
    if max(scores.medians) < PHOTO_MATCH_MIN:
        log.warning("%s leaves open how %s was trained, and under none of its readings do the renders look like the training "
                    "images (median grey correlation: %s; %s): the cameras are used as the saved transform gives them, and "
                    "the scene may not be this dataset's", path, what, said, scores.of_views())
        return cameras
    if chosen:
        log.warning("%s was trained in the frame of %s with its %s %s: only so do its renders look like its training "
                    "images (median grey correlation: %s; %s), so they are taken so", what, path,
                    "camera" if len(cameras) == 1 else f"{len(cameras)} cameras", readings[chosen][1],
                    said, scores.of_views())
    else:
        log.info("%s: the cameras are used as its saved transform gives them (median grey correlation: %s; %s)", path, said,
                 scores.of_views())
    return readings[chosen][2]


@dataclass(frozen=True)
class ReadingScores:
    """Several readings of the same cameras scored by their renders (`best_reading`): each one's median ρ
    over the compared views, how many views were compared, and the views left out and why."""

    medians: list[float]
    views: int
    left_out: str

    def of_views(self) -> str:
        return f"{self.views} view" if self.views == 1 else f"{self.views} views"


def best_reading(scene, readings: Sequence[Sequence[Camera]], margin: float, views: int = PHOTO_CHECK_VIEWS,
                 near: float = NEAR) -> tuple[int, ReadingScores]:
    """(the index of the reading of the same cameras (readings[r][i] is camera i read the r-th way) whose renders look
    most like the training images, its scores): `photo_agreement` of each over up to `views` cameras, a view one
    reading shows nothing of counting ρ = 0 for it; reading r > 0 is taken over reading 0 when

        median_v (ρ_v(r) − ρ_v(0)) > margin  and  median_v ρ_v(r) ≥ PHOTO_MATCH_MIN,

    the one of largest gain among those; else 0."""
    prepared, pictures, skipped = photo_scene(scene), {}, Counter()
    found = [photo_agreement(scene, cams, views=views, prepared=prepared, pictures=pictures, skipped=skipped if r == 0 else None, near=near)
             for r, cams in enumerate(readings)]
    common = sorted(set().union(*found))
    if not common:
        return 0, ReadingScores([0.0] * len(readings), 0, skipped_views(skipped))
    rho = np.array([[f.get(name, 0.0) for name in common] for f in found])
    medians = [float(m) for m in np.median(rho, axis=1)]
    gains = [float(np.median(rho[r] - rho[0])) for r in range(len(readings))]
    chosen = 0
    for r in range(1, len(readings)):
        if gains[r] > margin and medians[r] >= PHOTO_MATCH_MIN and gains[r] > gains[chosen]:
            chosen = r
    return chosen, ReadingScores(medians, len(common), skipped_views(skipped))


def cameras_with_principal_point(scene, cameras: Sequence[Camera], choice: str = DEFAULT_PRINCIPAL_POINT, what: str = "the scene",
                                 source: str | Path | None = None, near: float = NEAR) -> list[Camera]:
    """`cameras` with the principal points their scene (a GaussianScene) was trained with.

    choice: "file" keeps each camera's cx, cy (gsplat and nerfstudio train so); "centre" moves them
    to the image centres (`Camera.centred`), as INRIA's gaussian-splatting trains: it reads a COLMAP
    camera as fov_x = 2·atan(W / 2 fx), fov_y = 2·atan(H / 2 fy) and projects symmetrically; "auto"
    renders up to PRINCIPAL_POINT_VIEWS training views whose principal point is off-centre under both
    readings and takes the one whose renders look more like the training images (`photo_agreement`;
    a view one reading shows nothing of counts ρ = 0 for it): per view v,

        g_v = ρ_v(centred) − ρ_v(as given),   the centres when median_v g_v > PRINCIPAL_POINT_MARGIN
                                              and median_v ρ_v(centred) ≥ PHOTO_MATCH_MIN,

    since moving the principal point by (δx, δy) translates the whole render by (δx, δy) pixels and
    the scene was fitted to the images under its trainer's reading. "auto" keeps the file's without
    rendering when every principal point lies within PRINCIPAL_POINT_MIN_SHIFT of its centre, a
    camera has lens distortion (INRIA trains on undistorted images only) or every principal point is
    a multiple of its centre (`cameras.off_size_factors`: intrinsics of another image size, warned
    about on loading), and with a warning when no training image can be compared. Taking the centres
    is said in one warning naming `what`.
    """
    if choice not in PRINCIPAL_POINTS:
        raise ValueError(f"cameras_with_principal_point: choice must be one of {PRINCIPAL_POINTS}, got {choice!r}")
    cameras = list(cameras)
    if choice == "file":
        return cameras
    centred = [c.centred() for c in cameras]
    moved = sum(c.principal_point_shift() > 0 for c in cameras)
    every = f"the {len(cameras)} cameras" + (f" of {source}" if source is not None else "")
    of = f"{moved} of {every}" if moved < len(cameras) else every
    worst = f"{100 * max((c.principal_point_shift() for c in cameras), default=0.0):.2g} %"
    if choice == "centre":  # every one, however near its centre (round 56b: those within PRINCIPAL_POINT_MIN_SHIFT were kept)
        if moved:
            log.info("--principal-point centre: the principal points of %s are moved to their image centres (up to %s of the side)",
                     of, worst)
        return centred
    off = [i for i, c in enumerate(cameras) if c.principal_point_shift() >= PRINCIPAL_POINT_MIN_SHIFT]
    if not off:
        return cameras
    if any(c.distortion is not None and np.any(c.distortion) for c in cameras):
        log.info("the principal points of %s are used as the camera file gives them, up to %s of the side off-centre: a camera "
                 "has lens distortion, which INRIA's gaussian-splatting does not train with (--principal-point centre moves them)", of, worst)
        return cameras
    if off_size_factors(cameras) is not None:  # intrinsics of another image size, said on loading: centring would not mend them
        log.info("the principal points of %s are used as the camera file gives them: each is a multiple of its image centre, "
                 "intrinsics of another image size (the warning above)", of)
        return cameras
    # only the views whose principal point is off-centre tell the readings apart (round 55a: a rig with every third camera
    # off-centre gave gain 0 in most compared views, and the median kept the file's)
    chosen, compared = best_reading(scene, [[cameras[i] for i in off], [centred[i] for i in off]], PRINCIPAL_POINT_MARGIN,
                                    PRINCIPAL_POINT_VIEWS, near)
    given_rho, centre_rho = compared.medians
    if not compared.views:
        log.warning("the principal points of %d of %s lie off their image centres (up to %s of the side) and no training image "
                    "could be compared with %s's renders to tell how it was trained (%s): they are used as the camera file gives them "
                    "(as gsplat and nerfstudio train); for a scene trained by INRIA's gaussian-splatting, which takes every "
                    "principal point at the image centre, pass --principal-point centre", len(off), every, worst, what, compared.left_out)
        return cameras
    if chosen:
        log.warning("%s was trained with every principal point at its image centre, as INRIA's gaussian-splatting trains: its renders "
                    "look more like its training images so (median grey correlation %.3f against %.3f with the camera file's, %s): "
                    "the principal points of %s are moved to their image centres (up to %s of the side); "
                    "--principal-point file keeps them", what, centre_rho, given_rho, compared.of_views(), of, worst)
        return centred
    # the centres' better score under the floor decides nothing, and is said so (round 94b F1: the numbers favoured them)
    weak = (f"; the centres' is higher but under {PHOTO_MATCH_MIN:g}, too low to tell how the scene was trained: "
            "--principal-point centre takes them") if centre_rho > given_rho and centre_rho < PHOTO_MATCH_MIN else ""
    log.info("the principal points of %s are used as the camera file gives them (median grey correlation %.3f against %.3f at the "
             "image centres, %s%s)", of, given_rho, centre_rho, compared.of_views(), weak)
    return cameras


NEAR_PLANE_VIEWS = 8  # views `near_plane_as_trained` renders at each plane: those where the band's Gaussians cover most tiles
DECISION_HELD_BYTES = 24 << 20  # resident after a near-plane decision and `trim_heap`: its render kernels and image readers (13 MB measured, tiny room, 2026-12-06)
FIRST_COMPILE_HELD_BYTES = 192 << 20  # and more when it compiled the kernels, on a first run (156 MB measured, round 68a F3)
NEAR_PLANE_GREY_STEP = 4 / 255  # grey-level difference from which the two planes' renders of a pixel differ (`PlaneEvidence`)
NEAR_PLANE_MIN_PIXELS = 100  # differing pixels, over the views compared, from which they decide (48 decided wrongly: docs/raster.md)
# mean rank-error gain (ranks in [0, 1]) over the differing pixels that decides for INRIA's plane (docs/raster.md, "The near
# plane decided")
NEAR_PLANE_MARGIN = 0.01
NEAR_BAND_NOTABLE = 0.01  # the band's tiles / a view's tiles from which, with no image to compare, the choice is warned about


@dataclass
class PlaneEvidence:
    """Two near planes' renders of the same views held against the training images (`plane_evidence`).

    pixels: the compared pixels where the two renders differ by NEAR_PLANE_GREY_STEP or more, over the views;
    error_lo, error_hi: the sums over them of e = |rank(r) − rank(g)|, the rank error of the render r at each plane
    against the image g (`grey_ranks`); views: the views compared; left_out: the views left out and why."""

    pixels: int = 0
    error_lo: float = 0.0
    error_hi: float = 0.0
    views: int = 0
    left_out: str = ""

    def mean_errors(self) -> tuple[float, float]:
        """(mean e at lo, mean e at hi) over the differing pixels (0, 0 without any)."""
        return (self.error_lo / self.pixels, self.error_hi / self.pixels) if self.pixels else (0.0, 0.0)

    @property
    def gain(self) -> float:
        """How much closer to the images the renders at hi are where the two differ: mean e(lo) − mean e(hi)."""
        lo, hi = self.mean_errors()
        return lo - hi

    def of_views(self) -> str:
        return f"{self.pixels:,} pixels of {counted(self.views, 'view', 'views')}"


def grey_ranks(grey: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """[H, W] each pixel's grey level as its rank among `pixels` ([H, W] bool), scaled to [0, 1] (ties share their mean
    rank; 0 outside `pixels`): what any brightening, darkening or tone curve of the image (increasing) leaves as it is."""
    out = np.zeros(grey.shape)
    n = int(np.count_nonzero(pixels))
    if n > 1:
        out[pixels] = (average_ranks(grey[pixels]) - 1.0) / (n - 1.0)
    return out


def average_ranks(values: np.ndarray) -> np.ndarray:
    """[n] float64 the 1-based rank of each of `values` [n], ties sharing the mean of their ranks (scipy.stats.rankdata's
    'average'; all NaN where one is NaN, as it propagates). numpy's own, not scipy.stats: that import alone holds 36 MB,
    which the memory plan then counted against a --memory-budget (round 66a F4). The values are ranked as float64 (grey
    levels here): integers past 2**53 that float64 cannot tell apart tie, where rankdata ranks them apart (round 67a F8)."""
    values = np.asarray(values, np.float64).ravel()
    if np.isnan(values).any():
        return np.full(values.shape, np.nan)
    order = np.argsort(values, kind="stable")
    ordered = values[order]
    starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])  # where each run of equal values begins
    ends = np.r_[starts[1:], values.size]
    ranks = np.empty(values.size)
    ranks[order] = np.repeat((starts + ends + 1) / 2.0, ends - starts)
    return ranks


def plane_evidence(prepared, cameras: Sequence[Camera], lo: float, hi: float, width: int = PHOTO_CHECK_WIDTH,
                   supersample: int = PHOTO_SUPERSAMPLE) -> PlaneEvidence:
    """How much better the renders at near plane hi match the training images than those at lo, on the pixels
    where the two differ (a floater drawn at lo only): per view, the grey levels r_lo, r_hi of the renders (over
    the background the image fits best, `over_fitted_background`, clipped to [0, 1]) and g of the image, `width` px on
    the longer side, each turned into its rank among the pixels both renders cover (α ≥ ½, `grey_ranks`); over the
    covered pixels D where |r_lo − r_hi| ≥ NEAR_PLANE_GREY_STEP,

        gain = Σ_D (|rank r_lo − rank g| − |rank r_hi − rank g|) / |D|,   pooled over the views (> 0: hi matches better).

    Ranks, not grey levels: a photo's exposure and tone curve differ from the render's, and any increasing one keeps
    the ranks (round 65a F1: absolute grey errors took INRIA's plane for images drawn at 0.01 but 0.6x as bright, or
    with a gamma of 1.5: bright floaters then look wrong against dark images whichever plane drew them). A fitted gain
    and offset did no better: a Gaussian under a low camera changes every pixel alike, which the fit explains away
    (docs/raster.md "The near plane decided"). A view whose renders cover under PHOTO_MIN_PIXELS pixels, or neither of
    which correlates PHOTO_MATCH_MIN with the image there (it does not show its image), is left out. prepared: the
    scene's `photo_scene`."""
    evidence, pictures, skipped = PlaneEvidence(), {}, Counter()
    for camera in cameras:
        if camera.image_path is None or not camera.image_path.is_file():
            skipped[NO_IMAGE_FILE] += 1
            continue
        small, picture = view_picture(camera, width, pictures, skipped)
        if picture is None:
            continue
        grey = picture.astype(np.float64).mean(axis=2)
        renders = [supersampled_render(prepared, small, supersample, near) for near in (lo, hi)]
        r_lo, r_hi = (np.clip(over_fitted_background(rgb, alpha, picture).mean(axis=2), 0.0, 1.0) for rgb, alpha in renders)
        covered = (renders[0][1] >= 0.5) & (renders[1][1] >= 0.5)
        if np.count_nonzero(covered) < PHOTO_MIN_PIXELS:
            skipped[LITTLE_COVERED] += 1
            continue
        rho = np.array([grey_correlation(np.repeat(r[..., None], 3, axis=2), picture, covered) for r in (r_lo, r_hi)])
        if np.all(np.isnan(rho)):  # a flat image (or both renders flat): nothing to rank, not another place (round 67a F9)
            skipped[FLAT_PICTURE] += 1
            continue
        if not np.any(rho >= PHOTO_MATCH_MIN):  # NaN (a flat render) is no match, and does not hide the other's
            skipped[NOT_ITS_IMAGE] += 1
            continue
        differ = covered & (np.abs(r_lo - r_hi) >= NEAR_PLANE_GREY_STEP)
        image, at_lo, at_hi = (grey_ranks(v, covered) for v in (grey, r_lo, r_hi))
        evidence.pixels += int(np.count_nonzero(differ))
        evidence.error_lo += float(np.sum(np.abs(at_lo[differ] - image[differ])))
        evidence.error_hi += float(np.sum(np.abs(at_hi[differ] - image[differ])))
        evidence.views += 1
    evidence.left_out = skipped_views(skipped)
    return evidence


def near_plane_as_trained(scene, cameras: Sequence[Camera], what: str = "the scene") -> float:
    """The near plane (a camera depth, scene units) to render `scene` (a GaussianScene) at, as it was trained
    (`--near-plane auto`; `cameras_and_plane_as_trained` returns a plane given as a number as given).

    Trainers differ: gsplat and nerfstudio draw every
    Gaussian of camera depth z ≥ NEAR (0.01); INRIA's rasterizer, which trained LangSplat's and Dr. Splat's
    scenes, drops z ≤ INRIA_NEAR (0.2), so a Gaussian 0.01-0.2 in front of a camera (a floater) was never
    drawn in that view while training, and drawing it covers what the image shows. "auto" finds, per
    camera, the Gaussians of that band (`raster.near_band`, on the ≤ PHOTO_CHECK_SAMPLE Gaussians the photo
    check renders), renders the NEAR_PLANE_VIEWS views with an image whose tiles the band covers most at both
    planes and takes INRIA_NEAR when, where the renders differ, the one without the band matches the images
    better (`plane_evidence`: gain > NEAR_PLANE_MARGIN over at least NEAR_PLANE_MIN_PIXELS pixels); else NEAR.
    With no Gaussian in any view's band both planes render the same and nothing is rendered; with no image
    to compare it is NEAR, warned about when the band covers NEAR_BAND_NOTABLE of a view's tiles. Taking
    INRIA's plane is said in one warning naming `what`.
    """
    cameras = list(cameras)
    prepared = photo_scene(scene)
    bands = near_band(prepared, cameras, NEAR, INRIA_NEAR)
    seen = [i for i, band in enumerate(bands) if band.count]
    if not seen:
        log.debug("no Gaussian of %s lies %g-%g scene units in front of a camera: the near plane is %g", what, NEAR, INRIA_NEAR, NEAR)
        return NEAR
    widest = max(seen, key=lambda i: bands[i].cover)
    where = (f"{len(seen)} of its {counted(len(cameras), 'camera', 'cameras')} (in view {cameras[widest].name} they may draw on "
             f"{100 * bands[widest].cover:.0f} % of its 16x16 tiles)")
    with_images = [i for i in seen if cameras[i].image_path is not None and cameras[i].image_path.is_file()]
    picks = sorted(with_images, key=lambda i: (-bands[i].cover, i))[:NEAR_PLANE_VIEWS]
    evidence = plane_evidence(prepared, [cameras[i] for i in picks], NEAR, INRIA_NEAR)
    if evidence.views and evidence.pixels >= NEAR_PLANE_MIN_PIXELS:
        with_them, without = evidence.mean_errors()
        if evidence.gain > NEAR_PLANE_MARGIN:
            log.warning("%s was trained with INRIA's near plane: Gaussians lie %g-%g scene units in front of %s, and where they show "
                        "its renders look more like its training images without them (mean rank error %.3f, against %.3f with them; "
                        "%s): it is rendered at near plane %g, where INRIA's rasterizer never drew them; `drsplat register --near-plane %g` "
                        "draws them",
                        what, NEAR, INRIA_NEAR, where, without, with_them, evidence.of_views(), INRIA_NEAR, NEAR)
            return INRIA_NEAR
        log.info("Gaussians of %s lie %g-%g scene units in front of %s; where they show, its renders look %s its training "
                 "images with them (mean rank error %.3f, against %.3f without; %s): they are drawn (near plane %g)",
                 what, NEAR, INRIA_NEAR, where, "more like" if evidence.gain < -NEAR_PLANE_MARGIN else "about as much like",
                 with_them, without, evidence.of_views(), NEAR)
        return NEAR
    if evidence.views:  # the band shows in too few pixels of the compared views to matter there: nothing to tell a user
        log.debug("Gaussians of %s lie %g-%g scene units in front of %s, but change only %s of the renders compared: they are drawn "
                  "(near plane %g)", what, NEAR, INRIA_NEAR, where, evidence.of_views(), NEAR)
        return NEAR
    say = log.warning if bands[widest].cover >= NEAR_BAND_NOTABLE else log.info
    depth = median_seen_depth(scene.means, cameras)
    if depth < INRIA_NEAR:  # round 83b F2: the advice below would name a plane that culls most of this capture
        say("Gaussians of %s lie %g-%g scene units in front of %s, but the capture lies a median %.2g scene units from its cameras, "
            "nearer than INRIA's near plane (%g), so INRIA's rasterizer did not train it at this scale: they are drawn (near plane "
            "%g, gsplat's). The plane is in scene units: if the scene and its cameras were scaled down after training (other "
            "units), scale both up together and register again",
            what, NEAR, INRIA_NEAR, where, depth, INRIA_NEAR, NEAR)
        return NEAR
    say("Gaussians of %s lie %g-%g scene units in front of %s, where INRIA's rasterizer (which trained LangSplat's and Dr. Splat's "
        "scenes) never drew them, and no training image could be compared with its renders to tell how it was trained (%s): "
        "they are drawn (near plane %g, gsplat's); a scene trained by INRIA's gaussian-splatting registers as trained with "
        "`drsplat register --near-plane inria`",
        what, NEAR, INRIA_NEAR, where, evidence.left_out if picks else skipped_views(Counter({NO_IMAGE_FILE: len(seen)})), NEAR)
    return NEAR


# of the Gaussians under 1/255 opacity: a scene that draws next to nothing in any frame (at 60 %, the other 40 % draw in
# the right frame, so a scene they do not show is in another: round 93a F2)
FAINT_SCENE_SHARE = 0.95


def warn_if_scene_misses_its_images(scene, cameras: Sequence[Camera], near: float = NEAR) -> None:
    """One warning when the scene does not re-render its training images (`photo_agreement`'s
    median ρ under PHOTO_MATCH_MIN): a scene in another frame than its cameras, which may still
    sit inside every view (a splatfacto export shrunk into [−1, 1] without its
    dataparser_transforms.json), and then registers every Gaussian, wrongly (round 51)."""
    if scene.num_gaussians > PHOTO_CHECK_MAX_THINNING * PHOTO_CHECK_SAMPLE:
        log.info("the scene's frame is not checked against its training images: %s Gaussians, over the %s the check can draw "
                 "a faithful picture from", f"{scene.num_gaussians:,}", f"{PHOTO_CHECK_MAX_THINNING * PHOTO_CHECK_SAMPLE:,}")
        return
    skipped: Counter = Counter()
    agreement = photo_agreement(scene, cameras, skipped=skipped, near=near)
    if not agreement and skipped[LITTLE_COVERED] and skipped[LITTLE_COVERED] == sum(skipped.values()):
        # every view with an image shows (next to) nothing of the scene: the plainest wrong dataset (round 57c: said at DEBUG)
        faint = faint_share(scene)
        if faint >= FAINT_SCENE_SHARE:  # next to nothing draws in any frame: the frame is not what to look at (round 91c F2)
            log.warning("none of the %d training views checked shows the scene (each render covers under %d pixels): %d%% of its "
                        "Gaussians have an opacity under 1/255, which draws nothing (and the others may be in another frame "
                        "than the cameras)", skipped[LITTLE_COVERED], PHOTO_MIN_PIXELS, int(100 * faint))  # round 94a F4: both
            return
        log.warning("none of the %d training views checked shows the scene (each render covers under %d pixels): the scene may be "
                    "in another frame than its cameras (%s), or the dataset is not this scene's", skipped[LITTLE_COVERED],
                    PHOTO_MIN_PIXELS, SPLATFACTO_FRAME)
        return
    if not agreement:
        log.debug("the scene's frame is not checked against its training images: %s", skipped_views(skipped))
        return
    median = float(np.median(list(agreement.values())))
    log.debug("the scene re-renders its training images with a median grey correlation of %.2f (%s)", median,
              ", ".join(f"{n} {r:.2f}" for n, r in agreement.items()))
    if median >= PHOTO_MATCH_MIN:
        return
    log.warning("the scene does not look like its training images from their cameras: its renders and the images correlate "
                "%.2f (median of %d views; a scene in its cameras' frame is near 1): the scene may be in another frame than its "
                "cameras (%s), or the images are not this scene's", median, len(agreement), SPLATFACTO_FRAME)
