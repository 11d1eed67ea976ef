"""`drsplat info SCENE [--json]`: what a scene file (PLY, .splat, .spz) holds and what validation found."""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

import numpy as np

from drsplat.errors import shown_path
from drsplat.scene import GaussianScene, LoadReport
from drsplat.splat_formats import load_scene_report
from drsplat.utils import clipped, json_text


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
        f"{shown_path(s['path'])} ({s['layout']} layout)",
        f"  gaussians      {s['num_gaussians']:,} (rows in file {s['rows_in_file']:,})",
        f"  SH degree      {s['sh_degree']}",
        f"  bbox min       {box(lo)}",
        f"  bbox max       {box(hi)}",
        f"  bbox size      {box(size, '.4g')}",
        f"  opacity        {stats(s['opacity'])}",
        f"  largest scale  {stats(s['scale'])}",
        f"  extra props    {', '.join(s['extra_properties'][:8]) + (' …' if len(s['extra_properties']) > 8 else '') or '-'}",
        *format_field(s.get("language_field")),
        f"  findings       {'; '.join(s['findings']) or 'none'}",
    ]
    return "\n".join(lines)


def field_summary(scene: GaussianScene, path: Path) -> tuple[dict | None, list[str]]:
    """(the language field's summary, findings) of a registered PLY; (None, []) for a scene without
    one (no `drsplat.lang` comment and no `lang_meta` column: a file whose comments a tool dropped
    is still read by its column, as query reads it). A field that `query` would refuse is a finding
    naming the field and why, not an error: info describes the file as it is. What reading the field
    warns of (altered codes, norms too small to score, negative weights) is a finding too, in the
    loader's words. Counts: Gaussians with a feature, without one (unassigned), and with a
    non-finite one (they score 0)."""
    from drsplat.errors import InputError
    from drsplat.lang import read_field
    from drsplat.lang.plyformat import is_meta_column

    try:
        with LoggedFindings("drsplat.lang") as warned:
            field = read_field(scene, path, shared=True)  # neither is edited
    except InputError as exc:  # another file (its codebook) is named, as query names it (round 59a: "codebook file not found", whose?)
        where = f"{shown_path(exc.path)}: " if exc.path is not None and Path(exc.path) != Path(path) else ""
        return None, [f"language field: {where}{'' if exc.field is None else f'field {exc.field!r}: '}{exc.problem}"]
    if field is None:
        return None, []
    nonfinite = int(np.count_nonzero(~np.isfinite(field.norms)))
    assigned = int(np.count_nonzero(field.assigned()))
    # the field's own bytes and the `lang_meta` columns that carry its description (round 49: 1028 of 1030 were said), ushort
    # or, for metadata over 255 bytes, uint (round 56e: counted as 2 bytes each)
    meta_bytes = sum(np.asarray(column).dtype.itemsize for name, column in scene.extra.items() if is_meta_column(name))
    summary = {"kind": field.kind, "dim": field.dim, "clip_model": field.clip_model, "clip_weights": field.clip_weights, "bytes_per_gaussian": field.bytes_per_gaussian() + meta_bytes,
               "codebook": None if field.codebook_path is None else str(field.codebook_path), "assigned": assigned,
               "unassigned": field.num_gaussians - assigned, "nonfinite": nonfinite}
    findings = [f"language field: {text}" for text in warned.texts]
    if not assigned:
        findings.append("no Gaussian has a language feature: query and segment refuse this file")
    return summary, findings


class LoggedFindings(logging.Handler):
    """Collects, as text without the file's name, what a logger (and its children) warns of inside
    the `with` block, instead of printing it: `info` lists it with the findings (it set the logger to
    ERROR before, and altered PQ codes, which query warns of, were in neither: a probe, round 29a)."""

    def __init__(self, name: str):
        super().__init__(logging.WARNING)
        self.logger = logging.getLogger(name)
        self.texts: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        prefix = f"{record.args[0]}: " if isinstance(record.args, tuple) and record.args else ""
        self.texts.append(text[len(prefix):] if prefix and text.startswith(prefix) else text)

    def __enter__(self) -> "LoggedFindings":
        self.saved = (self.logger.propagate, self.logger.level)
        self.logger.addHandler(self)
        self.logger.propagate = False
        self.logger.setLevel(logging.WARNING)
        return self

    def __exit__(self, *exc) -> None:
        self.logger.removeHandler(self)
        self.logger.propagate, level = self.saved[0], self.saved[1]
        self.logger.setLevel(level)


SHOWN_MODEL_CHARS = 120  # the CLIP model id as `info` prints it, at most


def format_field(f: dict | None) -> list[str]:
    if f is None:
        return []
    book = f" (codebook {f['codebook']})" if f["codebook"] else ""
    model = clipped(f["clip_model"], SHOWN_MODEL_CHARS)  # a hand-made header's id could be megabytes
    if f.get("clip_weights"):  # the weights file's size:sha1, checked against a text encoder's
        model += f" (weights {f['clip_weights'].split(':')[0]} bytes, sha1 {f['clip_weights'].split(':')[1][:12]})"
    return [f"  language       {f['kind']}{book}, {f['dim']}-D, {model}, {f['bytes_per_gaussian']} bytes a Gaussian",
            f"  features       {f['assigned']:,} assigned, {f['unassigned']:,} without one"]


def run(args: argparse.Namespace) -> int:
    scene, report = load_scene_report(args.scene)
    summary = scene_summary(scene, report)
    field, findings = field_summary(scene, args.scene)
    summary["language_field"] = field
    summary["findings"] = summary["findings"] + findings
    print(json_text(summary) if args.json else format_summary(summary))
    return 0
