"""What several subcommands share: argument validators (bad values exit 2) and CLI helpers.

Validators are argparse `type=` callables: a value out of range raises ArgumentTypeError, so
argparse prints the usage and the flag's name and exits 2 before any work starts.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import re
import sys
from collections import Counter
from collections.abc import Callable, Sequence
from typing import TextIO
from pathlib import Path

import numpy as np

from drsplat.cameras import RESOLUTION_DIVISORS
from drsplat.defaults import DEFAULT_PRINCIPAL_POINT, MAX_TOPK, PRINCIPAL_POINTS
from drsplat.features.masks.base import LEVELS
from drsplat.eval.datasets import POINT_CLOUD_SUFFIXES
from drsplat.errors import DrsplatError, InputError, UsageError, hidden_character, one_line, shown_path
from drsplat.memory import parse_size
from drsplat.splat_formats import SCENE_SUFFIXES
from drsplat.lang import REGISTERED_IS_PLY, LanguageField, read_field
from drsplat.lang.plyformat import strip_field
from drsplat.scene import GaussianScene, counted
from drsplat.splat_formats import scene_format
from drsplat.utils import name_problem, names_a_folder

log = logging.getLogger(__name__)

DEFAULT_RELEVANCY_THRESHOLD = 0.5
MAX_IMAGE_WIDTH = 16384  # --resolution as a width, viewer windows (larger than any GPU texture)
MAX_COUNT = 10**9  # generic upper bound for "how many" flags (--top, --max-train...)


# ---------------------------------------------------------------------------------------------
# Validators (argparse type=)


def _number(text: str, kind: type) -> float | int:
    try:
        value = kind(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def int_range(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """argparse type: an integer in [lo, hi] (either bound may be None)."""

    def parse(text: str) -> int:
        value = int(_number(text, int))
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"{value} is out of range: expected {_describe(lo, hi)}")
        return value

    parse.__name__ = "integer"
    return parse


# what argparse reads as a negative number rather than an option: any float literal with a leading
# minus, as float() reads it (argparse's own pattern takes -1 and -.5 but not -1e-3 or -inf), digits
# grouped by underscores included (-1_000, as 1_000 is read), and a range that starts with one
# (`--taus -0.5:1:0.1`, START:STOP:STEP; round 89c F5: "expected one argument"), whose type judges the rest
_DIGITS = r"\d(?:_?\d)*"
NEGATIVE_NUMBER = re.compile(rf"^-(?:(?:{_DIGITS}\.?(?:{_DIGITS})?|\.{_DIGITS})(?:[eE][-+]?{_DIGITS})?|inf(?:inity)?|nan)(?::[^:]*)*$", re.IGNORECASE)


class ArgumentParser(argparse.ArgumentParser):
    """argparse's parser that takes `--threshold -1e-3` and `--threshold -inf` as a value (which the
    option's type then judges) instead of "expected one argument"; its subcommands' parsers are of
    this class too (add_subparsers makes parsers of the parent's class)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = NEGATIVE_NUMBER
        self.register("type", Path, path_value)  # every `type=Path` argument is read by path_value

    def error(self, message: str):
        """argparse's usage error, with the characters a terminal would not show as themselves escaped,
        newlines included: a type's error quotes the value as given (round 54: `--topks ESC[2J` cleared
        the screen; a newline forged a line)."""
        super().error(one_line(message))


def refuse_blank(text: str, wanted: str) -> str:
    """`text`, or argparse's error when it is empty or only blank space ("give `wanted`")."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"{text!r} is {'empty' if not text else 'only blank space'}: give {wanted}")
    return text


def path_value(text: str) -> Path:
    """argparse type of a path (what `type=Path` means on drsplat's parsers): an empty or blank value is
    refused, since Path("") is Path(".") (round 54: `query ''` read the current folder as the PLY and
    ended in a traceback)."""
    return Path(refuse_blank(text, "a path"))


path_value.__name__ = "path"


def text_value(text: str) -> str:
    """argparse type of a name or address that has no empty meaning (a codebook, a Ray address, a CLIP
    model or tag): an empty or blank value is refused, not read as unset or as the current folder
    (round 54: `register --codebook ''` read "." as the codebook, `--ray ''` and `--pretrained ''` the defaults)."""
    return refuse_blank(text, "a value, or leave the flag out")


text_value.__name__ = "value"


def ray_address(text: str) -> str:
    """argparse type of --ray's ADDRESS (`cluster.address_problem`): a malformed one is a usage error at once, not after
    the scene is loaded and the fit stage has run (round 60b)."""
    from drsplat.cluster import address_problem

    problem = address_problem(text_value(text))
    if problem is not None:
        raise argparse.ArgumentTypeError(f"{text!r} {problem}")
    return text


ray_address.__name__ = "address"


class Once(argparse.Action):
    """A one-value option given a second time is a usage error (argparse keeps the last without a word: `query
    --embedding a.npy --embedding b.npy` queried b alone beside `--text`, which repeats to add: round 78b F3)."""

    def __call__(self, parser, namespace, values, option_string=None):
        earlier = getattr(namespace, self.dest, self.default)
        if earlier is not self.default:
            parser.error(f"{option_string} is given twice ({earlier}, then {values}); it takes one {self.metavar or 'value'}")
        setattr(namespace, self.dest, values)


def refuse_repeats(flag: str, values: Sequence, shown: Callable[[object], str] = repr) -> None:
    """UsageError naming the entries of the list flag `flag` given more than once: a slip (a table row or
    an ablation's mode twice), refused as --classes refuses its names."""
    repeated = sorted(value for value, count in Counter(values).items() if count > 1)
    if repeated:
        raise UsageError(f"{flag}: {', '.join(map(shown, repeated))} given twice")


def shown_number(value: float) -> str:
    """`value` as short as %g writes it when that is the same number, else in full (round 91d F5: %g wrote 1.0000001
    as "1 is outside [-1, 1]", a value that is inside)."""
    short = f"{value:g}"
    return short if float(short) == value else repr(value)


def float_range(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, hi_open: bool = False) -> Callable[[str], float]:
    """argparse type: a finite float in [lo, hi] ((lo, hi] with lo_open, [lo, hi) with hi_open)."""

    def parse(text: str) -> float:
        value = float(_number(text, float))
        low_bad = lo is not None and (value <= lo if lo_open else value < lo)
        high_bad = hi is not None and (value >= hi if hi_open else value > hi)
        if low_bad or high_bad:
            raise argparse.ArgumentTypeError(f"{shown_number(value)} is out of range: expected {_describe(lo, hi, lo_open, hi_open)}")
        return value

    parse.__name__ = "number"
    return parse


def _describe(lo, hi, lo_open: bool = False, hi_open: bool = False) -> str:
    below = "<" if hi_open else "<="
    if lo is not None and hi is not None:
        return f"{lo} {'<' if lo_open else '<='} value {below} {hi}"
    if lo is not None:
        return f"value {'>' if lo_open else '>='} {lo}"
    return f"value {below} {hi}"


positive_int = int_range(1, MAX_COUNT)


def size_value(text: str) -> int:
    """argparse type: a size in bytes ('8GB', '512MB', '16GiB')."""
    try:
        return parse_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


size_value.__name__ = "size"
nonneg_int = int_range(0, MAX_COUNT)
seed_int = int_range(0, 2**32 - 1)  # numpy and faiss seeds are unsigned 32-bit
topk_int = int_range(1, MAX_TOPK)
unit_fraction = float_range(0.0, 1.0)
nonneg_float = float_range(0.0, None)
positive_float = float_range(0.0, None, lo_open=True)


def mask_level(text: str) -> int:
    """argparse type of --level: a level index (0 or more) or LangSplat's name of it, "default", "s",
    "m" or "l" (`features.masks.base.LEVELS`, in file order), which the help cites."""
    name = text.strip().lower()
    if name in LEVELS:
        return LEVELS.index(name)
    try:
        return nonneg_int(text)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"{exc}; or one of LangSplat's level names {', '.join(LEVELS)}") from None


def output_file(text: str) -> Path:
    """argparse type of a file to write: a path ending in a separator names a folder and is refused
    (Path("newdir/") is Path("newdir"): the file would take the folder's name)."""
    if names_a_folder(text):
        raise argparse.ArgumentTypeError(f"{text!r} ends with a path separator, so it names a folder; give a file name")
    if text == "-":  # round 57c: wrote a file named '-' where a user meant standard output
        raise argparse.ArgumentTypeError("'-' is not read as standard output here: give /dev/stdout (or ./- for a file of that name)")
    return path_value(text)


# what drsplat and 3DGS tools read by name: scenes and trainer checkpoints, point clouds (round 91a F2: `--json x.pth`
# replaced a checkpoint), codebooks, arrays, images, COLMAP's binary models
KNOWN_FILE_SUFFIXES = (*SCENE_SUFFIXES, *POINT_CLOUD_SUFFIXES, ".faiss", ".json", ".npy", ".npz", ".png", ".jpg", ".jpeg", ".bin")


def another_kind_name(path: Path | str | None, own_suffix: str) -> str | None:
    """Why an output of kind `own_suffix` ('.npy', '.json') named `path` would be read as another kind of file, or
    None: its name ("a .ply name") or, for a link, the file it writes to ("a link to a .ply file", round 91a F1:
    `--json link.json` replaced the scene the link named) has a suffix drsplat or a 3DGS tool reads by name
    (KNOWN_FILE_SUFFIXES, in any case): a scene overwritten by JSON, a .npy read as a PLY."""
    if path is None:
        return None
    suffix, target = Path(path).suffix, Path(os.path.realpath(path)).suffix
    if suffix.lower() in KNOWN_FILE_SUFFIXES and suffix.lower() != own_suffix:
        return f"a {suffix} name"
    if target.lower() in KNOWN_FILE_SUFFIXES and target.lower() != own_suffix:
        return f"a link to a {target} file"
    return None


def check_npy_name(flag: str, path: Path | None) -> None:
    """UsageError for a .npy array output named as another file type drsplat writes or reads
    (`scores.ply`), since an array under it would be read as that type (round 54: `query --scores
    o.ply` wrote .npy bytes as o.ply; `--out o.npy` was refused). Called after the input guard, which
    says first when the name is one of the command's inputs."""
    other = another_kind_name(path, ".npy")
    if other is not None:
        raise UsageError(f"{flag} {shown_path(path)}: this output is a .npy array; {other} would hold one (name it .npy)")


def json_output_file(text: str) -> Path:
    """argparse type of a JSON output (`output_file`), refused when named as another kind of file drsplat or a 3DGS
    tool reads (`another_kind_name`; round 89c F4: `eval iou --json scene.ply` replaced a registered PLY with
    JSON, exit 0, while a .npy output of that name was refused)."""
    path = output_file(text)
    other = another_kind_name(path, ".json")
    if other is not None:
        raise argparse.ArgumentTypeError(f"{text!r}: this output is JSON text; {other} would hold it (name it .json)")
    return path


def threshold_value(text: str) -> str:
    """argparse type for --threshold: 'auto' or a finite number in [-1, 1] (cosine and relevancy range).

    Returned as text ('auto' or the number) so `resolve_threshold` keeps one code path.
    """
    if text == "auto":
        return text
    value = float(_number(text, float))
    if not -1.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{shown_number(value)} is outside [-1, 1], the range of cosine and relevancy scores (or use 'auto')")
    return repr(value)


def resolution_value(text: str) -> float:
    """argparse type for 3DGS-style -r: -1, 1, 2, 4, 8 or a target width in pixels (finite, <= MAX_IMAGE_WIDTH)."""
    value = float(_number(text, float))
    if value == -1 or value in RESOLUTION_DIVISORS:
        return value
    if not 1 <= value <= MAX_IMAGE_WIDTH:  # a width: 0.5 or 1e-300 would make images of no pixels
        raise argparse.ArgumentTypeError(f"{shown_number(value)}: expected -1 (full size, capped at 1600 px), 1, 2, 4, 8 or a width in 1..{MAX_IMAGE_WIDTH} pixels")
    if value != int(value):  # 2.5 read as a 2.5-pixel width (round 61c): surely meant as a divisor
        raise argparse.ArgumentTypeError(f"{shown_number(value)}: a width is a whole number of pixels, and the divisors are 1, 2, 4 and 8 "
                                         "(3DGS's -r); give one of them or a width such as 640")
    return value


def near_plane_value(text: str) -> float:
    """argparse type for --near-plane: a positive, finite camera depth in scene units, or 'inria'
    (defaults.INRIA_NEAR, 0.2: the plane of the rasterizer that trained most 3DGS scenes)."""
    return _near_plane(text, ("'inria'",))


def _near_plane(text: str, words: tuple[str, ...]) -> float:
    """`near_plane_value`'s depth; the refusal names what else the flag takes (`words`) before what it got."""
    from drsplat.defaults import INRIA_NEAR

    if text.strip().lower() == "inria":
        return INRIA_NEAR
    try:
        value = float(text)
    except (TypeError, ValueError):
        value = math.nan
    if not (math.isfinite(value) and value > 0):  # round 65a F4: "expected a number, got 'foo', or 'inria'" read as if all were given
        raise argparse.ArgumentTypeError(f"expected a positive camera depth in scene units (such as 0.01 or 0.2) or "
                                         f"{' or '.join(words)}, got {text!r}")
    return value


def near_plane_choice(text: str) -> float | str:
    """argparse type for a --near-plane that may be decided: 'auto' (drsplat.frames.near_plane_as_trained), else `near_plane_value`."""
    if text.strip().lower() == "auto":
        return "auto"
    return _near_plane(text, ("'inria'", "'auto'"))


def add_near_plane_argument(parser: argparse.ArgumentParser, what: str, default: str | None = None, auto: bool = False) -> None:
    """--near-plane DEPTH|inria (`near_plane_value`) for a command that renders; what: of what it is the plane;
    default: the default's words (None: NEAR, which the argument then holds; else the argument is None when not given).
    auto: 'auto' is a choice too, and the default (`near_plane_choice`; drsplat.frames.near_plane_as_trained decides)."""
    from drsplat.defaults import DEFAULT_NEAR_PLANE, INRIA_NEAR, NEAR

    if auto:
        parser.add_argument("--near-plane", type=near_plane_choice, default=DEFAULT_NEAR_PLANE, metavar="DEPTH",
                            help=f"camera depth in scene units below which a Gaussian is not drawn, the plane {what}; 'auto' "
                                 f"(the default): {NEAR:g} (gsplat's) unless Gaussians lie between {NEAR:g} and {INRIA_NEAR:g} in "
                                 f"front of a camera and the training images show them undrawn, then {INRIA_NEAR:g} (docs/raster.md)")
        return
    parser.add_argument("--near-plane", type=near_plane_value, default=NEAR if default is None else None, metavar="DEPTH",
                        help=f"camera depth in scene units below which a Gaussian is not drawn, the plane {what} (default: "
                             f"{default or f'{NEAR:g}, gsplat' + chr(39) + 's'}; docs/raster.md)")


# ---------------------------------------------------------------------------------------------
# Shared arguments and loaders of the query-like commands (query, segment, eval)


def add_clip_arguments(parser: argparse.ArgumentParser, scoring: bool = False) -> None:
    """CLIP encoder flags; scoring: --device also places the scoring, with --engine (drsplat.device)."""
    group = parser.add_argument_group("CLIP text encoder (text queries)")
    group.add_argument("--clip-checkpoint", type=Path, metavar="PATH", help="local OpenCLIP weights file")
    group.add_argument("--clip-model", type=text_value, default=None, help="OpenCLIP architecture (default: the one recorded in the PLY)")
    group.add_argument("--pretrained", type=text_value, default=None, help="pretrained tag (default: the one recorded in the PLY)")
    group.add_argument("--clip-config", type=Path, default=None, metavar="JSON",
                       help="open_clip model config file, for an architecture open_clip does not ship (the one `features --clip-config` read)")
    if scoring:
        from drsplat.device import add_device_arguments

        add_device_arguments(parser.add_argument_group("compute (text encoder and scoring)"))
    else:
        group.add_argument("--device", default="cpu", choices=("auto", "cpu", "cuda"))


def scoring_device(args: argparse.Namespace) -> str | None:
    """Where to score (LanguageField.scores' device): None for the numba CPU kernels, else a torch device."""
    from drsplat.device import resolve_compute

    device, engine = resolve_compute(args)
    return device if engine == "torch" else None


def lut_bits_for(args: argparse.Namespace, field: LanguageField, device: str | None) -> int:
    """The tables to score with: --lut-bits, except that 8-bit tables (a CPU kernel for PQ codes of
    at most Q8_MAX_M sub-vectors) fall back to the exact float32 ones, with a warning saying why,
    on the torch engine, on an exact field (which has no tables) and on a codebook of more sub-vectors."""
    from drsplat.lang.lut import Q8_MAX_M

    bits = getattr(args, "lut_bits", 32)
    if bits == 32:
        return 32
    codebook = field.codebook
    why = ("the torch engine scores with float32 tables (8-bit tables are a CPU kernel)" if device is not None else
           "this field stores exact features, which are scored without tables" if codebook is None else
           f"8-bit tables need at most {Q8_MAX_M} sub-vectors and this field's codebook has {codebook.m}" if codebook.m > Q8_MAX_M else None)
    if why is None:
        return bits
    log.warning("--lut-bits 8: %s; scoring with exact float32 tables", why)
    return 32


def add_lut_bits_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--lut-bits", type=int, choices=(32, 8), default=32,
                        help="PQ look-up tables: 32 exact float32 (default), 8 faster 8-bit tables (see `drsplat bench query` for the error)")


def add_principal_point_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--principal-point", choices=PRINCIPAL_POINTS, default=DEFAULT_PRINCIPAL_POINT,
                        help="the cameras' principal points: 'file' (cx, cy as the camera file gives them, as gsplat and nerfstudio "
                        "train), 'centre' (every principal point at its image centre, as INRIA's gaussian-splatting trains, which "
                        "reads a COLMAP camera as two fields of view), or 'auto': the one under which the scene re-renders its "
                        "training images better, decided only when some principal point lies off-centre (default: %(default)s)")


