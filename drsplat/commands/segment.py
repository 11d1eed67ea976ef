"""`drsplat segment`: label every Gaussian of a registered PLY by argmax cosine over a label list."""

from __future__ import annotations

import argparse
import logging
from functools import partial
from pathlib import Path

import numpy as np

from drsplat.commands import common
from drsplat.commands.common import (
    add_clip_arguments,
    add_format_argument,
    add_lut_bits_argument,
    export_outputs,
    guard_field_codebook,
    float_range,
    load_registered,
    lut_bits_for,
    scoring_device,
    checked_phrases,
    table_stream,
)
from drsplat.defaults import ORACLE_LABEL_NAMES, ORACLE_TEXT_EMBEDDINGS
from drsplat.errors import DrsplatError, InputError, UsageError, shown_path
from drsplat.lang import strip_field
from drsplat.scene import SH_C0, GaussianScene
from drsplat.utils import checked_names, clipped, read_json

log = logging.getLogger(__name__)

BACKGROUND_GREY = 0.35
SHOWN_NAME_CHARS = 60  # of a label name in the printed table


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "segment",
        help="argmax segmentation of a registered PLY over a label list",
        description=(
            "Label every Gaussian with the label of highest cosine similarity. LABELS.npy is int32 (N,) in file "
            "order: the label index, -1 for background, unassigned Gaussians and scores below --min-score. An exact tie "
            "goes to the earlier label, and a tie with --background to the label."
        ),
    )
    parser.add_argument("registered", type=Path, metavar="REGISTERED.ply", help="PLY written by drsplat register")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--labels", metavar="A,B,...", help="comma-separated label phrases (needs CLIP weights)")
    source.add_argument("--embeddings", type=Path, action=common.Once, metavar="L.npy", help="label embeddings (L, D)")
    parser.add_argument("--names", type=Path, metavar="NAMES.json",
                        help="names of the --embeddings rows (a JSON list); default: for a synthetic dataset's own "
                        "text_embeddings.npy, the gt/label_names.json beside it, else label_0, label_1, ...")
    parser.add_argument(
        "--background",
        action="store_true",
        help="add a background label: the phrase 'background' with --labels, the last row of L.npy with --embeddings",
    )
    parser.add_argument("--min-score", type=float_range(-1.0, 1.0), default=None, help="Gaussians whose best cosine is below this get -1")
    add_lut_bits_argument(parser)
    parser.add_argument("--out", type=common.output_file, required=True, metavar="LABELS.npy", help="int32 (N,) label per Gaussian")
    parser.add_argument("--ply", type=Path, metavar="COLOURED.ply", help="also write the scene coloured by label: a PLY, or .splat / .spz / .compressed.ply by the name (see --format)")
    add_format_argument(parser, "--ply")
    add_clip_arguments(parser, scoring=True)
    parser.set_defaults(func=run)


def label_embeddings(args: argparse.Namespace, field, encoder_factory=None) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
    """(label embeddings [L, D], background embeddings [1, D] or None, label names)."""
    from drsplat.query import BACKGROUND_PHRASE, load_query_embeddings, text_embeddings

    if args.labels is not None:
        names = label_phrases(args.labels)
        typed = [name.lower() for name in names]
        if args.background and BACKGROUND_PHRASE in typed:  # round 57c: it became label k, not -1, silently
            raise UsageError(f"--labels: entry {typed.index(BACKGROUND_PHRASE) + 1} is {BACKGROUND_PHRASE!r}, which --background adds as "
                             "the background (label -1): leave it out of --labels, or drop --background to make it a label of its own")
        encoder = (encoder_factory or partial(common.load_encoder, instead=common.oracle_flag("--embeddings")))(args, field)
        emb = text_embeddings(encoder, names + ([BACKGROUND_PHRASE] if args.background else []), field)
    else:
        common.warn_unused_clip_flags(args, None)
        emb = load_query_embeddings(args.embeddings, field.dim, "label")
        names = embedding_names(args.embeddings, getattr(args, "names", None), emb.shape[0] - int(args.background), bool(args.background))
    if args.background:
        if emb.shape[0] < 2:
            raise DrsplatError("--background needs at least one label besides the background row")
        return emb[:-1], emb[-1:], names
    return emb, None, names


