"""Synthetic subjects: anny bodies rendered in the six postures (the ``synth`` extra).

Importing this package does not import ``anny``; :func:`torchfit.synth.body.load_anny` does,
when a body is first built. Modules: ``postures`` (the posture table and BAP rotations),
``raster`` (z-buffer rasteriser, Lambert shading), ``scene`` (room, light, camera, image
formation), ``body`` (posed anny bodies, joint centres), ``generate`` (subject folders) and
``sheet`` (contact sheets).
"""

from torchfit.synth.generate import SynthConfig, make_subject, make_subjects
from torchfit.synth.postures import POSTURES, STEREO_POSTURE, Posture
from torchfit.synth.raster import Raster, rasterize
from torchfit.synth.sheet import contact_sheet

__all__ = [
    "SynthConfig",
    "make_subject",
    "make_subjects",
    "POSTURES",
    "STEREO_POSTURE",
    "Posture",
    "Raster",
    "rasterize",
    "contact_sheet",
]
