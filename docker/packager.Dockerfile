# stgs pack / synth / train: the offline tools (torch on the CPU, PyAV with its own libx265, the native kernels).
# Build from the repository root:  docker build -f docker/packager.Dockerfile -t streamstgs-packager .
# Run:  docker run -v $PWD/work:/work streamstgs-packager pack /work/model /work/dash
# The Ray worker image is this image plus Ray (requirements-ray.lock):
#   docker build -f docker/packager.Dockerfile --target ray-worker -t streamstgs-ray .
# (docker/ray-compose.yaml builds it and runs a Ray head and N workers on one host; docs/SCALING.md).
FROM python:3.11-slim AS packager

RUN apt-get update \
    && apt-get install -y --no-install-recommends g++ \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /app
COPY requirements.lock pyproject.toml README.md ./
RUN pip install --no-cache-dir -r requirements.lock
COPY . .
RUN pip install --no-cache-dir --no-deps --no-build-isolation . \
    && useradd --create-home --uid 10001 stgs
USER stgs
# Compile the native kernels for this image (cached in the user's home).
RUN python -m stgs.native.build
VOLUME ["/work"]
ENTRYPOINT ["stgs"]
CMD ["--help"]

FROM packager AS ray-worker
USER root
RUN pip install --no-cache-dir -r requirements-ray.lock
USER stgs
ENV RAY_USAGE_STATS_ENABLED=0
# `ray start ... --block` (docker/ray-compose.yaml gives the head's and the workers' arguments); the driver runs
# `stgs train|pack ... --ray auto` inside the head container.
ENTRYPOINT ["ray"]
CMD ["--help"]

# The default target: the packager image.
FROM packager
