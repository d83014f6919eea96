#!/bin/sh
# Installs the project's core and the named extras' requirements into the image (see
# docker/requirements.py), then drops what no process runs: C++ headers and CMake files that
# Pinocchio's wheels ship for building against them, and others listed below. Where the build passes the host's CA bundle
# as the build secret `pip-ca` (machines whose package index is reached through a proxy with its
# own CA), pip trusts it for this step only: it never enters a layer.
#   install.sh EXTRA...
set -eu
if [ -f /run/secrets/pip-ca ]; then
    export PIP_CERT=/run/secrets/pip-ca
fi
python3 /build/requirements.py /build/pyproject.toml "$@" > /tmp/requirements.txt
touch /tmp/before-install
# A requirement published as source only (movement-primitives, whose setup builds a C extension)
# needs a compiler and Python's headers: installed for this step and removed in it, with binutils
# below, so no layer keeps them.
tools=""
if grep -qi '^movement-primitives' /tmp/requirements.txt; then
    tools="gcc libc6-dev"
    python3 -c 'import os, sysconfig; os.stat(os.path.join(sysconfig.get_paths()["include"], "Python.h"))' \
        2> /dev/null || tools="$tools libpython3-dev"
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends $tools > /dev/null
fi
python3 -m pip install --no-cache-dir --no-compile -r /tmp/requirements.txt
rm /tmp/requirements.txt
site="$(python3 -c 'import numpy, pathlib; print(pathlib.Path(numpy.__file__).parents[1])')"
rm -rf "$site"/cmeel.prefix/include "$site"/cmeel.prefix/lib/cmake "$site"/cmeel.prefix/share/doc
# MuJoCo's desktop GUI (Studio, Dear ImGui, ImPlot) draws no frame of a headless camera; the
# test suites of NumPy and SciPy run no process of the mesh.
rm -rf "$site"/mujoco/experimental "$site"/numpy/*/tests "$site"/numpy/tests \
    "$site"/scipy/tests "$site"/scipy/*/tests "$site"/scipy/*/*/tests
# Of icub-models, only the model the project loads (protocol.robotspec.MODEL_NAME) and its meshes.
python3 /build/prune_models.py iCubGazeboV2_5
# Symbol tables that some wheels leave in their own extension modules (Zenoh's alone holds
# 10 MB): binutils is installed for this step and removed in it, so no layer keeps it. Libraries
# a wheel grafted in (`*.libs/`) are left as they are, and so is every file of an earlier layer
# (rewriting it would copy it into this one).
apt-get update -qq
apt-get install -y -qq --no-install-recommends binutils > /dev/null
find "$site" -name '*.so*' -not -path '*.libs/*' -type f -newer /tmp/before-install \
    -exec strip --strip-unneeded {} +
apt-get purge -y -qq --auto-remove binutils $tools > /dev/null
apt-get clean
rm -rf /var/lib/apt/lists/* /tmp/before-install
# Byte-compile once here: the containers run as a user who cannot write beside the sources.
# (A file that does not compile, such as a package's Python 2 example, is left to the source.)
python3 -m compileall -q -j 0 "$site" > /dev/null || true
