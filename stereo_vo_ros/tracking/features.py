"""
What the stereo tracker keeps between pairs and how it prepares an image.

``FeatureSet`` holds the features alive in the last pair (ids, ages, raw and ideal pixels of
both images; raw pixels are those of the images as given, x right, y down, ideal ones their
undistorted pinhole positions); ``as_grey_u8`` turns an input image into the (H, W) uint8 image
KLT runs on.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ImageError
from ..records import Correspondences


@dataclass
class FeatureSet:
    """The tracker's state: the features alive in one stereo pair."""

    ids: np.ndarray  # (N,) int64
    ages: np.ndarray  # (N,) int64 frames tracked
    left_raw: np.ndarray  # (N, 2) float32 raw pixels, left image
    right_raw: np.ndarray  # (N, 2) float32 raw pixels, right image
    left_ideal: np.ndarray  # (N, 2) float64 ideal pixels, left image
    right_ideal: np.ndarray  # (N, 2) float64 ideal pixels, right image

    @classmethod
    def empty(cls) -> 'FeatureSet':
        z32, z64 = np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float64)
        zi = np.zeros(0, np.int64)
        return cls(zi, zi.copy(), z32, z32.copy(), z64, z64.copy())

    def __len__(self) -> int:
        return len(self.ids)

    def take(self, sel: np.ndarray) -> 'FeatureSet':
        return FeatureSet(self.ids[sel], self.ages[sel], self.left_raw[sel],
                          self.right_raw[sel], self.left_ideal[sel], self.right_ideal[sel])

    def concat(self, other: 'FeatureSet') -> 'FeatureSet':
        return FeatureSet(*(np.concatenate([a, b]) for a, b in (
            (self.ids, other.ids), (self.ages, other.ages), (self.left_raw, other.left_raw),
            (self.right_raw, other.right_raw), (self.left_ideal, other.left_ideal),
            (self.right_ideal, other.right_ideal))))


def empty_correspondences() -> Correspondences:
    z = np.zeros((0, 2), np.float64)
    return Correspondences(z, z.copy(), z.copy(), z.copy(), np.zeros(0, np.int64),
                           np.zeros(0, np.int64))


def as_grey_u8(img: np.ndarray, name: str, bits: int) -> tuple[np.ndarray, int]:
    """Return a contiguous (H, W) uint8 image and the bit depth used to scale uint16 input."""
    if not isinstance(img, np.ndarray):
        raise ImageError(f'{name} image must be a numpy array, got {type(img).__name__}')
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim != 2:
        raise ImageError(f'{name} image must be grey (H, W), got shape {img.shape}')
    if img.shape[0] < 2 or img.shape[1] < 2:
        raise ImageError(f'{name} image is too small: {img.shape[1]}x{img.shape[0]}')
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img), bits
    if img.dtype == np.uint16:
        # Scale by a bit depth that only grows (12-bit data in 16-bit containers stays bright
        # and the scale stays constant between frames, as KLT assumes).
        peak = int(img.max())
        bits = max(bits, 8, peak.bit_length())
        return cv2.convertScaleAbs(img, alpha=255.0 / (2 ** bits - 1)), bits
    raise ImageError(f'{name} image must be uint8 or uint16, got {img.dtype}')
