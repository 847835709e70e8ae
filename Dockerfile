# One image for every service of the fleet; the compose file picks the module to run.
FROM python:3.11-slim

ENV PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    RERUN_TELEMETRY_ENABLED=false \
    HF_HUB_OFFLINE=1 \
    EQA_DATA_DIR=/data

RUN apt-get update \
 && apt-get install -y --no-install-recommends libusb-1.0-0 libgomp1 \
 && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY pyproject.toml README.md ./
COPY eqa ./eqa
COPY services ./services
COPY gateway ./gateway
# torch first, pinned to the CPU wheel, so nothing pulls a CUDA build.
RUN pip install --index-url https://download.pytorch.org/whl/cpu torch==2.13.0 \
 && pip install .

VOLUME ["/data"]
CMD ["python", "-m", "gateway"]
