# One Dockerfile, one target per process of the mesh, all on one shared base layer (the OS, a
# non-root user and the core every process needs); each target adds only what its process runs:
#   docker build --target controller -t archery-controller .    (router robot camera detector
#                                                                controller learner foxglove)
# docker-compose.yml names one image per target. BASE is the official Python image; a machine
# that reaches no image registry passes a local stand-in (docker/standin-base.sh) as
# --build-arg BASE=... . Needs BuildKit (Docker 23+, or DOCKER_BUILDKIT=1): pip may be given the
# host's CA bundle as the build secret `pip-ca` (--secret id=pip-ca,src=FILE), never a layer.
ARG BASE=python:3.11-slim-bookworm

FROM ${BASE} AS base
ENV PYTHONUNBUFFERED=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_ROOT_USER_ACTION=ignore \
    HOME=/home/archery MPLCONFIGDIR=/tmp/matplotlib
RUN useradd --uid 1000 --user-group --create-home --home-dir /home/archery archery \
    && mkdir -p /app/runs && chown archery:archery /app/runs
WORKDIR /app
COPY pyproject.toml docker/requirements.py docker/prune_models.py docker/install.sh /build/
RUN --mount=type=secret,id=pip-ca sh /build/install.sh

# The project itself, as a wheel (only its code: every dependency is installed above).
FROM base AS wheel
COPY pyproject.toml README.md /src/
COPY archery /src/archery
COPY protocol /src/protocol
COPY mesh /src/mesh
COPY services /src/services
COPY apps /src/apps
COPY sim /src/sim
RUN --mount=type=secret,id=pip-ca sh -c '[ ! -f /run/secrets/pip-ca ] || export PIP_CERT=/run/secrets/pip-ca; \
    python3 -m pip wheel --no-cache-dir --no-deps -w /wheel /src'

FROM base AS router
COPY --from=wheel /wheel /wheel
RUN python3 -m pip install --no-cache-dir --no-deps /wheel/*.whl && rm -rf /wheel
USER archery
CMD ["archery", "router"]

FROM base AS robot
RUN --mount=type=secret,id=pip-ca sh /build/install.sh robot
COPY --from=wheel /wheel /wheel
RUN python3 -m pip install --no-cache-dir --no-deps /wheel/*.whl && rm -rf /wheel
# The robot renders nothing: MuJoCo loads no GL platform
ENV MUJOCO_GL=disable
USER archery
CMD ["archery", "robot"]

FROM base AS camera
# Mesa's EGL for headless MuJoCo rendering; PyOpenGL's EGL platform loads GL through
# libOpenGL.so.0 (libopengl0)
RUN apt-get update && apt-get install -y --no-install-recommends libegl1 libegl-mesa0 \
    libgl1-mesa-dri libopengl0 && apt-get clean && rm -rf /var/lib/apt/lists/*
RUN --mount=type=secret,id=pip-ca sh /build/install.sh camera
COPY --from=wheel /wheel /wheel
RUN python3 -m pip install --no-cache-dir --no-deps /wheel/*.whl && rm -rf /wheel
ENV MUJOCO_GL=egl
USER archery
CMD ["archery", "camera"]

FROM base AS detector
RUN --mount=type=secret,id=pip-ca sh /build/install.sh detector
COPY --from=wheel /wheel /wheel
RUN python3 -m pip install --no-cache-dir --no-deps /wheel/*.whl && rm -rf /wheel
USER archery
CMD ["archery", "detector"]

FROM base AS controller
# Pinocchio's wheels link GNU OpenMP's runtime
RUN apt-get update && apt-get install -y --no-install-recommends libgomp1 \
    && apt-get clean && rm -rf /var/lib/apt/lists/*
RUN --mount=type=secret,id=pip-ca sh /build/install.sh controller
COPY --from=wheel /wheel /wheel
RUN python3 -m pip install --no-cache-dir --no-deps /wheel/*.whl && rm -rf /wheel
USER archery
CMD ["archery", "controller"]

# The learner service and the programs that drive it (`learn`, `demo`, `experiment`, `report`).
FROM base AS learner
RUN --mount=type=secret,id=pip-ca sh /build/install.sh learner
COPY --from=wheel /wheel /wheel
RUN python3 -m pip install --no-cache-dir --no-deps /wheel/*.whl && rm -rf /wheel
USER archery
CMD ["archery", "learner"]

# `archery foxglove` (the compose file's `watch` profile): the robot's 3D records need MuJoCo's
# model, never its rendering
FROM base AS foxglove
RUN --mount=type=secret,id=pip-ca sh /build/install.sh foxglove
COPY --from=wheel /wheel /wheel
RUN python3 -m pip install --no-cache-dir --no-deps /wheel/*.whl && rm -rf /wheel
ENV MUJOCO_GL=disable
USER archery
CMD ["archery", "foxglove"]
