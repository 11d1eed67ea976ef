"""`drsplat pq`: train a general product-quantisation codebook, or describe a codebook file."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

import numpy as np

from drsplat.commands.common import MAX_COUNT, guard_args, int_range, output_file, positive_int, protected_feature_folders
from drsplat.defaults import MIN_NORM
from drsplat.errors import InputError, UsageError, shown_path
from drsplat.features.format import FEAT_SUFFIX, embedding_norms
from drsplat.lang.codebook import PQ_KSUB, SCENE_PQ_M
from drsplat.lang.plyformat import CODEBOOK_SUFFIX, codebook_path_for
from drsplat.scene import starts_as_ply
from drsplat.utils import load_npy, outputs_together

log = logging.getLogger(__name__)

FAISS_MAX_SEED = 2**31 - 1  # faiss's k-means seed is a C int: a larger one was an OverflowError traceback


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("pq", help="train or inspect product-quantisation codebooks")
    actions = parser.add_subparsers(dest="pq_action", metavar="ACTION", required=True)

    train = actions.add_parser(
        "train",
        help="train a general PQ codebook (faiss IndexPQ) from embeddings",
        description=(
            "Train a faiss IndexPQ (inner product, M sub-vectors x 8 bits) on CLIP embeddings: .npy arrays (n, D) "
            "and/or every <stem>_f.npy of LangSplat feature folders. For the paper's general codebook, embed many "
            "object crops (LVIS or COCO) with the same CLIP model as your scenes (see docs/index.md)."
        ),
    )
    source = train.add_argument_group("embeddings (at least one)")
    source.add_argument("--embeddings", type=Path, nargs="+", default=[], metavar="A.npy", help="embedding arrays (n, D)")
    source.add_argument("--features", type=Path, nargs="+", default=[], metavar="DIR", help="LangSplat feature folders (<stem>_f.npy)")
    train.add_argument("--out", type=output_file, required=True, metavar="CODEBOOK", help="output faiss file (e.g. general.codebook.faiss)")
    train.add_argument("--m", type=positive_int, default=SCENE_PQ_M, help=f"number of sub-vectors M (32, 64, 128 or 256 for D=512); default {SCENE_PQ_M}")
    train.add_argument("--max-train", type=int_range(PQ_KSUB, MAX_COUNT), default=200_000, help="use at most this many embeddings (random subset); default 200000")
    train.add_argument("--seed", type=int_range(0, FAISS_MAX_SEED), default=0, help=f"k-means seed, 0..{FAISS_MAX_SEED} (faiss takes a C int); default 0")
    train.set_defaults(func=run_train)

    info = actions.add_parser("info", help="print what a codebook file contains")
    info.add_argument("codebook", type=Path, metavar="CODEBOOK")
    info.set_defaults(func=run_info)


def collect_embeddings(arrays: list[Path], folders: list[Path], max_train: int | None = None, seed: int = 0) -> tuple[np.ndarray, int]:
    """(training rows [n, D] float32, usable rows in all) from .npy files and feature folders: the finite rows of a
    direction, and of those `max_train` at most, drawn with `seed` (the draw over the usable rows in file order).

    Two passes over the files, each read a block of rows at a time (memory-mapped): the first judges every row, the
    second gathers the drawn ones. Every file was loaded whole, cast, concatenated and judged before the draw: 8 GB for
    a 2 GB file with --max-train 256, a 4 GB one killed at 10 GB (round 61b); the rows drawn are the same.
    """
    files = _embedding_files(arrays, folders)
    usable, dim = [], None
    skipped = {"zero or non-finite": 0, "huge": 0, "tiny": 0}
    for path in files:
        arr = _embedding_array(path, dim)
        dim = arr.shape[1]
        keep = np.empty(arr.shape[0], bool)
        for lo in range(0, arr.shape[0], PQ_READ_ROWS):
            x = float32_rows(path, arr[lo : lo + PQ_READ_ROWS], lo, arr.shape[0])
            ok = np.isfinite(x).all(axis=1) & (x != 0).any(axis=1)
            # judged as the feature reader judges a mask's embedding (`features.format.read_features_report`), in float64: a float32
            # sum of values near 3e38 overflowed and such rows were trained on; a norm below float32's smallest normal holds no direction
            norms = embedding_norms(x)
            huge, tiny = ok & (norms > np.finfo(np.float32).max), ok & (norms < MIN_NORM)
            skipped["zero or non-finite"] += int((~ok).sum())
            skipped["huge"] += int(huge.sum())
            skipped["tiny"] += int(tiny.sum())
            keep[lo : lo + PQ_READ_ROWS] = ok & ~huge & ~tiny
        usable.append(keep)
    total = sum(k.shape[0] for k in usable)
    for key, why in (("zero or non-finite", "that are zero or non-finite"),
                     ("huge", "that have a norm beyond float32's range (+-3.4e38)"),
                     ("tiny", f"that have a norm below {MIN_NORM:.3g} (float32's smallest normal number), too small to hold a direction")):
        if skipped[key]:
            log.warning("skipping %d of %d embeddings %s", skipped[key], total, why)
    count = int(sum(int(k.sum()) for k in usable))
    drawn = np.arange(count) if max_train is None or count <= max_train else np.sort(np.random.default_rng(seed).choice(count, max_train, replace=False))
    out = np.empty((drawn.shape[0], dim or 0), np.float32)
    first, filled = 0, 0  # the usable rows before this file; the rows of `out` filled
    for path, keep in zip(files, usable):
        rows = np.flatnonzero(keep)
        take = drawn[(drawn >= first) & (drawn < first + rows.shape[0])] - first
        if take.size:
            arr = _embedding_array(path, dim)
            picked = rows[take]
            for lo in range(0, picked.shape[0], PQ_READ_ROWS):
                part = picked[lo : lo + PQ_READ_ROWS]
                out[filled : filled + part.shape[0]] = np.asarray(arr[part], np.float32)
                filled += part.shape[0]
        first += rows.shape[0]
    return out, count


PQ_READ_ROWS = 1 << 16  # embedding rows judged or gathered at a time


def _embedding_files(arrays: list[Path], folders: list[Path]) -> list[Path]:
    """The .npy files of --embeddings, then the *_f.npy files of each --features folder (each given once)."""
    files = list(arrays)
    given = [*arrays, *folders]
    for i, path in enumerate(given):
        for earlier in given[:i]:
            if path.resolve() == earlier.resolve():  # its rows would count twice in the training set
                raise UsageError(f"{path} is given twice (as {earlier}); each embedding file or folder may be given once")
    for folder in folders:
        if not folder.is_dir():
            raise InputError(folder, "features folder does not exist" if not folder.exists() else "is not a folder (--features takes a folder of *_f.npy files; a .npy file goes to --embeddings)")
        found = sorted(folder.glob(f"*{FEAT_SUFFIX}"))
        if not found:
            raise InputError(folder, f"no *{FEAT_SUFFIX} embedding files in this folder")
        files.extend(found)
    if not files:
        raise UsageError("no embeddings given: use --embeddings A.npy or --features DIR")
    return files


def _embedding_array(path: Path, dim: int | None) -> np.ndarray:
    """The file's rows [n, D], memory-mapped, checked to be floats or integers of the earlier files' D."""
    arr = load_npy(path, "embedding array", mmap=True)
    if arr.ndim != 2 or arr.shape[1] == 0 or arr.dtype.kind not in "fiu":
        raise InputError(path, f"expected a float array (n, D), got shape {arr.shape} dtype {arr.dtype}")
    if dim is not None and arr.shape[1] != dim:
        raise InputError(path, f"embeddings are {arr.shape[1]}-D but earlier files are {dim}-D")
    return arr


def float32_rows(path: Path, arr: np.ndarray, first_row: int = 0, file_rows: int | None = None) -> np.ndarray:
    """arr [n, D] as float32, or InputError naming the rows whose finite values lie beyond float32's
    range (a cast would make them inf, and they would be skipped as if the file held non-finite values).
    first_row: the file's row of arr's first; file_rows: the file's rows (arr a block of the file)."""
    if arr.dtype.itemsize > 4 or arr.dtype.kind in "iu":
        wide = np.asarray(arr, np.float64)
        big = (np.isfinite(wide) & (np.abs(wide) > np.finfo(np.float32).max)).any(axis=1)  # inf and NaN are skipped rows, counted later
        if big.any():
            rows = np.flatnonzero(big)
            total = arr.shape[0] if file_rows is None else file_rows
            which = (f"{rows.size} of {total} rows hold" if total == arr.shape[0] else  # a block: its count is not the file's (round 62a)
                     f"rows of its {total} hold")
            raise InputError(path, f"{which} values beyond float32's range (±3.4e38), e.g. row {first_row + int(rows[0])}; "
                             "embeddings are stored as float32")
    return np.asarray(arr, np.float32)


