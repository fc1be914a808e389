"""medseg: knowledge-based 3D segmentation with pose-invariant higher-order shape priors.

Segmentation after Wang, Teboul, Michel, Essafi & Paragios (MICCAI 2010) and surface matching
after Zeng, Wang, Wang, Gu, Samaras & Paragios (CVPR 2010).
"""

from medseg.errors import MedsegError

__version__ = "0.1.0"

__all__ = ["MedsegError", "__version__"]
