# esrp-eval: an image for evaluation jobs against running esrp-servers. It holds the Python package
# `esrp` with its Gymnasium env and Ray (`pip install ./clients/python[gym,ray]`, in the venv
# /opt/esrp, on PATH: `esrp eval`, `esrp eval --ray`) and the Rust evaluation tool `esrp-eval`
# (docs/evaluation.md). It renders nothing and starts no server: point it at servers
# (`esrp eval --server HOST:PORT`, `esrp eval --ray auto --servers HOST:PORT,...`,
# `esrp-eval --server http://HOST:PORT`).
#
# Targets (docker/README.md has the commands):
#   eval (the default, last)  build esrp-eval from source in a Rust image; install the package and
#                             its dependencies from the package index, pinned by
#                             clients/python/constraints.txt
#   eval-prebuilt             copy wheels and an esrp-eval binary made on the host (ARG WHEELS, a
#                             folder of wheels for CPython 3.11 on x86_64 Linux; ARG EVAL_BINARY):
#                             nothing fetched during the build but Debian packages
#   eval-ray                  `eval` plus what KubeRay expects of a Ray node image: Ray's dashboard
#                             agent (`ray[default]`, whose raylet health endpoint KubeRay's probes
#                             ask with wget) and wget; the image of docker/k8s/ray/rayjob.yaml
# As in server.Dockerfile, the stages are ordered so that `--target eval-prebuilt` needs no Rust image.

ARG BASE=debian:bookworm-slim
ARG BUILDER=rust:1-bookworm

# --- Python 3.11 (Debian's), a venv on PATH, an unprivileged user. ---
FROM ${BASE} AS eval-base
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 python3-venv ca-certificates \
    && rm -rf /var/lib/apt/lists/* \
    && python3 -m venv /opt/esrp \
    && useradd --system --uid 10001 --user-group --home-dir /nonexistent --no-create-home --shell /usr/sbin/nologin esrp
ENV PATH=/opt/esrp/bin:$PATH \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1
WORKDIR /results
ARG BASE
ARG VERSION=dev
LABEL org.opencontainers.image.title="esrp-eval" \
      org.opencontainers.image.description="ESRP evaluation jobs: the Python package esrp (Gymnasium env) and esrp-eval" \
      org.opencontainers.image.licenses="Apache-2.0" \
      org.opencontainers.image.documentation="docker/README.md" \
      org.opencontainers.image.version="${VERSION}" \
      org.opencontainers.image.base.name="${BASE}"

# --- The venv from wheels made on the host, offline. ---
FROM eval-base AS venv-prebuilt
ARG WHEELS=wheels
COPY ${WHEELS} /tmp/wheels
RUN pip install --no-index --find-links /tmp/wheels 'esrp[gym,ray]'

FROM eval-base AS eval-prebuilt
COPY --from=venv-prebuilt /opt/esrp /opt/esrp
ARG EVAL_BINARY=target/release/esrp-eval
COPY ${EVAL_BINARY} /usr/local/bin/esrp-eval
USER 10001:10001
CMD ["esrp-eval", "--help"]

# --- From source. ---
FROM ${BUILDER} AS builder
WORKDIR /src
COPY . .
RUN cargo build --release --locked -p esrp-client --bin esrp-eval \
    && strip --strip-debug -o /esrp-eval target/release/esrp-eval

FROM eval-base AS venv
COPY clients/python /tmp/esrp-python
RUN pip install '/tmp/esrp-python[gym,ray]' -c /tmp/esrp-python/constraints.txt

# --- For KubeRay: Ray's dashboard agent (the raylet health endpoint its probes ask) and wget. ---
FROM eval-base AS eval-ray
RUN apt-get update \
    && apt-get install -y --no-install-recommends wget \
    && rm -rf /var/lib/apt/lists/*
COPY --from=venv /opt/esrp /opt/esrp
COPY clients/python/constraints.txt /tmp/constraints.txt
RUN pip install "ray[default]" -c /tmp/constraints.txt && rm /tmp/constraints.txt
COPY --from=builder /esrp-eval /usr/local/bin/esrp-eval
USER 10001:10001
CMD ["esrp-eval", "--help"]

FROM eval-base AS eval
COPY --from=venv /opt/esrp /opt/esrp
COPY --from=builder /esrp-eval /usr/local/bin/esrp-eval
USER 10001:10001
CMD ["esrp-eval", "--help"]

