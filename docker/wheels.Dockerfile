# A Python user's machine, for the test of the wheels (docker/tests/test_wheels.py): Debian with
# Mesa's CPU renderers and no Rust toolchain, and either Debian's own Python (python3, venv, pip)
# or, with ARG PYTHON_PREFIX, a CPython built elsewhere for this Debian release and copied from
# the build context's python/ folder to that prefix (Debian ships no Python 3.10: the test copies
# the host's pyenv build to try the oldest Python the package supports). The three wheels of
# scripts/build-wheels.sh (esrp, esrp-native, esrp-server) are installed as the README's quick
# start says, from a folder of wheels made on the host (ARG WHEELS: ours and our dependencies'
# for the image's Python), offline, into the venv /opt/esrp on PATH; an ordinary user with a home
# (where the server keeps its scene cache) runs the commands.
#
#   bash docker/debootstrap-base.sh esrp-base:trixie trixie      # Debian 13: Python 3.13
#   docker build --network host -f docker/wheels.Dockerfile --build-arg BASE=esrp-base:trixie \
#       -t esrp-wheels:trixie CONTEXT                            # CONTEXT/wheels, CONTEXT/python
ARG BASE=debian:bookworm-slim
FROM ${BASE}
ARG PYTHON_PREFIX=
COPY python /tmp/python
# libegl1 + libegl-mesa0 + libgl1-mesa-dri: OpenGL through EGL with llvmpipe (the server's choice
# without a GPU); mesa-vulkan-drivers + libvulkan1: lavapipe, as the server's error message names.
# A copied CPython gets the shared libraries its modules link (ssl, ctypes, sqlite3, readline...).
RUN set -e; \
    if [ -n "$PYTHON_PREFIX" ]; then \
        python="libssl3 libffi8 libsqlite3-0 libbz2-1.0 liblzma5 zlib1g libreadline8 libncursesw6 libexpat1 libuuid1 libtirpc3 libcrypt1 ca-certificates"; \
    else \
        python="python3 python3-venv python3-pip"; \
    fi; \
    apt-get update; \
    apt-get install -y --no-install-recommends $python \
        libegl1 libegl-mesa0 libgl1-mesa-dri mesa-vulkan-drivers libvulkan1; \
    rm -rf /var/lib/apt/lists/*; \
    if [ -n "$PYTHON_PREFIX" ]; then \
        mkdir -p "$(dirname "$PYTHON_PREFIX")"; \
        mv /tmp/python "$PYTHON_PREFIX"; \
        folder="$PYTHON_PREFIX"; \
        while [ "$folder" != / ]; do chmod o+rx "$folder"; folder="$(dirname "$folder")"; done; \
        "$PYTHON_PREFIX/bin/python3" -m venv /opt/esrp; \
    else \
        rm -rf /tmp/python; \
        python3 -m venv /opt/esrp; \
    fi; \
    useradd --uid 10001 --user-group --create-home --shell /bin/bash researcher
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
