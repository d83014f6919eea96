"""YARP 3.5 for `archery yarp` and its tests, as a user without robotology-superbuild or conda
gets it: unless this Python imports a YARP built with this file's mend, install a wheel built
from PyPI's `yarp-middleware` 3.5.0 source distribution (libraries, device plugins, tools,
Python bindings), cached outside the checkout (`$XDG_CACHE_HOME/archery/yarp`, by default
`~/.cache/archery/yarp`): a machine builds it once (about 7 minutes on 2 cores).

The build edits setup.py's CMake options for Debian 12, GCC 12 and CMake 4 (no ACE; shared
libraries, so that the device plugins exist; the standard headers GCC 12 no longer includes;
the `fakeMotionControl` device, a simulated control board, which needs YARP_math and so Eigen 3:
the build installs `libeigen3-dev` with apt when Eigen is missing and it runs as root; without
root and without Eigen the wheel builds without that device), builds with CMake < 4, makes
the wheel relocatable (`import yarp` points YARP_DATA_DIRS and YARP_PLUGINS_DIR at the package
unless set) and mends YARP's bottle parser: a bottle nested deeper than 64 lists, from the
wire or from text, is read as empty, where YARP 3.5 recursed until its stack overflowed.
Usage: python tools/yarp_wheel.py [--build-only]
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

VERSION = "3.5.0"
SDIST = f"yarp_middleware-{VERSION}.tar.gz"
HEADERS = (
    "utility cstdint limits stdexcept iterator algorithm functional memory string cstring mutex "
    "array cmath"
)
#: setup.py's CMake options: (what it passes, what the build passes instead)
OPTIONS = (
    ('"-DBUILD_SHARED_LIBS:BOOL=OFF",', '"-DBUILD_SHARED_LIBS:BOOL=ON",'),
    (
        '"-DYARP_COMPILE_UNMAINTAINED:BOOL=OFF",',
        '"-DYARP_COMPILE_UNMAINTAINED:BOOL=OFF", "-DSKIP_ACE:BOOL=ON", '
        '"-DENABLE_yarpmod_fakeMotionControl:BOOL=ON", '
        f'"-DCMAKE_CXX_FLAGS={" ".join(f"-include {h}" for h in HEADERS.split())}",',
    ),
)
BOTTLE = "src/libYARP_os/src/yarp/os/impl/BottleImpl.cpp"
SOCKET = "src/libYARP_os/src/yarp/os/impl/SocketTwoWayStream.h"
_DEPTH = """namespace {
// archery: a bottle nested deeper than this is refused (read as empty), not recursed into
constexpr int archeryDepthMost = 64;
thread_local int archeryDepth = 0;
thread_local bool archeryTooDeep = false;
struct ArcheryDepth
{
    yarp::os::impl::BottleImpl* bottle;
    explicit ArcheryDepth(yarp::os::impl::BottleImpl* b) : bottle(b) { ++archeryDepth; }
    bool refused() const
    {
        if (archeryDepth > archeryDepthMost) {
            archeryTooDeep = true;
        }
        return archeryTooDeep;
    }
    ~ArcheryDepth()
    {
        if (--archeryDepth == 0 && archeryTooDeep) {
            archeryTooDeep = false;
            bottle->clear();
        }
    }
};
} // namespace

"""
#: mends to YARP's source: (file, what it holds, what the build puts instead)
MENDS = (
    (
        BOTTLE,
        "void BottleImpl::fromString(const std::string& line)\n{\n",
        _DEPTH + "void BottleImpl::fromString(const std::string& line)\n{\n"
        "    ArcheryDepth archeryGuard(this);\n"
        "    if (archeryGuard.refused()) {\n        clear();\n        return;\n    }\n",
    ),
    (
        BOTTLE,
        "bool BottleImpl::read(ConnectionReader& reader)\n{\n",
        "bool BottleImpl::read(ConnectionReader& reader)\n{\n"
        "    ArcheryDepth archeryGuard(this);\n"
        "    if (archeryGuard.refused()) {\n        return false;\n    }\n",
    ),
    # The authentication's handshake gives a connection 2 s timeouts, then "clears" them by a
    # flag only: the socket keeps SO_RCVTIMEO/SO_SNDTIMEO, and an authenticated connection left
    # idle for 2 s fails (a secure RPC client's next call with it). Cleared on the socket too.
    *(
        (
            SOCKET,
            f"        if (timeout < 1e-12) {{\n            have{kind}Timeout = false;\n",
            f"        if (timeout < 1e-12) {{\n            have{kind}Timeout = false;\n"
            "            struct timeval archeryNone = {0, 0};\n"
            f"            stream.set_option(SOL_SOCKET, {option}, &archeryNone, "
            "sizeof(archeryNone));\n",
        )
        for kind, option in (("Write", "SO_SNDTIMEO"), ("Read", "SO_RCVTIMEO"))
    ),
)
#: where Debian's libeigen3-dev puts Eigen 3's CMake package (YARP_math, fakeMotionControl)
EIGEN = Path("/usr/share/eigen3/cmake/Eigen3Config.cmake")
#: names the build's options and mends: a YARP installed without them is replaced, a wheel cached
#: under another name is built again
MENDED = hashlib.sha256(repr((OPTIONS, MENDS)).encode()).hexdigest()[:12]
PRELUDE = (
    f"archery_mends = {MENDED!r}\n"
    "import os as _os\n"
    "_here = _os.path.dirname(_os.path.abspath(__file__))\n"
    "_os.environ.setdefault('YARP_DATA_DIRS', _os.path.join(_here, 'share', 'yarp'))\n"
    "_os.environ.setdefault('YARP_PLUGINS_DIR', _os.path.join(_here, 'lib', 'yarp'))\n"
    "del _os, _here\n"
)


def say(text: str, started: float) -> None:
    print(f"yarp: {text} ({time.monotonic() - started:.0f} s)", flush=True)


def cache() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "archery" / "yarp"


def importable() -> bool:
    """True when this Python imports a YARP built with this build's mends."""
    check = f"import yarp, sys; sys.exit(getattr(yarp, 'archery_mends', '') != {MENDED!r})"
    found = subprocess.run([sys.executable, "-c", check], capture_output=True)
    return found.returncode == 0