def load_registered(path: Path, geometry: bool = True) -> tuple[GaussianScene | None, LanguageField]:
    """Load a registered PLY and its language field (InputError if it has none or rows were dropped,
    or if the file is a .splat / .spz scene, which cannot hold a field). geometry=False: the scene is
    None and its Gaussians are never held (`scene.load_ply_extras`), for a command that writes no
    scene: a query of 20M Gaussians of SH degree 3 holds 4.7 GB less."""
    from drsplat.scene import load_ply_extras, load_ply_report

    kind = scene_format(Path(path)) if Path(path).is_file() else "ply"
    if kind != "ply":
        what = "a trainer checkpoint" if kind == "checkpoint" else f"a .{kind} scene"
        raise InputError(path, f"is {what}, not a registered scene: {REGISTERED_IS_PLY}; run drsplat register on it first")
    # refuses a file with no usable row
    scene, report = load_ply_report(path, purpose="query or segment") if geometry else load_ply_extras(path, purpose="query or segment")
    dropped = report.dropped_nan_rows + report.dropped_inf_rows
    if dropped:
        raise InputError(path, f"{counted(dropped, 'row has', 'rows have')} non-finite values and would be dropped, so scores could not follow the file order")
    field = read_field(scene, path, shared=True)  # the scene's language columns are dropped below
    if field is None:
        raise InputError(path, "has no language field (no 'drsplat.lang' header comment); run drsplat register first")
    # the field holds the language columns now: the scene's copies of them (130 B a Gaussian for PQ, 1 kB exact) go, as
    # every output strips them before writing the field's own (round 61b: three copies of the codes held per query)
    return (strip_field(scene) if geometry else None), field


