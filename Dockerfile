# One image for every process of the mesh (docker-compose.yml picks the verb per container).
FROM python:3.11-slim-bookworm
# Mesa's EGL for headless MuJoCo rendering (the camera); PyOpenGL's EGL platform loads GL
# through libOpenGL.so.0 (libopengl0)
RUN apt-get update && apt-get install -y --no-install-recommends libegl1 libegl-mesa0 libgl1-mesa-dri \
    libopengl0 && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY pyproject.toml README.md ./
COPY protocol ./protocol
COPY services ./services
COPY sim ./sim
RUN pip install --no-cache-dir . && mkdir -p /app/runs
ENV MUJOCO_GL=egl PYTHONUNBUFFERED=1
CMD ["archery", "--help"]
