"""Stage 3, features: per-image masks embedded by CLIP, stored in LangSplat's file format.

- `format`: the LangSplat per-image files (`<stem>_s.npy`, `<stem>_f.npy`, `manifest.json`).
- `masks`: mask generators (SAM, felzenszwalb, slic) behind one `MaskGenerator` protocol.
- `clip`: the OpenCLIP encoder and its weights.
- `extract`: the resumable extraction loop (`drsplat features`).

Submodules are imported on use: torch, open_clip and SAM load only when a command needs them.
"""
