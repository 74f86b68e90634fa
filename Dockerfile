# quietframe denoising service. Two stages:
#   build   – compiles the onnxruntime custom-op library and the wheel (C++ toolchain, CMake)
#   runtime – slim Python with onnxruntime and the wheel (models baked in); no torch, no compiler
# Build: docker build -t quietframe .        Run: docker run -p 8000:8000 quietframe
# Configure with QUIETFRAME_* environment variables (docs/configuration.md), e.g.
#   docker run -p 8000:8000 -e QUIETFRAME_AUTH_TOKEN=… -e QUIETFRAME_STATE_DIR=/state -v qf:/state quietframe
# tests/deploy/test_docker.py runs this file's pip commands, CMD and HEALTHCHECK in a fresh
# virtualenv.

ARG PYTHON_VERSION=3.11

FROM python:${PYTHON_VERSION}-slim-bookworm AS build
# -march of the op library: x86-64-v3 (AVX2+FMA) as in CMakeLists; x86-64 for older CPUs.
ARG OPS_ARCH=x86-64-v3
RUN apt-get update \
    && apt-get install -y --no-install-recommends g++ \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY pyproject.toml README.md LICENSE NOTICE.md ./
COPY model model
COPY scenes scenes
COPY export export
COPY runtime runtime
COPY service service
COPY client client
COPY wire wire
COPY bench bench
COPY experiments experiments
COPY models models
# The op library is built only on request (pyproject.toml); scikit-build-core then fetches
# CMake and Ninja from PyPI into the isolated build environment.
ENV QUIETFRAME_BUILD_OPS=1
RUN python -m pip wheel --no-cache-dir --no-deps --wheel-dir /wheels \
    --config-settings=cmake.define.QUIETFRAME_ARCH=${OPS_ARCH} .

FROM python:${PYTHON_VERSION}-slim-bookworm AS runtime
ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PATH=/opt/quietframe/bin:$PATH \
    QUIETFRAME_LOG_JSON=true \
    QUIETFRAME_SESSION_TTL_S=900
RUN groupadd --system --gid 10001 quietframe \
    && useradd --system --uid 10001 --gid 10001 --create-home --home-dir /var/lib/quietframe quietframe
COPY --from=build /wheels /wheels
RUN python -m venv /opt/quietframe \
    && /opt/quietframe/bin/python -m pip install --no-cache-dir "$(ls /wheels/quietframe-*.whl)[serve]" \
    && rm -rf /wheels
USER 10001:10001
WORKDIR /var/lib/quietframe
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request as u; sys.exit(u.urlopen('http://127.0.0.1:8000/readyz', timeout=4).status != 200)"]
CMD ["quietframe", "serve", "--host", "0.0.0.0", "--port", "8000"]
