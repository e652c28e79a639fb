# handkse GPU image: camera source + detector on ONNX Runtime with CUDA/TensorRT.
# CUDA and cuDNN come as pip wheels (onnxruntime-gpu[cuda,cudnn]); the host needs only the
# NVIDIA driver and the container toolkit. The hand models are converted at build time from
# the mediapipe wheel on PyPI, so the running container needs no network.
# Build from the repository root: docker build -f docker/gpu.Dockerfile -t handkse-gpu .
FROM python:3.11.10-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    XDG_CACHE_HOME=/opt/handkse/cache

RUN useradd --create-home --uid 10001 --shell /usr/sbin/nologin handkse
WORKDIR /opt/handkse
COPY docker/requirements-gpu.txt ./
RUN pip install --no-cache-dir --requirement requirements-gpu.txt
COPY pyproject.toml README.md NOTICE ./
COPY services ./services
COPY bench ./bench
RUN pip install --no-cache-dir --no-deps . \
    && handkse models prepare \
    && chown -R 10001:10001 /opt/handkse/cache

USER 10001
ENTRYPOINT ["handkse"]
CMD ["detector", "--help"]