def label_phrases(text: str) -> list[str]:
    """The --labels phrases (`checked_phrases`): none, an empty entry, a hidden character or a repeated phrase is a usage error."""
    return checked_phrases("--labels", text)


def warn_repeated_rows(embeddings: np.ndarray, names: list[str], background: np.ndarray | None = None) -> None:
    """A warning naming each label whose embedding row [D] equals an earlier label's, or is a multiple of it
    (`first_of_direction`): argmax gives the
    first of equal scores, so the later label would never win a Gaussian. The background's rows [B, D] come after the
    labels' there: one equal to a label's never wins (round 69c F2: said for two labels, not for the background)."""
    from drsplat.query import first_of_direction, query_rows

    rows = embeddings if background is None else np.concatenate([embeddings, background.reshape(-1, embeddings.shape[1])])
    shown = [*names, *(["the background"] * (rows.shape[0] - len(names)))]
    first = first_of_direction(query_rows(rows, "label embedding"))  # a row times 3 too (round 85c F1: compared by bits)
    for i, earliest in enumerate(first.tolist()):
        if earliest != i:
            later = shown[i] if i >= len(names) else repr(shown[i])  # "the background", or the label's name quoted
            earlier = shown[earliest]
            log.warning("%s%s has the same embedding as %r: argmax gives every such Gaussian to %r, so %s gets none",
                        "" if i >= len(names) else "label ", later, earlier, earlier, later)


def embedding_names(embeddings: Path, names_path: Path | None, count: int, background: bool = False) -> list[str]:
    """Names of `count` label embeddings: NAMES.json (a JSON list) when given, else, for a synthetic dataset's own
    text_embeddings.npy, its gt/label_names.json when that names exactly `count` labels, else label_i.
    background: the file's rows hold one more, the background (--background, its last row), which a
    list may name too (round 49: a dataset's 8 names for its 8 rows were ignored as "not naming the
    7 label rows")."""
    explicit = names_path is not None
    path = names_path if explicit else default_names_path(embeddings)
    # the name, and no link to a file elsewhere (round 60c: a link of that name to reversed rows took the names)
    own = embeddings.name == ORACLE_TEXT_EMBEDDINGS and not embeddings.is_symlink()
    if not explicit and path.is_file() and not own:
        # the dataset's names are those of its own rows: another file beside them (rows reordered, other vectors) took
        # them too, and the table named the labels wrongly (round 59a)
        log.info("not naming the rows of %s by %s, which names the rows of %s; give --names to name them", shown_path(embeddings),
                 shown_path(path), ORACLE_TEXT_EMBEDDINGS)
        return [f"label_{i}" for i in range(count)]
    if explicit or path.is_file():
        names = read_json(path, "a JSON list of names")
        if isinstance(names, list) and (len(names) == count or (background and len(names) == count + 1)):
            return checked_names(path, names[:count])
        rows = f"{count} names (one per label row of {embeddings.name}" + (f"; or {count + 1}, the last the background row)" if background else ")")
        if explicit:
            raise InputError(path, f"must be a JSON list of {rows}")
        log.info("ignoring %s: it is not a list of %s", shown_path(path), rows)
    return [f"label_{i}" for i in range(count)]


def default_names_path(embeddings: Path) -> Path:
    """Where a synthetic dataset keeps the names of its label embeddings: gt/label_names.json beside them."""
    return embeddings.parent / ORACLE_LABEL_NAMES


def names_input(args: argparse.Namespace) -> Path | None:
    """The names file `embedding_names` will read (--names, else the default beside --embeddings when
    it exists), or None: an input that no output may replace."""
    if getattr(args, "embeddings", None) is None:
        return None
    if getattr(args, "names", None) is not None:
        return args.names
    default = default_names_path(args.embeddings)
    return default if default.is_file() else None


