# One image for every USER process (control, replay, inference, learner, edge): `docker run IMAGE <subcommand>`.
#   docker build -t user-robot-learning .
#   docker run --rm -e USER_TOKEN=... user-robot-learning control -c /app/configs/compose.yaml
# The base is a build argument: the public Python image by default; where public registries cannot be reached,
# deploy/docker/build-base.sh makes a Debian 13 base from Debian's archive (Python 3.13) and
#   docker build --build-arg BASE_IMAGE=user-base:trixie -t user-robot-learning .
# builds from it. Either base must bring python3 with the venv module; the code runs in the venv /opt/venv.
ARG BASE_IMAGE=python:3.12-slim-bookworm
FROM ${BASE_IMAGE}

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    MUJOCO_GL=egl \
    MALLOC_ARENA_MAX=2 \
    VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH

# Headless MuJoCo rendering: EGL through Mesa (llvmpipe on a CPU-only host); OSMesa as the fallback (MUJOCO_GL=osmesa).
# A venv, not the base's site-packages: Debian's python3 refuses system-wide pip installs (PEP 668).
RUN apt-get update \
    && apt-get install -y --no-install-recommends libegl1 libegl-mesa0 libgl1 libosmesa6 \
    && rm -rf /var/lib/apt/lists/* \
    && python3 -m venv $VIRTUAL_ENV

WORKDIR /app

# Dependencies first, from pyproject.toml + constraints.txt only, so a code change reuses this (large) layer.
# evdev (a lerobot[hilserl] dependency, for teleoperators) ships no wheel: gcc + kernel headers build it, then go
# (the Debian base brings them, and python3-dev, itself; purging there only hides them in this layer).
COPY pyproject.toml constraints.txt ./
RUN apt-get update \
    && apt-get install -y --no-install-recommends gcc libc6-dev \
    && python -c "import tomllib; print('\n'.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']))" \
        > /tmp/requirements.txt \
    && pip install -c constraints.txt -r /tmp/requirements.txt \
    && apt-get purge -y --auto-remove gcc libc6-dev \
    && rm -rf /var/lib/apt/lists/* /tmp/requirements.txt

COPY . .

# gRPC stubs are generated, never committed: the same protoc call as the Makefile's $(STUBS) rule.
# Generated before the install so the user.v1 package is part of it. --ignore-requires-python: the project is
# tested on Python 3.12 (pyproject says so); the Debian 13 base has 3.13, on which the compose test runs it.
RUN rm -rf user/v1 && mkdir -p user/v1 \
    && python -m grpc_tools.protoc -Iproto --python_out=. --pyi_out=. --grpc_python_out=. proto/user/v1/*.proto \
    && touch user/v1/__init__.py user/v1/.generated \
    && pip install --no-deps --ignore-requires-python -c constraints.txt . \
    && python -c "import user.v1.replay_pb2_grpc, services.control.server, cloud_learner.server, edge_agent.agent"

# Non-root; /data holds the named volumes (replay LMDB, checkpoints), created here so fresh volumes inherit the owner.
RUN useradd --create-home --uid 10001 --shell /usr/sbin/nologin user \
    && mkdir -p /data/control /data/replay /data/checkpoints /data/spool /data/weights-shm /data/replay-shm \
    && chown -R user:user /data
USER user

# gRPC: control 50051, replay 50052, inference 50053, learner 50054; Prometheus /metrics: 9101-9105.
EXPOSE 50051 50052 50053 50054 9101 9102 9103 9104 9105

ENTRYPOINT ["userctl"]
CMD ["--help"]
