"""What the image says: landmark candidates (pose-invariant features, Random Forests) and,
in the shape's frame, the label of each voxel near the boundary (:class:`VoxelClassifier`).

The singleton evidence of the shape MRF, ``U_i(x_i) = -log p(I | x_i)``, and the candidate
positions ``X_i`` of each landmark (Wang et al., MICCAI 2010).
"""

from medseg.detection._candidates import CandidateSet, non_maximum_suppression, subvoxel_peak
from medseg.detection._detector import LandmarkDetector, load_detector
from medseg.detection._directions import gradient_directions
from medseg.detection._features import FeatureSettings, compute_features, feature_names
from medseg.detection._memory import detection_bytes, feature_map_bytes
from medseg.detection._persistence import save_detector
from medseg.detection._sampling import LandmarkSamples, sample_landmark_voxels
from medseg.detection._voxels import (
    CONTRAST_RING_MM,
    VoxelClassifier,
    context_features,
    voxel_features,
)

__all__ = [
    "CONTRAST_RING_MM",
    "CandidateSet",
    "FeatureSettings",
    "LandmarkDetector",
    "LandmarkSamples",
    "compute_features",
    "detection_bytes",
    "feature_map_bytes",
    "feature_names",
    "gradient_directions",
    "load_detector",
    "non_maximum_suppression",
    "sample_landmark_voxels",
    "save_detector",
    "subvoxel_peak",
    "VoxelClassifier",
    "context_features",
    "voxel_features",
]