def coloured_scene(scene: GaussianScene, labels: np.ndarray, colors: np.ndarray, keep_degree: bool = True) -> GaussianScene:
    """Scene whose view-independent colour is its label's colour (grey for -1), its SH rest zero: at the scene's own
    degree when `keep_degree` (a PLY: written at degree 0, it failed INRIA's loader and GaussianSplattingViewer, which
    expect degree 3's 45 f_rest columns; round 56d), else at degree 0 (a .compressed.ply stores no exact 0, its rest
    came back 0.0156 and tinted every colour: round 56e)."""
    rgb = np.where(labels[:, None] >= 0, colors[np.maximum(labels, 0)] if len(colors) else BACKGROUND_GREY, BACKGROUND_GREY)
    sh = np.zeros((scene.num_gaussians, scene.sh.shape[1] if keep_degree else 1, 3), np.float32)
    sh[:, 0] = (rgb - 0.5) / SH_C0
    base = strip_field(scene)
    return GaussianScene(base.means, base.quats, base.log_scales, base.opacity_logits, sh, dict(base.extra), list(base.comments))


def run(args: argparse.Namespace, encoder_factory=None) -> int:
    from drsplat.lang import export_kind, export_scene, written_codebook_path
    from drsplat.query import label_colors, segment
    from drsplat.splat_formats import check_writable, written_format
    from drsplat.utils import check_outputs_writable, guard_outputs, outputs_together, save_npy_atomic

    inputs = {"REGISTERED.ply": args.registered, "--embeddings": args.embeddings, "--clip-checkpoint": args.clip_checkpoint,
              "the registered PLY's codebook": written_codebook_path(args.registered),
              "--names" if getattr(args, "names", None) is not None else "--names (by default gt/label_names.json)": names_input(args)}
    if args.labels is not None:
        label_phrases(args.labels)  # a usage error before any file is read
    outputs = {"--out": args.out, "--ply": args.ply, **export_outputs(args.ply, args.format, "--ply")}
    guard_outputs(inputs, outputs)
    # before the work, as query does: a write-protected --ply refused after LABELS.npy was written took the earlier labels
    # file with it (outputs_together), and nothing was left (round 60a)
    check_outputs_writable(*outputs.values())
    scene, field = load_registered(args.registered, geometry=args.ply is not None)  # the Gaussians only for --ply
    guard_field_codebook(args.registered, field, outputs)
    common.check_npy_name("--out", args.out)
    assigned = field.assigned()
    if not assigned.any():  # every label would be -1 (written so until 2026-11-30): nothing to segment
        raise DrsplatError(f"{args.registered}: none of its {len(field):,} Gaussians has a language feature (all unassigned or "
                           "non-finite): there is nothing to segment")
    labels_emb, background, names = label_embeddings(args, field, encoder_factory)
    warn_repeated_rows(labels_emb, names, background)
    device = scoring_device(args)
    seg = segment(field, labels_emb, background=background, min_score=args.min_score, lut_bits=lut_bits_for(args, field, device),
                  device=device)
    if args.min_score is not None and not (seg.labels >= 0).any():
        log.warning("no Gaussian's best score reaches --min-score %g (the best is %.4f): every label is -1", args.min_score,
                    float(seg.scores[assigned].max()))
    coloured = None if args.ply is None else coloured_scene(scene, seg.labels, label_colors(len(names)),
                                                             keep_degree=written_format(args.ply) == "ply")
    if coloured is not None:
        check_writable(coloured, args.ply)  # before LABELS.npy is written: a refused export leaves no half of the outputs
    with outputs_together(outputs.values()):  # a failed export (a full disk) takes LABELS.npy with it
        save_npy_atomic(args.out, seg.labels)
        log.info("wrote %d labels to %s", seg.labels.shape[0], shown_path(args.out))
        if coloured is not None:
            export_scene(coloured, field, args.ply, args.format)
            log.info("wrote the label-coloured scene to %s (%s)", shown_path(args.ply), export_kind(args.ply, args.format))
    counts = np.bincount(seg.labels + 1, minlength=len(names) + 1)
    stream = table_stream(args.out, args.ply)
    print(f"{'label':<24} {'gaussians':>10}", file=stream)
    for i, name in enumerate(names):  # a name is cut as an error quotes it: a names file can hold one of megabytes
        print(f"{clipped(name, SHOWN_NAME_CHARS):<24} {int(counts[i + 1]):>10}", file=stream)
    print(f"{'(none / background)':<24} {int(counts[0]):>10}", file=stream)
    return 0
