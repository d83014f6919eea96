#!/usr/bin/env bash
# Builds a local stand-in for the official `python:3.11-slim-bookworm` base image, for machines
# that reach Debian's package mirror but no image registry: a minimal Debian bookworm root file
# system (debootstrap) with Debian's Python 3.11 and pip, imported as one image layer.
#   docker/standin-base.sh [TAG]      (default TAG: archery-base:bookworm)
# Prints the tag on stdout when the image exists (built now or before); logs go to stderr.
set -euo pipefail
tag="${1:-archery-base:bookworm}"
if docker image inspect "$tag" >/dev/null 2>&1; then
    echo "$tag"
    exit 0
fi
command -v debootstrap >/dev/null || {
    echo "standin-base: debootstrap is not installed (apt-get install debootstrap)" >&2
    exit 1
}
root="$(mktemp -d)"
trap 'rm -rf "$root"' EXIT
echo "standin-base: debootstrap bookworm into $root (a few minutes)" >&2
debootstrap --variant=minbase --include=python3,python3-pip,python3-venv,ca-certificates \
    bookworm "$root" >&2
# Like the official image: pip may install into the system interpreter, `python` exists.
rm -f "$root"/usr/lib/python3.11/EXTERNALLY-MANAGED
ln -sf /usr/bin/python3 "$root"/usr/local/bin/python
rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/*
tar -C "$root" -c . | docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["python3"]' - "$tag" >&2
echo "$tag"
