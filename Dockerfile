# syntax=docker/dockerfile:1
#
# simserver in a container: the 1 kHz server, its numba kernels compiled at build time.
#
#   docker build -t simserver .
#   docker run --rm -p 127.0.0.1:7447:7447 simserver
#   docker run --rm -p 127.0.0.1:7447:7447 -v ./myconfigs:/etc/simserver:ro simserver
#
# Real-time scheduling: the server asks for SCHED_FIFO (priority 50, `--rt-priority`) for
# its tick thread and zenoh's threads; on a busy machine that keeps its 1 kHz. The image's
# user is not root, so grant it an rtprio limit (and CAP_SYS_NICE for a root user or the
# nice-level fallback):
#
#   docker run --rm --ulimit rtprio=99 --cap-add SYS_NICE -p 127.0.0.1:7447:7447 simserver
#
# Without them the server logs a warning and runs at normal priority (`--realtime off`
# silences it). With cgroup v1 real-time group scheduling add `--cpu-rt-runtime=950000`;
# for `--rt-lock-memory` add `--ulimit memlock=-1` (or `--cap-add IPC_LOCK`).
#
# Configuration: /etc/simserver holds the repository's configs/ tree (server/, scenes/,
# vehicles/, tires/, scenarios/); the default command loads /etc/simserver/server/default.yaml.
# Mount your own tree over it (it must contain server/default.yaml and whatever that names),
# or one file over its namesake, or give other arguments (they replace the whole CMD below).
#
# Network: inside the container the server listens on tcp/0.0.0.0:7447. That is the
# container's choice, not the project's default (loopback only): the container's network
# namespace is the boundary, and only what `docker run -p` publishes is reachable.
# Publish it on the host's loopback (`-p 127.0.0.1:7447:7447`) to keep the loopback-only
# default, or on an interface of your rig's network to drive from another machine.
# The live Rerun view is off (`--viewer off`): run `simserver view` on the host instead.
# The health check subscribes to the states on tcp/127.0.0.1:7447 inside the container;
# if you move the port, set SIMSERVER_HEALTH_CONNECT (docker/healthcheck.py).
#
# Compile cache: /var/cache/simserver/numba (SIMSERVER_CACHE_DIR, the setting a server, sweep
# workers and several checkouts share: README "Compile cache"), filled at build time and
# writable by the server's user (numba must be able to write there even to read it). With --read-only, mount
# a named volume there (`-v simserver-numba:/var/cache/simserver/numba`: Docker fills it from
# the image, so it stays warm); a tmpfs works but starts cold.
#
# tests/test_dockerfile.py checks this file and runs its install and warm-up steps in a
# fresh virtual environment (no container engine needed).

ARG PYTHON_IMAGE=python:3.11-slim-bookworm

# ---------------------------------------------------------------------------- builder
# Builds the wheel and installs it with its dependencies into a virtual environment. Every
# dependency ships manylinux wheels, so no compiler is needed even here.
FROM ${PYTHON_IMAGE} AS builder

ENV PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /src
COPY pyproject.toml README.md ./
COPY simserver/ simserver/
# (pip byte-compiles the install: the runtime user cannot write .pyc files there)
RUN python -m venv /opt/simserver \
    && /opt/simserver/bin/pip install --no-cache-dir .

# ---------------------------------------------------------------------------- runtime
FROM ${PYTHON_IMAGE} AS runtime

LABEL org.opencontainers.image.title="simserver" \
      org.opencontainers.image.description="Real-time driving-simulator server: lagged-slip tires (SAE 950311), numba physics at 1 kHz, zenoh I/O" \
      org.opencontainers.image.licenses="Apache-2.0"

# SIMSERVER_CACHE_DIR: the install is owned by root and read-only for the server's user, so
# the kernels' cache needs a writable place of its own (without it: "cannot cache function
# ...: no locator available"). The warm-up below fills it.
ENV PATH=/opt/simserver/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    SIMSERVER_CACHE_DIR=/var/cache/simserver/numba \
    MPLCONFIGDIR=/tmp/matplotlib

RUN groupadd --system --gid 10001 simserver \
    && useradd --system --uid 10001 --gid simserver --create-home \
       --home-dir /home/simserver --shell /usr/sbin/nologin simserver \
    && install -d -o simserver -g simserver -m 0755 /var/cache/simserver/numba

COPY --from=builder /opt/simserver /opt/simserver
COPY configs/ /etc/simserver/
COPY docker/warmup.py docker/healthcheck.py /usr/local/lib/simserver/

# numeric, so that runtimes (Kubernetes runAsNonRoot) can tell it is not root
USER 10001:10001
WORKDIR /home/simserver

# Compile every kernel (headless soak, serve, tire curves, view paths; paper_sedan's brush
# tires and mf_hatchback's MF 6.1) into SIMSERVER_CACHE_DIR, then prove a fresh process finds
# them all there. numba keys the cache on the CPU model: on another CPU the first start
# compiles again (15-30 s on 2 vCPUs) unless the image sets NUMBA_CPU_NAME=generic.
RUN python /usr/local/lib/simserver/warmup.py --configs /etc/simserver \
    && python /usr/local/lib/simserver/warmup.py --configs /etc/simserver --expect-cached

EXPOSE 7447

HEALTHCHECK --interval=30s --timeout=10s --start-period=60s --retries=3 \
    CMD ["python", "/usr/local/lib/simserver/healthcheck.py"]

ENTRYPOINT ["simserver", "serve"]
CMD ["--config", "/etc/simserver/server/default.yaml", "--listen", "tcp/0.0.0.0:7447", "--viewer", "off"]
