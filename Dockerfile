# rsucal: roadside camera calibration daemon. First working image; hardened multi-stage build follows with
# the deployment issue. Build: docker build -t rsucal . ; run: docker run --rm rsucal simulate --out /tmp/sim
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 PIP_NO_CACHE_DIR=1
WORKDIR /opt/rsucal
COPY pyproject.toml README.md ./
COPY schemas ./schemas
COPY pipeline ./pipeline
COPY daemon ./daemon
RUN pip install . && useradd --system --create-home rsucal
USER rsucal
WORKDIR /home/rsucal
ENTRYPOINT ["rsucal"]
CMD ["--help"]
