"""drsplat assets: GLSL shaders and the pre-registered demo scene (package data; see viewer/assets.py)."""
