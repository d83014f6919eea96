"""The paper's colour model: one GMM per object in the UV plane of YUV, sized by BIC, as a LUT.

From calibration pixels (RGB) of the target and of the arrow's tip, each object gets a Gaussian
mixture over (U, V) — Y is dropped so the model is robust to changes of brightness — with full
covariances and the number of components K chosen by the Bayesian Information Criterion (the
paper's Section III-C). The fitted densities are tabulated once on the 256×256 (U, V) grid, so
per-frame cost never depends on K: a frame costs one table look-up per pixel.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from sklearn.mixture import GaussianMixture

from services.detector.errors import CalibrationError, ModelFileError

__all__ = [
    "MODEL_FORMAT",
    "MODEL_VERSION",
    "ColourModel",
    "Gmm",
    "fit_gmm",
    "rgb_to_uv",
]

MODEL_FORMAT = "archery-colour-model"
MODEL_VERSION = 1
MIN_PIXELS = 8  # fewer calibration pixels than this cannot support even one full covariance
_REG_COVAR = 4.0  # (UV levels)²: JPEG and sensor noise floor, keeps single-colour sets sane


def rgb_to_uv(rgb: np.ndarray) -> np.ndarray:
    """(U, V) chrominance (0..255, float) of RGB uint8 pixels, shape (..., 3) → (..., 2)."""
    pixels = np.ascontiguousarray(rgb, dtype=np.uint8).reshape(-1, 1, 3)
    yuv = cv2.cvtColor(pixels, cv2.COLOR_RGB2YUV).reshape(*rgb.shape[:-1], 3)
    return yuv[..., 1:].astype(np.float64)


@dataclass(frozen=True)
class Gmm:
    """A Gaussian mixture in UV: priors π_k, centres μ_k (UV levels), full covariances Σ_k."""

    weights: np.ndarray  # (K,)
    means: np.ndarray  # (K, 2)
    covariances: np.ndarray  # (K, 2, 2)
    bic: dict[int, float]  # BIC of every K tried

    @property
    def n_components(self) -> int:
        """K, the number of Gaussians."""
        return len(self.weights)

    def density(self, uv: np.ndarray) -> np.ndarray:
        """Σ_k π_k N(c; μ_k, Σ_k) (the paper's Eq. 8 mixture) at UV points (..., 2)."""
        points = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        total = np.zeros(len(points))
        for w, mu, cov in zip(self.weights, self.means, self.covariances, strict=True):
            diff = points - mu
            inv = np.linalg.inv(cov)
            mahal = np.einsum("ni,ij,nj->n", diff, inv, diff)
            total += w * np.exp(-0.5 * mahal) / (2 * math.pi * math.sqrt(np.linalg.det(cov)))
        return total.reshape(np.shape(uv)[:-1])

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-friendly form."""
        return {
            "weights": self.weights.tolist(),
            "means": self.means.tolist(),
            "covariances": self.covariances.tolist(),
            "bic": {str(k): v for k, v in self.bic.items()},
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Gmm:
        """Inverse of `to_dict`; raises ModelFileError when inconsistent."""
        try:
            weights = np.asarray(data["weights"], dtype=float)
            means = np.asarray(data["means"], dtype=float).reshape(len(weights), 2)
            covs = np.asarray(data["covariances"], dtype=float).reshape(len(weights), 2, 2)
            bic = {int(k): float(v) for k, v in data.get("bic", {}).items()}
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFileError(f"a GMM entry is malformed: {exc}") from None
        if len(weights) == 0 or not np.all(np.isfinite(covs)) or np.any(np.linalg.det(covs) <= 0):
            raise ModelFileError("a GMM needs ≥ 1 component with positive-definite covariances")
        return cls(weights=weights, means=means, covariances=covs, bic=bic)


def fit_gmm(uv: np.ndarray, *, max_components: int = 5, seed: int = 0, name: str = "object") -> Gmm:
    """Fit a full-covariance GMM to UV samples (N, 2), K = argmin BIC over 1..max_components.

    Raises:
        CalibrationError: too few pixels, or not finite.
    """
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2 or not np.all(np.isfinite(uv)):
        raise CalibrationError(f"{name}: UV samples must be a finite (N, 2) array, got {uv.shape}")
    if len(uv) < MIN_PIXELS:
        raise CalibrationError(
            f"{name}: {len(uv)} calibration pixels; at least {MIN_PIXELS} are needed "
            f"(mark more pixels on the {name})"
        )
    distinct = len(np.unique(np.round(uv), axis=0))
    best: GaussianMixture | None = None
    bic: dict[int, float] = {}
    for k in range(1, min(max_components, max(1, distinct), len(uv) // MIN_PIXELS) + 1):
        gmm = GaussianMixture(
            n_components=k,
            covariance_type="full",
            reg_covar=_REG_COVAR,
            random_state=seed,
            n_init=2,
        ).fit(uv)
        bic[k] = float(gmm.bic(uv))
        if best is None or bic[k] < bic[best.n_components]:
            best = gmm
    assert best is not None
    return Gmm(
        weights=best.weights_.copy(),
        means=best.means_.copy(),
        covariances=best.covariances_.copy(),
        bic=bic,
    )


@dataclass(frozen=True)
class ColourModel:
    """The target's and (optionally) the arrow tip's colour GMMs, and their 256×256 UV tables.

    `density_floor` (per UV level²) is the likelihood below which a pixel belongs to neither
    object: background never pulls a centroid.
    """

    target: Gmm
    arrow: Gmm | None = None
    density_floor: float = 2e-5

    def tables(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-(U, V) membership of the target and of the arrow, uint8 0..255 each (256, 256).

        A colour belongs to the more likely model, and only above the floor; membership then
        saturates at 10× the floor, so that colours of high density (a tight cluster) do not
        outweigh equally certain colours of a broader one (this is what biases a plain
        likelihood-weighted centroid towards one ring).
        """
        grid = np.stack(np.meshgrid(np.arange(256), np.arange(256), indexing="ij"), axis=-1)
        p_target = self.target.density(grid.astype(np.float64))
        p_arrow = (
            self.arrow.density(grid.astype(np.float64)) if self.arrow else np.zeros_like(p_target)
        )
        ceiling = 10 * self.density_floor

        def membership(p: np.ndarray, other: np.ndarray) -> np.ndarray:
            m = np.clip((p - self.density_floor) / (ceiling - self.density_floor), 0, 1)
            m[p <= other] = 0
            return np.round(m * 255).astype(np.uint8)

        return membership(p_target, p_arrow), membership(p_arrow, p_target)

    def to_dict(self) -> dict[str, Any]:
        """The model file's content."""
        return {
            "format": MODEL_FORMAT,
            "version": MODEL_VERSION,
            "colour_space": "UV of YUV (OpenCV RGB2YUV), levels 0..255",
            "density_floor": self.density_floor,
            "target": self.target.to_dict(),
            "arrow": self.arrow.to_dict() if self.arrow else None,
        }

    @classmethod
    def from_dict(cls, data: Any) -> ColourModel:
        """Build from a model file's content.

        Raises:
            ModelFileError: not a colour model, or of another version.
        """
        if not isinstance(data, dict) or data.get("format") != MODEL_FORMAT:
            raise ModelFileError(f"not an archery colour model (expected format {MODEL_FORMAT!r})")
        if data.get("version") != MODEL_VERSION:
            raise ModelFileError(
                f"colour model version {data.get('version')!r} is not supported; this detector "
                f"reads version {MODEL_VERSION}: calibrate again with `archery calibrate`"
            )
        arrow = data.get("arrow")
        return cls(
            target=Gmm.from_dict(data["target"]),
            arrow=Gmm.from_dict(arrow) if arrow else None,
            density_floor=float(data.get("density_floor", 2e-5)),
        )

    def save(self, path: str | Path) -> None:
        """Write the model as JSON."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=1))

    @classmethod
    def load(cls, path: str | Path) -> ColourModel:
        """Read a model file; raises ModelFileError when missing or invalid."""
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ModelFileError(f"cannot read colour model {str(path)!r}: {exc}") from None
        return cls.from_dict(data)

    @classmethod
    def fit(
        cls,
        target_rgb: np.ndarray,
        arrow_rgb: np.ndarray | None = None,
        *,
        max_components: int = 5,
        seed: int = 0,
    ) -> ColourModel:
        """Fit both GMMs from calibration pixels (N, 3) RGB uint8.

        Raises:
            CalibrationError: too few pixels, or target and arrow colours that overlap so much
                the two objects cannot be told apart.
        """
        target = fit_gmm(
            rgb_to_uv(target_rgb), max_components=max_components, seed=seed, name="target"
        )
        arrow = None
        if arrow_rgb is not None and len(arrow_rgb):
            arrow_uv = rgb_to_uv(arrow_rgb)
            arrow = fit_gmm(arrow_uv, max_components=max_components, seed=seed, name="arrow")
            confused = float(np.mean(target.density(arrow_uv) >= arrow.density(arrow_uv)))
            if confused > 0.5:
                raise CalibrationError(
                    f"{confused:.0%} of the arrow pixels look more like the target: the arrow "
                    f"tip needs a colour the target does not have"
                )
        return cls(target=target, arrow=arrow)
