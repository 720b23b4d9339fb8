#!/usr/bin/env bash
# Builds the two local base images that let the compose stack run where public image registries cannot be reached
# (only Debian's package archive and the Python package registry can):
#   user-base:trixie        Debian 13 minbase from debootstrap: python3 (3.13) + venv + the C toolchain that evdev
#                           (a lerobot[hilserl] dependency without a wheel) builds with.
#   user-prometheus:trixie  FROM user-base:trixie, plus Debian's `prometheus` package (prometheus, promtool).
# Prometheus gets its own image so that the application image stays one process per container and does not carry
# it; it shares the base's layers, so it costs only the package and its dependencies (about 330 MB) on disk.
# Use them with:  docker build --build-arg BASE_IMAGE=user-base:trixie -t user-robot-learning .
#                 PROMETHEUS_IMAGE=user-prometheus:trixie docker compose up
# Needs root, debootstrap and a running docker engine. Usage: deploy/docker/build-base.sh [SUITE] [MIRROR]
# The base trusts every CA the host trusts (USER_BASE_CA_BUNDLE, default the host's bundle): behind a
# TLS-intercepting proxy, pip inside the image builds must accept what the host accepts. Empty: Debian's CAs only.
set -euo pipefail

SUITE=${1:-trixie}
MIRROR=${2:-http://deb.debian.org/debian}
BASE_TAG=${USER_BASE_IMAGE:-user-base:$SUITE}
PROM_TAG=${USER_PROMETHEUS_IMAGE:-user-prometheus:$SUITE}
HERE=$(cd "$(dirname "$0")" && pwd)
CA_BUNDLE=${USER_BASE_CA_BUNDLE-/etc/ssl/certs/ca-certificates.crt}
ROOTFS=$(mktemp -d /var/tmp/user-base-rootfs.XXXXXX)
trap 'rm -rf "$ROOTFS"' EXIT

# minbase: only Essential packages + apt; everything the image build needs from the C side comes in here, so the
# Dockerfile's own apt step is the same for this base and the public python image.
debootstrap --variant=minbase \
    --include=python3,python3-venv,python3-dev,gcc,libc6-dev,linux-libc-dev,ca-certificates,passwd \
    "$SUITE" "$ROOTFS" "$MIRROR"
if [ -n "$CA_BUNDLE" ] && [ -f "$CA_BUNDLE" ]; then
    # the host's certificates that Debian's bundle lacks, one file each, the way update-ca-certificates wants them
    python3 - "$CA_BUNDLE" "$ROOTFS" <<'PY'
import re, sys
from pathlib import Path
pem = re.compile(r"-----BEGIN CERTIFICATE-----.+?-----END CERTIFICATE-----", re.S)
host, root = Path(sys.argv[1]).read_text(), Path(sys.argv[2])
known = set(pem.findall((root / "etc/ssl/certs/ca-certificates.crt").read_text()))
extra = [c for c in dict.fromkeys(pem.findall(host)) if c not in known]
for i, cert in enumerate(extra):
    (root / f"usr/local/share/ca-certificates/host-{i}.crt").write_text(cert + "\n")
print(f"{len(extra)} CA certificate(s) of the host added to the base")
PY
    chroot "$ROOTFS" update-ca-certificates
fi
chroot "$ROOTFS" apt-get clean
rm -rf "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/var/cache/apt/*.bin "$ROOTFS"/tmp/* "$ROOTFS"/var/log/*.log

tar -C "$ROOTFS" --numeric-owner -c . | docker import \
    --change 'ENV LANG=C.UTF-8' \
    --change 'ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt' \
    --change 'CMD ["/bin/bash"]' \
    - "$BASE_TAG"
docker build -t "$PROM_TAG" --build-arg BASE_IMAGE="$BASE_TAG" -f "$HERE/prometheus.Dockerfile" "$HERE"
docker image ls --format '{{.Repository}}:{{.Tag}} {{.Size}}' | grep -E "^($BASE_TAG|$PROM_TAG) "
