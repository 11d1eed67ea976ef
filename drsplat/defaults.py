"""Defaults a user meets in several places (CLI flags, the viewer's panels, library signatures), owned here once.

This module imports nothing, so argument parsers can read it without loading numba or torch at start-up.
"""

# float32's smallest normal number (np.finfo(np.float32).tiny): a feature or mask embedding of a smaller
# norm holds no direction in float32 (its entries are subnormal; 1/norm overflows), wherever it is read
MIN_NORM = 1.1754943508222875e-38
# OpenMP threads (numba's parallel kernels, torch) sleep rather than spin while they wait for work. A spinning thread takes
# its core from every other process: on 2 cores shared with other jobs (load 10) a tiny registration took 4.5 s instead of
# 0.12 s, its small parallel regions each waiting for a time slice (docs/raster.md, "OpenMP threads that wait")
OPENMP_WAIT_POLICY = "passive"


C_BLANKS = " \t\n\v\f\r"  # what C's isspace skips (not a non-breaking space): the blanks an OpenMP runtime reads around a value


def openmp_wait_policy(value: str | None) -> str | None:
    """The wait policy an OpenMP runtime reads from OMP_WAIT_POLICY = `value`, or None where it reads none: libgomp and
    Intel's runtime take "active" or "passive" in any case, C's blanks around (isspace: not a non-breaking space, which
    a value copied from a web page carries: round 70a F4); anything else (unset, empty, misspelt) they call invalid and
    leave their threads spinning (round 67a F5, round 68a F15)."""
    policy = (value or "").strip(C_BLANKS).lower()
    return policy if policy in ("active", "passive") else None


VOXEL_RESOLUTION = 96  # the voxel IoU's voxels along the longest side of the labelled region (`eval iou --voxel-resolution`)
VOXEL_EMPTY = 0.01  # α-mass below which a voxel is empty (`eval iou --voxel-empty`)

MAX_TOPK = 1024  # Gaussians kept per pixel at most (top-k buffers are [H, W, k])
DEFAULT_TOPK = 40  # Gaussians kept per pixel: the paper's k; the top-k ablation plateaus from k = 10 (docs/evaluation.md)
DEFAULT_LEVEL = 1  # the LangSplat mask level registration reads: "s" (levels are default, s, m, l)
DEFAULT_CODEBOOK = "none"  # exact float16 field; "scene" trains PQ on the scene, a path names a faiss codebook
DEFAULT_AGGREGATE = "fit-check-vote-reject"  # registration's aggregation mode: the fit stage's footprint (paper or sharp), contradicted masks dropped, the mean trimmed by votes across views, floaters rejected (docs/evaluation.md, "The fit stage")
AGGREGATE_MODES = ("paper", "core", "ellipse", "responsibility", "reject", "core-reject", "ellipse-reject",
                   "centre", "anchor", "anchor-reject", "explain", "explain-reject",
                   "vote", "vote-reject", "explain-vote-reject",
                   "solve", "solve-reject", "solve-vote", "solve-vote-reject",
                   "check", "check-reject", "check-vote", "check-vote-reject",
                   "sharp", "sharp-reject", "sharp-vote", "sharp-vote-reject",
                   "fit", "fit-reject", "fit-vote", "fit-vote-reject",
                   "sharp-check-vote-reject", "fit-check-vote-reject",
                   "explain-vote", "sharp-check-vote", "fit-check-vote")  # drsplat.registration.aggregate implements them; every "-reject" mode has its mode without the rejection