def warn_if_a_registrations_codebook(out: Path) -> None:
    """A warning, before the training, when `out` (or the file a link there names) is an existing
    `<stem>.codebook.faiss` beside another file of that stem (`<stem>.ply`, `<stem>.PLY`, `<stem>`: `register
    --out` takes any): the codebook a registration wrote for it, whose codes would then decode to other vectors
    (round 85c F3: replaced without a word; the PLY's next query said only that the codebook's d disagreed; round
    86a F1: a `Room.PLY` or a link was missed)."""
    for path in dict.fromkeys([Path(out), Path(out).resolve()]):
        name = path.name
        if not name.endswith(CODEBOOK_SUFFIX) or not path.is_file():
            continue
        try:
            entries = sorted(os.listdir(path.parent))
        except OSError:
            continue
        # the files whose registration writes this name (`codebook_path_for`, the one owner of that rule)
        owners = [e for e in entries if e != name and codebook_path_for(path.parent / e).name == name and _is_ply(path.parent / e)]
        if owners:
            ply = path.parent / owners[0]
            log.warning("--out %s replaces the codebook that registration writes for %s beside it: if %s uses it, its codes will "
                        "decode to other vectors and it must be registered again (stop now, or choose another --out)",
                        shown_path(out), shown_path(ply), ply.name)
            return