def cached_wheel() -> Path | None:
    tag = f"cp{sys.version_info.major}{sys.version_info.minor}"
    wheels = sorted((cache() / MENDED).glob(f"yarp_middleware-{VERSION}-{tag}-*.whl"))
    return wheels[-1] if wheels else None


def apt_install(packages: list[str], started: float) -> None:
    """Install Debian `packages` with apt-get (as root)."""
    say(f"installing {' and '.join(packages)}", started)
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    subprocess.run(["apt-get", "update", "-qq"], check=True, env=env)
    subprocess.run(["apt-get", "install", "-y", "-qq", *packages], check=True, env=env)


def build(started: float) -> Path:
    """Build the wheel into the cache; its path."""
    can_apt = os.geteuid() == 0 and shutil.which("apt-get") is not None
    if shutil.which("swig") is None or shutil.which("g++") is None:
        if not can_apt:
            sys.exit("yarp: the build needs swig and g++: install them (e.g. apt install swig g++)")
        apt_install(["swig", "g++"], started)
    if not EIGEN.is_file():
        if can_apt:
            apt_install(["libeigen3-dev"], started)
        else:
            say(
                "no Eigen 3 (apt install libeigen3-dev): building without fakeMotionControl",
                started,
            )
    with tempfile.TemporaryDirectory(prefix="yarp-build-") as folder:
        work = Path(folder)
        say(f"downloading yarp-middleware {VERSION}'s source distribution", started)
        pip = [sys.executable, "-m", "pip"]
        subprocess.run(
            [*pip, "download", "-q", "--no-deps", "--no-binary", "yarp-middleware",
             f"yarp-middleware=={VERSION}", "-d", str(work)],
            check=True,
        )  # fmt: skip
        shutil.unpack_archive(work / SDIST, work)
        source = work / SDIST.removesuffix(".tar.gz")
        setup = source / "setup.py"
        text = setup.read_text()
        for old, new in OPTIONS:
            if old not in text:
                sys.exit(f"yarp: unexpected setup.py: no {old}")
            text = text.replace(old, new)
        setup.write_text(text)
        for path, old, new in MENDS:
            code = (source / path).read_text()
            if old not in code:
                sys.exit(f"yarp: unexpected {path}: no {old.splitlines()[0]}")
            (source / path).write_text(code.replace(old, new, 1))
        (work / "constraints.txt").write_text("cmake<4\n")
        env = {
            **os.environ,
            "CMAKE_POLICY_VERSION_MINIMUM": "3.5",
            "PIP_CONSTRAINT": str(work / "constraints.txt"),
            "CMAKE_BUILD_PARALLEL_LEVEL": str(os.cpu_count() or 1),
        }
        say("building YARP (libraries, device plugins, tools, bindings): about 7 minutes", started)
        subprocess.run(
            [*pip, "wheel", "-q", "--no-deps", str(source), "-w", str(work / "dist")],
            check=True,
            env=env,
        )
        wheel = next((work / "dist").glob("yarp_middleware-*.whl"))
        relocate(wheel)
        (cache() / MENDED).mkdir(parents=True, exist_ok=True)
        kept = cache() / MENDED / wheel.name
        shutil.copyfile(wheel, kept)
    say(f"built {kept}", started)
    return kept


def relocate(wheel: Path) -> None:
    """Rewrite `wheel` so that its plugins load wherever it is installed."""
    with zipfile.ZipFile(wheel) as zipped:
        entries = [(info, zipped.read(info.filename)) for info in zipped.infolist()]
    rewritten = []
    for info, data in entries:
        if info.filename == "yarp/__init__.py" and b"YARP_PLUGINS_DIR" not in data:
            data = PRELUDE.encode() + data
        elif info.filename == "yarp/share/yarp/plugins/yarp.ini":
            data = re.sub(rb"(?m)^path .*$", b'path "${YARP_PLUGINS_DIR}"', data)
        rewritten.append((info, data))
    record = next(i.filename for i, _ in rewritten if i.filename.endswith(".dist-info/RECORD"))
    rows = []
    for info, data in rewritten:
        if info.filename != record:
            digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=")
            rows.append(f"{info.filename},sha256={digest.decode()},{len(data)}")
    rows.append(f"{record},,")
    out = wheel.with_suffix(".tmp")
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zipped:
        for info, data in rewritten:
            zipped.writestr(
                info, ("\n".join(rows) + "\n").encode() if info.filename == record else data
            )
    out.replace(wheel)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--build-only", action="store_true", help="build (or find) the wheel only")
    args = parser.parse_args()
    started = time.monotonic()
    if not args.build_only and importable():
        return 0
    wheel = cached_wheel() or build(started)
    if args.build_only:
        print(wheel)
        return 0
    say(f"installing {wheel.name}", started)
    pip = [sys.executable, "-m", "pip", "install", "-q", "--force-reinstall", "--no-deps"]
    subprocess.run([*pip, str(wheel)], check=True)
    return 0 if importable() else 1


if __name__ == "__main__":
    sys.exit(main())
