# esrp-server: the ESRP environment server in a slim Debian image that renders on Mesa's CPU
# renderers (llvmpipe through EGL, lavapipe through Vulkan), or on an NVIDIA GPU when the container
# is started with one (`docker run --gpus all`, the NVIDIA Container Toolkit).
#
# Targets (docker/README.md has the commands):
#   runtime (the default, last)  build the server from source in a Rust image, copy it into the runtime
#   runtime-prebuilt             copy a binary built on the host (ARG BINARY, a path in the build
#                                context): no Rust toolchain needed in the build, only Debian packages
#
# The stages are ordered so that `--target runtime-prebuilt` never needs the Rust builder image:
# Docker's classic builder runs every stage above the target, BuildKit only those it uses.

ARG BASE=debian:bookworm-slim
ARG BUILDER=rust:1-bookworm

# --- The runtime: Debian slim, Mesa's CPU renderers, the Vulkan loader, an unprivileged user. ---
FROM ${BASE} AS runtime-base
# libegl1 + libegl-mesa0 + libgl1-mesa-dri: OpenGL through EGL, with llvmpipe on the CPU (the
# server's choice without a GPU); mesa-vulkan-drivers: lavapipe; libvulkan1: the Vulkan loader, which
# also finds the NVIDIA driver that the Container Toolkit mounts when there is a GPU.
RUN apt-get update \
    && apt-get install -y --no-install-recommends libegl1 libegl-mesa0 libgl1-mesa-dri mesa-vulkan-drivers libvulkan1 \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --system --uid 10001 --user-group --home-dir /nonexistent --no-create-home --shell /usr/sbin/nologin esrp
# ESRP_LISTEN: every interface, inside the container. NODEVICE_SELECT: Mesa's Vulkan device-select
# layer is not loaded (it adds nothing to one device and has crashed in containers).
# NVIDIA_DRIVER_CAPABILITIES: with `--gpus all` (or a Kubernetes GPU), the toolkit mounts the
# driver's Vulkan and EGL libraries (graphics) and nvidia-smi (utility); its default,
# compute,utility, would leave the GPU invisible to the renderer. It is inert without a GPU.
# NO_COLOR: plain log lines (no terminal escapes) in `docker logs`; ESRP_LOG_FORMAT=json for JSON.
# ESRP_SCENE_CACHE: the user has no home; the built-in benchmark's generated scenes are kept in /tmp
# (an emptyDir in the Kubernetes manifests; mount a volume there to keep them across restarts).
# Only other benchmarks or seeds than esrp-bench-v2 at seed 0 generate any (tens of MB for all of
# one benchmark's scenes): the binary holds that one's.
ENV ESRP_LISTEN=0.0.0.0:50051 \
    ESRP_SCENE_CACHE=/tmp/esrp-scenes \
    NODEVICE_SELECT=1 \
    NVIDIA_DRIVER_CAPABILITIES=graphics,utility \
    NO_COLOR=1
# gRPC (esrp.v1, dm_env_rpc, grpc.health.v1, reflection); Prometheus metrics when the server is
# started with --metrics-listen 0.0.0.0:9090 (ESRP_METRICS_LISTEN), off by default.
EXPOSE 50051 9090
# The server's own health check, through grpc.health.v1 (needs no token; speaks TLS when
# ESRP_TLS_CERT is set). The start period covers the renderer's start.
HEALTHCHECK --interval=10s --timeout=5s --start-period=20s --retries=3 CMD ["esrp-server", "health-check"]
USER 10001:10001
WORKDIR /tmp
ENTRYPOINT ["esrp-server"]
ARG BASE
ARG VERSION=dev
LABEL org.opencontainers.image.title="esrp-server" \
      org.opencontainers.image.description="ESRP environment server: esrp.v1 and dm_env_rpc over gRPC, rendering on a GPU or Mesa's CPU renderers" \
      org.opencontainers.image.licenses="Apache-2.0" \
      org.opencontainers.image.documentation="docker/README.md" \
      org.opencontainers.image.version="${VERSION}" \
      org.opencontainers.image.base.name="${BASE}"

# --- A binary built on the host (`cargo build --release -p esrp-server`), copied in. ---
FROM runtime-base AS runtime-prebuilt
ARG BINARY=target/release/esrp-server
COPY ${BINARY} /usr/local/bin/esrp-server

# --- The Rust builder. ---
FROM ${BUILDER} AS builder
WORKDIR /src
COPY . .
RUN cargo build --release --locked -p esrp-server \
    && strip --strip-debug -o /esrp-server target/release/esrp-server

# --- The default target: the runtime with the binary built above. ---
FROM runtime-base AS runtime
COPY --from=builder /esrp-server /usr/local/bin/esrp-server
