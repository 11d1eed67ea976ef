"""drsplat viewer: moderngl splat rendering and imgui-bundle panels on top of the drsplat library.

GUI and GL code only: every score, selection, segmentation and registration comes from drsplat.
"""
