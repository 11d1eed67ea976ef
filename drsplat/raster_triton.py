"""Fused per-tile top-k compositing in Triton: the torch engine's compositing on a CUDA device.

Projection, tile binning and the depth sort stay in torch on the device (drsplat.raster_torch:
`project_gaussians_torch`, `bin_gaussians_torch`); one Triton program then composites a block of
BLOCK pixels of one 16x16 tile, walking the tile's depth-sorted list front to back and keeping
each pixel's top-k in registers (local memory when they spill). The rules are the numba kernel's
(drsplat._raster_kernels.composite_tiles), in float64 like it:

    d = mean2d - pixel centre, power = -½(a·dx² + c·dy²) - b·dx·dy
    α = min(0.99, o·exp(power)); the entry is skipped when power > 0 or α < 1/255
    the pixel stops (and the entry does not count) when T·(1 - α) < 1e-4
    otherwise w = T·α, T ← T·(1 - α)

Top-k without sorting inside the loop: each pixel holds k unsorted slots (weight, list position);
a newcomer replaces the slot with the smallest weight — the latest-arrived among equal smallest —
when its weight is strictly larger. So the slots end up holding exactly the first k entries of a
stable sort of all the pixel's contributions by descending weight (a later equal weight never
displaces an earlier one), which is what the numba kernel keeps; `_finish` then sorts the k
slots by (weight descending, list position ascending) and turns positions into Gaussian ids.

The kernel source is one function; under TRITON_INTERPRET=1 (read by triton when it is imported,
so the tests set it in a subprocess) Triton runs it with numpy on the CPU, which is how the tests
check the same source against numba (tests/test_raster_triton.py). Otherwise it is compiled for
CUDA and refused on any other device.
"""

from __future__ import annotations

import functools

import torch

from drsplat import _raster_kernels as kernels
from drsplat.defaults import DEFAULT_TOPK
from drsplat.errors import DrsplatError
from drsplat.raster import _check_args

try:  # triton comes with torch's CUDA builds; without it only the pure-torch compositing exists
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - depends on the torch build
    triton = None
    tl = None

CUDA_BLOCK = 64  # pixels per program on a GPU: 64 x k slots of (float64, int32) per program
INTERPRET_BLOCK = 256  # a whole tile per program in the interpreter (fewer, larger numpy steps)


def available() -> bool:
    """Whether Triton is importable (the fused kernel can run at all)."""
    return triton is not None


