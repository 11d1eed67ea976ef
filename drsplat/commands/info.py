"""`drsplat info SCENE [--json]`: what a scene file (PLY, .splat, .spz) holds and what validation found."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from drsplat.scene import GaussianScene, LoadReport
from drsplat.splat_formats import load_scene_report
from drsplat.utils import json_text


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("info", help="summarise a 3DGS scene file: count, SH degree, bounds, statistics, findings",
                              description="Summarise a 3DGS scene file: PLY (INRIA layout or SuperSplat compressed), .splat or .spz.")
    p.add_argument("scene", type=Path, help="3DGS scene: PLY (INRIA or compressed), .splat or .spz")
    p.add_argument("--json", action="store_true", help="print machine-readable JSON instead of text")
    p.set_defaults(func=run)


def _stats(values: np.ndarray) -> dict[str, float | None]:
    if values.size == 0:  # no Gaussians: no statistics (null in JSON, "-" in text), not zeros that look measured
        return {"min": None, "median": None, "max": None}
    return {"min": float(values.min()), "median": float(np.median(values)), "max": float(values.max())}


def scene_summary(scene: GaussianScene, report: LoadReport) -> dict:
    """JSON-serialisable summary of a loaded scene and its load report."""
    lo, hi = scene.bounding_box()
    largest = scene.largest_scales()  # a log scale past float64's exp is infinite, and said so in the findings
    summary = {
        "path": str(report.path),
        "layout": report.layout,
        "num_gaussians": scene.num_gaussians,
        "rows_in_file": report.rows_in_file,
        "sh_degree": scene.sh_degree,
        "has_normals": report.has_normals,
        "bbox_min": [float(v) for v in lo] if scene.num_gaussians else None,
        "bbox_max": [float(v) for v in hi] if scene.num_gaussians else None,
        "opacity": _stats(scene.opacities()),
        # float64: a log scale above 88.7 overflows float32 (reported as a finding, without numpy's warning)
        "scale": _stats(largest),
        "nonfinite_rows": report.nonfinite_rows,
        "dropped_rows": report.dropped_nan_rows + report.dropped_inf_rows,
        "clamped_opacity": report.clamped_opacity,
        "zero_quaternions": report.zero_quaternions,
        "extra_properties": list(scene.extra),
        "comments": scene.comments,
        "findings": report.findings(),
    }
    return summary


def _number(value: float | None, spec: str) -> str:
    """A statistic as text: '-' where the scene has none (no Gaussians)."""
    return "-" if value is None else format(value + 0.0, spec)  # + 0.0: a -0 (a flipped axis of a .spz) prints as 0


def _box_digits(lo: list[float] | None, hi: list[float] | None) -> int:
    """Significant digits that show the box's corners 4 digits into its size: a scene far from the
    origin (georeferenced, 1e6 units away) spans a few units that '.4g' would print as one value."""
    if lo is None:
        return 4
    finite = [(a, b) for a, b in zip(lo, hi) if math.isfinite(a) and math.isfinite(b)]
    far = max((max(abs(a), abs(b)) for a, b in finite), default=0.0)
    size = max((b - a for a, b in finite), default=0.0)
    if far == 0.0 or size <= 0.0:
        return 4
    return int(min(12, 4 + max(0, math.ceil(math.log10(far / size)))))


def format_summary(s: dict) -> str:
    def stats(d: dict) -> str:
        return "  ".join(f"{key} {_number(d[key], '.3g')}" for key in ("min", "median", "max"))

    lo, hi = s["bbox_min"], s["bbox_max"]
    size = None if lo is None else [b - a for a, b in zip(lo, hi)]
    digits = _box_digits(lo, hi)

    def box(values: list[float] | None, spec: str = f".{digits}g") -> str:
        return "-" if values is None else " ".join(_number(v, spec) for v in values)

    lines = [
        f"{s['path']} ({s['layout']} layout)",
        f"  gaussians      {s['num_gaussians']:,} (rows in file {s['rows_in_file']:,})",
        f"  SH degree      {s['sh_degree']}",
        f"  bbox min       {box(lo)}",
        f"  bbox max       {box(hi)}",
        f"  bbox size      {box(size, '.4g')}",
        f"  opacity        {stats(s['opacity'])}",
        f"  largest scale  {stats(s['scale'])}",
        f"  extra props    {', '.join(s['extra_properties'][:8]) + (' …' if len(s['extra_properties']) > 8 else '') or '-'}",
        f"  findings       {'; '.join(s['findings']) or 'none'}",
    ]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    scene, report = load_scene_report(args.scene)
    summary = scene_summary(scene, report)
    print(json_text(summary) if args.json else format_summary(summary))
    return 0
