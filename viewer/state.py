"""The viewer's state and actions, free of any GUI or GL code (testable headless).

`ViewerState` owns the scene, its language field, the current query's scores, the selection and
the display mode, and the user's settings (`settings`: viewer.settings.ViewerSettings, which the
panels edit), and turns them into a per-splat style for the renderer. Every number comes
from the drsplat library: scores from `drsplat.query`, picks from `drsplat.raster`, the
registration from `drsplat.registration` and `drsplat.lang`. Actions never raise for bad
input: they record a message (shown in the GUI) and return False.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import math
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drsplat import query as dq
from drsplat.cameras import Camera, dataset_inputs, load_cameras
from drsplat.commands.common import DEFAULT_RELEVANCY_THRESHOLD, checked_phrases, protected_feature_folders
from drsplat.defaults import DEFAULT_CODEBOOK, DEFAULT_LEVEL, DEFAULT_TOPK, NEAR, ORACLE_LABEL_NAMES, ORACLE_TEXT_EMBEDDINGS
from drsplat.device import resolve_device, resolve_engine
from drsplat.errors import DrsplatError, InputError, WeightsUnavailableError, hidden_character, one_line
from drsplat.features.clip import ClipEncoder, unsupported_model_name, use_clip_config  # imports open_clip/torch only when an encoder is built
from drsplat.features.modelid import DEFAULT_MODEL, DEFAULT_PRETRAINED, clip_weights_problem, is_oracle, named_model
from drsplat.lang import REGISTERED_IS_PLY, export_kind, export_problem, export_scene, other_data_name, read_field, written_codebook_path
from drsplat.query import load_query_embeddings, otsu_split_problem, otsu_threshold, select, threshold_digits
from drsplat.raster import prepare_scene, rasterize
from drsplat.registration import RegisterOptions
from drsplat.registration.checkpoint import checkpoint_path_for
from drsplat.scene import GaussianScene, counted
from drsplat.splat_formats import load_scene_report, written_format
from drsplat.utils import check_output_writable, check_outputs_writable, checked_names, describe_os_error, fifo_reader, guard_outputs, load_npy, names_a_folder, read_json
from viewer.cameracheck import CameraCheck, checked_cameras, concurrent_kernels_safe, start_camera_check
from viewer.messages import LibraryWarnings, Message, MessageLog  # noqa: F401 - Message re-exported
from viewer.paths import typed_path
from viewer.registration import RegistrationJob, start_job
from viewer.settings import ViewerSettings
from viewer.style import DISPLAY_MODE_NAMES, DISPLAY_MODES, HEATMAP_MIX, HIGHLIGHT_MIX, HIGHLIGHT_RGB, SEGMENT_MIX, heat_colors, splat_style  # noqa: F401 - re-exported

log = logging.getLogger(__name__)
CAMERAS_BEING_CHECKED = "the training cameras are still being checked against the scene"  # what waits for `cameras_pending` says
NO_FIELD_STATUS = "no language field loaded"  # the encoder status until a scene with a language field opens


@dataclass
class QueryResult:
    """The scores [N] of the current query, what produced them and how they are scored."""

    name: str
    source: str  # "text" | "oracle" | "embedding" | "click"
    scores: np.ndarray
    metric: str  # "relevancy" | "cosine"
    picked: np.ndarray | None = None  # Gaussian ids a click query started from
    assigned: np.ndarray | None = None  # [N] bool the Gaussians with a feature (LanguageField.assigned): only they are selected
    file: Path | None = None  # the embedding file an "embedding" query was read from: an input no output may replace


@dataclass
class OracleQueries:
    """Synthetic datasets' "text": label names and their oracle vectors [L, D] (not CLIP)."""

    names: list[str]
    embeddings: np.ndarray