def is_text_ply(path: Path) -> bool:
    """Whether `path` is a regular file and an ASCII PLY (its header says `format ascii`); False for anything else, a file
    that cannot be read included (its load then says why)."""
    from drsplat.scene import read_ply_header

    try:
        return Path(path).is_file() and read_ply_header(Path(path)).format == "ascii"  # a FIFO is not opened twice
    except (OSError, InputError):
        return False


def load_registered_rows(path: Path, keep: np.ndarray, stamp=None) -> GaussianScene:
    """The Gaussians where keep [N] is True of a registered PLY that `load_registered(geometry=False)`
    read, without its language columns and without holding the other Gaussians (`scene.load_ply_rows`):
    a selection written by `query --out`. stamp: the file's `scene.FileStamp` taken before that read (an
    error when it changed since)."""
    from drsplat.scene import load_ply_rows

    return strip_field(load_ply_rows(path, keep, stamp))


def oracle_flag(flag: str) -> str:
    """What an oracle scene's error tells to pass instead of text: the command's embedding flag."""
    return f"{flag} (rows of the synthetic dataset's text_embeddings.npy)"


def load_encoder(args: argparse.Namespace, field: LanguageField, instead: str = oracle_flag("--embedding")):
    """The CLIP text encoder for a field: architecture and tag default to the field's model id.
    instead: what the error for an oracle field (no text encoder embeds into its space) says to pass."""
    from drsplat.features.clip import ClipEncoder, model_for_config, unsupported_model_name, use_clip_config
    from drsplat.features.modelid import DEFAULT_MODEL, is_oracle, named_model

    if is_oracle(field.clip_model):
        raise DrsplatError(f"this scene's features are synthetic oracle embeddings, not CLIP: pass {instead} instead of text")
    named = named_model(field.clip_model)  # the field's own model (round 78b F2: an id without "/" asked for ViT-B-16's weights)
    model, pretrained = named or (DEFAULT_MODEL, None)
    problem = unsupported_model_name(model)
    if problem is not None:  # no --pretrained or --clip-model can help (round 83a F3: it was asked for; round 84b F2)
        raise DrsplatError(f"this scene's CLIP model id {field.clip_model!r} {problem}: pass query embeddings made with that model "
                           "instead of text")
    if named is not None and pretrained is None and not args.pretrained and args.clip_checkpoint is None:
        raise DrsplatError(f"this scene's CLIP model id {field.clip_model!r} names no weights tag: pass --pretrained TAG "
                           "or --clip-checkpoint FILE for the weights its features were made with")
    config = getattr(args, "clip_config", None)
    model = model_for_config(args.clip_model, config, default=model)
    use_clip_config(config)
    return ClipEncoder(
        model=model,
        pretrained=args.pretrained or pretrained,
        checkpoint=args.clip_checkpoint,
        device=args.device,
    )


