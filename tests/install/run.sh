#!/usr/bin/env bash
# The install test (CTest: install_consumer_test). Installs the build into a temporary prefix, builds
# tests/install/consumer against it with find_package(springblend CONFIG REQUIRED), starts the installed
# springblend-server on a free loopback port with a temporary cache, runs the consumer against it, and checks:
# the versions the programs print, the springblend_build_info metric, (ldd) that the client consumer links
# none of the solver's libraries, and that the README's plug-in (a MODULE linking the shared SDK, dlopened by a
# host) needs only the SDK and the C++ runtime, while the SDK exports springblend::sdk alone.
#   bash tests/install/run.sh BUILD_DIR TEST_DATA_DIR VERSION
set -euo pipefail
build="$1" data="$2" version="$3"
here="$(cd "$(dirname "$0")" && pwd)"
work="$(mktemp -d "${TMPDIR:-/tmp}/springblend-install.XXXXXX")"
server_pid=""
cleanup() {
  if [ -n "$server_pid" ]; then kill "$server_pid" 2>/dev/null || true; wait "$server_pid" 2>/dev/null || true; fi
  rm -rf "$work"
}
trap cleanup EXIT
fail() { echo "install test: FAILED: $*" >&2; [ -f "$work/server.log" ] && sed 's/^/  server: /' "$work/server.log" >&2; exit 1; }
prefix="$work/prefix"

echo "== cmake --install $build --prefix $prefix"
cmake --install "$build" --prefix "$prefix" >"$work/install.log" || { cat "$work/install.log"; fail "install"; }
for f in bin/springblend-server bin/springblend libexec/springblend/springblend-tetgen \
         include/springblend/client.h include/springblend/sdk.h include/springblend/geometry.h include/springblend/version.h \
         include/springblend/v1/springblend.grpc.pb.h lib/cmake/springblend/springblendConfig.cmake \
         lib/cmake/springblend/springblendConfigVersion.cmake share/springblend/python/springblend/_version.py; do
  [ -e "$prefix/$f" ] || fail "$f is not installed"
done

echo "== versions"
[ "$("$prefix/bin/springblend" --version)" = "springblend $version" ] || fail "springblend --version"
[ "$("$prefix/bin/springblend-server" --version)" = "springblend-server $version" ] || fail "springblend-server --version"
grep -q "SPRINGBLEND_VERSION \"$version\"" "$prefix/include/springblend/version.h" || fail "version.h"

echo "== the consumer project"
launcher=()
if command -v ccache >/dev/null; then launcher=(-DCMAKE_CXX_COMPILER_LAUNCHER=ccache); fi
cmake -S "$here/consumer" -B "$work/consumer" -G Ninja -DCMAKE_BUILD_TYPE=Release -DCMAKE_PREFIX_PATH="$prefix" \
  "${launcher[@]}" >"$work/configure.log" || { cat "$work/configure.log"; fail "configuring the consumer"; }
cmake --build "$work/consumer" >"$work/build.log" || { cat "$work/build.log"; fail "building the consumer"; }

echo "== ldd: no solver library in the client consumer"
ldd "$work/consumer/consumer" >"$work/ldd.txt"
if grep -Ei 'cholmod|suitesparse|libtet|cgal|gmp|mpfr|openmesh|tbb|blas|lapack' "$work/ldd.txt"; then
  fail "the client consumer links a solver library (above)"
fi
grep -q 'libgrpc++' "$work/ldd.txt" || fail "the client consumer does not link gRPC?"

echo "== the plug-in needs the SDK and the C++ runtime only; the SDK exports springblend::sdk only"
plugin="$work/consumer/plugin.so"
[ -f "$plugin" ] || fail "no plugin.so was built"
needed="$(objdump -p "$plugin" | awk '$1 == "NEEDED" {print $2}' | sort | tr '\n' ' ')"
echo "plugin.so needs: $needed"
for lib in $needed; do
  case "$lib" in
    libspringblend_sdk.so.0|libstdc++.so.6|libm.so.6|libgcc_s.so.1|libc.so.6) ;;
    *) fail "plugin.so needs $lib (only libspringblend_sdk.so.0 and the C++ runtime expected)" ;;
  esac
