# stgs pack / synth / train: the offline tools (torch on the CPU, PyAV with its own libx265, the native kernels).
# Build from the repository root:  docker build -f docker/packager.Dockerfile -t streamstgs-packager .
# Run:  docker run -v $PWD/work:/work streamstgs-packager pack /work/model /work/dash
FROM python:3.11-slim

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
