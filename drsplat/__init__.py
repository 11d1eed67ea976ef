"""drsplat: language search for trained 3D Gaussian Splatting scenes (Dr. Splat, CVPR 2025).

Stages, each one module, data flowing one way:
scene -> cameras -> features -> registration -> index -> query -> (viewer).
"""

__version__ = "0.1.0"
