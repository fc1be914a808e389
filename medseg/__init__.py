"""medseg: knowledge-based 3D segmentation with pose-invariant higher-order shape priors.

Segmentation after Wang, Teboul, Michel, Essafi & Paragios (MICCAI 2010) and surface matching
after Zeng, Wang, Wang, Gu, Samaras & Paragios (CVPR 2010).

>>> import medseg
>>> model = medseg.load_model("model/")               # doctest: +SKIP
>>> seg = model.segment("case.nii.gz")                # doctest: +SKIP
"""

from medseg._version import __version__
from medseg.errors import MedsegError

__all__ = ["MedsegError", "ShapePriorSegmenter", "Segmentation", "load_model", "__version__"]

_LAZY = {"ShapePriorSegmenter", "Segmentation", "load_model"}


def __getattr__(name: str):
    # The segmenter pulls in scikit-learn, pyvista, ...: import it on first use only.
    if name in _LAZY:
        from medseg import segmenter

        return getattr(segmenter, name)
    raise AttributeError(f"module 'medseg' has no attribute {name!r}")
