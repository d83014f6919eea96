"""The paper's colour model: one GMM per object in the UV plane of YUV, sized by BIC, as a LUT.

From calibration pixels (RGB) of the target and of the arrow's tip, each object gets a Gaussian
mixture over (U, V) — Y is dropped so the model is robust to changes of brightness — with full
covariances and the number of components K chosen by the Bayesian Information Criterion (the
paper's Section III-C), fitted by EM (`em.fit_mixture`). The fitted densities are tabulated
once on the 256×256 (U, V) grid, so per-frame cost never depends on K: a frame costs one table
look-up per pixel.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from archery.protocol.vectors import finite_vector
from archery.services.detector.em import Mixture, fit_mixture
from archery.services.detector.errors import CalibrationError, ModelFileError

__all__ = [
    "MIN_CHROMA",
    "MIN_PIXELS",
    "MODEL_FORMAT",
    "MODEL_VERSION",
    "ColourModel",
    "Gmm",
    "fit_gmm",
    "rgb_to_uv",
    "rgb_to_uv_exact",
]

log = logging.getLogger("archery.detector")
MODEL_FORMAT = "archery-colour-model"
MODEL_VERSION = 1
MIN_PIXELS = 8  # fewer calibration pixels than this cannot support even one full covariance
MIN_CHROMA = 10.0  # UV levels from grey: a set this close to grey is white, grey or black
_REG_COVAR = 4.0  # (UV levels)²: JPEG and sensor noise floor, keeps single-colour sets sane


def rgb_to_uv(rgb: np.ndarray) -> np.ndarray:
    """(U, V) chrominance (0..255, float) of RGB uint8 pixels, shape (..., 3) → (..., 2)."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    if rgb.size == 0:
        return np.zeros((*rgb.shape[:-1], 2))
    yuv = cv2.cvtColor(rgb.reshape(-1, 1, 3), cv2.COLOR_RGB2YUV).reshape(*rgb.shape[:-1], 3)
    return yuv[..., 1:].astype(np.float64)


def rgb_to_uv_exact(rgb: np.ndarray) -> np.ndarray:
    """(U, V) in floating point, unrounded: BT.601 as OpenCV's RGB→YUV, (..., 3) → (..., 2)."""
    c = np.asarray(rgb, dtype=np.float64)
    y = 0.299 * c[..., 0] + 0.587 * c[..., 1] + 0.114 * c[..., 2]
    u = 0.492 * (c[..., 2] - y) + 128.0
    v = 0.877 * (c[..., 0] - y) + 128.0
    return np.clip(np.stack([u, v], axis=-1), 0.0, 255.0)


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
    def from_dict(cls, data: Any, name: str = "object") -> Gmm:
        """Inverse of `to_dict`.

        Raises:
            ModelFileError: missing or inconsistent entries; the message names the object.
        """
        try:
            weights = np.asarray(data["weights"], dtype=float).reshape(-1)
            means = np.asarray(data["means"], dtype=float).reshape(len(weights), 2)
            covs = np.asarray(data["covariances"], dtype=float).reshape(len(weights), 2, 2)
            bic = {int(k): float(v) for k, v in dict(data.get("bic", {})).items()}
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ModelFileError(
                f"the {name} GMM of the model file is malformed ({exc!r}); it needs "
                f"weights, means and covariances"
            ) from None
        finite = all(np.all(np.isfinite(a)) for a in (weights, means, covs))
        if len(weights) == 0 or not finite or np.any(np.linalg.eigvalsh(covs) <= 0):
            raise ModelFileError(
                f"the {name} GMM needs ≥ 1 component, finite values and positive-definite "
                f"covariances"
            )
        if np.any(weights < 0) or abs(float(weights.sum()) - 1.0) > 1e-6:
            raise ModelFileError(f"the {name} GMM priors must be ≥ 0 and sum to 1, got {weights}")
        return cls(weights=weights, means=means, covariances=covs, bic=bic)


