"""The detector's development set: target faces with a known centre, under what changes between
calibration and use (light, camera, angle, arrows in the face, the face cut by the border).

Scenes are drawn faces (a 10-ring face on a textured background, 110–1300 px across) and, when
they are given, the shared photographs of real faces (`photo_scenes`). Each scene is calibrated
once, from pixels marked inside its yellow, red and blue rings, and every change is applied to
its picture with the true centre carried along. Besides single changes, four kinds of face
combine several (the misses of issue 28): cut by the border at a steep angle with arrows;
filling a small picture with a thick shaft across the gold; in bright sun at an angle with many
arrows, their fletchings and shadows; alone on a dark boss, seen from above, in other light.
Everything is deterministic for a seed.

Each case says what a detector must do (`expect`):
- "visible": the centre must be found within 5 % of the blue ring's diameter;
- "hidden": the face is mostly outside the image: "not seen" or a confidence below 0.5;
- "either": partly visible: either, but never a wrong centre with confidence ≥ 0.5.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from archery.services.detector.calibration import sample_pixels
from archery.services.detector.colour_model import ColourModel
from archery.services.detector.detect import WHITE_SIDE, downscale
from archery.services.detector.whitebalance import estimate_white

__all__ = [
    "CHANGES",
    "TOLERANCE",
    "Case",
    "Scene",
    "calibrate",
    "cases",
    "draw_face",
    "drawn_scenes",
    "judge",
    "photo_scenes",
    "ring_marks",
    "white_balance",
]

# ring colours of a 10-ring face (sRGB), outer to inner, two scoring zones each
FACE_COLOURS = [
    (238, 238, 232),  # white
    (30, 30, 32),  # black
    (45, 150, 215),  # blue
    (222, 40, 45),  # red
    (250, 214, 32),  # yellow
]
TOLERANCE = 0.05  # a centre within this fraction of the blue ring's diameter is right
FLETCHING_COLOURS = [(250, 220, 40), (230, 40, 40), (40, 200, 60), (250, 130, 20), (245, 245, 245)]


@dataclass(frozen=True)
class Scene:
    """A picture of a face (RGB uint8), its true centre (px), the blue ring's outer diameter
    (px) and the calibration marks {"target": [[x, y], ...]} on it."""

    name: str
    rgb: np.ndarray
    centre: tuple[float, float]
    diameter: float
    marks: dict[str, list[list[float]]] = field(default_factory=dict)


@dataclass(frozen=True)
class Case:
    """One changed picture of a scene: `kind` and `level` of the change, the image, the true
    centre and blue-ring diameter there (px), and what a detector must do (`expect`)."""

    scene: str
    kind: str
    level: str
    rgb: np.ndarray
    centre: tuple[float, float]
    diameter: float
    expect: str


def ring_marks(
    centre: tuple[float, float], diameter: float, per_ring: int = 40, seed: int = 0
) -> dict[str, list[list[float]]]:
    """Calibration marks inside the yellow, red and blue rings of a frontal face (px), away
    from the ring borders, as a user would click them."""
    rng = np.random.default_rng(seed)
    radius = diameter / 2
    points: list[list[float]] = []
    for inner, outer in ((0.04, 0.28), (0.38, 0.62), (0.72, 0.95)):
        rho = radius * rng.uniform(inner, outer, per_ring)
        phi = rng.uniform(0, 2 * math.pi, per_ring)
        points += [
            [round(centre[0] + r * math.cos(p), 1), round(centre[1] + r * math.sin(p), 1)]
            for r, p in zip(rho, phi, strict=True)
        ]
    return {"target": points}


def _background(shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """A dim textured backdrop (straw, wood, wall): smoothed noise around a brownish grey."""
    height, width = shape
    coarse = rng.normal(0, 1, (max(2, height // 40), max(2, width // 40), 3))
    texture = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    base = np.array([120.0, 108.0, 92.0]) * rng.uniform(0.6, 1.1)
    fine = rng.normal(0, 6, (height, width, 1))
    return np.clip(base + 14 * texture + fine, 0, 255).astype(np.uint8)


def draw_face(image: np.ndarray, centre: tuple[float, float], face_diameter: float) -> float:
    """Draw a 10-ring face (white paper square behind it) in place; returns the blue ring's
    outer diameter (px)."""
    shift = 4
    one = 1 << shift
    c = (round(centre[0] * one), round(centre[1] * one))
    half = 0.55 * face_diameter
    x0, y0 = centre[0] - half, centre[1] - half
    cv2.rectangle(
        image,
        (round(x0 * one), round(y0 * one)),
        (round((x0 + 2 * half) * one), round((y0 + 2 * half) * one)),
        (246, 246, 242),
        -1,
        cv2.LINE_AA,
        shift,
    )
    line = max(1, round(face_diameter / 500))
    for zone in range(10):
        radius = face_diameter / 2 * (10 - zone) / 10
        colour = FACE_COLOURS[zone // 2]
        axes = (round(radius * one), round(radius * one))
        cv2.ellipse(image, c, axes, 0, 0, 360, colour, -1, cv2.LINE_AA, shift)
        border = (60, 60, 60) if zone // 2 != 1 else (200, 200, 200)
        cv2.ellipse(image, c, axes, 0, 0, 360, border, line, cv2.LINE_AA, shift)
    return face_diameter * 0.6


def drawn_scenes(seed: int = 0) -> list[Scene]:
    """Drawn faces 110, 350, 650 px across in 1280×720 frames, 1300 px in a 1920×1440 one and
    100 px in a 2400×1800 one (a phone photo of a distant face)."""
    rng = np.random.default_rng(seed)
    scenes = []
    for name, (width, height), face in (
        ("drawn-110", (1280, 720), 110.0),
        ("drawn-350", (1280, 720), 350.0),
        ("drawn-650", (1280, 720), 650.0),
        ("drawn-1300", (1920, 1440), 1300.0),
        ("drawn-100-in-2400", (2400, 1800), 100.0),
    ):
        image = _background((height, width), rng)
        centre = (
            float(width / 2 + rng.uniform(-0.25, 0.25) * (width - 1.1 * face)),
            float(height / 2 + rng.uniform(-0.25, 0.25) * (height - 1.1 * face)),
        )
        diameter = draw_face(image, centre, face)
        marks = ring_marks(centre, diameter, seed=int(rng.integers(1 << 30)))
        scenes.append(Scene(name, image, centre, diameter, marks))
    return scenes


def photo_scenes(folder: str | Path) -> list[Scene]:
    """The photographs `target-N.jpg` of `folder` with their `target-N.json` truth; marks from
    the file when it has them, else drawn inside the rings from the truth. Empty if absent."""
    scenes = []
    for truth_path in sorted(Path(folder).glob("target-*.json")):
        truth = json.loads(truth_path.read_text())
        bgr = cv2.imread(str(truth_path.with_name(truth["image"])), cv2.IMREAD_COLOR)
        if bgr is None:
            continue
        centre = (float(truth["centre_px"][0]), float(truth["centre_px"][1]))
        diameter = float(truth["blue_ring_outer_diameter_px"])
        marks = truth.get("calibration") or ring_marks(centre, diameter)
        rgb = np.ascontiguousarray(bgr[:, :, ::-1])
        scenes.append(Scene(truth_path.stem, rgb, centre, diameter, {"target": marks["target"]}))
    return scenes


# -- the changes ----------------------------------------------------------------------------


def _linear(rgb: np.ndarray) -> np.ndarray:
    return (rgb.astype(np.float32) / 255.0) ** 2.2


def _encode(linear: np.ndarray) -> np.ndarray:
    return (np.clip(linear, 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)


def _blackbody(kelvin: float) -> np.ndarray:
    """Approximate sRGB colour (0..255) of a black body at `kelvin` K."""
    t = kelvin / 100
    r = 255.0 if t <= 66 else 329.698727446 * (t - 60) ** -0.1332047592
    g = (
        99.4708025861 * math.log(t) - 161.1195681661
        if t <= 66
        else 288.12216 * (t - 60) ** -0.07551
    )
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.5177312231 * math.log(t - 10) - 305.04479)
    return np.clip([r, g, b], 1, 255)


def white_balance(rgb: np.ndarray, kelvin: float, reference: float = 5500.0) -> np.ndarray:
    """The picture as lit by a black body of `kelvin` K instead of `reference` K (von Kries
    gains in linear light, luminance kept)."""
    gains = (_blackbody(kelvin) / 255) ** 2.2 / (_blackbody(reference) / 255) ** 2.2
    gains /= float(gains @ np.array([0.2126, 0.7152, 0.0722]))
    return _encode(_linear(rgb) * gains.astype(np.float32))


def _jpeg(rgb: np.ndarray, quality: int) -> np.ndarray:
    ok, data = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError(f"JPEG encoding at quality {quality} failed")
    return np.ascontiguousarray(cv2.imdecode(data, cv2.IMREAD_COLOR)[:, :, ::-1])


def _tilt(
    scene: Scene, degrees: float, axis: str, shift: float = 0.0
) -> tuple[np.ndarray, tuple[float, float], float]:
    """The face turned by `degrees` about its vertical ("y") or horizontal ("x") axis through
    its centre, seen by a pinhole camera of focal length = image width, then the picture
    moved `shift` px sideways (beyond the scene: dark): image, centre, the
    blue ring's equivalent diameter (px, √ of the imaged area's scale)."""
    height, width = scene.rgb.shape[:2]
    focal = float(width)
    t = math.radians(degrees)
    if axis == "y":
        rotation = np.array(
            [[math.cos(t), 0, math.sin(t)], [0, 1, 0], [-math.sin(t), 0, math.cos(t)]]
        )
    else:
        rotation = np.array(
            [[1, 0, 0], [0, math.cos(t), -math.sin(t)], [0, math.sin(t), math.cos(t)]]
        )
    principal = np.array([width / 2, height / 2])
    offset = np.asarray(scene.centre) - principal
    camera = np.array([[focal, 0, principal[0]], [0, focal, principal[1]], [0, 0, 1]])
    plane = np.stack([rotation[:, 0], rotation[:, 1], [offset[0], offset[1], focal]], axis=1)
    to_plane = np.array([[1, 0, -scene.centre[0]], [0, 1, -scene.centre[1]], [0, 0, 1]])
    moved = np.array([[1.0, 0.0, shift], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    homography = moved @ camera @ plane @ to_plane
    warped = cv2.warpPerspective(
        scene.rgb,
        homography,
        (width, height),
        flags=cv2.INTER_AREA,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(20, 20, 20),
    )
    centre = homography @ np.array([scene.centre[0], scene.centre[1], 1.0])
    centre = centre[:2] / centre[2]
    # local area scale of the map at the centre: |det J| = det(H)/w³ for H normalised
    h = homography / homography[2, 2]
    w = float(h[2] @ np.array([scene.centre[0], scene.centre[1], 1.0]))
    scale = math.sqrt(abs(np.linalg.det(h)) / w**3)
    return warped, (float(centre[0]), float(centre[1])), scene.diameter * scale


def _arrows(scene: Scene, count: int, rng: np.random.Generator, shadow: float = 0.0) -> np.ndarray:
    """`count` arrows stuck in and around the yellow: dark or metal shafts leaving the face
    obliquely, with coloured fletchings and nocks (px sizes from the ring diameter); with
    `shadow` > 0, each shaft casts a hard shadow (sunlight) that far off, in blue radii."""
    image = scene.rgb.copy()
    radius = scene.diameter / 2
    width = max(2, round(radius / 45))
    arrows = []
    for _ in range(count):
        rho, phi = radius * rng.uniform(0.0, 0.36), rng.uniform(0, 2 * math.pi)
        tip = np.array(scene.centre) + rho * np.array([math.cos(phi), math.sin(phi)])
        heading = rng.uniform(0, 2 * math.pi)
        direction = np.array([math.cos(heading), math.sin(heading)])
        length = radius * rng.uniform(0.45, 0.9)
        shaft = (40, 40, 44) if rng.random() < 0.6 else (175, 175, 180)
        colour = FLETCHING_COLOURS[int(rng.integers(len(FLETCHING_COLOURS)))]
        arrows.append((tip, direction, length, shaft, colour))
    if shadow:
        dark = np.zeros(image.shape[:2], np.uint8)
        away = shadow * radius * np.array([0.6, 0.8])
        for tip, direction, length, _, _ in arrows:
            cv2.line(dark, _pt(tip), _pt(tip + length * direction + away), 1, width, cv2.LINE_AA)
        image = np.where(dark[:, :, None] > 0, _encode(_linear(image) * 0.3), image)
    for tip, direction, length, shaft, colour in arrows:
        end = tip + length * direction
        cv2.line(image, _pt(tip), _pt(end), shaft, width, cv2.LINE_AA)
        normal = np.array([-direction[1], direction[0]])
        vane = radius * 0.09
        for side in (-1.0, 1.0):
            base0 = end - 0.3 * length * direction
            poly = np.array([base0, end - 0.05 * length * direction, end + side * vane * normal])
            cv2.fillPoly(image, [np.round(poly).astype(np.int32)], colour, cv2.LINE_AA)
        cv2.circle(image, _pt(end), width + 1, colour, -1, cv2.LINE_AA)
    return image


def _pt(p: np.ndarray) -> tuple[int, int]:
    return round(float(p[0])), round(float(p[1]))


def _cut(scene: Scene, inside: float) -> tuple[np.ndarray, tuple[float, float], str]:
    """The picture shifted so the face centre lies `inside`·(blue radius) from the left border
    (negative: outside the image); the rest is padded by repeating the border."""
    x = inside * scene.diameter / 2
    dx = x - scene.centre[0]
    shift = np.array([[1.0, 0.0, dx], [0.0, 1.0, 0.0]])
    height, width = scene.rgb.shape[:2]
    moved = cv2.warpAffine(scene.rgb, shift, (width, height), borderMode=cv2.BORDER_REPLICATE)
    expect = "visible" if inside >= 0.7 else ("hidden" if inside <= -0.2 else "either")
    return moved, (scene.centre[0] + dx, scene.centre[1]), expect


# kind → levels; each level is applied by `_apply`
CHANGES: dict[str, list[Any]] = {
    "none": [""],
    "exposure": [0.4, 0.6, 1.6, 2.5],
    "gamma": [0.6, 1.6],
    "white balance": [3000, 4000, 6500, 7500],
    "jpeg": [30, 60, 95],
    "blur": [1.5, 3.0],
    "noise": [8.0, 16.0],
    "perspective": [("y", 30), ("y", 50), ("x", 50), ("y", -40)],
    "arrows": [3, 6, 10],
    "border": [0.8, 0.3, -0.4],
    "shadow": [0.5, 0.25],
    "distractors": [3, 6],
    "combined": ["warm, tilted, arrows, JPEG", "dim, cold, noisy, blurred"],
    # issue 28's four kinds of face, each at several settings
    "cut, steep, arrows": [("y", 55, 0.6), ("y", -60, 0.75), ("x", 60, 0.5)],
    "fills the frame": [0.8, 1.1, 1.4],
    "sunlit, angled, arrows": [("y", 40, 12), ("x", -45, 16), ("y", -50, 20)],
    "dark boss, from above": [(50, 3200, 0.7), (60, 7000, 1.3), (45, 4000, 0.45)],
}


def _shadow(scene: Scene, darkest: float) -> np.ndarray:
    """Light falling off across the face, diagonally, from 1 to `darkest` (linear light)."""
    height, width = scene.rgb.shape[:2]
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    across = ((x - scene.centre[0]) + (y - scene.centre[1])) / (math.sqrt(2) * scene.diameter)
    light = 1.0 - (1.0 - darkest) * np.clip(across + 0.5, 0.0, 1.0)
    return _encode(_linear(scene.rgb) * light[:, :, None])


def _distractors(scene: Scene, count: int, rng: np.random.Generator) -> np.ndarray:
    """Up to `count` blobs in the face's own colours (discs, squares, a letter's bar), each as
    large as a ring, around the face but off it (the scene's logo, a pin, a bag)."""
    image = scene.rgb.copy()
    height, width = image.shape[:2]
    face = scene.diameter / 0.6 / 2  # the whole face's radius, px
    for i in range(count):
        size = scene.diameter * rng.uniform(0.15, 0.35)
        colour = FACE_COLOURS[2 + i % 3]
        for _ in range(50):
            x, y = rng.uniform(size, width - size), rng.uniform(size, height - size)
            if math.dist((x, y), scene.centre) > face + 1.5 * size:
                break
        else:
            continue
        if i % 2 == 0:
            cv2.circle(image, _pt(np.array([x, y])), round(size), colour, -1, cv2.LINE_AA)
        else:
            corner = np.array([x - size, y - 0.4 * size])
            far = corner + np.array([2 * size, 0.8 * size])
            cv2.rectangle(image, _pt(corner), _pt(far), colour, -1)
    return image


def _cut_steep(scene: Scene, level: tuple[str, float, float], rng: np.random.Generator) -> Case:
    """Issue 28's first miss: arrows in the face, the face turned steeply (`level`: axis,
    degrees) and cut by the left border, the centre `level[2]`·(the blue ring's imaged
    half-width) inside (the gold, a third of the blue radius, stays in the frame)."""
    axis, degrees, inside = level
    step = Scene(scene.name, _arrows(scene, 5, rng), scene.centre, scene.diameter)
    half_width = 0.5 * scene.diameter * (math.cos(math.radians(degrees)) if axis == "y" else 1.0)
    image, centre, diameter = _tilt(step, degrees, axis, inside * half_width - scene.centre[0])
    name = f"{degrees}° about {axis}, centre {inside} inside"
    return Case(scene.name, "cut, steep, arrows", name, image, centre, diameter, "visible")


def _fills_frame(scene: Scene, fill: float, rng: np.random.Generator) -> Case:
    """Issue 28's second miss: a small picture (shorter side 400 px) the face fills beyond its
    edges, the blue ring `fill` times the shorter side across, one thick arrow shaft lying
    across the gold."""
    side = 400
    height, width = scene.rgb.shape[:2]
    crop = min(scene.diameter / fill, float(min(height, width)))
    scale = side / crop
    offset = rng.uniform(-0.08, 0.08, 2) * side  # the centre a little off the middle
    out_w, out_h = round(side * 4 / 3), side
    matrix = np.array(
        [
            [scale, 0.0, out_w / 2 + offset[0] - scale * scene.centre[0]],
            [0.0, scale, out_h / 2 + offset[1] - scale * scene.centre[1]],
        ]
    )
    image = cv2.warpAffine(
        scene.rgb, matrix, (out_w, out_h), flags=cv2.INTER_AREA, borderMode=cv2.BORDER_REPLICATE
    )
    centre = (out_w / 2 + float(offset[0]), out_h / 2 + float(offset[1]))
    diameter = scene.diameter * scale
    yellow = diameter / 3  # the gold's diameter, px
    heading = rng.uniform(0, math.pi)
    direction = np.array([math.cos(heading), math.sin(heading)])
    near = np.array(centre) + rng.uniform(-0.25, 0.25) * yellow * direction[::-1] * [1, -1]
    start, end = near - 2.5 * yellow * direction, near + 2.5 * yellow * direction
    cv2.line(image, _pt(start), _pt(end), (48, 44, 40), max(3, round(0.14 * yellow)), cv2.LINE_AA)
    return Case(scene.name, "fills the frame", f"{fill}", image, centre, diameter, "visible")


def _glare(rgb: np.ndarray, centre: tuple[float, float], radius: float) -> np.ndarray:
    """Sunlight's sheen on the paper: a soft bright patch of `radius` px beside `centre`,
    washing colours towards white (linear light)."""
    height, width = rgb.shape[:2]
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    spot = np.exp(-((x - centre[0] - radius) ** 2 + (y - centre[1] + radius) ** 2) / radius**2)
    linear = _linear(rgb)
    return _encode(linear + 0.3 * spot[:, :, None] * (1.0 - linear))


def _sunlit(scene: Scene, level: tuple[str, float, int], rng: np.random.Generator) -> Case:
    """Issue 28's third miss: a face in bright sun (×1.3 light at 6000 K, a sheen, the shafts'
    hard shadows), turned by `level` degrees about its axis, with many arrows and fletchings;
    the calibration is the scene's own, indoors: another picture of the same face."""
    axis, degrees, count = level
    step = _arrows(scene, count, rng, shadow=0.12)
    bright = white_balance(_encode(_linear(step) * 1.3), 6000)
    lit = Scene(scene.name, _glare(bright, scene.centre, 0.4 * scene.diameter), scene.centre,
                scene.diameter)  # fmt: skip
    image, centre, diameter = _tilt(lit, degrees, axis)
    name = f"{degrees}° about {axis}, {count} arrows"
    return Case(scene.name, "sunlit, angled, arrows", name, _jpeg(image, 85), centre, diameter,
                "visible")  # fmt: skip


def _dark_boss(scene: Scene, level: tuple[float, int, float], rng: np.random.Generator) -> Case:
    """Issue 28's fourth miss: the round face alone on a dark boss (straw or foam, almost
    black), seen from above (`level`: degrees about the horizontal axis), in other light than
    the calibration's (`level`: kelvin, exposure)."""
    degrees, kelvin, exposure = level
    height, width = scene.rgb.shape[:2]
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    face = scene.diameter / 0.6 / 2  # the whole face's radius, px
    outside = np.hypot(x - scene.centre[0], y - scene.centre[1]) > 1.02 * face
    boss = _background((height, width), rng).astype(np.float32) * 0.28
    image = scene.rgb.copy()
    image[outside] = boss[outside].astype(np.uint8)
    lit = white_balance(_encode(_linear(image) * exposure), kelvin)
    seen, centre, diameter = _tilt(Scene(scene.name, lit, scene.centre, scene.diameter),
                                   degrees, "x")  # fmt: skip
    name = f"{degrees}° from above, {kelvin} K, ×{exposure}"
    return Case(scene.name, "dark boss, from above", name, seen, centre, diameter, "visible")


def _combined(scene: Scene, name: str, rng: np.random.Generator) -> Case:
    """Several changes at once: "warm, tilted, arrows, JPEG" (6 arrows, 40° about the
    vertical, 3200 K, quality 60) or "dim, cold, noisy, blurred" (×0.5, 7000 K, noise σ 10,
    blur σ 1.2)."""
    if name.startswith("warm"):
        step = Scene(scene.name, _arrows(scene, 6, rng), scene.centre, scene.diameter)
        tilted, centre, diameter = _tilt(step, 40, "y")
        image = _jpeg(white_balance(tilted, 3200), 60)
    else:
        centre, diameter = scene.centre, scene.diameter
        image = white_balance(_encode(_linear(scene.rgb) * 0.5), 7000)
        noisy = image.astype(np.float32) + rng.normal(0, 10, image.shape).astype(np.float32)
        image = cv2.GaussianBlur(np.clip(noisy, 0, 255).astype(np.uint8), (0, 0), 1.2)
    return Case(
        scene.name, "combined", name, np.ascontiguousarray(image), centre, diameter, "visible"
    )


_MISSES = {
    "cut, steep, arrows": _cut_steep,
    "fills the frame": _fills_frame,
    "sunlit, angled, arrows": _sunlit,
    "dark boss, from above": _dark_boss,
}


def _apply(scene: Scene, kind: str, level: Any, rng: np.random.Generator) -> Case:
    image, centre, diameter, expect = scene.rgb, scene.centre, scene.diameter, "visible"
    if kind == "exposure":
        image = _encode(_linear(image) * level)
    elif kind == "gamma":
        image = (((image / 255.0) ** level) * 255 + 0.5).astype(np.uint8)
    elif kind == "white balance":
        image = white_balance(image, level)
    elif kind == "jpeg":
        image = _jpeg(image, level)
    elif kind == "blur":
        image = cv2.GaussianBlur(image, (0, 0), level)
    elif kind == "noise":
        noisy = image.astype(np.float32) + rng.normal(0, level, image.shape).astype(np.float32)
        image = np.clip(noisy, 0, 255).astype(np.uint8)
    elif kind == "perspective":
        image, centre, diameter = _tilt(scene, level[1], level[0])
        level = f"{level[1]}° about {level[0]}"
    elif kind == "arrows":
        image = _arrows(scene, level, rng)
    elif kind == "border":
        image, centre, expect = _cut(scene, level)
    elif kind == "shadow":
        image = _shadow(scene, level)
    elif kind == "distractors":
        image = _distractors(scene, level, rng)
    elif kind == "combined":
        return _combined(scene, level, rng)
    elif kind in _MISSES:
        return _MISSES[kind](scene, level, rng)
    return Case(scene.name, kind, str(level), np.ascontiguousarray(image), centre, diameter, expect)


def cases(scene: Scene, seed: int = 0, kinds: list[str] | None = None) -> Iterator[Case]:
    """Every change of `CHANGES` (or of `kinds`) applied to one scene, in order."""
    rng = np.random.default_rng(seed)
    for kind, levels in CHANGES.items():
        if kinds is not None and kind not in kinds:
            continue
        for level in levels:
            yield _apply(scene, kind, level, rng)


def calibrate(scene: Scene, seed: int = 0) -> ColourModel:
    """The scene's colour model: its marked pixels and its white (`ColourModel.fit`)."""
    pixels = sample_pixels(scene.rgb, scene.marks["target"], "target")
    white = estimate_white(downscale(scene.rgb, WHITE_SIDE)[0])
    return ColourModel.fit(pixels, seed=seed, white_rgb=white)


def judge(case: Case, px: tuple[float, float] | None, confidence: float) -> str:
    """ "right" (within 5 % of the blue ring's diameter), "wrong" (farther, with confidence ≥
    0.5), "unsure" (farther, or not seen, below 0.5)."""
    if px is not None and math.dist(px, case.centre) <= TOLERANCE * case.diameter:
        return "right"
    return "wrong" if px is not None and confidence >= 0.5 else "unsure"