CLIP_FLAGS = (("--clip-checkpoint", "clip_checkpoint"), ("--clip-model", "clip_model"), ("--pretrained", "pretrained"),
              ("--clip-config", "clip_config"))


def warn_unused_clip_flags(args: argparse.Namespace, encoder: object | None) -> None:
    """One warning naming the CLIP flags given when no text encoder was loaded (encoder None): every
    query, label and negative came as embeddings, so the flags were not read. Round 54: a
    `--clip-checkpoint` that does not exist passed without a word."""
    given = [flag for flag, dest in CLIP_FLAGS if getattr(args, dest, None) is not None]
    if encoder is None and given:
        log.warning("%s not used: every query, label and negative came as embeddings (or Gaussian ids), so no CLIP text "
                    "encoder was loaded", ", ".join(given))


def checked_phrases(flag: str, text: str) -> list[str]:
    """The comma-separated phrases of `flag` (`--labels`, `--negatives`), stripped, or one UsageError
    naming the first entry that `name_problem` finds (empty: `a,,b`, a trailing comma; a hidden
    character; a repeat), and when there is none at all (`""`, `","`). The phrases label a printed
    table (a newline in one forges a line of it) and are embedded one by one: a dropped or doubled
    entry would shift or waste a row."""
    entries = text.split(",")
    phrases = [entry.strip() for entry in entries]
    if not any(phrases):
        raise UsageError(f"{flag} {text!r} gives no phrases; expected comma-separated phrases such as 'chair,table'")
    problem = name_problem(phrases)
    if problem is not None:
        i, kind, detail = problem
        if kind == "empty":
            raise UsageError(f"{flag} {text[:60]!r}: entry {i + 1} of {len(entries)} is empty (two commas in a row, or one at an end)")
        if kind == "hidden":
            raise UsageError(f"{flag}: entry {i + 1} ({phrases[i][:40]!r}) holds {detail}, which a terminal would not show as itself")
        raise UsageError(f"{flag}: entry {i + 1} repeats the phrase {phrases[i][:40]!r} of entry {detail + 1}")
    return phrases


