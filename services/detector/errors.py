"""Errors of the colour model and the detector, with their RPC codes."""

from __future__ import annotations

from archery.protocol.errors import ArcheryError, BadRequest

__all__ = ["CalibrationError", "DetectorError", "ImageError", "ModelFileError", "NoLanding"]


class DetectorError(ArcheryError):
    """Base of the detector's errors."""

    code = "detector_error"


class CalibrationError(DetectorError, BadRequest):
    """Calibration pixels that cannot give a model (too few, outside the image, ambiguous)."""

    code = "bad_calibration"


class ModelFileError(DetectorError, ValueError):
    """A colour model file that is missing, malformed or of another version."""

    code = "bad_model"


class ImageError(DetectorError, BadRequest):
    """An image of the wrong type, shape or size."""

    code = "bad_image"


class NoLanding(DetectorError):
    """No landing seen within a measurement's timeout: no new object since the baseline, or
    a picture that never came to rest; the message says how long, how many frames, the
    largest change seen and whether the picture was moving."""

    code = "no_landing"
