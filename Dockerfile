# One image for every vergence process: `vergence <role> ...` (see docker-compose.yml).
#   docker build -t vergence .
#   docker run --rm vergence match --help
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    NUMBA_CACHE_DIR=/var/cache/vergence/numba

# openssl: deploy/make-certs.sh runs in the image too (docker compose run --rm certs);
# libglib2.0-0: needed by some builds of opencv-python-headless
RUN apt-get update \
    && apt-get install -y --no-install-recommends openssl libglib2.0-0 \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /src
COPY pyproject.toml README.md ./
COPY vergence ./vergence
COPY services ./services
RUN pip install . && rm -rf /src

# a non-root user in the dialout group (serial adapters are root:dialout on most hosts);
# the numba cache dir is writable so compiled kernels survive in the numba-cache volume
RUN useradd --uid 10001 --user-group --groups dialout --no-create-home --home-dir /var/lib/vergence vergence \
    && mkdir -p /var/cache/vergence/numba /var/lib/vergence \
    && chown -R vergence:vergence /var/cache/vergence /var/lib/vergence

# the default configs; docker-compose.yml mounts ./deploy over this (with secrets/ from make-certs.sh)
COPY deploy /etc/vergence
WORKDIR /var/lib/vergence
USER vergence
EXPOSE 7447
ENTRYPOINT ["vergence"]
CMD ["up"]
