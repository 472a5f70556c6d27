"""torchface: 3D face tracking in PyTorch (pose, expression and illumination in one minimisation per frame).

Pipeline, one sub-package per stage: ``model`` -> ``geometry`` -> ``rendering`` (rasterizer, visibility,
shading) -> ``appearance`` -> ``solver`` -> ``template`` -> ``tracker`` -> ``normalise``.
``synth`` renders test sequences with ground truth. Conventions: :mod:`torchface.conventions`.
"""

__version__ = "0.1.0"
