"""A classical (non-learned) stand-in for the map-prediction ensemble of
docs/algorithms.md#prediction.

Plain image inpainting, not a neural network: every member paints the observed wall image
(known free 0, occupied 1) into the unknown cells with OpenCV's `cv2.inpaint` (Navier-Stokes
or Telea), each with its own settings (`InpaintMemberConfig`), only in a band near the known
cells, with a constant wall prior beyond. All are deterministic. Why these choices:
docs/prediction.md#the-classical-predictor---predictor-classical.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from mapex.grid import OCCUPIED, UNKNOWN
from mapex.prediction.base import Predictor
from mapex.prediction.config import ClassicalPredictorConfig, InpaintMemberConfig

_CV_METHODS = {"ns": cv2.INPAINT_NS, "telea": cv2.INPAINT_TELEA}


class ClassicalInpaintingEnsemble(Predictor):
    """Ensemble of OpenCV inpaintings of the observed map; member 0 is G."""

    name = "classical"

    def __init__(self, config: ClassicalPredictorConfig | None = None) -> None:
        config = config or ClassicalPredictorConfig()
        if not config.members:
            raise ValueError("classical predictor needs at least one member")
        for member in config.members:
            _check_member(member)
        self.config = config
        self.n_members = len(config.members)

    def predict_members(self, observed: np.ndarray, members: Sequence[int]) -> np.ndarray:
        """Float32 (len(members), rows, cols) wall probabilities in [0, 1] for a map crop."""
        if not isinstance(observed, np.ndarray) or observed.ndim != 2 or observed.dtype != np.uint8:
            raise ValueError(
                "observed map must be a 2-D uint8 array of FREE/UNKNOWN/OCCUPIED codes"
            )
        if observed.size == 0:
            return np.zeros((len(members), *observed.shape), dtype=np.float32)
        return np.stack([inpaint_member(observed, self.config.members[k]) for k in members])


def _check_member(member: InpaintMemberConfig) -> None:
    if member.method not in _CV_METHODS:
        raise ValueError(f"inpaint method '{member.method}' is not one of {sorted(_CV_METHODS)}")
    if member.scale < 1 or member.radius_cells < 1 or member.band_cells < 0:
        raise ValueError("inpaint member needs scale >= 1, radius_cells >= 1 and band_cells >= 0")
    if not (0.0 <= member.prior <= 1.0 and 0.0 < member.wall_level < 1.0):
        raise ValueError("inpaint member needs prior in [0, 1] and wall_level in (0, 1)")


def inpaint_member(observed: np.ndarray, member: InpaintMemberConfig) -> np.ndarray:
    """One member's float32 wall probability (rows, cols) in [0, 1] for `observed`."""
    walls, unknown = _working_scale_maps(observed, member.scale)
    in_band = unknown & (distance_to_known(unknown) * member.scale <= member.band_cells)
    probability = np.where(unknown & ~in_band, np.float32(member.prior), walls)
    painted = cv2.inpaint(
        probability, in_band.view(np.uint8), member.radius_cells, _CV_METHODS[member.method]
    )
    # cv2.inpaint has been seen to return NaN on a tiny (2 x 7) map once in a full test run
    # and never on its own: such a cell knows nothing, so it takes the member's prior.
    band_values = np.nan_to_num(painted[in_band], nan=member.prior, posinf=1.0, neginf=0.0)
    probability[in_band] = np.interp(band_values, (0.0, member.wall_level, 1.0), (0, 0.5, 1))
    return _to_map_scale(probability, member.scale, observed.shape)


def _working_scale_maps(observed: np.ndarray, scale: int) -> tuple[np.ndarray, np.ndarray]:
    """Float32 wall image and bool unknown mask at 1/scale resolution.

    A coarse cell is a wall if any of its cells is one (thin walls survive) and
    unknown only if all of its cells are (edge blocks are padded with unknown).
    """
    rows, cols = observed.shape
    padded = np.full((-(-rows // scale) * scale, -(-cols // scale) * scale), UNKNOWN, np.uint8)
    padded[:rows, :cols] = observed
    blocks = padded.reshape(padded.shape[0] // scale, scale, padded.shape[1] // scale, scale)
    walls = (blocks == OCCUPIED).any(axis=(1, 3)).astype(np.float32)
    unknown = (blocks == UNKNOWN).all(axis=(1, 3))
    return walls, unknown


def distance_to_known(unknown: np.ndarray) -> np.ndarray:
    """Distance (working cells, 5x5-mask approximation of Euclidean) to the nearest known cell.

    With no known cell at all every distance is huge, so everything is beyond the band.
    """
    if unknown.all():
        return np.full(unknown.shape, np.inf, dtype=np.float32)
    return cv2.distanceTransform(unknown.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)


def _to_map_scale(probability: np.ndarray, scale: int, shape: tuple[int, int]) -> np.ndarray:
    """Bilinear upsampling back to map resolution, cropped to `shape`, clipped to [0, 1]."""
    if scale > 1:
        size = (probability.shape[1] * scale, probability.shape[0] * scale)
        probability = cv2.resize(probability, size, interpolation=cv2.INTER_LINEAR)
    return np.clip(probability[: shape[0], : shape[1]], 0.0, 1.0)