def checked_text_query(phrase: str) -> str:
    """A `--text` phrase as given, or one UsageError when it is blank (CLIP would embed the empty
    string, and the ranking would mean nothing) or holds a hidden character (`errors.hidden_character`)."""
    if not phrase.strip():
        raise UsageError(f"--text {phrase!r} is blank; give the phrase to search for, e.g. --text 'a red chair'")
    hidden = hidden_character(phrase)
    if hidden is not None:
        raise UsageError(f"--text {phrase[:40]!r} holds {hidden}, which a terminal would not show as itself")
    return phrase


def resolve_threshold(value: str | None, scores: np.ndarray, relevancy: bool) -> float:
    """The selection threshold: a number, or 'auto' (Otsu); None = 0.5 for relevancy, 'auto' for cosine."""
    from drsplat.query import otsu_split_problem, otsu_threshold

    if value is None:
        value = str(DEFAULT_RELEVANCY_THRESHOLD) if relevancy else "auto"
    if value == "auto":
        threshold = otsu_threshold(scores)
        problem = otsu_split_problem(scores, threshold)
        if problem is not None:
            log.warning("--threshold auto: %s (give --threshold a number to choose)", problem)
        else:
            log.info("automatic (Otsu) threshold: %.4f", threshold)
        return threshold
    try:
        threshold = float(value)
    except ValueError:
        raise DrsplatError(f"--threshold must be a number or 'auto', got {value!r}") from None
    if not math.isfinite(threshold):
        raise DrsplatError(f"--threshold must be finite, got {value!r}")
    return threshold


