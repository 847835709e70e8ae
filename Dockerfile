# One image for every service of the fleet; the compose file picks the module to run.
# BASE is any Debian-based image with Python 3.11 and its venv module: python:3.11-slim from a registry by
# default; where no registry is reachable, scripts/containers.sh makes localhost/eqa-base:bookworm (debootstrap
# of Debian bookworm, whose python3 is 3.11) and builds with --build-arg BASE=localhost/eqa-base:bookworm.
ARG BASE=python:3.11-slim
FROM ${BASE}

# Where torch's CPU wheel comes from; empty = the pip configuration in effect (scripts/containers.sh mounts the
# host's pip settings, wheel directories and CA bundle into the build, so the host's indexes are used).
ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu

ENV PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    RERUN_TELEMETRY_ENABLED=false \
    HF_HUB_OFFLINE=1 \
    EQA_DATA_DIR=/data \
    NUMBA_CACHE_DIR=/var/cache/eqa-numba \
    VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH

# open3d imports libusb, libgomp, libEGL, libGL and libX11 even without a display.
RUN apt-get update \
 && apt-get install -y --no-install-recommends libusb-1.0-0 libgomp1 libegl1 libgl1 libx11-6 \
 && rm -rf /var/lib/apt/lists/* \
 && python3 -m venv /opt/venv

WORKDIR /app
# Dependencies first (their own layer: a change of code alone does not reinstall them). torch first, pinned
# to the CPU wheel, so nothing pulls a CUDA build.
COPY pyproject.toml ./
RUN pip install ${TORCH_INDEX:+--index-url "$TORCH_INDEX"} torch==2.13.0 \
 && python -c "import tomllib; print('\n'.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']))" \
      > /tmp/requirements.txt \
 && pip install -r /tmp/requirements.txt \
 && rm /tmp/requirements.txt
COPY README.md ./
COPY eqa ./eqa
COPY eqa_app ./eqa_app
COPY services ./services
COPY gateway ./gateway
RUN pip install --no-deps . && rm -rf build \
 && mkdir -p /var/cache/eqa-numba && chmod 1777 /var/cache/eqa-numba \
 && python -c "import services.mapper.tsdf_kernel"  # numba compiles the TSDF kernel into the image

VOLUME ["/data"]
CMD ["python", "-m", "gateway"]
