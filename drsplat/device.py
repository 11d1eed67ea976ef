"""One owner of device choice: "auto" | "cpu" | "cuda", and the engine that suits a device.

torch is imported only inside these functions, so importing this module (the CLI does) costs
nothing; `resolve_device("cpu")` does not import torch at all, nor does "auto" on a machine
without an NVIDIA driver (`nvidia_driver_present`).
"""

from __future__ import annotations

from drsplat.defaults import ENGINES
from drsplat.errors import DrsplatError

DEVICES = ("auto", "cpu", "cuda")


def nvidia_driver_present() -> bool:
    """Whether an NVIDIA driver could serve a CUDA GPU here, from cheap checks that import nothing heavy.

    Any of: the kernel module's /proc/driver/nvidia, a loadable libcuda (ctypes.util.find_library),
    an `nvidia-smi` on PATH. False means torch.cuda.is_available() would be False too, so the
    ~0.6 GB and ~2 s of importing the CUDA build of torch are not spent to learn it.
    """
    import ctypes.util
    import os
    import shutil

    if os.path.exists("/proc/driver/nvidia"):
        return True
    if shutil.which("nvidia-smi") is not None:
        return True
    try:
        return ctypes.util.find_library("cuda") is not None
    except (OSError, RuntimeError):  # find_library runs ldconfig/gcc; a broken toolchain means "not found"
        return False


def cuda_available() -> bool:
    """torch.cuda.is_available(), asked only where an NVIDIA driver is present (`nvidia_driver_present`)."""
    if not nvidia_driver_present():
        return False
    import torch  # only here: a driver is present, so the answer needs torch

    return bool(torch.cuda.is_available())


def resolve_device(device: str = "auto") -> str:
    """"auto" -> "cuda" when a CUDA GPU is available, else "cpu"; "cuda" without a GPU is an error.

    Without an NVIDIA driver neither "auto" nor "cpu" imports torch.
    """
    if device not in DEVICES:
        raise DrsplatError(f"unknown device '{device}': use auto, cpu or cuda")
    if device == "cpu":
        return "cpu"
    available = cuda_available()
    if device == "auto":
        return "cuda" if available else "cpu"
    if not available:
        raise DrsplatError("--device cuda was requested but no CUDA GPU is available; use --device cpu")
    return "cuda"


def resolve_engine(engine: str | None, device: str) -> str:
    """The compute engine for a resolved `device`: `engine` if given, else torch on cuda and numba on the CPU.

    numba runs on the CPU only, so numba with cuda is an error.
    """
    if engine is None:
        return "torch" if device == "cuda" else "numba"
    if engine not in ENGINES:
        raise DrsplatError(f"unknown engine '{engine}': use numba or torch")
    if engine == "numba" and device != "cpu":
        raise DrsplatError(f"--engine numba runs on the CPU only; use --engine torch with --device {device}")
    return engine


def add_device_arguments(parser) -> None:
    """--device auto|cpu|cuda and --engine numba|torch on an argparse parser (resolved by `resolve_compute`)."""
    parser.add_argument("--device", default="auto", choices=DEVICES, help="where to compute: auto (cuda if available), cpu or cuda")
    parser.add_argument(
        "--engine", default=None, choices=ENGINES, help="compute engine: numba (CPU) or torch (CPU or CUDA); default torch on cuda, numba on cpu"
    )


def resolve_compute(args) -> tuple[str, str]:
    """(device, engine) from parsed --device / --engine flags."""
    device = resolve_device(getattr(args, "device", "auto") or "auto")
    return device, resolve_engine(getattr(args, "engine", None), device)
