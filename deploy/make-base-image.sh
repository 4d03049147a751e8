#!/usr/bin/env bash
# Makes the container base image localhost/springblend-base:bookworm from Debian's archive, for machines that
# cannot pull from a registry. The image is a minbase Debian 12 made with mmdebstrap from the mirrors this machine's
# apt already uses (read from its apt sources, so no host name is written down here) and imported into podman.
# Idempotent: does nothing when the image exists (FORCE=1 remakes it).
#   bash deploy/make-base-image.sh [IMAGE]
# Needs root (mmdebstrap --mode=root), podman and mmdebstrap (apt-get install podman runc mmdebstrap).
set -euo pipefail
cd "$(dirname "$0")/.."
image="${1:-localhost/springblend-base:bookworm}"
export CONTAINERS_CONF="${CONTAINERS_CONF:-$PWD/deploy/podman/containers.conf}"

if [ "${FORCE:-0}" != 1 ] && podman image exists "$image"; then
  echo "make-base-image: $image exists"
  exit 0
fi

# The configured sources for bookworm, bookworm-updates and bookworm-security, in either apt format (one-line
# .list or deb822 .sources): apt itself resolves them.
mapfile -t mirrors < <(apt-get indextargets --format '$(REPO_URI) $(RELEASE)' 'Created-By: Packages' |
  awk '$2 ~ /^bookworm(-updates|-security)?$/ { print "deb " $1 " " $2 " main" }' | sort -u)
if [ ${#mirrors[@]} -eq 0 ]; then
  echo "make-base-image: no bookworm source in this machine's apt sources (run apt-get update?)" >&2
  exit 1
fi
printf 'make-base-image: mirror %s\n' "${mirrors[@]}"

start=$(date +%s)
# ca-certificates lets later RUN apt-get steps use https mirrors too.
mmdebstrap --mode=root --variant=minbase --format=tar --include=ca-certificates \
  --aptopt='Acquire::Retries "3"' \
  bookworm - "${mirrors[@]}" | podman import - "$image" >/dev/null
echo "make-base-image: $image made in $(( $(date +%s) - start )) s"
