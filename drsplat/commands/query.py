"""`drsplat query`: score every Gaussian of a registered PLY against a text, embedding or click query."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from drsplat.device import add_device_arguments, resolve_compute
from drsplat.errors import DrsplatError, InputError
from drsplat.lang import LanguageField, read_field, strip_field
from drsplat.scene import GaussianScene

log = logging.getLogger(__name__)

DEFAULT_RELEVANCY_THRESHOLD = 0.5


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "query",
        help="score every Gaussian of a registered PLY against a query",
        description=(
            "Cosine similarity (or LERF relevancy with --relevancy) of every Gaussian of REGISTERED.ply to a text "
            "phrase, an embedding file or the mean feature of some Gaussians. Without --scores/--out the best "
            "Gaussians are printed."
        ),
    )
    parser.add_argument("registered", type=Path, metavar="REGISTERED.ply", help="PLY written by drsplat register")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--text", action="append", metavar="PHRASE", help="text query (repeat for several); needs CLIP weights")
    source.add_argument("--embedding", type=Path, metavar="Q.npy", help="query embedding(s), (D,) or (K, D)")
    source.add_argument("--gaussians", type=Path, metavar="IDS.npy", help="Gaussian indices (or a boolean mask): query = mean of their features")
    parser.add_argument("--relevancy", action="store_true", help="LERF relevancy against canonical negatives instead of cosine")
    add_lut_bits_argument(parser)
    parser.add_argument("--negatives", default="", metavar="A,B", help="extra negative phrases for --relevancy (comma-separated)")
    parser.add_argument("--negative-embeddings", type=Path, metavar="N.npy", help="negative embeddings (C, D) for --relevancy without a text encoder")
    parser.add_argument("--threshold", default=None, metavar="T|auto", help="selection threshold (number, or 'auto' for Otsu); default 0.5 for relevancy, auto for cosine")
    parser.add_argument("--scores", type=Path, metavar="OUT.npy", help="write float32 scores, (N,) for one query or (N, K)")
    parser.add_argument("--out", type=Path, metavar="SELECTION.ply", help="write the Gaussians scoring >= T as a standard 3DGS PLY")
    parser.add_argument("--top", type=int, default=10, help="how many best Gaussians to print when nothing is written")
    add_clip_arguments(parser, scoring=True)
    parser.set_defaults(func=run)


def add_clip_arguments(parser: argparse.ArgumentParser, scoring: bool = False) -> None:
    """CLIP encoder flags; scoring: --device also places the scoring, with --engine (drsplat.device)."""
    group = parser.add_argument_group("CLIP text encoder (text queries)")
    group.add_argument("--clip-checkpoint", type=Path, metavar="PATH", help="local OpenCLIP weights file")
    group.add_argument("--clip-model", default=None, help="OpenCLIP architecture (default: the one recorded in the PLY)")
    group.add_argument("--pretrained", default=None, help="pretrained tag (default: the one recorded in the PLY)")
    if scoring:
        add_device_arguments(parser.add_argument_group("compute (text encoder and scoring)"))
    else:
        group.add_argument("--device", default="cpu", choices=("auto", "cpu", "cuda"))


def scoring_device(args: argparse.Namespace) -> str | None:
    """Where to score (LanguageField.scores' device): None for the numba CPU kernels, else a torch device."""
    device, engine = resolve_compute(args)
    return device if engine == "torch" else None


def load_registered(path: Path) -> tuple[GaussianScene, LanguageField]:
    """Load a registered PLY and its language field (InputError if it has none or rows were dropped)."""
    from drsplat.scene import load_ply_report

    scene, report = load_ply_report(path)
    dropped = report.dropped_nan_rows + report.dropped_inf_rows
    if dropped:
        raise InputError(path, f"{dropped} rows have non-finite values and would be dropped, so scores could not follow the file order")
    field = read_field(scene, path)
    if field is None:
        raise InputError(path, "has no language field (no 'drsplat.lang' header comment); run drsplat register first")
    return scene, field


def load_encoder(args: argparse.Namespace, field: LanguageField):
    """The CLIP text encoder for a field: architecture and tag default to the field's model id."""
    from drsplat.features.clip import DEFAULT_MODEL, ClipEncoder
    from drsplat.features.modelid import is_oracle

    if is_oracle(field.clip_model):
        raise DrsplatError(
            "this scene's features are synthetic oracle embeddings, not CLIP: query it with --embedding "
            "(rows of the synthetic dataset's text_embeddings.npy) instead of text"
        )
    model, pretrained = DEFAULT_MODEL, None
    if "/" in field.clip_model:
        model, pretrained = field.clip_model.split("/", 1)
    return ClipEncoder(
        model=args.clip_model or model,
        pretrained=args.pretrained or pretrained,
        checkpoint=args.clip_checkpoint,
        device=args.device,
    )


def split_phrases(text: str) -> list[str]:
    return [p.strip() for p in text.split(",") if p.strip()]


def build_queries(args: argparse.Namespace, field: LanguageField, encoder_factory=None) -> tuple[np.ndarray, bool, object]:
    """(queries [K, D], single (scores written as (N,)), encoder or None)."""
    from drsplat.query import click_query, load_gaussian_ids, load_query_embeddings, text_embeddings

    encoder_factory = encoder_factory or load_encoder
    if args.text:
        encoder = encoder_factory(args, field)
        return text_embeddings(encoder, args.text, field), len(args.text) == 1, encoder
    if args.embedding is not None:
        queries = load_query_embeddings(args.embedding, field.dim)
        return queries, np.load(args.embedding, mmap_mode="r").ndim == 1, None
    ids = load_gaussian_ids(args.gaussians, field.num_gaussians)
    return click_query(field, ids)[None], True, None


def add_lut_bits_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--lut-bits", type=int, choices=(32, 8), default=32,
                        help="PQ look-up tables: 32 exact float32 (default), 8 faster 8-bit tables (see `drsplat bench query` for the error)")


