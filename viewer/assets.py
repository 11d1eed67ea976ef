"""The files under assets/ (GLSL shaders, the pre-registered demo scene), found in a source checkout
and in an installed package alike.

pyproject.toml installs assets/ as a package with its files as package data, so it sits beside
`viewer/` both in a checkout and in site-packages.
"""

from __future__ import annotations

from pathlib import Path


def asset_root() -> Path:
    """The assets folder beside the `viewer` package."""
    return Path(__file__).resolve().parent.parent / "assets"


def asset_path(*parts: str) -> Path:
    return asset_root().joinpath(*parts)


def load_shader(name: str, defines: dict[str, int | float | str] | None = None) -> str:
    """GLSL source of assets/shaders/`name`, with `#define KEY VALUE` lines inserted after its
    `#version` line (GLSL requires #version first)."""
    source = asset_path("shaders", name).read_text()
    if not defines:
        return source
    version, _, body = source.partition("\n")
    if not version.startswith("#version"):
        raise ValueError(f"shader {name} does not start with a #version line")
    return "\n".join([version, *(f"#define {k} {v}" for k, v in defines.items()), body])
