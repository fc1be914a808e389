"""Exceptions raised by medseg.

Every error caused by the user's input is a :class:`MedsegError` subclass whose message says
what was wrong and what to do about it. The command-line tools print that message on one line
and exit non-zero; they never show a traceback for a ``MedsegError``.
"""

from __future__ import annotations

__all__ = [
    "MedsegError",
    "ParameterError",
    "InputFileError",
    "ImageFormatError",
    "ImageGeometryError",
    "LabelError",
    "LandmarkFileError",
    "CohortError",
    "ModelFileError",
    "NotFittedError",
    "ResourceLimitError",
    "ProblemDefinitionError",
    "MeshError",
]


class MedsegError(Exception):
    """Base class of every error medseg raises for bad input or bad use."""


class ParameterError(MedsegError, ValueError):
    """A parameter or argument has a value that cannot be used (wrong range, shape or choice).

    Also a ``ValueError``, as scikit-learn and numpy raise for bad arguments, so code that
    catches ``ValueError`` keeps working; estimators raise it from ``fit`` (their
    ``__init__`` only stores).
    """


class InputFileError(MedsegError):
    """A file is missing, unreadable, or would be overwritten."""


class ImageFormatError(InputFileError):
    """An image file has an unknown format, or is corrupt or truncated."""


class ImageGeometryError(MedsegError):
    """An image has the wrong dimension, non-finite voxels, or an unusable geometry."""


class LabelError(MedsegError):
    """A label map is empty, lacks the requested labels, or does not match its image."""


class LandmarkFileError(InputFileError):
    """A landmark file is malformed or uses an unsupported coordinate system."""


class CohortError(MedsegError):
    """A cohort (dataset folder or manifest) is empty, inconsistent or too small."""


class ModelFileError(InputFileError):
    """A saved model is corrupt, tampered with, or from an incompatible version."""


class NotFittedError(MedsegError):
    """A model or detector is used before it was fitted."""


class ResourceLimitError(MedsegError):
    """A computation would exceed a memory or size limit; the message gives the estimate."""


class ProblemDefinitionError(MedsegError):
    """An optimisation problem (MRF, matching) is malformed."""


class MeshError(MedsegError):
    """A surface mesh is unreadable, degenerate, or of an unsupported topology."""