done
grep -q 'libspringblend_sdk.so.0' <<<"$needed" || fail "plugin.so does not need libspringblend_sdk.so.0"
sdk_lib="$prefix/lib/libspringblend_sdk.so.0"
[ -e "$sdk_lib" ] || sdk_lib="$(ls "$prefix"/lib/*/libspringblend_sdk.so.0 2>/dev/null | head -n1)"
[ -e "$sdk_lib" ] || fail "libspringblend_sdk.so.0 is not installed"
# (the whole output first: grep -q stops reading early, and pipefail would count objdump's SIGPIPE)
sdk_headers="$(objdump -p "$sdk_lib")"
grep -q 'SONAME *libspringblend_sdk.so.0' <<<"$sdk_headers" || fail "the SDK's SONAME is not libspringblend_sdk.so.0"
exported="$(nm -D --defined-only -C "$sdk_lib" | cut -d' ' -f3-)"
strays="$(grep -v -e '^springblend::sdk::' -e '^typeinfo for springblend::sdk::' -e '^typeinfo name for springblend::sdk::' \
               -e '^vtable for springblend::sdk::' -e '^SPRINGBLEND_SDK_0' <<<"$exported" || true)"
[ -z "$strays" ] || { echo "$strays" | head -n 20; fail "the SDK exports symbols beyond springblend::sdk (above)"; }
grep -q 'springblend::sdk::Client::Solve' <<<"$exported" || fail "the SDK does not export Client::Solve"
ldd "$plugin" >"$work/plugin-ldd.txt"
if grep -Ei 'cholmod|suitesparse|libtet|cgal|openmesh|tbb|blas' "$work/plugin-ldd.txt"; then
  fail "the plug-in loads a solver library (above)"
fi
"$work/consumer/solver_consumer" "$data/cylinder/cylinder.obj" || fail "solver_consumer"

echo "== the consumer against the installed server"
# The installed server, away from the build tree: it must find its TetGen helper in ../libexec/springblend.
mkdir -p "$work/cache"
"$prefix/bin/springblend-server" --listen 127.0.0.1:0 --cache-dir "$work/cache" --workers 1 \
  --metrics 127.0.0.1:0 >"$work/server.out" 2>"$work/server.log" &
server_pid=$!
port="" metrics_port=""
for _ in $(seq 1 100); do
  port="$(sed -n 's/^springblend-server listening on 127.0.0.1:\([0-9]*\)$/\1/p' "$work/server.out")"
  [ -n "$port" ] && break
  kill -0 "$server_pid" 2>/dev/null || fail "the server exited"
  sleep 0.1
done
[ -n "$port" ] || fail "the server did not say where it listens"
metrics_port="$(sed -n 's|^springblend-server metrics on http://127.0.0.1:\([0-9]*\)/metrics$|\1|p' "$work/server.out")"
grep -q "springblend-server $version serving on" "$work/server.log" || fail "the start-up log line has no version"
"$work/consumer/consumer" "127.0.0.1:$port" "$data/cylinder" "$version" || fail "the consumer"
echo "== the plug-in, dlopened by a host, against the installed server"
"$work/consumer/plugin_host" "$plugin" "127.0.0.1:$port" "$data/cylinder" "$version" || fail "the plug-in"

echo "== springblend_build_info"
# (Python rather than bash's /dev/tcp: the endpoint answers after the first read, and a request written in two
# pieces would then meet a closed socket.)
metrics="$(/usr/bin/python3 -c 'import sys, urllib.request
print(urllib.request.urlopen(sys.argv[1], timeout=10).read().decode())' "http://127.0.0.1:$metrics_port/metrics")" ||
  fail "cannot read the metrics"
grep -qF "springblend_build_info{version=\"$version\"} 1" <<<"$metrics" || fail "no springblend_build_info{version=\"$version\"} 1"

kill -TERM "$server_pid"
wait "$server_pid" || fail "the server did not exit 0 on SIGTERM"
server_pid=""
echo "install test: ok"
