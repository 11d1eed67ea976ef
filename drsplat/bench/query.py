"""`drsplat bench query`: query speed against accuracy for every language-field backend.

For N synthetic Gaussians with CLIP-like clustered embeddings it times one cosine query (and a
batch of 16) with float32 matmul, the float16 exact field, faiss PQ of each M (LUT kernel), the
official IVFPQ codebook (LUT kernel, float32 and 8-bit tables) and faiss's own search, and measures each approximation
against exact float32 cosines: mean |Δcos|, Spearman correlation, selection IoU at the threshold.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drsplat.commands.common import int_range, output_file, positive_int
from drsplat.bench.common import choice_list, count_arg, count_list, format_table, guard_bench_outputs, machine_line, median_seconds, peak_rss_mb
from drsplat.errors import DrsplatError, InputError, UsageError, shown_path
from drsplat.lang import (PQ_KSUB, Codebook, ExactStorage, LanguageField, PQStorage, blocked_codes, load_codebook, lut_scores,
                          lut_scores_blocked, train_codebook)
from drsplat.lang.codebook import SCENE_PQ_M
from drsplat.query import embedding_row_problems, unit_rows

log = logging.getLogger(__name__)

DEFAULT_OFFICIAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "drsplat" / "pq_index.faiss"
TEXT_NEGATIVES = "text_negative.npy"  # beside the official codebook: real CLIP text embeddings (`text_query_table`)
TEXT_TABLE_N = 100_000  # random unit features scored in `text_query_table`
BACKENDS = ("float32", "float16", "pq32", "pq64", "pq128", "pq256", "official", "faiss")
FAISS_SEARCHED = ("pq128", "official")  # the codebooks whose codes `faiss` searches with faiss's own index
MAX_DIM = 8192  # embedding width (CLIP's are 512-1024)
MAX_LABELS = 100_000  # classes of the synthetic embeddings (each with its directions in memory)
FAISS_SEED_MAX = 2**31 - 1  # the codebooks' k-means seed is a C int in faiss (commands.common.seed_int's 2^32 - 1 overflows it)
GEN_CHUNK = 250_000
SPEARMAN_SAMPLE = 200_000
BATCH = 16
BOUNDARY_FRACTION = 0.1
GAUSSIAN_NOISE = 0.2


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("query", help="ms/query and error against exact for every language-field backend")
    p.add_argument("--sizes", type=count_list, default="100k,1M", help="comma-separated Gaussian counts, e.g. 100k,1M,5M (default 100k,1M)")
    p.add_argument("--backends", type=choice_list(BACKENDS, "backend"), default=",".join(BACKENDS), help=f"subset of {','.join(BACKENDS)}")
    p.add_argument("--dim", type=int_range(1, MAX_DIM), default=512, help=f"embedding width, 1..{MAX_DIM} (default: 512)")
    p.add_argument("--labels", type=int_range(2, MAX_LABELS), default=40,
                   help=f"object classes in the synthetic embeddings, 2..{MAX_LABELS:,} (a query's class against the rest; default: 40)")
    p.add_argument("--queries", type=positive_int, default=8, help="text queries whose errors are averaged, one class each: at most --labels (default: 8)")
    p.add_argument("--train", type=positive_int, default=5_000, help=f"embeddings used to train the general PQ codebooks, at least {PQ_KSUB} (default: 5000)")
    p.add_argument("--train-sizes", type=count_list, default=None, metavar="SIZES",
                   help=f"also train PQ codebooks (M of the first pq backend, {SCENE_PQ_M} without one) on each of these numbers of embeddings, "
                        "e.g. 1k,5k,20k, and report the training time beside the scores' error on the first --sizes Gaussians: what "
                        "`pq train --max-train` and the scene codebook's training sample cost (default: not run)")
    p.add_argument("--cache-dir", type=Path, default=None,
                   help="trained PQ codebooks (the pq* backends) are kept here for reuse (default: drsplat-bench-query in the temp folder)")
    p.add_argument("--official", type=Path, default=None,
                   help="official Dr. Splat IVFPQ codebook, with text_negative.npy beside it (default: ../shared/data/drsplat/pq_index.faiss, "
                        "skipped when absent)")
    p.add_argument("--max-float32", type=count_arg, default="2M", help="skip the float32 baseline above this N (it needs 2 KB per Gaussian)")
    p.add_argument("--repeats", type=positive_int, default=5, help="timed repeats (median); fewer are used above 1M")
    p.add_argument("--seed", type=int_range(0, FAISS_SEED_MAX), default=0, help="random seed, 0..2^31-1 (default: 0)")
    p.add_argument("--plot", type=output_file, default=Path("bench_query.png"), help="PNG of speed against error (default: bench_query.png in the working folder, always written)")
    p.add_argument("--device", default=None, choices=("auto", "cpu", "cuda"),
                   help="also time the torch scorer on this device against the numba kernels (ratio and max |Δ| per backend)")
    p.set_defaults(func=run)


# ---------------------------------------------------------------------------------------------
# Synthetic CLIP-like embeddings


@dataclass
class EmbeddingModel:
    """Embeddings that look like CLIP's: every vector shares a common component, objects of a class
    share a class direction, instances vary around it, and text lives across a modality gap.

    object: normalize(1.0·c + 0.75·d_label + 0.45·u_instance); Gaussian: normalize(object (or a
    mix of two objects on boundaries) + 0.2·noise)
    text:  normalize(0.3·c + 0.9·c_text + 0.35·d_label + 0.15·noise)
    (image-text cosines ≈ 0.43 for the right class, 0.26 for others; image-image ≈ 0.56: CLIP-like)
    """

    common: np.ndarray
    text_common: np.ndarray
    label_dirs: np.ndarray
    instance_dirs: np.ndarray
    seed: int

    @classmethod
    def create(cls, dim: int, labels: int, seed: int, instances_per_label: int = 6) -> "EmbeddingModel":
        rng = np.random.default_rng(seed)
        vecs = unit_rows(rng.standard_normal((2 + labels + labels * instances_per_label, dim), dtype=np.float32))
        return cls(vecs[0], vecs[1], vecs[2 : 2 + labels], vecs[2 + labels :].reshape(labels, instances_per_label, dim), seed)

    def images(self, n: int, chunk_seed: int) -> tuple[np.ndarray, np.ndarray]:
        """([n, D] unit float32 embeddings, [n] labels), deterministic per chunk_seed.

        A Gaussian's registered feature is its object's embedding plus a little noise (it averages
        many masks); BOUNDARY_FRACTION of them mix two objects (Gaussians on an edge get weight
        from both masks), which fills the score range between classes.
        """
        rng = np.random.default_rng([self.seed, chunk_seed])
        labels, inst = self.label_dirs.shape[0], self.instance_dirs.shape[1]
        dim = self.common.shape[0]
        lab, ins = rng.integers(0, labels, n), rng.integers(0, inst, n)
        x = self._objects(lab, ins)
        edge = np.flatnonzero(rng.random(n) < BOUNDARY_FRACTION)
        lam = rng.random((edge.size, 1)).astype(np.float32)
        other = self._objects(rng.integers(0, labels, edge.size), rng.integers(0, inst, edge.size))
        x[edge] = lam * x[edge] + (1 - lam) * other
        x += rng.standard_normal((n, dim), dtype=np.float32) * np.float32(GAUSSIAN_NOISE / np.sqrt(dim))
        return unit_rows(x), lab

    def _objects(self, lab: np.ndarray, ins: np.ndarray) -> np.ndarray:
        return unit_rows(self.common + np.float32(0.75) * self.label_dirs[lab] + np.float32(0.45) * self.instance_dirs[lab, ins])

    def texts(self, labels: np.ndarray) -> np.ndarray:
        rng = np.random.default_rng([self.seed, 999_999])
        noise = rng.standard_normal((len(labels), self.common.shape[0]), dtype=np.float32) * np.float32(0.15 / np.sqrt(self.common.shape[0]))
        return unit_rows(0.3 * self.common + 0.9 * self.text_common + 0.35 * self.label_dirs[labels] + noise)


# ---------------------------------------------------------------------------------------------
# Measurement


@dataclass
class Row:
    backend: str
    n: int
    bytes_per_gaussian: float
    ms_query: float
    ms_query_batch: float
    cpu_ms_query: float
    mean_abs_err: float | None = None  # None: not measured (the faiss search rows: top-k only, no all-N scores)
    spearman: float | None = None
    iou: float | None = None
    notes: list[str] = field(default_factory=list)


def unmeasured_as_dash(*values: float | None) -> list:
    """The values for a table, "–" where not measured (None)."""
    return ["–" if v is None else v for v in values]


def cpu_and_wall(fn, repeats: int) -> tuple[float, float]:
    """(median wall seconds, median process CPU seconds) of fn() after one warm-up."""
    fn()
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return float(np.median(walls)), float(np.median(cpus))


def errors_against(exact: np.ndarray, approx: np.ndarray, thresholds: np.ndarray, rng: np.random.Generator) -> tuple[float, float, float]:
    """(mean |Δcos|, mean Spearman ρ, mean selection IoU at each query's threshold) over queries."""
    from scipy.stats import spearmanr

    n = exact.shape[0]
    sample = rng.choice(n, size=min(n, SPEARMAN_SAMPLE), replace=False)
    rhos, ious = [], []
    for k in range(exact.shape[1]):
        rhos.append(spearmanr(exact[sample, k], approx[sample, k]).statistic)
        a, b = exact[:, k] >= thresholds[k], approx[:, k] >= thresholds[k]
        union = np.count_nonzero(a | b)
        ious.append(np.count_nonzero(a & b) / union if union else 1.0)
    return float(np.mean(np.abs(exact - approx))), float(np.mean(rhos)), float(np.mean(ious))


def localisation_thresholds(exact: np.ndarray, labels: np.ndarray, query_labels: np.ndarray) -> np.ndarray:
    """[K] per query: midway between the mean exact cosine of its class's Gaussians and of the rest."""
    out = np.empty(len(query_labels))
    for k, lab in enumerate(query_labels):
        hit = labels == lab
        out[k] = 0.5 * (exact[hit, k].mean() + exact[~hit, k].mean())
    return out


def faiss_search_index(book: Codebook, codes: np.ndarray, list_ids: np.ndarray | None):
    """A faiss index over the same codes (IndexPQ, or IndexIVFPQ scanning every list)."""
    import faiss

    index = faiss.clone_index(book.index)
    if book.kind == "pq":
        index.codes.resize(0)
        faiss.copy_array_to_vector(np.ascontiguousarray(codes).ravel(), index.codes)
        index.ntotal = codes.shape[0]
        return index
    coarse_bytes = index.sa_code_size() - book.m
    packed = np.concatenate([list_ids.astype("<u8").view(np.uint8).reshape(-1, 8)[:, :coarse_bytes], codes], axis=1)
    index.add_sa_codes(np.ascontiguousarray(packed), np.arange(codes.shape[0], dtype=np.int64))
    index.nprobe = index.nlist
    return index


def text_queries(model: EmbeddingModel, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(labels [Q], text embeddings [Q, D]) of `count` queries, one class each (at most the model's classes), drawn from
    `seed` + 1: the same queries for every table of a run."""
    labels = np.random.default_rng(seed + 1).choice(model.label_dirs.shape[0], size=min(count, model.label_dirs.shape[0]), replace=False)
    return labels, model.texts(labels)


def bench_size(args: argparse.Namespace, n: int, model: EmbeddingModel, books: dict[str, Codebook], backends: list[str]) -> list[Row]:
    q_labels, queries = text_queries(model, args.queries, args.seed)
    q1, qb = queries[:1], np.repeat(queries, -(-BATCH // len(queries)), axis=0)[:BATCH]
    keep32 = "float32" in backends and n <= args.max_float32
    f32 = np.empty((n, args.dim), np.float32) if keep32 else None
    f16 = np.empty((n, args.dim), np.float16)
    exact = np.empty((n, len(queries)), np.float32)
    labels = np.empty(n, np.int64)
    coded = {name: (np.zeros((n, b.m), np.uint8), np.zeros(n, np.int32) if b.kind == "ivfpq" else None, np.zeros(n, np.float32)) for name, b in books.items()}
    t0 = time.perf_counter()
    for ci, start in enumerate(range(0, n, GEN_CHUNK)):
        stop = min(n, start + GEN_CHUNK)
        x, labels[start:stop] = model.images(stop - start, ci)
        exact[start:stop] = x @ queries.T
        f16[start:stop] = x
        if f32 is not None:
            f32[start:stop] = x
        for name, book in books.items():
            stored = PQStorage.encode(x, np.ones(stop - start, bool), book)
            codes, ids, norms = stored.codes, stored.list_ids, stored.norms
            coded[name][0][start:stop] = codes
            if ids is not None:
                coded[name][1][start:stop] = ids
            coded[name][2][start:stop] = norms
    log.info("N=%d: generated and encoded in %.1f s", n, time.perf_counter() - t0)
    thresholds = localisation_thresholds(exact, labels, q_labels)
    repeats = args.repeats if n <= 1_000_000 else max(2, args.repeats // 2)
    rows: list[Row] = []
    if getattr(args, "device", None):
        fields = [("float16 exact", LanguageField(args.dim, "bench", np.ones(n, np.float32), ExactStorage(f16, _norms16(f16))))]
        for name, book in books.items():
            codes, ids, norms = coded[name]
            fields.append((f"PQ M={book.m}" if book.kind == "pq" else f"official IVFPQ M={book.m}",
                           LanguageField(args.dim, "bench", np.ones(n, np.float32), PQStorage(codes, ids, norms, book))))
        args.device_rows.extend(device_rows(fields, n, q1, queries, args.device, repeats))

    def measure(name: str, bpg: float, single, batch, scores_all) -> None:
        wall, cpu = cpu_and_wall(single, repeats)
        wall_b = median_seconds(batch, max(1, repeats // 2), warmup=0) / BATCH
        row = Row(name, n, bpg, wall * 1e3, wall_b * 1e3, cpu * 1e3)
        if scores_all is exact:  # the reference itself
            row.mean_abs_err, row.spearman, row.iou = 0.0, 1.0, 1.0
        elif scores_all is not None:
            row.mean_abs_err, row.spearman, row.iou = errors_against(exact, scores_all(), thresholds, np.random.default_rng(args.seed))
        rows.append(row)
        err = "–" if row.mean_abs_err is None else f"{row.mean_abs_err:.4f}"
        log.info("N=%d %s: %.2f ms/query (%.2f batched), err %s", n, name, row.ms_query, row.ms_query_batch, err)

    if f32 is not None:
        measure("float32 matmul", 4 * args.dim, lambda: f32 @ q1.T, lambda: f32 @ qb.T, exact)
        del f32
    if "float16" in backends:
        fp16 = LanguageField(args.dim, "bench", np.ones(n, np.float32), ExactStorage(f16, _norms16(f16)))
        measure("float16 exact", 2 * args.dim + 4, lambda: fp16.scores(q1), lambda: fp16.scores(qb), lambda: fp16.scores(queries))
    del f16
    for name, book in books.items():
        codes, ids, norms = coded[name]
        label = f"PQ M={book.m}" if book.kind == "pq" else f"official IVFPQ M={book.m}"
        bpg = book.m + 4 + (4 if ids is not None else 0)
        measure(label + " (LUT)", bpg, lambda: lut_scores(book, codes, ids, norms, q1), lambda: lut_scores(book, codes, ids, norms, qb), lambda: lut_scores(book, codes, ids, norms, queries))
        t0 = time.perf_counter()
        blocked = blocked_codes(codes)
        log.info("N=%d %s: blocked codes for 8-bit tables in %.2f s", n, label, time.perf_counter() - t0)
        for bits, suffix in ((32, "blocked"), (8, "u8")):
            measure(
                f"{label} (LUT {suffix})",
                bpg,
                lambda: lut_scores_blocked(book, blocked, n, ids, norms, q1, bits),
                lambda: lut_scores_blocked(book, blocked, n, ids, norms, qb, bits),
                lambda: lut_scores_blocked(book, blocked, n, ids, norms, queries, bits),
            )
        blocked = None  # frees the copy before the next codebook
        if "faiss" in backends and (book.m == 128 or book.kind == "ivfpq"):
            index = faiss_search_index(book, codes, ids)
            top = 1000
            measure(label + f" faiss search top-{top}", bpg, lambda: index.search(q1, top), lambda: index.search(qb, top), None)
            del index
    return rows


def train_sample_m(backends: list[str]) -> int:
    """The M of `--train-sizes`' codebooks: the first pq backend's, else `pq train`'s default (SCENE_PQ_M, the paper's 128)."""
    return next((int(name[2:]) for name in backends if name.startswith("pq")), SCENE_PQ_M)


def train_sample_table(model: EmbeddingModel, m: int, samples: list[int], n: int, num_queries: int, seed: int) -> str:
    """A PQ codebook of M = `m` trained on each number of embeddings in `samples` (a draw of its own, as a general codebook
    never sees the scene), its training time beside its scores' error against the exact cosines of `n` Gaussians
    (`errors_against`: mean |Δcos|, Spearman ρ, IoU at each query's threshold): the speed against error of training on
    a sample (`pq train --max-train`, the scene codebook's sample of rows)."""
    q_labels, queries = text_queries(model, num_queries, seed)
    x, labels = model.images(n, 0)
    exact = x @ queries.T
    thresholds = localisation_thresholds(exact, labels, q_labels)
    rows = []
    for size in samples:
        train, _ = model.images(size, 10_000_019)
        t0 = time.perf_counter()
        book = train_codebook(train, m=m, seed=seed)
        seconds = time.perf_counter() - t0
        stored = PQStorage.encode(x, np.ones(n, bool), book)
        approx = lut_scores(book, stored.codes, stored.list_ids, stored.norms, queries)
        rows.append([f"{size:,}", seconds, *errors_against(exact, approx, thresholds, np.random.default_rng(seed))])
    head = (f"PQ M={m} trained on a sample of embeddings: training time against the scores' error on {n:,} Gaussians "
            f"({len(queries)} text queries; errors vs exact cosine)")
    return head + "\n" + format_table(["train embeddings", "train s", "mean |Δcos|", "Spearman", "IoU@T"], rows)


def device_rows(fields: list[tuple[str, LanguageField]], n: int, q1: np.ndarray, queries: np.ndarray, device: str, repeats: int) -> list[list]:
    """Per field: numba CPU ms/query, torch ms/query on `device` (scores back in host memory), their ratio and the max |Δ| of the scores."""
    from drsplat.device import resolve_device

    dev = resolve_device(device)
    rows = []
    for name, fld in fields:
        numba_s = median_seconds(lambda f=fld: f.scores(q1), repeats)
        torch_s = median_seconds(lambda f=fld: f.scores(q1, device=dev), repeats)  # warm-up inside: copies the field once
        diff = float(np.abs(fld.scores(queries, device=dev) - fld.scores(queries)).max())
        rows.append([name, f"{n:,}", dev, 1e3 * numba_s, 1e3 * torch_s, numba_s / torch_s, diff])
        fld._on_device = None  # free the device copy
    return rows


def _norms16(f16: np.ndarray) -> np.ndarray:
    out = np.empty(f16.shape[0], np.float32)
    for start in range(0, f16.shape[0], GEN_CHUNK):
        out[start : start + GEN_CHUNK] = np.linalg.norm(f16[start : start + GEN_CHUNK].astype(np.float32), axis=1)
    return out


def text_query_table(book: Codebook, negatives: np.ndarray, name: str, n: int, seed: int, repeats: int) -> str:
    """8-bit tables against float32 ones for real CLIP text embeddings (the official codebook's
    canonical negatives, one component of 0.6-0.75) over n random unit features: one scale for
    every sub-table (faiss fast-scan's) and the wide sub-tables kept in float32 (the default,
    `quantize_luts`). Per query: ms (median of `repeats`), mean |Δcos| against the exact cosines,
    mean |Δ| against the float32 tables, IoU of the top 1 % against the float32 tables'."""
    from drsplat.lang import build_field

    rng = np.random.default_rng(seed)
    feats = unit_rows(rng.normal(size=(n, book.dim)).astype(np.float32))
    field = build_field(feats, np.ones(n, np.float32), codebook=book)
    store = field.storage
    blocked = blocked_codes(store.codes)
    queries = unit_rows(negatives)
    exact = feats @ queries.T
    runs = {"float32 tables": dict(lut_bits=32), "8-bit, one scale": dict(lut_bits=8, exact_span=np.inf), "8-bit, wide tables float32": dict(lut_bits=8)}
    scores, times = {}, {}
    for tables, kw in runs.items():  # not `name`: the queries' file, which the header names (round 101b F2)
        call = lambda kw=kw: lut_scores_blocked(book, blocked, n, store.list_ids, store.norms, queries, **kw)  # noqa: E731
        scores[tables], times[tables] = call(), median_seconds(call, repeats) / len(queries)
    top = np.quantile(scores["float32 tables"], 0.99, axis=0)
    rows = []
    for tables, got in scores.items():
        picked, ref = got >= top, scores["float32 tables"] >= top
        iou = float(np.mean([(picked[:, k] & ref[:, k]).sum() / max((picked[:, k] | ref[:, k]).sum(), 1) for k in range(len(queries))]))
        rows.append([tables, 1e3 * times[tables], float(np.abs(got - exact).mean()), float(np.abs(got - scores["float32 tables"]).mean()), iou])
    head = (f"8-bit tables on CLIP text queries ({name}, {len(queries)} rows) over {n:,} random unit features, "
            f"{book.kind} M={book.m}; per query, mean over the queries; IoU of each query's top 1 % against the float32 tables'")
    return head + "\n" + format_table(["tables", "ms/query", "mean |Δcos| vs exact", "mean |Δ| vs float32 tables", "top-1 % IoU vs float32"], rows)


def cached_codebook_path(args: argparse.Namespace, backend: str) -> Path:
    """Where the general PQ codebook of `backend` ('pq64') for these flags is kept between runs."""
    return args.cache_dir / f"v2_pq{int(backend[2:])}_d{args.dim}_l{args.labels}_n{args.train}_s{args.seed}.faiss"


def cached_codebook(path: Path, dim: int, m: int) -> Codebook | None:
    """The cached codebook at `path`, or None when there is none or it cannot serve (unreadable,
    truncated by a killed run, another shape): it is then trained again and replaced, so that one
    bad file in the cache is not fatal to every later run."""
    if not path.is_file():
        return None
    try:
        book = load_codebook(path)
    except DrsplatError as exc:
        log.warning("cached codebook %s; training it again, and replacing it", exc)  # the error names the file
        return None
    if (book.kind, book.dim, book.m) != ("pq", dim, m):
        log.warning("cached codebook %s is a %s of %d-D, M=%d, not PQ %d-D M=%d; training it again", path, book.kind, book.dim, book.m, dim, m)
        return None
    return book


def train_books(args: argparse.Namespace, model: EmbeddingModel, backends: list[str]) -> dict[str, Codebook]:
    """The general PQ codebooks of `backends` (from the cache, else trained and cached)."""
    books: dict[str, Codebook] = {}
    train = None
    for name in backends:
        if name.startswith("pq"):
            m = int(name[2:])
            cached = cached_codebook_path(args, name)
            books[name] = cached_codebook(cached, args.dim, m)
            if books[name] is not None:
                continue
            if train is None:
                train, _ = model.images(args.train, 10_000_019)  # a separate draw: a general codebook never sees the scene
            t0 = time.perf_counter()
            books[name] = train_codebook(train, m=m, seed=args.seed)
            print(f"trained PQ M={m} on {len(train):,} embeddings in {time.perf_counter() - t0:.1f} s")
            books[name].save(cached)
    return books


def official_path(args: argparse.Namespace) -> Path:
    return DEFAULT_OFFICIAL if args.official is None else args.official


def official_codebook(args: argparse.Namespace) -> Codebook | None:
    """The official codebook, read and checked before any work: None (with a line saying why) when the
    default one is absent or of another width than --dim; one error naming the file when a given
    --official is absent, unreadable or of another width."""
    path, given = official_path(args), args.official is not None
    if not path.is_file():
        if given:
            raise InputError(path, "does not exist (--official)" if not path.exists() else "is not a file (--official); give a faiss codebook file")
        print(f"official codebook skipped ({path} absent)")
        return None
    book = load_codebook(path)
    if book.dim != args.dim:
        if given:
            raise InputError(path, f"is a {book.dim}-D codebook but --dim is {args.dim} (--official); pass --dim {book.dim} or leave 'official' "
                                   "out of --backends")
        print(f"official codebook skipped ({path} is {book.dim}-D, --dim is {args.dim})")
        return None
    return book


def text_negatives(path: Path, dim: int) -> np.ndarray | None:
    """The CLIP text embeddings [K, dim] of `path` (float32), None when there is no such file.
    One error naming the file when it is not a readable 2-D numeric array of `dim` columns; rows no
    float32 embedding can stand for (drsplat.query.embedding_row_problems: non-finite, zero, beyond
    float32, a subnormal norm) are counted by kind and left out, with a warning (all of them: an error)."""
    from drsplat.utils import load_npy

    if not path.is_file():
        return None
    rows = load_npy(path, "array of text embeddings")
    if rows.ndim != 2 or rows.shape[1] != dim or rows.dtype.kind not in "fiu":
        raise InputError(path, f"is a {rows.dtype} array of shape {rows.shape}; expected [K, {dim}] numbers, one text embedding per row, "
                               "as wide as the codebook beside it")
    bad = embedding_row_problems(rows)
    unusable = bad.any()
    if unusable.all():
        raise InputError(path, f"none of its {len(rows)} rows is usable as a float32 embedding ({bad.counts()})")
    if unusable.any():
        log.warning("%s: %d of its %d rows are no float32 embedding (%s); left out of the 8-bit table", path, int(unusable.sum()), len(rows),
                    bad.counts())
    return rows[~unusable].astype(np.float32)


def check_flags(args: argparse.Namespace, backends: list[str]) -> None:
    """Flags that are wrong together, refused before any work (exit 2); flags no chosen backend reads,
    warned about (round 54: taken without a word); --cache-dir's default filled in."""
    pq = [b for b in backends if b.startswith("pq")]
    if args.cache_dir is not None and not pq:
        log.warning("--cache-dir holds trained PQ codebooks; --backends %s trains none, so it is not used", ",".join(backends))
    if args.official is not None and "official" not in backends:
        log.warning("--official is read by the 'official' backend, which --backends %s leaves out; it is not used", ",".join(backends))
    if args.cache_dir is None:
        args.cache_dir = Path(tempfile.gettempdir()) / "drsplat-bench-query"
    if args.queries > args.labels:
        raise UsageError(f"--queries {args.queries} is more than --labels {args.labels}: each query asks for a different class")
    uneven = [b for b in pq if args.dim % int(b[2:])]
    if uneven:
        raise UsageError(f"--dim {args.dim} cannot be split into the sub-vectors of {', '.join(uneven)} (--backends): "
                         f"M must divide the dimension (e.g. --dim 512)")
    if pq and args.train < PQ_KSUB:
        raise UsageError(f"--train {args.train}: training a PQ codebook ({', '.join(pq)}) needs at least {PQ_KSUB} embeddings")
    if args.train_sizes and min(args.train_sizes) < PQ_KSUB:
        raise UsageError(f"--train-sizes {min(args.train_sizes)}: training a PQ codebook needs at least {PQ_KSUB} embeddings")
    m = train_sample_m(backends)
    if args.train_sizes and args.dim % m:
        raise UsageError(f"--train-sizes trains PQ M={m}, which does not divide --dim {args.dim}")
    if "faiss" in backends and not any(b in backends for b in FAISS_SEARCHED):
        raise UsageError(f"--backends faiss times faiss's own search over the codes of {' or '.join(FAISS_SEARCHED)}: add one of them")


def check_outputs(args: argparse.Namespace, backends: list[str]) -> None:
    """The plot may not replace a file the run reads that its command line does not name: a cached
    codebook, or the text embeddings beside the official codebook (and every output must be writable)."""
    inputs: dict[str, Path | None] = {f"--cache-dir's {b} codebook": cached_codebook_path(args, b) for b in backends if b.startswith("pq")}
    if "official" in backends:
        inputs["--official"] = official_path(args)
        inputs[f"--official's {TEXT_NEGATIVES}"] = official_path(args).parent / TEXT_NEGATIVES
    guard_bench_outputs(inputs, {"--plot": args.plot})
    if args.plot.suffix.lower() != ".png":  # after the guard, which names an input it would hit; matplotlib writes PNG bytes whatever the name (round 54: --plot x.npy)
        raise UsageError(f"--plot {shown_path(args.plot)}: the plot is a PNG image; name it .png")
    from drsplat.utils import check_output_writable

    for path in inputs.values():  # a codebook to train is cached: an unwritable --cache-dir is found now, not after the training
        if path.suffix == ".faiss" and path.parent == args.cache_dir and not path.is_file():
            check_output_writable(path)


def plot(rows: list[Row], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    plotted = [r for r in rows if r.mean_abs_err is not None and "float32" not in r.backend]  # the rows measured against float32
    for n in sorted({r.n for r in plotted}):
        sub = [r for r in plotted if r.n == n]
        ax1.scatter([r.ms_query for r in sub], [max(r.mean_abs_err, 1e-5) for r in sub], label=f"N={n:,}")
        ax2.scatter([r.bytes_per_gaussian for r in sub], [r.iou for r in sub], label=f"N={n:,}")
        for r in sub:
            ax1.annotate(r.backend.replace(" (LUT)", ""), (r.ms_query, max(r.mean_abs_err, 1e-5)), fontsize=7)
            ax2.annotate(r.backend.replace(" (LUT)", ""), (r.bytes_per_gaussian, r.iou), fontsize=7)
    ax1.set(xlabel="ms per query", ylabel="mean |Δcos| vs float32", title="speed vs error")
    ax2.set(xlabel="bytes per Gaussian", ylabel="selection IoU vs float32", title="memory vs selection fidelity")
    if plotted:  # a log axis of no positive value cannot be drawn (--backends float32 alone: nothing is compared)
        ax1.set(xscale="log", yscale="log")
        ax2.set(xscale="log")
    for ax in (ax1, ax2):
        ax.grid(True, which="both", alpha=0.3)
        if plotted:
            ax.legend()
        else:
            ax.text(0.5, 0.5, "no backend measured against float32", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    from drsplat.utils import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    sizes, backends = args.sizes, args.backends
    check_flags(args, backends)
    check_outputs(args, backends)
    if args.device is not None:  # "--device cuda" without a GPU refused before the codebooks are trained
        from drsplat.device import resolve_device

        resolve_device(args.device)
    official = official_codebook(args) if "official" in backends else None
    negatives = text_negatives(official_path(args).parent / TEXT_NEGATIVES, official.dim) if official is not None else None
    model = EmbeddingModel.create(args.dim, args.labels, args.seed)
    books = train_books(args, model, backends)
    if official is not None:
        books["official"] = official
    rows: list[Row] = []
    args.device_rows = []
    for n in sizes:
        rows.extend(bench_size(args, n, model, books, backends))
    if not rows:
        raise DrsplatError(f"nothing was measured: --backends {','.join(backends)} left no backend to time "
                           f"(float32 is skipped above --max-float32 {args.max_float32:,}, the default official codebook when it is absent)")
    print(f"one cosine query over N Gaussians (D={args.dim}); K=16 batch column is per query; errors vs float32 cosine over {args.queries} text queries")
    print(
        format_table(
            ["backend", "N", "bytes/G", "ms/query", "ms/query (K=16)", "CPU ms/query", "mean |Δcos|", "Spearman", "IoU@T"],
            [[r.backend, f"{r.n:,}", int(r.bytes_per_gaussian), r.ms_query, r.ms_query_batch, r.cpu_ms_query, *unmeasured_as_dash(r.mean_abs_err, r.spearman, r.iou)]
             for r in rows],
        )
    )
    print(f"threshold T per query: midway between the mean exact cosine of the queried class and of the rest; faiss search rows time top-k only "
          f"(no all-N scores, so no error is measured: –); peak RSS {peak_rss_mb():.0f} MB")
    if args.device_rows:
        print("torch scorer against the numba kernels (one query; speed-up = numba ms / torch ms; max |Δ| over all queries)")
        print(format_table(["backend", "N", "device", "numba ms", "torch ms", "speed-up", "max |Δ|"], args.device_rows))
    if negatives is not None:
        print(text_query_table(official, negatives, TEXT_NEGATIVES, TEXT_TABLE_N, args.seed, args.repeats))
    if args.train_sizes:
        print(train_sample_table(model, train_sample_m(backends), args.train_sizes, sizes[0], args.queries, args.seed))
    print(machine_line())
    plot(rows, args.plot)
    print(f"plot: {shown_path(args.plot)}")
    return 0