POSITIONAL_NAMES = {"scene": "SCENE", "registered": "REGISTERED.ply", "codebook": "CODEBOOK", "out_dir": "OUT_DIR"}  # the commands' positional arguments


def guard_args(args: argparse.Namespace, outputs: tuple[str, ...], extra_inputs: dict[str, Path | None] | None = None,
               extra_outputs: dict[str, Path | None] | None = None, protected_folders: dict[str, tuple[Path | None, tuple[str, ...]]] | None = None,
               protected_trees: dict[str, Path | None] | None = None) -> None:
    """`drsplat.utils.guard_outputs` over a parsed command line: every Path-valued argument that is
    not one of `outputs` (attribute names) is an input. Raises OutputError before any work starts."""
    from drsplat.utils import guard_outputs

    def flag(name: str) -> str:  # a positional argument is named as its usage line shows it
        return POSITIONAL_NAMES.get(name, "--" + name.replace("_", "-"))

    inputs: dict[str, Path | None] = {}
    for name, value in vars(args).items():
        if name in outputs:
            continue
        if isinstance(value, Path):
            inputs[flag(name)] = value
        elif isinstance(value, list) and value and all(isinstance(v, Path) for v in value):
            inputs.update({f"{flag(name)} {v}": v for v in value})
    inputs.update(extra_inputs or {})
    written = {flag(name): getattr(args, name, None) for name in outputs}
    written.update(extra_outputs or {})
    guard_outputs(inputs, written, protected_folders, protected_trees)


