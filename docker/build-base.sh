#!/bin/sh
# A Debian base image for the Dockerfile, made from Debian packages alone, for hosts that reach a Debian mirror
# and PyPI but no container registry (so `FROM python:3.11-slim` cannot be pulled).
#
#   sudo docker/build-base.sh [TAG]                  # default TAG: nemsim-base:bookworm
#   docker build --build-arg BASE_IMAGE=nemsim-base:bookworm -t nemsim .
#
# Choices:
# - debootstrap --variant=minbase of bookworm, plus python3 (3.11, the Python of python:3.11-slim) and
#   python3-venv: the Dockerfile needs only `python3 -m venv`, so one Dockerfile serves both bases.
# - The mirror is the one apt uses on this host (first deb822 `URIs:` or sources.list `deb` line), else
#   deb.debian.org; override with MIRROR=...
# - Extra CA certificates the host trusts (/usr/local/share/ca-certificates/*.crt) are added, so pip inside the
#   build works behind a TLS-inspecting proxy; HOST_CA=0 leaves them out. The image then trusts them too.
# - apt lists, caches, docs and man pages are removed: the image holds what the service needs to run.
# - The container CLI is $CONTAINER_CLI (default docker; podman works the same: `podman import`).
set -eu

TAG=${1:-nemsim-base:bookworm}
SUITE=${SUITE:-bookworm}
CLI=${CONTAINER_CLI:-docker}
HOST_CA=${HOST_CA:-1}

if [ "$(id -u)" -ne 0 ]; then
    echo "build-base.sh: debootstrap needs root (run it with sudo)" >&2
    exit 2
fi
for tool in debootstrap "$CLI"; do
    command -v "$tool" >/dev/null || { echo "build-base.sh: $tool not found (apt-get install $tool)" >&2; exit 2; }
done

host_mirror() {
    for f in /etc/apt/sources.list.d/*.sources; do
        [ -f "$f" ] && awk '/^URIs:/ && $2 !~ /security/ {print $2; exit}' "$f"
    done | head -n 1
    [ -f /etc/apt/sources.list ] && awk '$1 == "deb" && $0 !~ /security/ {print ($2 ~ /^\[/ ? $3 : $2); exit}' \
        /etc/apt/sources.list
}
MIRROR=${MIRROR:-$(host_mirror | head -n 1)}
MIRROR=${MIRROR:-http://deb.debian.org/debian}

ROOTFS=$(mktemp -d /var/tmp/nemsim-base.XXXXXX)
trap 'rm -rf "$ROOTFS"' EXIT
echo "build-base.sh: debootstrap $SUITE from $MIRROR into $ROOTFS" >&2
debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates "$SUITE" "$ROOTFS" "$MIRROR"

if [ "$HOST_CA" = 1 ] && ls /usr/local/share/ca-certificates/*.crt >/dev/null 2>&1; then
    cp /usr/local/share/ca-certificates/*.crt "$ROOTFS/usr/local/share/ca-certificates/"
    chroot "$ROOTFS" update-ca-certificates >/dev/null
fi
printf 'deb %s %s main\n' "$MIRROR" "$SUITE" >"$ROOTFS/etc/apt/sources.list"
chroot "$ROOTFS" apt-get clean
rm -rf "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/var/cache/apt/* "$ROOTFS"/var/log/*.log \
    "$ROOTFS"/usr/share/doc/* "$ROOTFS"/usr/share/man/* "$ROOTFS"/usr/share/info/* "$ROOTFS"/tmp/*

# PIP_CERT: the system bundle (with the CAs above), which pip's own certifi copy would not include
tar --numeric-owner -C "$ROOTFS" -c . | "$CLI" import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt' \
    --change 'CMD ["python3"]' \
    - "$TAG"
echo "build-base.sh: built $TAG" >&2
