"""The rig simulator: a master and a panning slave camera over a rectified stereo pair, the generated
scene, a first-order motor, and the closed loop of `vergence sim` (the library only, no Zenoh)."""

from .optics import homography, rotation
from .rig import Rig
from .scene import Scene, generate

__all__ = ["Rig", "Scene", "generate", "homography", "rotation"]