def _composite_topk_source(
    offsets_ptr, counts_ptr, list_ptr, means_ptr, conics_ptr, opacities_ptr,
    out_w_ptr, out_pos_ptr, out_trans_ptr, out_med_ptr,
    width, height, n_tiles_x, topk,
    TILE: tl.constexpr, BLOCK: tl.constexpr, KP: tl.constexpr,
    ALPHA_MIN: tl.constexpr, ALPHA_MAX: tl.constexpr, T_MIN: tl.constexpr, MEDIAN_T: tl.constexpr,
):  # fmt: skip
    """Program (tile, block): pixels block·BLOCK .. +BLOCK of the tile (row-major inside the tile).

    Writes out_w / out_pos [n_tiles, TILE², KP] (unsorted slots: weight float64, -1 where empty;
    list position int32), out_trans [n_tiles, TILE²] final T and out_med [n_tiles, TILE²] the list
    position of the median Gaussian (-1: none). Slots ≥ topk are padding (KP is a power of two).
    """
    tile = tl.program_id(0)
    local = tl.program_id(1) * BLOCK + tl.arange(0, BLOCK)
    px = (tile % n_tiles_x) * TILE + local % TILE
    py = (tile // n_tiles_x) * TILE + local // TILE
    cx = px.to(tl.float64) + 0.5
    cy = py.to(tl.float64) + 0.5
    done = (px >= width) | (py >= height)
    n_active = tl.sum((~done).to(tl.int32), axis=0)
    start = tl.load(offsets_ptr + tile)
    count = tl.load(counts_ptr + tile)
    slots = tl.arange(0, KP)
    real = (slots < topk)[None, :] & (local >= 0)[:, None]  # [BLOCK, KP]
    buf_w = tl.where(real, -1.0, 2.0).to(tl.float64)  # empty: -1; padding: 2 > any weight, never evicted
    buf_pos = (-1 - slots[None, :] + tl.zeros([BLOCK, KP], tl.int32)).to(tl.int32)  # empty slots: distinct negatives
    trans = tl.full([BLOCK], 1.0, tl.float64)
    med = tl.full([BLOCK], -1, tl.int32)
    j = tl.zeros([], dtype=tl.int32)  # a typed loop-carried counter (list positions are int32)
    while (j < count) & (n_active > 0):
        g = tl.load(list_ptr + start + j)
        u = tl.load(means_ptr + 2 * g)
        v = tl.load(means_ptr + 2 * g + 1)
        ca = tl.load(conics_ptr + 3 * g)
        cb = tl.load(conics_ptr + 3 * g + 1)
        cc = tl.load(conics_ptr + 3 * g + 2)
        o = tl.load(opacities_ptr + g).to(tl.float64)
        dx = u - cx
        dy = v - cy
        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
        alpha = tl.minimum(o * tl.exp(tl.minimum(power, 0.0)), ALPHA_MAX)
        hit = (~done) & (power <= 0.0) & (alpha >= ALPHA_MIN)
        test_t = trans * (1.0 - alpha)
        stop = hit & (test_t < T_MIN)
        ok = hit & (test_t >= T_MIN)
        w = alpha * trans
        med = tl.where(ok & (test_t <= MEDIAN_T) & (trans > MEDIAN_T), j, med)
        # evict the smallest slot, the latest-arrived among equal smallest, if w beats it strictly
        min_w = tl.min(buf_w, axis=1)
        tie = buf_w == min_w[:, None]
        last = tl.max(tl.where(tie, buf_pos, -KP - 1), axis=1)
        replace = tie & (buf_pos == last[:, None]) & (ok & (w > min_w))[:, None]
        buf_w = tl.where(replace, w[:, None], buf_w)
        buf_pos = tl.where(replace, j, buf_pos)
        trans = tl.where(ok, test_t, trans)
        done = done | stop
        n_active -= tl.sum(stop.to(tl.int32), axis=0)
        j += 1
    base = tile * TILE * TILE + local
    tl.store(out_trans_ptr + base, trans)
    tl.store(out_med_ptr + base, med)
    at = base[:, None] * KP + slots[None, :]
    tl.store(out_w_ptr + at, buf_w)
    tl.store(out_pos_ptr + at, buf_pos)


def interpreting() -> bool:
    """Whether Triton runs kernels in its CPU interpreter (TRITON_INTERPRET=1, read when triton is imported)."""
    return triton is not None and bool(triton.knobs.runtime.interpret)


@functools.cache
def _kernel():
    """The kernel: compiled for CUDA, or interpreted under TRITON_INTERPRET=1 (triton.jit decides)."""
    if triton is None:
        raise DrsplatError("the fused top-k kernel needs triton (it comes with torch's CUDA builds: pip install triton)")
    return triton.jit(_composite_topk_source)


def composite_topk_triton(projected, bins, topk: int = DEFAULT_TOPK, *, with_median: bool = False, block: int | None = None):
    """Top-k ids [H, W, k] int32 and weights [H, W, k] float32, alpha [H, W] float32 (and median ids [H, W] int32 or None).

    projected: a drsplat.raster_torch.TorchProjected on a CUDA device (or on the CPU under TRITON_INTERPRET=1: the tests).
    bins: the tile lists (offsets [T], counts [T], tile_list [L]) of drsplat.raster_torch.bin_gaussians_torch,
    passed in so that this module does not import its caller. The rest is one kernel launch plus
    `_finish`'s fixed-size sort and gathers (no host synchronisation).
    """

    _check_args(topk, (0.0, 0.0, 0.0))
    dev = projected.valid.device
    interpret = interpreting()
    if dev.type != "cuda" and not interpret:
        raise DrsplatError(f"the fused Triton top-k kernel runs on CUDA devices only, not on {dev.type!r}; use the torch compositing there")
    ts = projected.tile_size
    p_count = ts * ts
    block = block or (INTERPRET_BLOCK if interpret else CUDA_BLOCK)
    if p_count % block:
        raise ValueError(f"block {block} must divide the {p_count} pixels of a tile")
    n_tiles_x, n_tiles_y = projected.tile_grid
    n_tiles = n_tiles_x * n_tiles_y
    offsets, counts, tile_list = bins
    if tile_list.numel() == 0:  # nothing visible: a one-entry list keeps the gathers in range (every count is 0)
        tile_list = torch.zeros(1, dtype=torch.int64, device=dev)
    kp = max(1, 1 << max(0, topk - 1).bit_length())
    out_w = torch.empty((n_tiles, p_count, kp), dtype=torch.float64, device=dev)
    out_pos = torch.empty((n_tiles, p_count, kp), dtype=torch.int32, device=dev)
    out_trans = torch.empty((n_tiles, p_count), dtype=torch.float64, device=dev)
    out_med = torch.empty((n_tiles, p_count), dtype=torch.int32, device=dev)
    _kernel()[(n_tiles, p_count // block)](
        offsets, counts, tile_list, projected.means2d.contiguous(), projected.conics.contiguous(), projected.opacities.contiguous(),
        out_w, out_pos, out_trans, out_med, projected.width, projected.height, n_tiles_x, topk,
        TILE=ts, BLOCK=block, KP=kp, ALPHA_MIN=kernels.ALPHA_MIN, ALPHA_MAX=kernels.ALPHA_MAX, T_MIN=kernels.T_MIN, MEDIAN_T=kernels.MEDIAN_T,
    )  # fmt: skip
    return _finish(projected, out_w[..., :topk], out_pos[..., :topk], out_trans, out_med if with_median else None, offsets, tile_list)


def _finish(projected, slot_w, slot_pos, trans, med, offsets, tile_list):
    """Sort each pixel's slots [n_tiles, P, k] by (weight descending, list position ascending), map
    list positions to Gaussian ids and tiles to the image (ids -1 / weights 0 in empty slots)."""
    by_pos = torch.sort(slot_pos, dim=-1, stable=True).indices
    slot_w, slot_pos = torch.gather(slot_w, -1, by_pos), torch.gather(slot_pos, -1, by_pos)
    by_w = torch.sort(slot_w, dim=-1, descending=True, stable=True).indices
    slot_w, slot_pos = torch.gather(slot_w, -1, by_w), torch.gather(slot_pos, -1, by_w)
    filled = slot_w > 0
    first = offsets[:, None, None]
    ids = torch.where(filled, tile_list[torch.where(filled, first + slot_pos, 0)], -1).to(torch.int32)
    weights = torch.where(filled, slot_w, 0.0).float()
    median = None
    if med is not None:
        has = med >= 0
        median = torch.where(has, tile_list[torch.where(has, offsets[:, None] + med, 0)], -1).to(torch.int32)
    ts = projected.tile_size
    n_tiles_x, n_tiles_y = projected.tile_grid
    h, w = projected.height, projected.width

    def image(t):
        rest = t.shape[2:]
        t = t.reshape(n_tiles_y, n_tiles_x, ts, ts, *rest).transpose(1, 2).reshape(n_tiles_y * ts, n_tiles_x * ts, *rest)
        return t[:h, :w].contiguous()

    return image(ids), image(weights), image((1.0 - trans).float()), None if median is None else image(median)


def compile_ptx(capability: int = 90, block: int = CUDA_BLOCK, kp: int = 64, tile: int = 16) -> str:
    """The kernel compiled to PTX for CUDA compute capability `capability` (90: H100), without a GPU.

    Runs Triton's front end and NVIDIA backend stages (ttir -> ttgir -> llir -> ptx), not ptxas, so
    it checks that the source compiles in Triton's typed mode (the interpreter is looser) but says
    nothing about registers or speed. Uses Triton's backend API (checked with triton 3.8).
    """
    from triton._C.libtriton import ir  # Triton internals, only for this offline check
    from triton.backends.compiler import GPUTarget
    from triton.backends.nvidia.compiler import CUDABackend
    from triton.compiler import ASTSource

    fn = _kernel()
    pointers = {"offsets_ptr": "*i64", "counts_ptr": "*i64", "list_ptr": "*i64", "means_ptr": "*fp64", "conics_ptr": "*fp64",
                "opacities_ptr": "*fp32", "out_w_ptr": "*fp64", "out_pos_ptr": "*i32", "out_trans_ptr": "*fp64", "out_med_ptr": "*i32"}
    consts = {"TILE": tile, "BLOCK": block, "KP": kp, "ALPHA_MIN": kernels.ALPHA_MIN, "ALPHA_MAX": kernels.ALPHA_MAX, "T_MIN": kernels.T_MIN,
              "MEDIAN_T": kernels.MEDIAN_T}
    signature = {**pointers, **dict.fromkeys(("width", "height", "n_tiles_x", "topk"), "i32"), **dict.fromkeys(consts, "constexpr")}
    source = ASTSource(fn=fn, signature=signature, constexprs={(fn.arg_names.index(k),): v for k, v in consts.items()})
    target = GPUTarget("cuda", capability, 32)
    backend = CUDABackend(target)
    options = backend.parse_options({})
    context = ir.context()
    ir.load_dialects(context)
    backend.load_dialects(context)
    module = source.make_ir(target, options, backend.get_codegen_implementation(options), backend.get_module_map(), context)
    stages: dict = {}
    backend.add_stages(stages, options, source.language)
    metadata: dict = {}
    for name in ("ttir", "ttgir", "llir", "ptx"):
        module = stages[name](module, metadata)
    return module
