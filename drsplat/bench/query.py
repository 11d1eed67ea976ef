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

from drsplat.commands.common import positive_int
from drsplat.bench.common import count_arg, count_list, format_table, machine_line, median_seconds, peak_rss_mb
from drsplat.errors import InputError
from drsplat.lang import Codebook, ExactStorage, LanguageField, PQStorage, blocked_codes, load_codebook, lut_scores, lut_scores_blocked, train_codebook
from drsplat.query import unit_rows

log = logging.getLogger(__name__)

DEFAULT_OFFICIAL = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "drsplat" / "pq_index.faiss"
TEXT_NEGATIVES = "text_negative.npy"  # beside the official codebook: real CLIP text embeddings (`text_query_table`)
TEXT_TABLE_N = 100_000  # random unit features scored in `text_query_table`
BACKENDS = ("float32", "float16", "pq32", "pq64", "pq128", "pq256", "official", "faiss")
GEN_CHUNK = 250_000
SPEARMAN_SAMPLE = 200_000
BATCH = 16
BOUNDARY_FRACTION = 0.1
GAUSSIAN_NOISE = 0.2


def add_bench(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("query", help="ms/query and error against exact for every language-field backend")
    p.add_argument("--sizes", type=count_list, default="100k,1M", help="comma-separated Gaussian counts, e.g. 100k,1M,5M (default 100k,1M)")
    p.add_argument("--backends", default=",".join(BACKENDS), help=f"subset of {','.join(BACKENDS)}")
    p.add_argument("--dim", type=int, default=512)
    p.add_argument("--labels", type=int, default=40, help="object classes in the synthetic embeddings")
    p.add_argument("--queries", type=int, default=8, help="text queries whose errors are averaged")
    p.add_argument("--train", type=int, default=5_000, help="embeddings used to train the general PQ codebooks")
    p.add_argument("--cache-dir", type=Path, default=Path(tempfile.gettempdir()) / "drsplat-bench-query", help="trained codebooks are kept here for reuse")
    p.add_argument("--official", type=Path, default=DEFAULT_OFFICIAL, help="official Dr. Splat IVFPQ codebook (skipped when absent)")
    p.add_argument("--max-float32", type=count_arg, default="2M", help="skip the float32 baseline above this N (it needs 2 KB per Gaussian)")
    p.add_argument("--repeats", type=positive_int, default=5, help="timed repeats (median); fewer are used above 1M")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--plot", type=Path, default=Path("bench_query.png"), help="PNG of speed against error")
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
    mean_abs_err: float = 0.0
    spearman: float = 1.0
    iou: float = 1.0
    notes: list[str] = field(default_factory=list)


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


def bench_size(args: argparse.Namespace, n: int, model: EmbeddingModel, books: dict[str, Codebook], backends: list[str]) -> list[Row]:
    rng = np.random.default_rng(args.seed + 1)
    q_labels = rng.choice(model.label_dirs.shape[0], size=args.queries, replace=False)
    queries = model.texts(q_labels)
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
        if scores_all is not None:
            row.mean_abs_err, row.spearman, row.iou = errors_against(exact, scores_all(), thresholds, np.random.default_rng(args.seed))
        rows.append(row)
        log.info("N=%d %s: %.2f ms/query (%.2f batched), err %.4f", n, name, row.ms_query, row.ms_query_batch, row.mean_abs_err)

    if f32 is not None:
        measure("float32 matmul", 4 * args.dim, lambda: f32 @ q1.T, lambda: f32 @ qb.T, None)
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


def text_query_table(book: Codebook, negatives: Path, n: int, seed: int, repeats: int) -> str:
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
    queries = unit_rows(np.load(negatives).astype(np.float32))
    exact = feats @ queries.T
    runs = {"float32 tables": dict(lut_bits=32), "8-bit, one scale": dict(lut_bits=8, exact_span=np.inf), "8-bit, wide tables float32": dict(lut_bits=8)}
    scores, times = {}, {}
    for name, kw in runs.items():
        call = lambda kw=kw: lut_scores_blocked(book, blocked, n, store.list_ids, store.norms, queries, **kw)  # noqa: E731
        scores[name], times[name] = call(), median_seconds(call, repeats) / len(queries)
    top = np.quantile(scores["float32 tables"], 0.99, axis=0)
    rows = []
    for name, got in scores.items():
        picked, ref = got >= top, scores["float32 tables"] >= top
        iou = float(np.mean([(picked[:, k] & ref[:, k]).sum() / max((picked[:, k] | ref[:, k]).sum(), 1) for k in range(len(queries))]))
        rows.append([name, 1e3 * times[name], float(np.abs(got - exact).mean()), float(np.abs(got - scores["float32 tables"]).mean()), iou])
    head = (f"8-bit tables on CLIP text queries ({negatives.name}, {len(queries)} rows) over {n:,} random unit features, "
            f"{book.kind} M={book.m}; per query, mean over the queries; IoU of each query's top 1 % against the float32 tables'")
    return head + "\n" + format_table(["tables", "ms/query", "mean |Δcos| vs exact", "mean |Δ| vs float32 tables", "top-1 % IoU vs float32"], rows)


def train_books(args: argparse.Namespace, model: EmbeddingModel, backends: list[str]) -> dict[str, Codebook]:
    books: dict[str, Codebook] = {}
    train, _ = model.images(args.train, 10_000_019)  # a separate draw: a general codebook never sees the scene
    for name in backends:
        if name.startswith("pq"):
            m = int(name[2:])
            cached = args.cache_dir / f"v2_pq{m}_d{args.dim}_l{args.labels}_n{args.train}_s{args.seed}.faiss"
            if cached.is_file():
                books[name] = load_codebook(cached)
                continue
            t0 = time.perf_counter()
            books[name] = train_codebook(train, m=m, seed=args.seed)
            print(f"trained PQ M={m} on {len(train):,} embeddings in {time.perf_counter() - t0:.1f} s")
            books[name].save(cached)
    if "official" in backends:
        if args.official.is_file() and args.dim == 512:
            books["official"] = load_codebook(args.official)
        else:
            print(f"official codebook skipped ({args.official} absent or --dim is not 512)")
    return books


def plot(rows: list[Row], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    for n in sorted({r.n for r in rows}):
        sub = [r for r in rows if r.n == n and "faiss" not in r.backend and "float32" not in r.backend]
        ax1.scatter([r.ms_query for r in sub], [max(r.mean_abs_err, 1e-5) for r in sub], label=f"N={n:,}")
        ax2.scatter([r.bytes_per_gaussian for r in sub], [r.iou for r in sub], label=f"N={n:,}")
        for r in sub:
            ax1.annotate(r.backend.replace(" (LUT)", ""), (r.ms_query, max(r.mean_abs_err, 1e-5)), fontsize=7)
            ax2.annotate(r.backend.replace(" (LUT)", ""), (r.bytes_per_gaussian, r.iou), fontsize=7)
    ax1.set(xscale="log", yscale="log", xlabel="ms per query", ylabel="mean |Δcos| vs float32", title="speed vs error")
    ax2.set(xscale="log", xlabel="bytes per Gaussian", ylabel="selection IoU vs float32", title="memory vs selection fidelity")
    for ax in (ax1, ax2):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    from drsplat.utils import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    sizes = args.sizes
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    unknown = sorted(set(backends) - set(BACKENDS))
    if unknown:
        raise InputError(None, f"unknown backends {unknown}; choose from {', '.join(BACKENDS)}")
    if args.device is not None:  # "--device cuda" without a GPU refused before the codebooks are trained
        from drsplat.device import resolve_device

        resolve_device(args.device)
    model = EmbeddingModel.create(args.dim, args.labels, args.seed)
    books = train_books(args, model, backends)
    rows: list[Row] = []
    args.device_rows = []
    for n in sizes:
        rows.extend(bench_size(args, n, model, books, backends))
    print(f"one cosine query over N Gaussians (D={args.dim}); K=16 batch column is per query; errors vs float32 cosine over {args.queries} text queries")
    print(
        format_table(
            ["backend", "N", "bytes/G", "ms/query", "ms/query (K=16)", "CPU ms/query", "mean |Δcos|", "Spearman", "IoU@T"],
            [[r.backend, f"{r.n:,}", int(r.bytes_per_gaussian), r.ms_query, r.ms_query_batch, r.cpu_ms_query, r.mean_abs_err, r.spearman, r.iou] for r in rows],
        )
    )
    print(f"threshold T per query: midway between the mean exact cosine of the queried class and of the rest; faiss search rows time top-k only (no all-N scores); peak RSS {peak_rss_mb():.0f} MB")
    if args.device_rows:
        print("torch scorer against the numba kernels (one query; speed-up = numba ms / torch ms; max |Δ| over all queries)")
        print(format_table(["backend", "N", "device", "numba ms", "torch ms", "speed-up", "max |Δ|"], args.device_rows))
    negatives = args.official.parent / TEXT_NEGATIVES
    if "official" in books and negatives.is_file():
        print(text_query_table(books["official"], negatives, TEXT_TABLE_N, args.seed, args.repeats))
    print(machine_line())
    plot(rows, args.plot)
    print(f"plot: {args.plot}")
    return 0