def _is_ply(path: Path) -> bool:
    """Whether `path` is a regular file that begins as a PLY does ('ply' and a line end): a registration's output, not
    the embeddings or notes of the same stem (round 86c F3: `--embeddings crops.npy --out crops.codebook.faiss` warned)."""
    if not path.is_file():  # before opening: a FIFO of that name would block the open (round 87a F1)
        return False
    try:
        with open(path, "rb") as f:
            return starts_as_ply(f.read(4))
    except OSError:
        return False


def run_train(args: argparse.Namespace) -> int:
    from drsplat.lang import train_codebook
    from drsplat.utils import check_output_writable

    guard_args(args, ("out",), protected_folders=protected_feature_folders("--features", args.features))
    check_output_writable(args.out)  # before minutes of k-means (round 57c: a read-only folder failed after them)
    warn_if_a_registrations_codebook(args.out)
    x, usable = collect_embeddings(args.embeddings, args.features, args.max_train, args.seed)
    if x.shape[1] % args.m:
        divisors = [m for m in range(1, x.shape[1] + 1) if x.shape[1] % m == 0 and m <= 256]
        shown = divisors[-4:]
        listed = f"{', '.join(map(str, shown[:-1]))} or {shown[-1]}" if len(shown) > 1 else str(shown[0])
        raise UsageError(f"--m {args.m} does not divide the embedding dimension {x.shape[1]}; choose a divisor of it, e.g. {listed}")
    if usable < PQ_KSUB:
        sources = [*args.embeddings, *args.features]
        where = "" if len(sources) == 1 else " in " + ", ".join(str(p) for p in sources)
        raise InputError(sources[0] if len(sources) == 1 else None, f"only {usable} usable embeddings (finite, nonzero rows){where}: "
                         f"a codebook needs at least {PQ_KSUB} (ideally 10,000+)")
    log.info("training PQ M=%d x 8 bits on %d embeddings of dimension %d", args.m, x.shape[0], x.shape[1])
    book = train_codebook(x, m=args.m, seed=args.seed, show_progress=sys.stderr.isatty())  # a minute or more: shown (round 68a F13)
    with outputs_together([args.out]):  # settled: an interrupt after it names it (round 96a F6)
        book.save(args.out)
    # logged as every command's "wrote" line: printed, it went into the codebook's bytes with `--out /dev/stdout | ...` and past -q (round 100f F1)
    log.info("wrote %s: pq d=%d M=%d x 8 bits, %d bytes per Gaussian, trained on %d embeddings", shown_path(args.out), book.dim, book.m, book.m, x.shape[0])
    return 0


def run_info(args: argparse.Namespace) -> int:
    from drsplat.lang import load_codebook

    book = load_codebook(args.codebook)
    index = book.index
    print(f"file:        {shown_path(args.codebook)}")
    print(f"type:        {type(index).__name__} ({book.kind})")
    print(f"dimension:   {book.dim}")
    print(f"metric:      {'inner product' if index.metric_type == 0 else 'L2'}")
    print(f"PQ:          M={book.m} sub-vectors of {book.dsub} dims x 8 bits")
    if book.kind == "ivfpq":
        empty = int((np.linalg.norm(book.coarse, axis=1) == 0).sum()) if book.coarse is not None else 0
        print(f"coarse:      nlist={index.nlist} ({empty} zero centroids), by_residual={bool(index.by_residual)}")
        print(f"code bytes:  {index.sa_code_size()} (faiss sa_encode: list id + PQ), drsplat stores {book.m} + 4 (lang_list)")
    else:
        print(f"code bytes:  {book.m}")
    return 0