class ViewerState:
    """Everything the panels show and every action they trigger."""

    def __init__(self) -> None:
        self.scene: GaussianScene | None = None
        self.scene_path: Path | None = None
        self.scene_refinements: np.ndarray | None = None  # the open scene's trainer's camera refinements (drsplat.frames)
        self.field = None  # drsplat.lang.LanguageField | None
        self.field_problem: str | None = None
        self.assigned_count = 0  # the field's Gaussians with a feature (`LanguageField.assigned`), counted once per scene
        self.cameras: list[Camera] = []
        self.near_plane = NEAR  # registration's, decided with the cameras (`checked_cameras`)
        self.source_dir: Path | None = None
        self.dataset_scene_folders: set[Path] = set()  # folders of the scenes shown with this dataset: its scenes may be reopened there
        self.features_dir: Path | None = None
        self.clip_checkpoint: Path | None = None
        self.clip_config: Path | None = None  # an open_clip model config for an architecture it does not ship
        self.settings = ViewerSettings()
        self.oracle: OracleQueries | None = None
        self.encoder = None
        self.encoder_status = NO_FIELD_STATUS
        self.query: QueryResult | None = None
        self.threshold = 0.5
        self.mode = "color"
        self.segmentation = None  # drsplat.query.Segmentation | None
        self.segment_names: list[str] = []
        self.segment_colors = np.zeros((0, 3), np.float32)
        self.messages = MessageLog()
        self.registration: RegistrationJob | None = None
        self.style_version = 0
        self.scene_version = 0
        self._prepared = None
        self._encoder_lock = threading.Lock()
        self.same_place = False  # the scene just loaded is the registered one of the scene in view: the window keeps its view
        self._pending_replace: tuple | None = None  # (path, size, mtime) of a file an export asked to replace (`_replace_confirmed`)
        self._encoder_loaders: list[threading.Thread] = []  # `start_text_encoder`'s threads, waited for at exit (`wait_for_encoder_loads`)
        self.camera_check: CameraCheck | None = None
        self._stopped_check: CameraCheck | None = None  # a check stopped with its scene, which the next one waits for
        self._kernels_safe: bool | None = None  # `kernels_safe`, once asked
        self.dataset_cameras: list[Camera] = []  # as read from source_dir, before any check: the files they name are guarded
        self.camera_problem: str | None = None  # why the last check of the training cameras failed

    # ---------------------------------------------------------------- messages

    def info(self, text: str) -> None:
        self.messages.add("info", text)

    def warning(self, text: str) -> None:
        self.messages.add("warning", text)

    def error(self, text: str) -> None:
        self.messages.add("error", text)

    def _fail(self, exc: BaseException, what: str) -> bool:
        # one line: a typed path or query holding a newline forged a line of the log (round 54)
        if isinstance(exc, OSError):  # the cause in words ("the disk is full"), not "[Errno 28] ..."
            self.error(one_line(f"{what}: {describe_os_error(exc)}"))
        elif isinstance(exc, (DrsplatError, ValueError)):
            self.error(one_line(f"{what}: {exc}"))
        else:
            log.debug("%s", traceback.format_exc())
            self.error(one_line(f"{what}: unexpected {type(exc).__name__}: {exc}"))
        return False

    # ---------------------------------------------------------------- loading

    @property
    def num_gaussians(self) -> int:
        return 0 if self.scene is None else self.scene.num_gaussians

    def load_scene(self, path: str | Path) -> bool:
        """Load a PLY and its language field (if registered); clears the query."""

        try:
            path = typed_path(path)
            with LibraryWarnings(self.messages):  # what the load warns of is shown, not only logged
                scene, report = load_scene_report(path, purpose="show; open another PLY")  # refuses a file with no usable row
        except Exception as exc:  # noqa: BLE001 - the viewer reports any loading failure
            return self._fail(exc, "cannot open" if str(path) in str(exc) else f"cannot open {path}")
        try:
            with LibraryWarnings(self.messages):
                lang = read_field(scene, path, shared=True)  # the viewer never edits the scene's columns
            problem = None
        except (DrsplatError, ValueError, OSError) as exc:  # a missing or other codebook: the splats are intact (round 61a)
            lang, problem = None, one_line(str(exc))
        self.set_scene(scene, lang, path, report.camera_refinements)
        if problem is not None:
            self.field_problem = f"the language field of {path.name} cannot be read ({problem})"
            self.encoder_status = f"Queries are off: {self.field_problem}"
            self.warning(f"opened {path.name} without its language field: {problem}")
        return True

    def set_scene(self, scene: GaussianScene, lang=None, path: Path | None = None, refinements: np.ndarray | None = None) -> None:
        """Show `scene` with nothing of the previous one: no query, segmentation, display mode or
        CLIP encoder (another scene's features may come from another model; `start_text_encoder`
        loads this one's). refinements: its trainer's camera refinements (`LoadReport.camera_refinements`),
        which the training cameras read next take (`load_source`)."""
        self.drop_camera_check()  # it checked the cameras against the scene closed now
        self.same_place = False  # another scene: its own home view (a registration of the one in view sets it after this)
        self.scene, self.field, self.scene_path, self.scene_refinements = scene, lang, path, refinements
        self.field_problem = None  # why a registered file's field could not be read (its codebook missing: `load_scene`)
        self.assigned_count = 0 if lang is None else int(lang.assigned().sum())
        self.query = None
        self.segmentation = None
        self.segment_names, self.segment_colors = [], np.zeros((0, 3), np.float32)
        self.mode = "color"
        with self._encoder_lock:
            self.encoder = None
        self.encoder_status = NO_FIELD_STATUS
        self._prepared = None
        self.scene_version += 1
        self.style_version += 1
        if lang is None:
            self.encoder_status = "this scene has no language field: register it (Registration panel) to query it"
        self.info(f"loaded {path.name if path else 'scene'}: {counted(scene.num_gaussians, 'Gaussian', 'Gaussians')}, SH degree {scene.sh_degree}" + (f", language field {lang.kind} {lang.dim}-D ({lang.clip_model})" if lang is not None else ""))
        if lang is not None and not self.assigned_count and len(lang):
            self.warning(self.unassigned_message())

    def load_source(self, source: str | Path, background: bool = False) -> bool:
        """Training cameras of a dataset directory, and its oracle label queries if it has them.

        The cameras are read here (a bad file is refused now); their checks against the open scene
        (`checked_cameras`: the frame, the principal point) render views of it, seconds on a 500k-Gaussian
        scene, so with `background` they run on a worker thread (`viewer.cameracheck`; where numba's
        threads allow two at once, `concurrent_kernels_safe`) and `poll_camera_check` takes the cameras
        when they end (the window froze for them). Until then `cameras` is empty; the dataset's files are
        guarded all the while (`dataset_cameras`)."""

        try:
            source = typed_path(source)
            with LibraryWarnings(self.messages):
                cameras = load_cameras(source, require_images=False)
        except Exception as exc:  # noqa: BLE001
            return self._fail(exc, f"cannot read cameras from {source}")
        previous, self.camera_check = self.camera_check or self._stopped_check, None  # replaced: its cameras are not taken
        self._stopped_check = None
        if previous is not None:
            previous.stop()
        read, near_plane = cameras, NEAR
        if self.scene is not None and background and self.kernels_safe():
            self.camera_check = start_camera_check(self.scene, cameras, source, self.scene_path, self.scene_refinements,
                                                   self.scene_version, previous)
            self.cameras = []
            self.info(f"checking the {len(cameras)} training cameras of {source} against the scene (its frame, principal points and near plane)...")
        elif self.scene is not None:
            try:
                with LibraryWarnings(self.messages):  # a move into gsplat's world is said on screen
                    trained = checked_cameras(self.scene, cameras, source, self.scene_path, self.scene_refinements)
                cameras, near_plane = trained.cameras, trained.near_plane
            except Exception as exc:  # noqa: BLE001 - the cameras and dataset in use stay as they were
                return self._fail(exc, f"cannot read cameras from {source}")
        self.dataset_cameras, self.camera_problem = read, None
        if source != self.source_dir:
            self.dataset_scene_folders = set()
        self.source_dir = source
        if self.scene_path is not None:
            self.dataset_scene_folders.add(resolved_folder(self.scene_path))
        if self.features_dir is None and (source / "features").is_dir():
            self.features_dir = source / "features"
        problems: list[str] = []
        self.oracle = read_oracle_queries(source, problems)
        if self.camera_check is None:
            self.cameras, self.near_plane = cameras, near_plane
            self.info(f"{counted(len(self.cameras), 'training camera', 'training cameras')} from {source}" + (f"; {len(self.oracle.names)} oracle label queries" if self.oracle else ""))
        elif self.oracle is not None:
            self.info(f"{len(self.oracle.names)} oracle label queries from {source}")
        for problem in problems:  # the labels are gone from the panel: say why there (last, in the status line), not only in the terminal
            self.warning(f"no oracle labels: {problem}")
        return True

    @property
    def cameras_pending(self) -> bool:
        """True while the training cameras are being checked against the scene (`load_source` in the background)."""
        return self.camera_check is not None and not self.camera_check.reported

    def forget_source(self) -> None:
        """No dataset: no training cameras (nor a check of them), oracle labels or guarded dataset files."""
        self.drop_camera_check()
        self.cameras, self.dataset_cameras, self.camera_problem, self.oracle, self.source_dir = [], [], None, None, None
        self.dataset_scene_folders = set()
        self.near_plane = NEAR

    def drop_camera_check(self) -> None:
        """Stop a check still running (another scene opened, or no dataset now): its cameras and warnings are not taken.
        It is kept as `_stopped_check` until it ends, so that the next check waits for it (round 56e: reopening a scene
        started a second one beside it)."""
        if self.camera_check is not None:
            self.camera_check.stop()
            self._stopped_check, self.camera_check = self.camera_check, None

    def poll_camera_check(self) -> bool:
        """When a finished camera check is pending: take its cameras, with the warnings it gave (or report its
        failure, after which the dataset stays guarded and registration says why it cannot run); True when done now."""
        check = self.camera_check
        if check is None or not check.finished or check.reported:
            return False
        check.reported = True
        self.camera_check = None
        if check.scene_version != self.scene_version or check.cancel.cancelled:
            return False
        if check.error is not None:
            self._fail(check.error, f"cannot read cameras from {check.source}")
            self.camera_problem = self.messages[-1].text
            return True
        self.messages.extend(check.messages)
        self.cameras, self.near_plane = check.cameras, check.near_plane
        self.info(f"{counted(len(self.cameras), 'training camera', 'training cameras')} from {check.source}")
        return True

    @property
    def usable_oracle(self) -> OracleQueries | None:
        """The dataset's oracle labels where they can query the open field: its features are in the oracle
        space too. A field of CLIP features (the same synthetic dataset run through `drsplat features`)
        scored against the oracle vectors gave plausible counts of nothing (round 61a)."""
        return self.oracle if self.oracle_problem() is None else None

    def oracle_problem(self) -> str | None:
        """Why the oracle labels cannot query the open field (None when they can, or there are none)."""
        if self.oracle is None or self.field is None or is_oracle(self.field.clip_model):
            return None
        return (f"the dataset's oracle labels are not offered: they are ground-truth vectors of the synthetic oracle space, "
                f"and this field holds features of {self.field.clip_model or 'an unknown model'} (type text queries or labels instead)")

    def next_step(self) -> str:
        """What a person should do next, for the first screen (shown until a query runs)."""
        if self.scene is None:
            return "Open a scene: type a scene path (.ply, .splat, .spz) in the Scene panel, or drop the file on the window."
        if self.field is None and self.field_problem is not None:
            return f"Queries are off: {self.no_field_message()}."
        if self.field is None:
            return ("This scene has no language field yet: open the Registration panel and press 'register' "
                    "(it needs the dataset, --source DIR, and its features). Drag to orbit, F1 lists the keys.")
        if not self.assigned_count:
            return f"Queries are off: {self.unassigned_message()}."
        steps = []
        if (oracle := self.usable_oracle) is not None:
            steps.append(f"click a label above (e.g. '{oracle.names[min(3, len(oracle.names) - 1)]}') to highlight it")
        if self.encoder is not None:
            steps.append("type what to find (e.g. 'a mug') and press Enter")
        steps.append("ctrl+click a splat to find similar ones")
        return "Next: " + ", or ".join(steps) + ". Drag to orbit, scroll to zoom, F1 lists every key."

    def start_text_encoder(self, background: bool = True) -> None:
        """Load the CLIP text encoder matching the field's model (on a thread when `background`).

        Synthetic (oracle) fields need none; without weights the status says how to provide them.
        """
        if self.field is None:
            return
        model = self.field.clip_model or "unknown"
        if is_oracle(model):
            self.encoder_status = "Text queries are off because this scene's features are synthetic oracle vectors (query their labels: the oracle buttons below, or --oracle LABEL with --screenshot); for a real scene pass --clip-checkpoint PATH to a local open_clip checkpoint."
            return
        self.encoder_status = "loading the CLIP text encoder..."
        if background:
            loader = threading.Thread(target=self._load_encoder, args=(self.scene_version,), name="clip-loader", daemon=True)
            self._encoder_loaders = [t for t in self._encoder_loaders if t.is_alive()] + [loader]
            loader.start()
        else:
            self._load_encoder(self.scene_version)

    def encoder_being_built(self) -> bool:
        """True while a text encoder started in the background (for this scene or an earlier one) is still being built."""
        return any(t.is_alive() for t in self._encoder_loaders)

    def wait_for_encoder_loads(self, timeout: float) -> bool:
        """Wait up to `timeout` s for the encoders being built in the background; True when none is left.

        The process must not end while one is: torch's threads, torn down under a model being built,
        ended the closing viewer with "terminate called without an active exception" and SIGABRT
        (exit 134; 5 of 6 closes within seconds of opening a scene, round 61a)."""
        deadline = time.monotonic() + timeout
        for loader in self._encoder_loaders:
            loader.join(max(0.0, deadline - time.monotonic()))
        self._encoder_loaders = [t for t in self._encoder_loaders if t.is_alive()]
        return not self._encoder_loaders

    def _load_encoder(self, version: int) -> None:
        """Load the encoder for the scene of `version`; dropped if another scene opened meanwhile."""
        model_id = self.field.clip_model if self.field is not None else ""
        named = named_model(model_id)  # as the command line reads it (rounds 79a F3, 80a F4)
        name, pretrained = named or (DEFAULT_MODEL, DEFAULT_PRETRAINED)
        unsupported = unsupported_model_name(name)
        if unsupported is not None:  # no checkpoint can help (round 83a F3)
            if version == self.scene_version:
                self.encoder_status = (f"Text queries are off: this scene's CLIP model id {model_id!r} {unsupported}. "
                                       "Embedding files and clicks query by cosine.")
            return
        if named is not None and pretrained is None and self.clip_checkpoint is None:
            if version == self.scene_version:
                self.encoder_status = (f"Text queries are off: this scene's CLIP model id {model_id!r} names no weights tag; pass "
                                       "--clip-checkpoint PATH to the weights its features were made with.")
            return
        try:
            use_clip_config(self.clip_config)
            encoder = ClipEncoder(name, pretrained or None, self.clip_checkpoint, device=self.settings.device)
            field = self.field
            # on the loader's thread (~1 s of ViT-B-16's file), and now: an encoder of other weights made every query
            # fail, embedding and click queries too (their relevancy negatives are its text; round 61a)
            mismatch = (None if field is None or field.clip_weights is None
                        else clip_weights_problem(field.clip_weights, encoder.weights_digest, self.clip_checkpoint))
        except WeightsUnavailableError as exc:
            if version == self.scene_version:
                self.encoder_status = f"Text queries are off: {exc}"
            return
        except Exception as exc:  # noqa: BLE001
            if version == self.scene_version:
                self.encoder_status = (f"Text queries are off: the CLIP encoder could not be loaded ({exc}); pass --clip-checkpoint PATH "
                                       "to a local open_clip checkpoint.")
            return
        if mismatch is not None:
            if version == self.scene_version:
                self.encoder_status = f"Text queries are off: {mismatch}. Embedding files and clicks query by cosine meanwhile."
            return
        with self._encoder_lock:
            if version != self.scene_version:  # another scene opened while this one loaded: not its encoder
                return
            self.encoder = encoder
        self.encoder_status = f"CLIP text encoder ready ({encoder.model_id})"

    @property
    def encoder_loading(self) -> bool:
        return self.encoder_status.startswith("loading")

    # ---------------------------------------------------------------- queries

    def kernels_safe(self) -> bool:
        """`concurrent_kernels_safe`, asked once, before any worker thread runs kernels (asking runs one)."""
        if self._kernels_safe is None:
            self._kernels_safe = concurrent_kernels_safe()
        return self._kernels_safe

    def kernels_busy(self, what: str) -> bool:
        """True, with an error naming `what`, while a registration runs kernels on its thread and numba's threading
        layer cannot run the window's beside them (workqueue ends the process: round 56e)."""
        job = self.registration
        if job is None or job.finished or self._kernels_safe is not False:
            return False
        self.error(f"{what} waits for the registration running: numba's threading layer here cannot run two threads' kernels "
                   "at once (install tbb, or an OpenMP runtime, to query while registering)")
        return True

    def no_field_message(self) -> str:
        """Why nothing can be queried: the registered file's field unreadable (round 79b F1: a PQ PLY copied without its
        codebook was told to register again), or no field at all."""
        if self.field_problem is not None:
            return f"{self.field_problem}; mend what it names (a codebook moved away: put it back) and open the scene again"
        return "this scene has no language field; register it first (the Registration panel, or `drsplat register`)"

    def unassigned_message(self) -> str:
        """Why a field none of whose Gaussians has a feature cannot be queried (round 86d F4: it pointed to "the warnings
        above", which a file of all-unassigned rows does not give)."""
        return (f"none of this scene's {len(self.field):,} Gaussians has a language feature (all unassigned, or their codes do not "
                "match their codebook); there is nothing to search: register the scene again")

    def _require_field(self) -> bool:
        if self.kernels_busy("a query"):
            return False
        if self.scene is None:
            self.error("no scene is loaded")
            return False
        if self.field is None:
            self.error(self.no_field_message())
            return False
        if not self.field.assigned().any():  # as `drsplat query` refuses it: no threshold can select anything
            self.error(self.unassigned_message())
            return False
        return True

    def _score(self, embeddings: np.ndarray) -> tuple[np.ndarray, str]:
        """Scores [N] of one query [D]: relevancy when a CLIP encoder provides the canonical
        negatives (plus the user's negative phrases), else cosine."""

        # as given: the library makes them unit rows once, and float32 normalising is not idempotent, so a second
        # pass here moved scores by up to 6e-8 from `drsplat query`'s and a Gaussian at the threshold changed sides
        q = np.atleast_2d(np.asarray(embeddings, np.float32))[:1]
        typed = self.settings.query.negatives
        negatives = checked_phrases("negative phrases", typed) if typed.strip() else []  # as `drsplat query --negatives` checks them
        if self.encoder is not None:
            neg = dq.negative_embeddings(self.encoder, self.field, negatives)
            return dq.relevancy(self.field, q, neg)[:, 0], "relevancy"
        if negatives:
            self.warning("negative phrases need a CLIP text encoder; scoring by cosine without them")
        return dq.cosine(self.field, q)[:, 0], "cosine"

    def _set_query(self, result: QueryResult) -> None:

        if result.assigned is None and self.field is not None:
            result.assigned = self.field.assigned()
        self.query = result
        self.threshold = self._first_threshold(result)
        if self.mode in ("color", "segmentation"):
            self.mode = "highlight"
        self.style_version += 1
        self.info(f"{result.source} query '{result.name}' ({result.metric}): {counted(int(self.selection.sum()), 'Gaussian', 'Gaussians')} at threshold {self.threshold:.3f}")

    def run_text_query(self, text: str) -> bool:

        text = text.strip()
        if not text:
            self.error("type a phrase to search for")
            return False
        hidden = hidden_character(text)
        if hidden is not None:  # as `drsplat query --text` refuses it: a pasted control character would be embedded too
            self.error(f"the query {text[:40]!r} holds {hidden}, which a terminal would not show as itself; type the phrase again")
            return False
        if not self._require_field():
            return False
        if self.encoder is None:
            self.error(self.encoder_status)
            return False
        try:
            with LibraryWarnings(self.messages):  # a phrase past CLIP's context is cut: said on screen
                emb = dq.text_embeddings(self.encoder, [text], self.field)
                scores, metric = self._score(emb)
        except Exception as exc:  # noqa: BLE001
            return self._fail(exc, f"query '{text}' failed")
        self._set_query(QueryResult(text, "text", scores, metric))
        return True

    def run_oracle_query(self, index: int) -> bool:
        """Query with synthetic label `index`'s oracle vector (not CLIP: exact ground-truth text)."""
        if not self._require_field():
            return False
        if (problem := self.oracle_problem()) is not None:
            self.error(problem)
            return False
        if self.oracle is None or not 0 <= index < len(self.oracle.names):
            self.error(f"no oracle label {index}")
            return False
        if not np.isfinite(self.oracle.embeddings[index]).all():  # round 95a F9: the library numbered the one row it was given "query 0"
            self.error(f"the oracle vector of {self.oracle.names[index]!r} (row {index} of {ORACLE_TEXT_EMBEDDINGS}) holds non-finite values: "
                       "it has no direction to score by")
            return False
        try:
            scores, metric = self._score(self.oracle.embeddings[index])
        except Exception as exc:  # noqa: BLE001
            return self._fail(exc, "oracle query failed")
        self._set_query(QueryResult(f"oracle:{self.oracle.names[index]}", "oracle", scores, metric))
        return True

    def run_embedding_query(self, path: str | Path) -> bool:
        """Query with the first row of an embedding file Q.npy ([D] or [K, D])."""

        if not self._require_field():
            return False
        if not str(path).strip():  # Path("") is ".", which was then "not a file" (round 71b F4)
            self.error("type the path of a Q.npy embedding file to query by")
            return False
        path = typed_path(path)
        try:
            emb = load_query_embeddings(path, self.field.dim)
            scores, metric = self._score(emb[0])
        except Exception as exc:  # noqa: BLE001
            return self._fail(exc, f"embedding query {path} failed")
        if emb.shape[0] > 1:  # `drsplat query` scores every row; the viewer shows one query, and said nothing of the rest
            self.warning(f"{Path(path).name} holds {emb.shape[0]} embeddings; the viewer queries by the first (row 0) and ignores the rest")
        self._set_query(QueryResult(Path(path).name, "embedding", scores, metric, file=Path(path)))
        return True

    def _first_threshold(self, result: QueryResult) -> float:
        """The threshold a new query starts at, as `drsplat query` chooses it: 0.5 for relevancy (a
        Gaussian nearer the query than the negatives), Otsu's split of the assigned scores for cosine,
        with a warning when that split is none (one value, or rounding noise)."""
        if result.metric == "relevancy":
            return float(DEFAULT_RELEVANCY_THRESHOLD)
        scored = result.scores if result.assigned is None else result.scores[result.assigned]
        threshold = float(otsu_threshold(scored))
        problem = otsu_split_problem(scored, threshold)
        if problem is not None:
            self.warning(f"automatic threshold: {problem} (move the threshold to choose)")
        return threshold

    def pick(self, camera: Camera, u: float, v: float, radius: int = 2, topk: int = 8) -> np.ndarray:
        """Gaussians under pixel (u, v) of `camera`: ids [k] by descending blending weight w = T·α.

        Rasterizes a (2·radius + 1)² window around the pixel with drsplat.raster (the weights the
        registration uses) and keeps each Gaussian's largest weight in the window.
        """

        if self.scene is None or self.kernels_busy("picking a splat"):
            return np.zeros(0, np.int64)
        if self._prepared is None:
            self._prepared = prepare_scene(self.scene)
        shown = None
        if self.query is not None and self.mode in ("selection", "hide_selection"):  # hidden splats are not under the cursor
            shown = self.export_mask()
        size = 2 * radius + 1
        u0, v0 = int(np.floor(u)) - radius, int(np.floor(v)) - radius
        window = dataclasses.replace(camera, cx=camera.cx - u0, cy=camera.cy - v0, width=size, height=size)
        out = rasterize(self._prepared, window, topk=topk, mask=shown)
        ids, weights = out.ids.reshape(-1), out.weights.reshape(-1)
        keep = ids >= 0
        if not keep.any():
            return np.zeros(0, np.int64)
        ids, weights = ids[keep], weights[keep]
        order = np.argsort(-weights, kind="stable")
        unique, first = np.unique(ids[order], return_index=True)
        return unique[np.argsort(first)][:topk].astype(np.int64)

    def click_query(self, camera: Camera, u: float, v: float) -> bool:
        """Pick the Gaussians under the cursor, then score every Gaussian by similarity to them."""

        if not self._require_field():
            return False
        if not (0 <= u < camera.width and 0 <= v < camera.height):
            self.error(f"the click ({u:.0f}, {v:.0f}) is outside the {camera.width}x{camera.height} view")
            return False
        try:
            ids = self.pick(camera, u, v)
            if ids.size == 0:
                self.error("nothing under the cursor to query")
                return False
            emb = dq.click_query(self.field, ids)
            scores, metric = self._score(emb)
        except Exception as exc:  # noqa: BLE001
            return self._fail(exc, "click query failed")
        self._set_query(QueryResult(f"click at ({u:.0f}, {v:.0f})", "click", scores, metric, picked=ids))
        return True

    def clear_query(self) -> None:
        self.query = None
        self.mode = "color"
        self.style_version += 1

    def set_threshold(self, value: float) -> bool:
        """Select at `value`; a value that is not a number (imgui's ctrl+click takes "nan" typed into
        the slider, which selected nothing while the slider showed "nan") is refused, the threshold kept."""
        if not math.isfinite(float(value)):
            self.error(f"the threshold must be a finite number, not {value}; kept {self.threshold:.3f}")
            return False
        self.threshold = float(value)
        self.style_version += 1
        return True

    def set_mode(self, mode: str) -> bool:
        if mode not in DISPLAY_MODES:
            self.error(f"unknown display mode {mode!r}")
            return False
        if mode == "segmentation" and self.segmentation is None:
            self.error("run a segmentation first (labels field and 'segment' button in the Display panel)")
            return False
        if mode not in ("color", "segmentation") and self.query is None:  # hide-selection with no query would export every splat
            self.error(f"run a query first: '{DISPLAY_MODE_NAMES.get(mode, mode)}' shows its matches")
            return False
        self.mode = mode
        self.style_version += 1
        return True

    @property
    def selection(self) -> np.ndarray:
        """[N] bool Gaussians with a feature at or above the threshold (drsplat.query.select); empty without a query."""

        if self.query is None:
            return np.zeros(self.num_gaussians, bool)
        return select(self.query.scores, self.threshold, self.query.assigned)

    def scored(self) -> np.ndarray:
        """The finite scores of the query's Gaussians with a feature (the others score 0, which stretched a relevancy
        scale down to 0: round 76a F4); empty without a query."""
        if self.query is None:
            return np.zeros(0, np.float32)
        s = self.query.scores if self.query.assigned is None else self.query.scores[self.query.assigned]
        return s[np.isfinite(s)]

    def best_score(self) -> float:
        """The highest of `scored`, NaN when there is none."""
        s = self.scored()
        return float(s.max()) if s.size else float("nan")

    def score_range(self) -> tuple[float, float]:
        """The colour scale's ends: the range of `scored`."""
        if self.query is None:
            return 0.0, 1.0
        s = self.scored()
        if s.size == 0:
            return 0.0, 1.0
        lo, hi = float(s.min()), float(s.max())
        return (lo, hi) if hi > lo else (lo - 0.5, lo + 0.5)

    # ---------------------------------------------------------------- segmentation

    def run_segmentation(self, names: list[str] | str | None = None) -> bool:
        """Argmax segmentation (drsplat.query.segment) over typed labels (CLIP) or the oracle labels.
        names: the labels, or the Display panel's comma-separated field as typed, checked as
        `drsplat segment --labels` checks it (`checked_phrases`: `mug,,table` is refused, not read as
        two labels); None or a blank field: the oracle's labels."""

        if not self._require_field():
            return False
        try:
            if isinstance(names, str):
                names = checked_phrases("labels", names) if names.strip() else None
            if names:
                names = checked_names(Path("the typed labels"), list(names))  # no repeats or blanks: each names one colour
                if self.encoder is None:
                    self.error(self.encoder_status)
                    return False
                with LibraryWarnings(self.messages):
                    emb = dq.text_embeddings(self.encoder, names, self.field)
            elif self.usable_oracle is not None:
                names, emb = list(self.oracle.names), self.oracle.embeddings
            else:
                self.error("type comma-separated labels to segment by" + (f" ({problem})" if (problem := self.oracle_problem()) else ""))
                return False
            seg = dq.segment(self.field, emb)
        except Exception as exc:  # noqa: BLE001
            return self._fail(exc, "segmentation failed")
        self.segmentation, self.segment_names = seg, list(names)
        self.segment_colors = dq.label_colors(len(names))
        self.mode = "segmentation"
        self.style_version += 1
        counts = np.bincount(seg.labels[seg.labels >= 0], minlength=len(names))
        self.info("segmentation: " + ", ".join(f"{n} {c:,}" for n, c in zip(names, counts)))
        return True

    # ---------------------------------------------------------------- style

    def style(self) -> np.ndarray:
        """Per-splat style for the renderer, [N, 4] float32 (viewer.style.splat_style of the current mode)."""
        seg = self.segmentation
        if self.query is None:
            return splat_style(self.num_gaussians, self.mode, labels=None if seg is None else seg.labels, label_colors=self.segment_colors)
        return splat_style(self.num_gaussians, self.mode, self.query.scores, self.selection, self.score_range(),
                           None if seg is None else seg.labels, self.segment_colors)

    # ---------------------------------------------------------------- what must not be written over

    def read_inputs(self) -> tuple[dict[str, Path | None], dict]:
        """(guard_outputs inputs, protected folders): every file the viewer read: the PLY, the
        codebooks beside it and named by its field, the dataset's camera files and images, its
        oracle label files; and the features folder, whose feature files an output may not replace."""
        inputs: dict[str, Path | None] = {
            "PLY you opened": self.scene_path,
            "codebook beside the PLY you opened": written_codebook_path(self.scene_path) if self.scene_path is not None else None,
            "codebook the opened PLY's field names": self.field.codebook_path if self.field is not None else None,
        }
        if self.source_dir is not None:
            inputs.update(dataset_inputs(self.source_dir, self.dataset_cameras or self.cameras))
            inputs.update({f"--source's {name}": self.source_dir / name for name in (ORACLE_LABEL_NAMES, ORACLE_TEXT_EMBEDDINGS)})
        inputs.update({"--clip-checkpoint": self.clip_checkpoint, "--clip-config": self.clip_config})  # round 95a F2, as the CLI's guard
        if self.query is not None and self.query.file is not None:  # round 86d F5: a screenshot replaced it, which the CLI refuses
            inputs["embedding file of the query shown"] = self.query.file
        if self.registration is not None and self.registration.running:  # it replaces them when it ends: an export there would be lost
            # named as phrases ("the ..."), which guard_outputs says as such: "the input output of ..." read wrong (round 60a)
            inputs["the output of the registration running"] = self.registration.output
            inputs["the codebook of the registration running"] = written_codebook_path(self.registration.output)
        return inputs, protected_feature_folders("--features", [self.features_dir])

    def guard_output(self, path: str | Path, what: str) -> bool:
        """False, with an error, when `path` is blank, names a folder (ends in a separator, or is
        one), or is a file the viewer read (`read_inputs`)."""
        if not str(path).strip():
            self.error(f"type the path of {what}")
            return False
        if names_a_folder(path):
            self.error(f"{what} to {path} refused: the path ends with a separator, so it names a folder; give a file name")
            return False
        path = typed_path(path)
        try:
            inputs, folders = self.read_inputs()
            guard_outputs(inputs, {what: Path(path)}, folders)
        except Exception as exc:  # noqa: BLE001
            return self._fail(exc, f"{what} to {path} refused")
        return True

    # ---------------------------------------------------------------- export

    def selection_text(self) -> str:
        """The Query panel's count above the export controls: the selection, and in hide-selection mode what an export
        writes, which is the rest (round 71b F3: "selected: 78 of 2,744" above an export of 2,666)."""
        selected = int(self.selection.sum())
        text = f"selected: {selected:,} of {self.num_gaussians:,}"
        if self.mode == "hide_selection":
            text += f"; an export writes the {int(self.export_mask().sum()):,} shown"
        return text

    def export_mask(self) -> np.ndarray:
        """[N] bool the Gaussians an export writes: the selection, or what is shown in hide-selection mode."""
        return ~self.selection if self.mode == "hide_selection" else self.selection

    def export_selection(self, path: str | Path | None = None, fmt: str | None = None) -> int | None:
        """Write the selected Gaussians (`export_mask`) with drsplat.lang.export_scene: `standard`
        (for other tools: an INRIA PLY, or .splat / .spz / .compressed.ply by the path's name) or `drsplat` (a PLY
        with the field, its codebook copied beside; `drsplat query` reads it); the path and format
        default to the export settings.
        Returns the number written, or None (with a message)."""

        path = self.settings.export.path if path is None else path
        fmt = self.settings.export.format if fmt is None else fmt
        if self.scene is None:
            self.error("no scene is loaded")
            return None
        if fmt == "drsplat" and self.field is None:
            self.error(f"{self.field_problem}: export it as a standard 3DGS PLY, or mend what it names first" if self.field_problem
                       else "this scene has no language field: export it as a standard 3DGS PLY")
            return None
        selected = self.export_mask()
        count = int(selected.sum())
        if count == 0 and self.mode == "hide_selection":  # what is written is what is shown: the Gaussians not selected
            self.error("nothing is shown to export: every Gaussian is selected and hidden; raise the threshold, or leave hide selection")
            return None
        if count == 0:
            d = threshold_digits(self.threshold, self.best_score())
            why = ("run a query and lower the threshold" if self.query is None or self.mode == "segmentation" else
                   f"no Gaussian scores >= {self.threshold:.{d}f} (the best score is {self.best_score():.{d}f}): lower the threshold")  # round 95a F8, as the CLI says it
            self.error(f"the selection is empty: {why}"
                       + (" (an export writes a query's selection; the segmentation's colours are written by drsplat segment --ply)"
                          if self.mode == "segmentation" else ""))
            return None
        if not str(path).strip():
            self.error("type the path of the file to export to (.ply, .compressed.ply, .splat or .spz)")
            return None
        if names_a_folder(path):  # Path("sel/") is Path("sel"): the export took the folder's name, as the CLI's --out once did
            self.error(f"export to {path} refused: the path ends with a separator, so it names a folder; give a file name")
            return None
        path = typed_path(path)
        try:
            codebook = written_codebook_path(path) if fmt == "drsplat" else None
            inputs, folders = self.read_inputs()
            guard_outputs(inputs, {"the export": path, "the export's codebook": codebook}, folders)
            check_outputs_writable(path, codebook)  # both, before either is written, as the CLI's export checks them (round 60a)
            if (problem := export_problem(path, fmt)) is not None:  # before a replacement is asked for that cannot happen (round 86d F3)
                raise ValueError(problem)
            if not self._replace_confirmed(path, codebook, fmt):
                return None
            with fifo_reader(path, wait=False):  # the window's thread: a FIFO nobody reads is refused, not waited on
                export_scene(self.scene.subset(selected), None if self.field is None else self.field.subset(selected), path, fmt)
        except Exception as exc:  # noqa: BLE001
            self._fail(exc, f"export to {path} failed")
            return None
        self.info(f"exported {count:,} Gaussian{'' if count == 1 else 's'} to {path} ({export_kind(path, fmt)})"
                  + (": the query's selection, not the segmentation shown (drsplat segment --ply writes its colours)"
                     if self.mode == "segmentation" else ""))
        return count

    def _replace_confirmed(self, path: Path, codebook: Path | None = None, fmt: str = "standard") -> bool:
        """Whether an export may write `path` (and its `codebook`): files there are replaced only by a second export to
        them in a row.

        The export path stays in the panel, so a second query's export replaced the first's without a word
        (and, with an export open, the registered scene it came from could be typed over: round 61a). The
        first press names the files and asks for another; the confirmation holds for those files as they
        are now, this scene, query and format (round 62b: the codebook beside a new PLY name was replaced
        unasked, and a confirmation outlived the scene it was asked for)."""
        existing = []
        for target in (path, codebook):
            if target is None:
                continue
            try:
                st = target.stat()
            except OSError:
                continue
            if target.is_file():
                existing.append((str(target.absolute()), st.st_size, st.st_mtime_ns))
        if not existing:
            self._pending_replace = None
            return True
        stamp = (tuple(existing), fmt, self.scene_version, id(self.query))
        if self._pending_replace == stamp:
            self._pending_replace = None
            return True
        self._pending_replace = stamp
        names = " and ".join(f"{Path(name).name} ({size:,} bytes)" for name, size, _ in existing)
        self.warning(f"{names} exist{'s' if len(existing) == 1 else ''}: export again to replace {'it' if len(existing) == 1 else 'them'}")
        return False


    # ---------------------------------------------------------------- registration

    def start_registration(self, output: str | Path, topk: int = DEFAULT_TOPK, level: int = DEFAULT_LEVEL, codebook: str = DEFAULT_CODEBOOK, background: bool = True) -> bool:
        """Register the scene with the features of `features_dir` (drsplat.registration.register, the CLI's
        pipeline and defaults) on a worker thread
        (viewer.registration), store the field in `output`, then load it."""

        if self.scene is None or self.scene_path is None:
            self.error("no scene file is loaded")
            return False
        if self.cameras_pending:
            self.error(f"{CAMERAS_BEING_CHECKED} (its frame and principal points); register when they are in")
            return False
        if not self.cameras and self.camera_problem is not None:
            self.error(f"registration needs the training cameras, and those of {self.source_dir} could not be used: {self.camera_problem}")
            return False
        if not self.cameras:
            self.error("registration needs the training cameras: set the dataset directory (--source)")
            return False
        if self.features_dir is None or not Path(self.features_dir).is_dir():
            self.error(f"features directory {self.features_dir} does not exist (--features)")
            return False
        if self.registration is not None and not self.registration.finished:
            self.error("a registration is already running")
            return False
        output = typed_path(output) if str(output).strip() else output
        codebook = codebook if codebook in ("none", "scene") or not codebook.strip() else str(typed_path(codebook))
        if codebook not in ("none", "scene") and not Path(codebook).is_file():
            self.error(f"codebook file {codebook or '(empty)'} does not exist")
            return False
        if written_format(output) != "ply":
            self.error(f"{Path(output).name}: {REGISTERED_IS_PLY}; name it .ply")
            return False
        if not self.guard_output(output, "the registration's output"):  # never over the scene, its dataset or features
            return False
        other = other_data_name(output)
        if other is not None:  # after the input guard, as `register --out` (round 107b F1: a PLY over the dataset's gt/labels.npy)
            self.error(other)
            return False
        try:
            check_output_writable(Path(output))  # a read-only folder: now, not after registering every view
        except Exception as exc:  # noqa: BLE001
            return self._fail(exc, "cannot register")

        try:
            device = resolve_device(self.settings.device)
            engine = resolve_engine(self.settings.engine, device)
        except DrsplatError as exc:
            self.error(str(exc))
            return False
        options = RegisterOptions(topk=topk, level=level, codebook=codebook, engine=engine, device=device, near_plane=self.near_plane)
        self.kernels_safe()  # asked before the job's thread runs kernels
        self.registration = start_job(Path(output), self.scene, self.cameras, Path(self.features_dir), options, background)
        self.registration.scene_version = self.scene_version
        if not background:
            self.poll_registration()
        return True

    def cancel_registration(self) -> None:
        if self.registration is not None and not self.registration.finished:
            self.registration.cancel.cancel()

    def poll_registration(self) -> bool:
        """When a finished registration is pending: report it, load its output; True when done now."""
        job = self.registration
        if job is None or not job.finished or job.reported:
            return False
        job.reported = True
        self.messages.extend(job.messages)  # the run's own warnings, before its outcome (the status line shows the last)
        if job.error is not None:
            if job.cancel is not None and job.cancel.cancelled:  # the user's own stop, not a failure (round 71b F5: shown in red)
                self.info(f"registration stopped: {job.error}")
            else:
                self.error(f"registration did not finish: {job.error}")
            if os.path.lexists(checkpoint_path_for(job.output)):
                self.info(f"its finished views are kept beside {job.output.name}: press Register with the same output and settings to "
                          "resume from them (other settings start over)")
            return True
        if job.scene_version is not None and job.scene_version != self.scene_version:  # another scene was opened meanwhile: keep it
            if self.scene_path is None or self.scene_path.resolve() != Path(job.output).resolve():
                self.info(f"registration saved to {job.output}; another scene is open now, so it was not loaded (open it to query it)")
                return True
            # the scene opened meanwhile is the output's earlier file, which this replaced: "another scene is open" showed the
            # old field as if it were the file on disk (round 61a)
            self.info(f"registration replaced {job.output}, the file open: the new one is loaded")
        else:
            self.info(f"registration saved to {job.output}")
        cameras, oracle, near_plane = self.cameras, self.oracle, self.near_plane
        if self.load_scene(job.output):
            self.cameras, self.oracle, self.near_plane = cameras, oracle, near_plane
            self.same_place = True  # the same Gaussians, pruned: the window stays where the user was
            self.start_text_encoder()
        return True