def protected_feature_folders(flag: str, folders: list[Path | None]) -> dict[str, tuple[Path | None, tuple[str, ...]]]:
    """`guard_args`' protected_folders for feature folders given to `flag`: an output there may not
    be named like a feature file (`*_f.npy`, `*_s.npy`, manifest.json), which it would replace."""
    from drsplat.features.format import FEATURE_FILE_PATTERNS

    given = [f for f in folders if f is not None]
    if len(given) == 1:
        return {flag: (given[0], FEATURE_FILE_PATTERNS)}
    return {f"{flag} {folder}": (folder, FEATURE_FILE_PATTERNS) for folder in given}


def add_format_argument(parser: argparse.ArgumentParser, flag: str) -> None:
    """`--format standard|drsplat` for the PLY an option (`flag`) writes (drsplat.lang.export_scene)."""
    from drsplat.lang import EXPORT_FORMAT_HELP, EXPORT_FORMATS

    parser.add_argument("--format", choices=EXPORT_FORMATS, default="standard",
                        help=f"file written by {flag}: " + "; ".join(f"'{k}' {v}" for k, v in EXPORT_FORMAT_HELP.items()) + " (default: standard)")


def guard_field_codebook(registered: Path, field: LanguageField, outputs: dict) -> None:
    """`drsplat.utils.guard_outputs` for the codebook a registered PLY's header names, known only
    once the field is read: it need not be the `<stem>.codebook.faiss` beside the PLY (a renamed
    PLY keeps naming its old codebook), and no output may be written over it."""
    from drsplat.utils import guard_outputs

    guard_outputs({f"the codebook {Path(registered).name} names": field.codebook_path}, outputs)


def export_outputs(path, fmt: str, flag: str) -> dict:
    """The files an export to `path` (given by `flag`) in format `fmt` writes besides the file itself
    (for guard_outputs): a drsplat PLY's codebook beside it. UsageError when the name and the format
    disagree (a drsplat export named .spz), before any work."""
    from drsplat.lang import export_problem, written_codebook_path

    if path is None:
        return {}
    problem = export_problem(path, fmt)
    if problem is not None:
        raise UsageError(f"{flag}: {problem}")
    return {"the export's codebook": written_codebook_path(path)} if fmt == "drsplat" else {}


def table_stream(*outputs: Path | None) -> TextIO:
    """Where a command prints its table: standard output, or standard error when one of its outputs is
    standard output itself (`--json /dev/stdout`, `--out /dev/stdout | ...`), so the table does not
    mix into the file's bytes (probe round 44)."""
    try:
        shown = os.fstat(sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # no real descriptor (a captured or closed stream): no output can be it
        return sys.stdout
    for path in outputs:
        if path is None:
            continue
        try:
            st = os.stat(path)
        except OSError:
            continue
        if (st.st_dev, st.st_ino) == (shown.st_dev, shown.st_ino):
            return sys.stderr
    return sys.stdout