def fit_gmm(uv: np.ndarray, *, max_components: int = 5, seed: int = 0, name: str = "object") -> Gmm:
    """Fit a full-covariance GMM to UV samples (N, 2), K = argmin BIC over 1..max_components.

    K is also capped by the number of distinct colours and by N / `MIN_PIXELS`, so a set of a
    single colour gives one Gaussian whose covariance is the noise floor `_REG_COVAR`·I.

    Raises:
        CalibrationError: too few pixels, non-finite values, or grey/white/black pixels (no
            chroma: UV cannot tell them from the background).
    """
    if not isinstance(max_components, int) or not 1 <= max_components <= 10:
        raise CalibrationError(
            f"max_components must be an integer in 1..10, got {max_components!r}"
        )
    uv = np.asarray(uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2 or not np.all(np.isfinite(uv)):
        raise CalibrationError(f"{name}: UV samples must be a finite (N, 2) array, got {uv.shape}")
    if len(uv) < MIN_PIXELS:
        raise CalibrationError(
            f"{name}: {len(uv)} calibration pixels; at least {MIN_PIXELS} are needed "
            f"(mark more pixels on the {name}, or a rectangle inside it)"
        )
    chroma = float(np.median(np.hypot(uv[:, 0] - 128.0, uv[:, 1] - 128.0)))
    if chroma < MIN_CHROMA:
        raise CalibrationError(
            f"{name}: the calibration pixels are grey, white or black (median chroma "
            f"{chroma:.1f} UV levels, at least {MIN_CHROMA:g} needed), and UV colour detection "
            f"cannot tell those from the background: mark coloured parts (the yellow, red and "
            f"blue rings; the tip's colour)"
        )
    distinct = len(np.unique(np.round(uv), axis=0))
    best: Mixture | None = None
    bic: dict[int, float] = {}
    for k in range(1, min(max_components, max(1, distinct), len(uv) // MIN_PIXELS) + 1):
        mixture = fit_mixture(uv, k, reg=_REG_COVAR, seed=seed, n_init=2)
        bic[k] = mixture.bic(len(uv))
        if best is None or bic[k] < bic[best.n_components]:
            best = mixture
    if best is None:  # unreachable: at least K = 1 is tried
        raise CalibrationError(f"{name}: no GMM could be fitted")
    # A Gaussian centred on grey models mis-clicked pixels (a shaft, a hole, the background):
    # UV cannot tell grey from the rest of the scene, so it is dropped (the median check above
    # guarantees that most pixels, hence some Gaussian, have colour).
    mean_chroma = np.hypot(best.means[:, 0] - 128.0, best.means[:, 1] - 128.0)
    keep = mean_chroma >= MIN_CHROMA
    if not keep.any():
        raise CalibrationError(f"{name}: every Gaussian of the fit is grey; mark coloured pixels")
    if not keep.all():
        log.info("%s: dropped %d grey Gaussian(s) of %d", name, int((~keep).sum()), len(keep))
    weights = best.weights[keep]
    return Gmm(
        weights=weights / weights.sum(),
        means=best.means[keep].copy(),
        covariances=best.covariances[keep].copy(),
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
    white_rgb: tuple[float, float, float] | None = None  # the calibration frame's white, 0..255

    def widened(self, variance: float) -> ColourModel:
        """This model with `variance` (UV levels²) added to every target covariance: a looser
        target model, for finding the face when the colours have drifted (JPEG, light)."""
        target = Gmm(
            self.target.weights,
            self.target.means,
            self.target.covariances + variance * np.eye(2),
            self.target.bic,
        )
        return ColourModel(target, self.arrow, self.density_floor, self.white_rgb)

    def component_table(self) -> np.ndarray:
        """Index of the target's most responsible Gaussian for every 8-bit (U, V): uint8
        (256, 256) indexed [U, V] (the rings of a face are its components)."""
        u, v = np.meshgrid(np.arange(256.0), np.arange(256.0), indexing="ij")
        uv = np.stack([u, v], axis=-1)
        single = [
            Gmm(np.ones(1), mu[None], cov[None], {}).density(uv) * w
            for w, mu, cov in zip(
                self.target.weights, self.target.means, self.target.covariances, strict=True
            )
        ]
        labels: np.ndarray = np.argmax(np.stack(single), axis=0).astype(np.uint8)
        return labels

    def tables(self) -> tuple[np.ndarray, np.ndarray]:
        """Membership of the target and of the arrow for every 8-bit (U, V): uint8 (256, 256).

        Indexed [U, V]; 255 = surely the object, 0 = not it (see `memberships`).
        """
        u, v = np.meshgrid(np.arange(256.0), np.arange(256.0), indexing="ij")
        target, arrow = self.memberships(np.stack([u, v], axis=-1))
        return np.round(target * 255).astype(np.uint8), np.round(arrow * 255).astype(np.uint8)

    def memberships(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(target, arrow) memberships 0..1 at UV points (..., 2), evaluated exactly.

        A colour belongs to the more likely model only (densities compared, Eq. 8), and only
        above the floor; membership then rises linearly and saturates at 10× the floor, so that
        colours of high density (a tight cluster) do not outweigh equally certain colours of a
        broader one (this is what biases a plain likelihood-weighted centroid towards one ring).
        """
        p_target = self.target.density(uv)
        p_arrow = self.arrow.density(uv) if self.arrow else np.zeros_like(p_target)
        ceiling = 10 * self.density_floor

        def membership(p: np.ndarray, other: np.ndarray) -> np.ndarray:
            m = np.clip((p - self.density_floor) / (ceiling - self.density_floor), 0.0, 1.0)
            m[p <= other] = 0.0
            return m

        return membership(p_target, p_arrow), membership(p_arrow, p_target)

    def summary(self) -> dict[str, Any]:
        """Components and BIC per object (for logs and replies)."""

        def one(gmm: Gmm | None) -> dict[str, Any] | None:
            if gmm is None:
                return None
            bic = {str(k): round(v, 2) for k, v in gmm.bic.items()}
            return {"components": gmm.n_components, "bic": bic}

        return {"target": one(self.target), "arrow": one(self.arrow)}

    def to_dict(self) -> dict[str, Any]:
        """The model file's content."""
        return {
            "format": MODEL_FORMAT,
            "version": MODEL_VERSION,
            "colour_space": "UV of YUV (OpenCV RGB2YUV), levels 0..255",
            "density_floor": self.density_floor,
            "target": self.target.to_dict(),
            "arrow": self.arrow.to_dict() if self.arrow else None,
            "white_rgb": list(self.white_rgb) if self.white_rgb is not None else None,
        }

    @classmethod
    def from_dict(cls, data: Any) -> ColourModel:
        """Build from a model file's content.

        Raises:
            ModelFileError: not a colour model, or of another version.
        """
        if not isinstance(data, dict) or data.get("format") != MODEL_FORMAT:
            raise ModelFileError(
                f'not an archery colour model (expected "format": {MODEL_FORMAT!r}); '
                f"make one with `archery calibrate`"
            )
        if data.get("version") != MODEL_VERSION:
            raise ModelFileError(
                f"colour model version {data.get('version')!r} is not supported; this detector "
                f"reads version {MODEL_VERSION}: calibrate again with `archery calibrate`"
            )
        if "target" not in data:
            raise ModelFileError('the model file has no "target" GMM')
        arrow = data.get("arrow")
        try:
            floor = float(data.get("density_floor", 2e-5))
        except (TypeError, ValueError):
            floor = float("nan")
        if not (math.isfinite(floor) and floor > 0):
            raise ModelFileError(
                f"density_floor must be a number > 0, got {data['density_floor']!r}"
            )
        return cls(
            target=Gmm.from_dict(data["target"], "target"),
            arrow=Gmm.from_dict(arrow, "arrow") if arrow is not None else None,
            density_floor=floor,
            white_rgb=_white_from(data.get("white_rgb")),
        )

    def save(self, path: str | Path) -> None:
        """Write the model as JSON."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=1) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> ColourModel:
        """Read a model file; raises ModelFileError when missing or invalid."""
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
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
        white_rgb: np.ndarray | None = None,
    ) -> ColourModel:
        """Fit both GMMs from calibration pixels (N, 3) RGB uint8; `white_rgb` is the
        calibration frame's white (`whitebalance.estimate_white`), None if unknown.

        Raises:
            CalibrationError: too few pixels, or target and arrow colours that overlap so much
                the two objects cannot be told apart.
        """
        target = fit_gmm(
            rgb_to_uv(target_rgb), max_components=max_components, seed=seed, name="target"
        )
        arrow = None
        if arrow_rgb is not None:
            arrow_uv = rgb_to_uv(arrow_rgb)
            arrow = fit_gmm(arrow_uv, max_components=max_components, seed=seed, name="arrow")
            confused = float(np.mean(target.density(arrow_uv) >= arrow.density(arrow_uv)))
            if confused > 0.2:
                raise CalibrationError(
                    f"{confused:.0%} of the arrow pixels look more like the target than like "
                    f"the arrow (at most 20 % may): the tip needs a colour the target does not "
                    f"have, or the arrow pixels were marked on the target"
                )
        white = None if white_rgb is None else _white_from(list(np.asarray(white_rgb, float)))
        return cls(target=target, arrow=arrow, white_rgb=white)


def _white_from(value: Any) -> tuple[float, float, float] | None:
    """A model's white RGB from its JSON form (None: not recorded).

    Raises:
        ModelFileError: not three numbers in 1..255.
    """
    if value is None:
        return None
    white = finite_vector("white_rgb", value, ModelFileError, unit="8-bit RGB levels")
    if np.any(white < 1.0) or np.any(white > 255.0):
        raise ModelFileError(f"white_rgb must be three numbers in 1..255, got {value!r}")
    red, green, blue = white.tolist()
    return (red, green, blue)