def read_oracle_queries(source: Path, problems: list[str] | None = None) -> OracleQueries | None:
    """The oracle "text" of a synthetic dataset: gt/label_names.json and text_embeddings.npy."""
    names_path, emb_path = source / ORACLE_LABEL_NAMES, source / ORACLE_TEXT_EMBEDDINGS
    if not (names_path.exists() and emb_path.exists()):  # a FIFO or folder there is refused by name below
        return None
    try:
        names = read_json(names_path, "a JSON list of label names")  # not a file, bad or too deep JSON: one InputError
        if not isinstance(names, list):
            raise InputError(names_path, f"holds a JSON {type(names).__name__}; expected a JSON list of label names")
        names = checked_names(names_path, names)  # strings, not blank, no control characters, none repeated
        emb = load_npy(emb_path, "embedding array")  # header checked against the file size
    except (OSError, ValueError, DrsplatError) as exc:
        return _no_oracle(problems, f"ignoring oracle queries of {source}: {exc}")
    if emb.ndim != 2 or emb.shape[0] != len(names):
        return _no_oracle(problems, f"ignoring oracle queries of {source}: {len(names)} names but embeddings of shape {emb.shape}")
    if not names:  # round 86d F1: zero labels passed, and the first screen's example label raised IndexError
        return _no_oracle(problems, f"ignoring oracle queries of {source}: {names_path.name} lists no label")
    return OracleQueries([str(n) for n in names], emb.astype(np.float32))


def resolved_folder(path: Path) -> Path:
    """The folder of `path`, links resolved where they can be (a link loop or an unreadable part: as written, made absolute)."""
    try:
        return Path(path).resolve().parent
    except (OSError, RuntimeError, ValueError):  # ValueError: a NUL in the name (round 88a F2)
        return Path(os.path.abspath(path)).parent


def _no_oracle(problems: list[str] | None, text: str) -> None:
    """Record why the oracle labels were not read: in `problems` (shown in the GUI), else the log."""
    if problems is not None:
        problems.append(text)
    else:
        log.warning("%s", text)
    return None
