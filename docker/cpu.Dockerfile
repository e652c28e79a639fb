# handkse CPU image: tracker, kinematics, robot bridge (MuJoCo), router helper, CLI.
# Build from the repository root: docker build -f docker/cpu.Dockerfile -t handkse-cpu .
FROM python:3.11.10-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    MUJOCO_GL=disable

RUN useradd --create-home --uid 10001 --shell /usr/sbin/nologin handkse
WORKDIR /opt/handkse
COPY docker/requirements-cpu.txt ./
RUN pip install --no-cache-dir --requirement requirements-cpu.txt
COPY pyproject.toml README.md NOTICE ./
COPY services ./services
COPY bench ./bench
RUN pip install --no-cache-dir --no-deps . \
    && mkdir -p /var/lib/handkse && chown 10001:10001 /var/lib/handkse

USER 10001
VOLUME ["/var/lib/handkse"]
ENTRYPOINT ["handkse"]
CMD ["--help"]
