# rsucal: the roadside camera calibration daemon as a container (deploy/README.md, "Container").
#   docker build -t rsucal .
#   docker run -d -v rsucal-state:/var/lib/rsucal -v $PWD/rsu.yaml:/etc/rsucal/rsu.yaml:ro rsucal
# Other subcommands: docker run --rm --entrypoint rsucal rsucal simulate --out /tmp/sim
# Two stages: the builder installs rsucal with the README's own install step (tests/deploy/test_dockerfile.py
# keeps them identical, so CI proves the step); the runtime copies only the resulting virtual environment.

FROM python:3.11-slim AS builder
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PYTHONDONTWRITEBYTECODE=1
WORKDIR /src
COPY pyproject.toml README.md ./
COPY schemas ./schemas
COPY pipeline ./pipeline
COPY sim ./sim
COPY daemon ./daemon
# Every dependency ships binary wheels for linux x86_64 and aarch64: no compiler in either stage.
RUN python3 -m venv /opt/rsucal && . /opt/rsucal/bin/activate && pip install .
# The installer itself is not needed at run time.
RUN /opt/rsucal/bin/python -m pip uninstall --yes pip setuptools wheel

FROM python:3.11-slim AS runtime
LABEL org.opencontainers.image.title="rsucal" \
      org.opencontainers.image.description="Automatic geo-referenced calibration of roadside-unit cameras"
ENV PATH=/opt/rsucal/bin:$PATH PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1
# A fixed uid/gid, so a bind-mounted state directory can be chown'ed to it (chown 10001:10001 DIR).
RUN groupadd --system --gid 10001 rsucal \
    && useradd --system --uid 10001 --gid rsucal --home-dir /var/lib/rsucal --no-create-home \
       --shell /usr/sbin/nologin rsucal \
    && install -d -o rsucal -g rsucal -m 0750 /var/lib/rsucal \
    && install -d -m 0755 /etc/rsucal
COPY --from=builder /opt/rsucal /opt/rsucal
# Reference files only: the site's rsu.yaml (and TLS material) are mounted by the operator.
COPY deploy/rsu.example.yaml /etc/rsucal/rsu.example.yaml
COPY deploy/zenoh /etc/rsucal/zenoh
USER rsucal:rsucal
WORKDIR /var/lib/rsucal
VOLUME ["/var/lib/rsucal"]
# 7447: Zenoh. The daemon's default listener is loopback only: publish it with zenoh.listen tcp/0.0.0.0:7447
# (or tls/...) in rsu.yaml, or run as a client of a router (deploy/compose.yaml).
EXPOSE 7447
# Healthy = the daemon answers its health queryable. Start period: job workers warm up at start.
HEALTHCHECK --interval=30s --timeout=10s --start-period=60s --retries=3 \
    CMD ["rsucal", "status", "--connect", "tcp/127.0.0.1:7447", "--timeout", "3"]
# SIGTERM: the daemon finishes the open recording and persists its state (docker stop waits 10 s).
STOPSIGNAL SIGTERM
ENTRYPOINT ["rsucal", "daemon", "--config", "/etc/rsucal/rsu.yaml"]
