# syntax=docker/dockerfile:1
# osmo container image: the server, workers and the CLI share it (ENTRYPOINT is `osmo`).
#
#   docker build -t osmo:0.1.0 .                                  # core only
#   docker build --build-arg OSMO_EXTRAS=sim -t osmo:0.1.0-sim .  # + simulation task types
#   docker build --build-arg OSMO_EXTRAS=all -t osmo:0.1.0-all .  # every extra (learn needs 3.12)
#
# Two stages: the builder installs osmo (and the chosen extras) into a virtualenv at /opt/osmo;
# the runtime stage copies only that virtualenv onto a fresh slim base with the task sandbox
# (bubblewrap, slirp4netns) and runs as an unprivileged user (uid 10001), so no compiler, pip cache or
# source tree ships in the image.
#
# tests/helm/test_dockerfile_build.py builds this file as it is, with podman, on a local stand-in
# for python:3.12-slim (--build-arg PYTHON_IMAGE=...), and runs the image as the chart does.

ARG PYTHON_IMAGE=python:3.12-slim

FROM ${PYTHON_IMAGE} AS builder
# Comma-separated pip extras: empty = core; sim, learn, viz or all.
ARG OSMO_EXTRAS=
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PYTHONDONTWRITEBYTECODE=1
RUN python -m venv /opt/osmo
WORKDIR /src
COPY pyproject.toml README.md ./
COPY osmo ./osmo
# The kubernetes extra always: a chart pool of kind kubernetes runs `osmo worker --runtime
# kubernetes` from this image (the client is all it needs; tasks run in their own images).
RUN if [ -n "${OSMO_EXTRAS}" ]; then spec="/src[kubernetes,${OSMO_EXTRAS}]"; \
    else spec="/src[kubernetes]"; fi \
 && /opt/osmo/bin/pip install "${spec}" \
 && /opt/osmo/bin/osmo --help >/dev/null

FROM ${PYTHON_IMAGE} AS runtime
ARG OSMO_UID=10001
# Extra Debian packages for task types that need them (e.g. libegl1 for MuJoCo offscreen
# rendering with MUJOCO_GL=egl); empty by default.
ARG OSMO_APT_PACKAGES=
# Every build: bubblewrap, the sandbox each process task runs in (without it `--sandbox auto`
# runs tasks unsandboxed beside osmo's home, and the chart's `--sandbox on` refuses to start),
# and slirp4netns, which gives the node's network namespace (the one the sandboxed tasks
# share, osmo/runtime/netns.py) its outbound connectivity; util-linux brings setpriv and
# nsenter, which enter it. As uid 10001, the pod needs /dev/net/tun for slirp4netns (without
# it, tasks get loopback only, and each task's log says so).
RUN apt-get update \
 && apt-get install -y --no-install-recommends bubblewrap slirp4netns util-linux \
      ${OSMO_APT_PACKAGES} \
 && rm -rf /var/lib/apt/lists/* \
 && bwrap --version && slirp4netns --version >/dev/null && command -v nsenter >/dev/null \
 && groupadd --system --gid "${OSMO_UID}" osmo \
 && useradd --system --uid "${OSMO_UID}" --gid "${OSMO_UID}" --home-dir /home/osmo \
      --create-home --shell /usr/sbin/nologin osmo \
 && mkdir -p /var/lib/osmo \
 && chown "${OSMO_UID}:${OSMO_UID}" /var/lib/osmo
COPY --from=builder /opt/osmo /opt/osmo
ENV PATH=/opt/osmo/bin:${PATH} \
    OSMO_HOME=/var/lib/osmo \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1
WORKDIR /var/lib/osmo
# 7447: zenoh over TCP; 7448: zenoh over TLS (when the server is started with a tls/ endpoint).
EXPOSE 7447 7448
# A numeric user, so Kubernetes' runAsNonRoot can verify it without reading /etc/passwd.
USER ${OSMO_UID}:${OSMO_UID}
ENTRYPOINT ["osmo"]
CMD ["--help"]
