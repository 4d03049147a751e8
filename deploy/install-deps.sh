#!/usr/bin/env bash
# Installs everything springblend needs to build, test and run, from Debian 12's archive only.
# Idempotent: when every package is already present it touches nothing and returns at once.
#   bash deploy/install-deps.sh          build, tests (with the Python client's and headless Blender's) and the
#                                        benchmark's plot
#   bash deploy/install-deps.sh --build  only what building the C++ server and CLI needs (the container image)
#   bash deploy/install-deps.sh fuzz     also clang and its libFuzzer runtime (fuzz/run.sh; not in the image)
set -euo pipefail

packages=(
  build-essential cmake ninja-build pkg-config git ca-certificates
  libeigen3-dev libopenmesh-dev libtet1.5-dev libcgal-dev libgmp-dev libmpfr-dev
  libsuitesparse-dev libopenblas-dev libmumps-seq-dev
  libspdlog-dev libfmt-dev libcli11-dev nlohmann-json3-dev libtbb-dev
  libgrpc++-dev libprotobuf-dev protobuf-compiler protobuf-compiler-grpc libssl-dev
  libgtest-dev libgmock-dev libbenchmark-dev
  openssl ccache
)
build_only=0
for group in "$@"; do
  case "$group" in
    --build) build_only=1 ;;
    fuzz) packages+=(clang libclang-rt-14-dev) ;;
    *) echo "install-deps: unknown group '$group' (known: --build, fuzz)" >&2; exit 2 ;;
  esac
done
if [ "$build_only" -eq 0 ]; then
  # The DCC clients' tests (Python package, headless Blender) and the benchmark's plot.
  packages+=(python3 python3-grpcio python3-numpy python3-protobuf blender gnuplot-nox)
  # The JSON Schemas' test (tests/docs/schema_test.py).
  packages+=(python3-jsonschema)
  # The Python package's install test: a virtual environment, pip, setuptools and wheel, all offline.
  packages+=(python3-venv python3-pip python3-setuptools python3-wheel)
fi

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "install-deps: all ${#packages[@]} packages present"
  exit 0
fi

sudo=""
if [ "$(id -u)" -ne 0 ]; then sudo="sudo"; fi
echo "install-deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
$sudo apt-get update -qq
$sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
echo "install-deps: done"
