# A Python user's machine, for the test of the wheels (docker/tests/test_wheels.py): Debian with
# its own Python, venv and pip, Mesa's CPU renderers, and no Rust toolchain. The three wheels of
# scripts/build-wheels.sh (esrp, esrp-native, esrp-server) are installed as the README's quick
# start says, from a folder of wheels made on the host (ARG WHEELS: ours and our dependencies'
# for the image's Python), offline, into the venv /opt/esrp on PATH, by an ordinary user with a
# home (where the server keeps its scene cache).
#
#   bash docker/debootstrap-base.sh esrp-base:trixie trixie      # Debian 13: Python 3.13
#   docker build --network host -f docker/wheels.Dockerfile --build-arg BASE=esrp-base:trixie \
#       -t esrp-wheels:trixie CONTEXT                            # CONTEXT/wheels: the wheels
ARG BASE=debian:bookworm-slim
FROM ${BASE}
# libegl1 + libegl-mesa0 + libgl1-mesa-dri: OpenGL through EGL with llvmpipe (the server's choice
# without a GPU); mesa-vulkan-drivers + libvulkan1: lavapipe, as the server's error message names.
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 python3-venv python3-pip \
        libegl1 libegl-mesa0 libgl1-mesa-dri mesa-vulkan-drivers libvulkan1 \
    && rm -rf /var/lib/apt/lists/* \
    && python3 -m venv /opt/esrp \
    && useradd --uid 10001 --user-group --create-home --shell /bin/bash researcher
ENV PATH=/opt/esrp/bin:$PATH \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    NODEVICE_SELECT=1
ARG WHEELS=wheels
COPY ${WHEELS} /tmp/wheels
RUN pip install --no-index --find-links /tmp/wheels 'esrp[gym,server]' esrp-native \
    && rm -rf /tmp/wheels
USER 10001:10001
WORKDIR /home/researcher
LABEL org.opencontainers.image.title="esrp-wheels" \
      org.opencontainers.image.description="The esrp, esrp-native and esrp-server wheels installed with pip on Debian, for their test"
