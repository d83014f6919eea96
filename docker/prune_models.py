"""Remove from an image the icub-models files no process loads: every robot's folder but the
one model the project uses, and every mesh that model's URDF does not name (the package ships
53 MB of meshes for many iCub versions; one model uses about 14 MB).

    python3 docker/prune_models.py iCubGazeboV2_5

Does nothing where icub-models is not installed (an image whose process loads no robot).
"""

from __future__ import annotations

import importlib.util
import pathlib
import re
import shutil
import sys

_MESH = re.compile(r'filename="package://iCub/([^"]+)"')


def prune(model: str) -> int:
    """Remove what `model` does not use; the bytes removed.

    Raises:
        FileNotFoundError: icub-models has no such model (nothing is removed).
    """
    if importlib.util.find_spec("icub_models") is None:
        return 0
    import icub_models

    urdf = pathlib.Path(icub_models.get_model_file(model))
    if not urdf.is_file():
        raise FileNotFoundError(f"icub-models has no model {model!r}: {urdf}")
    share = urdf.parents[2]  # …/share/iCub/robots/<model>/model.urdf → …/share/iCub
    keep = {(share / name).resolve() for name in _MESH.findall(urdf.read_text())}
    missing = [str(p) for p in keep if not p.is_file()]
    if missing:
        raise FileNotFoundError(f"{model}'s URDF names meshes that are not installed: {missing}")
    removed = 0
    for robot in (share / "robots").iterdir():
        if robot.is_dir() and robot.name != model:
            removed += sum(f.stat().st_size for f in robot.rglob("*") if f.is_file())
            shutil.rmtree(robot)
    for mesh in (share / "meshes").rglob("*"):
        if mesh.is_file() and mesh.resolve() not in keep:
            removed += mesh.stat().st_size
            mesh.unlink()
    return removed


def main(argv: list[str]) -> int:
    """`prune_models.py MODEL`: exit 2 when the model is not installed."""
    try:
        removed = prune(argv[0])
    except FileNotFoundError as exc:
        print(f"prune_models.py: {exc}", file=sys.stderr)
        return 2
    print(f"prune_models.py: removed {removed / 1e6:.1f} MB of icub-models", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
