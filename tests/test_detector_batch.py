"""`archery calibrate` / `archery detect IMAGE...` on drawn faces: one JSON line per image with
its name and rings, a progress bar on stderr, unreadable images named, overlays per image."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import archery
from tests.devset import cases, drawn_scenes


def _write(path: Path, rgb: np.ndarray) -> str:
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[:, :, ::-1]))
    return str(path)


def test_calibrate_once_then_detect_many(tmp_path: Path) -> None:
    scene = drawn_scenes()[1]
    image = _write(tmp_path / "calibration.png", scene.rgb)
    pixels = tmp_path / "pixels.json"
    pixels.write_text(json.dumps(scene.marks))
    model = tmp_path / "model.json"
    done = archery("calibrate", image, "--pixels", str(pixels), "--out", str(model))
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["target"]["components"] >= 3 and len(summary["white_rgb"]) == 3
    changed = list(cases(scene, kinds=["white balance", "arrows"]))
    paths = [_write(tmp_path / f"case-{i}.png", c.rgb) for i, c in enumerate(changed)]
    missing = str(tmp_path / "missing.jpg")
    overlays = tmp_path / "overlays"
    overlays.mkdir()
    done = archery(
        "detect", *paths[:3], missing, *paths[3:], "--model", str(model), "--overlay", str(overlays)
    )
    assert done.returncode == 2  # one image could not be read; the others were measured
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    assert [line["image"] for line in lines] == [*paths[:3], missing, *paths[3:]]
    assert "no such file" in lines[3]["error"] and "missing.jpg" in done.stderr
    del lines[3]
    for line, case in zip(lines, changed, strict=True):
        assert math.dist(line["target"]["px"], case.centre) < 0.05 * case.diameter, line
        assert line["target"]["confidence"] >= 0.5 and line["rings"]
        outer = line["rings"][-1]
        assert np.mean(outer["axes_px"]) == pytest.approx(case.diameter, rel=0.05)
    assert "8/8" in done.stderr  # the progress bar reached the end
    assert sorted(p.name for p in overlays.iterdir()) == sorted(
        f"{Path(p).stem}.png" for p in paths
    )
    picture = cv2.imread(str(overlays / "case-0.png"))
    assert picture.shape[0] == scene.rgb.shape[0] and picture.shape[1] > 2 * scene.rgb.shape[1]


def test_batch_input_mistakes_are_one_line_and_exit_2(tmp_path: Path) -> None:
    scene = drawn_scenes()[0]
    image = _write(tmp_path / "a.png", scene.rgb)
    done = archery("detect", image, image, "--model", str(tmp_path / "none.json"))
    assert done.returncode == 2 and done.stdout == ""
    assert "cannot read colour model" in done.stderr and "Traceback" not in done.stderr
    pixels = tmp_path / "pixels.json"
    pixels.write_text(json.dumps(scene.marks))
    model = tmp_path / "model.json"
    assert archery("calibrate", image, "--pixels", str(pixels), "--out", str(model)).returncode == 0
    done = archery(
        "detect", image, image, "--model", str(model), "--overlay", str(tmp_path / "x.png")
    )
    assert (
        done.returncode == 2
        and "must be a folder" in done.stderr
        and "Traceback" not in done.stderr
    )
    done = archery("detect", "--model", str(model))
    assert done.returncode == 2 and "Traceback" not in done.stderr
    done = archery("detect", str(tmp_path), "--model", str(model))
    assert done.returncode == 2 and "a folder, not a file" in done.stderr
    done = archery("detect", image, image, "--model", str(model), "--no-progress")
    assert done.returncode == 0 and done.stderr == "" and len(done.stdout.splitlines()) == 2
    overlays = tmp_path / "overlays"
    overlays.mkdir()
    done = archery("detect", image, image, "--model", str(model), "--overlay", str(overlays))
    assert done.returncode == 0 and sorted(p.name for p in overlays.iterdir()) == [
        "a-2.png",
        "a.png",
    ]