def compute_scores(args: argparse.Namespace, field: LanguageField, queries: np.ndarray, encoder, encoder_factory=None) -> np.ndarray:
    """[N, K] cosine, or relevancy with --relevancy."""
    from drsplat.query import cosine, load_query_embeddings, negative_embeddings, relevancy

    lut_bits = getattr(args, "lut_bits", 32)
    device = scoring_device(args)
    if not args.relevancy:
        return cosine(field, queries, lut_bits=lut_bits, device=device)
    user = split_phrases(args.negatives)
    extra = None if args.negative_embeddings is None else load_query_embeddings(args.negative_embeddings, field.dim)
    if encoder is None and (extra is None or user):
        encoder = (encoder_factory or load_encoder)(args, field)
    return relevancy(field, queries, negative_embeddings(encoder, field, user, extra), lut_bits=lut_bits, device=device)


def resolve_threshold(value: str | None, scores: np.ndarray, relevancy: bool) -> float:
    from drsplat.query import otsu_threshold

    if value is None:
        value = str(DEFAULT_RELEVANCY_THRESHOLD) if relevancy else "auto"
    if value == "auto":
        threshold = otsu_threshold(scores)
        log.info("automatic (Otsu) threshold: %.4f", threshold)
        return threshold
    try:
        return float(value)
    except ValueError:
        raise DrsplatError(f"--threshold must be a number or 'auto', got {value!r}") from None


def run(args: argparse.Namespace, encoder_factory=None) -> int:
    from drsplat.scene import save_ply
    from drsplat.utils import save_npy_atomic

    scene, field = load_registered(args.registered)
    queries, single, encoder = build_queries(args, field, encoder_factory)
    scores = compute_scores(args, field, queries, encoder, encoder_factory)
    best = scores.max(axis=1) if scores.shape[1] else np.zeros(len(field), np.float32)
    wrote = False
    if args.scores is not None:
        written = scores[:, 0].copy() if single else scores
        save_npy_atomic(args.scores, written)
        log.info("wrote %s scores %s to %s", "relevancy" if args.relevancy else "cosine", written.shape, args.scores)
        wrote = True
    if args.out is not None or args.threshold is not None:
        threshold = resolve_threshold(args.threshold, best, args.relevancy)
        mask = best >= threshold
        print(f"{int(mask.sum())} of {len(mask)} Gaussians score >= {threshold:.4f}")
        if args.out is not None:
            save_ply(strip_field(scene.subset(mask)), args.out)
            log.info("wrote %d selected Gaussians to %s", int(mask.sum()), args.out)
            wrote = True
    if not wrote:
        print_top(best, args.top, "relevancy" if args.relevancy else "cosine")
    return 0


def print_top(best: np.ndarray, top: int, what: str) -> None:
    order = np.argsort(-best, kind="stable")[: max(top, 0)]
    print(f"{'gaussian':>10}  {what:>9}")
    for i in order:
        print(f"{int(i):>10}  {best[i]:>9.4f}")
