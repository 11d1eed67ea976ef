"""Evaluation: the paper's protocols on registered scenes (`drsplat eval`).

- `metrics`: volume-aware, count and voxel 3D IoU, localisation and segmentation scores.
- `pseudolabels`: pseudo ground truth from labelled point clouds.
- `lerf`: the LERF-OVS 2D object-selection protocol.
- `datasets`: LERF-OVS and ScanNet readers.
- `ablations`: the paper's ablations on synthetic exact-ground-truth scenes.
"""