# --principal-point (register, eval lerf): decide from the training images, the camera file's cx, cy (gsplat, nerfstudio) or the
# image centres (INRIA's gaussian-splatting); drsplat.frames.cameras_with_principal_point
PRINCIPAL_POINTS = ("auto", "file", "centre")
DEFAULT_PRINCIPAL_POINT = "auto"
ENGINES = ("numba", "torch")  # the --engine choices: keys of drsplat.raster.ENGINES (numba on the CPU, torch on the CPU or CUDA)
VOTE_SLOTS = 8  # candidate mask clusters kept per Gaussian by the -vote stage (drsplat.registration.vote; the memory plan counts them)
VOTE_SLOT_BYTES = 20 * VOTE_SLOTS  # per Gaussian: each slot's cluster (int32), votes and paper weight (float64)
SPECIFICITY_SLOT_BYTES = 8 * VOTE_SLOTS  # per Gaussian of a block the vote trims by specificity: each slot's P (float64)
EXACT_TRIM_SLOT_BYTES = 28  # per Gaussian of a block the vote trims exactly (after the check): its trimmed-slot bits (uint64), the removed weight (float32) and a buffered pair (16 with its place in the flush's sort: the buffer holds at least one per Gaussian)
CHECK_SLOTS = 16  # clusters per Gaussian whose votes the cross-view check keeps (drsplat.registration.check; 12 bytes each)
GAUSSIAN_TERM_BYTES = 8 * CHECK_SLOTS + 12  # per Gaussian of a view while the check sums its support: each slot's other views' votes (float64), its share φ and top cluster (drsplat.registration.check.gaussian_terms)
SUPPORT_SCRATCH_BYTES = 64 << 20  # one layer of the check's dense support scratch: a view's masks are summed in runs that keep it within this
SUPPORT_TABLE_BYTES = 256 << 20  # the check's support tables held in memory; their parts past it spill to disk (registration.supports)
SUPPORT_READ_BYTES = 32 << 20  # a view's support table larger than this is judged in runs of its masks of at most this (registration.supports)
SUPPORT_EXTRA_SCRATCH = 64 << 20  # the further layers that let the check sum a view's parts in parallel (the memory plan counts both)
SOLVE_SLOTS = 8  # candidate mask clusters per Gaussian of the solve stage (drsplat.registration.solve)
# a synthetic (oracle) dataset's label files, relative to its folder (drsplat.synthetic.write_dataset writes them)
ORACLE_LABEL_NAMES = "gt/label_names.json"  # JSON list of the label names
ORACLE_TEXT_EMBEDDINGS = "text_embeddings.npy"  # [labels, D] the oracle "text" vectors, one per name
# The rasterizers' transmittance floor (3DGS's 1e-4; every engine: drsplat.raster): a pixel stops blending before its
# T would fall below it, so its occupancy 1 − T never exceeds 1 − T_MIN. Here because `eval lerf` bounds a flag by it.
T_MIN = 1e-4
# `eval lerf --alpha-threshold` stays below this: a threshold at or above it selects nothing (round 60a: 0.9999 scored mIoU 0)
LERF_ALPHA_LIMIT = 1.0 - T_MIN
LERF_ALPHA_THRESHOLD = 0.7  # `eval lerf`: OpenGaussian's render_lerf_by_text.py keeps pixels whose silhouette passes 0.7 (0.5 until 2026-11-30)
LANGSPLAT_MASK_THRESHOLD = 0.4  # `eval lerf --protocol langsplat`: LangSplat's evaluate_iou_loc.py --mask_thresh
# |norm - 1| of an embedding past which it is rescaled to unit length: mask embeddings when read for
# registration (drsplat.features.format), stored rows before encoding (drsplat.lang.codebook.unit_check).
# CLIP's and LangSplat's are 1 to float precision, a float16 file's within ~1e-4: kept bit for bit.
UNIT_TOLERANCE = 1e-3
NEAR = 0.01  # the default near plane (gsplat's, nerfstudio's): Gaussians with camera depth z < NEAR are not drawn (drsplat.raster)
INRIA_NEAR = 0.2  # the INRIA rasterizer's (`in_frustum`: z <= 0.2 dropped), which trained LangSplat's and Dr. Splat's scenes
DEFAULT_NEAR_PLANE = "auto"  # `register` (and the viewer's registration): NEAR or INRIA_NEAR, whichever renders the training images (drsplat.frames.near_plane_as_trained)
