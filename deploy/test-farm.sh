#!/usr/bin/env bash
# CI test of the containerised farm: builds the springblend image (podman, from a base image made with
# mmdebstrap, no registry needed), runs three replicas sharing one cache directory behind nginx (gRPC, consistent
# hash on the x-springblend-character header), and checks through the load balancer, with the host's CLI:
#   (a) health; (b) uploads of several characters; (c) affinity: every solve of one character is served by the
#   same replica, and at least two replicas serve something; (c') each upload reached the replica that then
#   serves its character (the client sends the id it computed as the routing header); (d) a replica killed while solves run: the others'
#   streams finish, and its characters move to a live replica and are rebuilt from the shared cache without a
#   re-upload; (e) the farm's frames equal a local `springblend blend` of the same frames; (f) a bake split into
#   chunks on two replicas is byte-identical to the whole bake (stateless frames); plus the image's
#   non-root user and its HEALTHCHECK. Cleans up containers and nginx on exit; exits non-zero on any failure.
#
#   bash deploy/test-farm.sh
# Environment: NO_CACHE=1 rebuilds every image layer; FARM_DIR (default /tmp/springblend-farm) holds the
# rendered nginx config, logs, outputs and the shared cache; KEEP=1 leaves the farm running for inspection
# (clean up with `podman rm -f springblend-farm-1 springblend-farm-2 springblend-farm-3; kill $(cat FARM_DIR/nginx.pid)`).
# Needs root (apt-get, mmdebstrap --mode=root, host networking) on Debian 12 with the Debian archive reachable.
# Ports: 127.0.0.1:50050 (load balancer), 50061..50063 (replicas), 50071..50073 (replicas' metrics).
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$PWD
export CONTAINERS_CONF="$repo/deploy/podman/containers.conf"
farm="${FARM_DIR:-/tmp/springblend-farm}"
base_image=localhost/springblend-base:bookworm
image=localhost/springblend:test
lb=127.0.0.1:50050
replicas=(1 2 3)
client="$repo/build/release/client/springblend"
data="$repo/tests/data"

t0=$(date +%s)
declare -a results=()
failures=0
pass() { results+=("PASS  $*"); echo "PASS: $*"; }
fail() { results+=("FAIL  $*"); echo "FAIL: $*" >&2; failures=$((failures + 1)); }
die() {
  fail "$*"
  exit 1
}
summary() {
  echo
  echo "================ springblend farm test ================"
  local r
  for r in "${results[@]}"; do echo "$r"; done
  [ -n "${timing_base:-}" ] && echo "timing: base image ${timing_base} s, image build ${timing_build:-?} s, farm test ${timing_test:-?} s, total $(( $(date +%s) - t0 )) s"
  [ -n "${image_size:-}" ] && echo "image: $image, $image_size"
  if [ "$failures" -eq 0 ] && [ "${finished:-0}" = 1 ]; then
    echo "RESULT: PASS"
  else
    echo "RESULT: FAIL ($failures failed; logs in $farm)"
  fi
}

nginx_pid=""
background=""
cleanup() {
  local rc=$?
  if [ -n "$background" ]; then kill "$background" 2>/dev/null || true; fi
  if [ "${KEEP:-0}" != 1 ]; then
    for i in "${replicas[@]}"; do podman rm -f -t 2 "springblend-farm-$i" >/dev/null 2>&1 || true; done
    if [ -n "$nginx_pid" ]; then kill "$nginx_pid" 2>/dev/null || true; wait "$nginx_pid" 2>/dev/null || true; fi
  fi
  summary
  if [ "$failures" -ne 0 ] || [ "${finished:-0}" != 1 ]; then exit 1; fi
  exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# ---------------------------------------------------------------------------------------------------- tools
need=()
for p in podman runc mmdebstrap nginx catatonit; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || need+=("$p")
done
if [ ${#need[@]} -gt 0 ]; then
  echo "test-farm: installing ${need[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi

for i in "${replicas[@]}"; do podman rm -f -t 2 "springblend-farm-$i" >/dev/null 2>&1 || true; done
for port in 50050 50061 50062 50063 50071 50072 50073; do
  if ss -Hltn "sport = :$port" | grep -q .; then die "port $port is already in use on this machine"; fi
done

# ---------------------------------------------------------------------------------------------------- images
s=$(date +%s)
bash deploy/make-base-image.sh "$base_image"
timing_base=$(( $(date +%s) - s ))

s=$(date +%s)
build_args=(--format docker --pull=never --build-arg "BASE=$base_image" --ignorefile deploy/containerignore
            -f deploy/Dockerfile -t "$image")
[ "${NO_CACHE:-0}" = 1 ] && build_args+=(--no-cache)
# The host's compiler cache, mounted for the image's build step only (never part of the image): with the host's
# CCACHE_COMPILERCHECK=content (.ci/run sets it), the objects of the host's release build are reused.
if command -v ccache >/dev/null; then
  ccache_dir=$(ccache -k cache_dir)
  mkdir -p "$ccache_dir"
  build_args+=(-v "$ccache_dir:/ccache")
  # ccache hashes these locale variables too: the image's compiler runs with the host's.
  host_locale=$(env | grep -E '^(LANG|LC_ALL|LC_CTYPE|LC_MESSAGES)=' | tr '\n' ' ' || true)
  build_args+=(--build-arg "HOST_LOCALE=$host_locale")
fi
echo "test-farm: podman build ${build_args[*]} ."
podman build "${build_args[@]}" . || die "podman build failed"
timing_build=$(( $(date +%s) - s ))
image_size=$(podman image ls --format '{{.Size}}' "$image" | head -n1)
pass "image built in ${timing_build} s ($image_size)"

# The host's CLI drives the farm (tests/run.sh or quickstart.sh normally built it already).
if [ ! -x "$client" ]; then
  echo "test-farm: building the host client"
  bash deploy/install-deps.sh
  cmake --preset release >/dev/null
  cmake --build --preset release --target springblend -j "$(nproc)"
fi

# ---------------------------------------------------------------------------------------------------- farm
s=$(date +%s)
rm -rf "$farm"
mkdir -p "$farm/cache" "$farm/out" "$farm/local"
chmod 0777 "$farm/cache"   # the image runs as uid 10001; root-made files stay readable by it
cp "$client" "$farm/springblend"   # a private copy: a rebuild of build/release cannot swap it mid-test
# with the solver's TetGen helper beside it, where `springblend blend` looks first
cp "$repo/build/release/libexec/springblend/springblend-tetgen" "$farm/springblend-tetgen"
client="$farm/springblend"
# Without systemd (CI containers) podman logs an error per container about the health-check timer; the image's
# HEALTHCHECK still runs on demand (`podman healthcheck run`, checked below). Those lines go to podman.log.
for i in "${replicas[@]}"; do
  podman run -d --init --network=host --name "springblend-farm-$i" \
    -e "SPRINGBLEND_PORT=5006$i" -v "$farm/cache:/var/cache/springblend" \
    "$image" --listen "127.0.0.1:5006$i" --cache-dir /var/cache/springblend --replica-name "replica-$i" \
    --workers 1 --metrics "127.0.0.1:5007$i" >/dev/null 2>>"$farm/podman.log" ||
    die "podman run replica-$i failed: $(tail -n1 "$farm/podman.log")"
done
sed "s#/tmp/springblend-farm#$farm#g" deploy/nginx.conf >"$farm/nginx.conf"
nginx -e "$farm/error.log" -c "$farm/nginx.conf" &
nginx_pid=$!

wait_healthy() {  # address, seconds
  local _
  for _ in $(seq $(( $2 * 5 ))); do
    "$client" health --server "$1" >/dev/null 2>&1 && return 0
    sleep 0.2
  done
  return 1
}
for i in "${replicas[@]}"; do
  wait_healthy "127.0.0.1:5006$i" 30 || { podman logs "springblend-farm-$i" >&2 || true; die "replica-$i did not become healthy"; }
done
pass "3 replicas serving on 127.0.0.1:50061..50063"

uid=$(podman exec springblend-farm-1 id -u)
[ "$uid" != 0 ] && pass "replicas run as a non-root user (uid $uid)" || fail "replicas run as root"
if podman healthcheck run springblend-farm-2 >/dev/null 2>&1; then
  pass "image HEALTHCHECK (springblend health) reports healthy"
else
  fail "image HEALTHCHECK failed: $(podman healthcheck run springblend-farm-2 2>&1 | tail -n1)"
fi

# (a) health through the load balancer
if wait_healthy "$lb" 15; then pass "(a) health through the load balancer"; else die "(a) load balancer $lb not healthy (see $farm/error.log)"; fi

# (b) uploads through the load balancer: name | upload arguments (relative to tests/data)
characters=(
  "cylinder-bend-twist|--rest cylinder/cylinder.obj --target cylinder/poses-2_cylinder-1.obj --target cylinder/poses-2_cylinder-3.obj"
  "cube|--rest cube/cube.obj --target cube/poses-1_cube-1.obj"
  "cylinder-bend|--rest cylinder/cylinder.obj --target cylinder/poses-2_cylinder-1.obj"
  "cylinder-bend-fixed-a|--rest cylinder/cylinder.obj --target cylinder/poses-2_cylinder-1.obj --fixed 0,1,2"
  "cylinder-bend-fixed-b|--rest cylinder/cylinder.obj --target cylinder/poses-2_cylinder-1.obj --fixed 10,11,12,13"
  "cylinder-twist|--rest cylinder/cylinder.obj --target cylinder/poses-2_cylinder-3.obj"
  "cylinder-poses-1|--rest cylinder/cylinder.obj --target cylinder/poses-1_cylinder-1.obj --target cylinder/poses-1_cylinder-2.obj"
  "cube-2|--rest cube/cube.obj --target cube/poses-1_cube-2.obj"
)
declare -A id_of=() args_of=() weights_of=() served=()
names=()
ok=1
for c in "${characters[@]}"; do
  name=${c%%|*}
  args=${c#*|}
  names+=("$name")
  args_of[$name]=$args
  ntargets=$(grep -o -- '--target' <<<"$args" | wc -l)
  weights_of[$name]=$( [ "$ntargets" = 2 ] && echo 0.8,0.4 || echo 0.9 )
  # shellcheck disable=SC2086
  if ! (cd "$data" && "$client" upload --server "$lb" $args --name "$name") >"$farm/out/$name.upload.json" 2>"$farm/out/$name.upload.err"; then
    ok=0; fail "(b) upload of $name: $(tail -n1 "$farm/out/$name.upload.err")"; continue
  fi
  id_of[$name]=$(sed -n 's/.*"id":"\([0-9a-f]*\)".*/\1/p' "$farm/out/$name.upload.json")
  [ -n "${id_of[$name]}" ] || { ok=0; fail "(b) upload of $name printed no id"; }
done
distinct_ids=$(printf '%s\n' "${id_of[@]}" | sort -u | wc -l)
if [ "$ok" = 1 ] && [ "$distinct_ids" = "${#names[@]}" ]; then
  pass "(b) ${#names[@]} characters uploaded through the load balancer, ${distinct_ids} distinct ids"
else
  die "(b) uploads: $distinct_ids distinct ids for ${#names[@]} characters"
fi

solve() {  # name, output directory; prints the replica that served every frame, fails on mixed or none
  local name=$1 out=$2
  "$client" solve --server "$lb" --character "${id_of[$name]}" --sweep 3 --weights "${weights_of[$name]}" \
    --out "$out" >"$out.jsonl" 2>"$out.err" || { echo "solve failed: $(tail -n1 "$out.err")"; return 1; }
  local frames by
  frames=$(grep -c '"served_by"' "$out.jsonl" || true)
  by=$(sed -n 's/.*"served_by":"\([^"]*\)".*/\1/p' "$out.jsonl" | sort -u)
  [ "$frames" = 3 ] || { echo "$frames frames instead of 3"; return 1; }
  [ "$(wc -l <<<"$by")" = 1 ] || { echo "frames of one stream from several replicas: $by"; return 1; }
  echo "$by"
}

# (c) affinity: three rounds of solves of every character
ok=1
for round in 1 2 3; do
  for name in "${names[@]}"; do
    if ! by=$(solve "$name" "$farm/out/$name.r$round"); then ok=0; fail "(c) round $round, $name: $by"; continue; fi
    served[$name]+="$by "
  done
done
replicas_used=()
for name in "${names[@]}"; do
  uniq=$(tr ' ' '\n' <<<"${served[$name]}" | sed '/^$/d' | sort -u)
  if [ "$(wc -l <<<"$uniq")" != 1 ]; then ok=0; fail "(c) $name served by several replicas: ${served[$name]}"; fi
  replicas_used+=("$(head -n1 <<<"$uniq")")
  echo "  $name (${id_of[$name]:0:12}) -> $(head -n1 <<<"$uniq")"
done
distinct_replicas=$(printf '%s\n' "${replicas_used[@]}" | sort -u | wc -l)
if [ "$ok" = 1 ] && [ "$distinct_replicas" -ge 2 ]; then
  pass "(c) 3 solves of each of ${#names[@]} characters: one replica per character, $distinct_replicas replicas used"
else
  fail "(c) affinity: $distinct_replicas distinct replicas used"
fi

# (c') routing: each upload carried its character's id (computed by the client before the upload) in the
# header the balancer hashes, so it reached the replica that then served every solve of that character
ok=1
for k in "${!names[@]}"; do
  name=${names[$k]}
  upstream=$(grep 'UploadCharacter' "$farm/access.log" | grep "character=${id_of[$name]} " |
    sed -n 's/.*upstream=127\.0\.0\.1:5006\([0-9]\).*/replica-\1/p' | sort -u)
  if [ "$upstream" != "${replicas_used[$k]}" ]; then
    ok=0; fail "(c') $name's upload went to '${upstream:-no replica with its id as header}', its solves to ${replicas_used[$k]}"
  fi
done
[ "$ok" = 1 ] && pass "(c') each of ${#names[@]} uploads reached the replica that serves its character (routed by the id)"

# (d) kill the replica with the most characters while the others stream solves
victim=$(printf '%s\n' "${replicas_used[@]}" | sort | uniq -c | sort -k1,1nr -k2 | awk 'NR==1{print $2}')
moved=() stayed=()
for k in "${!names[@]}"; do
  if [ "${replicas_used[$k]}" = "$victim" ]; then moved+=("${names[$k]}"); else stayed+=("${names[$k]}"); fi
done
echo "test-farm: killing $victim (characters: ${moved[*]})"
rebuilds_before=0
for i in "${replicas[@]}"; do
  [ "replica-$i" = "$victim" ] && continue
  n=$(curl -fsS "http://127.0.0.1:5007$i/metrics" | awk '$1=="springblend_cache_rebuilds_from_disk_total"{print $2}' || true)
  rebuilds_before=$((rebuilds_before + ${n:-0}))
done
(
  rc=0
  for round in 1 2 3 4; do
    for name in "${stayed[@]}"; do
      by=$(solve "$name" "$farm/out/$name.bg$round") || { echo "background solve of $name: $by" >&2; rc=1; }
    done
  done
  exit $rc
) &
background=$!
sleep 1
podman kill "springblend-farm-${victim#replica-}" >/dev/null 2>>"$farm/podman.log"
declare -A after=()
ok=1
for round in 1 2 3; do
  for name in "${moved[@]}" "${stayed[@]}"; do
    if ! by=$(solve "$name" "$farm/out/$name.d$round"); then ok=0; fail "(d) after the kill, round $round, $name: $by"; continue; fi
    if [ "$by" = "$victim" ]; then ok=0; fail "(d) $name served by the killed $victim"; fi
    after[$name]+="$by "
  done
done
if wait "$background"; then background=""
  pass "(d) solves on the surviving replicas kept streaming while $victim was killed"
else
  fail "(d) a solve on a surviving replica failed while $victim was killed"
fi
for name in "${moved[@]}" "${stayed[@]}"; do
  uniq=$(tr ' ' '\n' <<<"${after[$name]:-}" | sed '/^$/d' | sort -u)
  if [ "$(wc -l <<<"$uniq")" != 1 ]; then ok=0; fail "(d) $name after the kill served by: ${after[$name]:-none}"; fi
done
for k in "${!names[@]}"; do
  name=${names[$k]}
  if [ "${replicas_used[$k]}" != "$victim" ]; then
    first=$(tr ' ' '\n' <<<"${after[$name]:-}" | sed '/^$/d' | head -n1)
    [ "$first" = "${replicas_used[$k]}" ] || { ok=0; fail "(d) $name moved from ${replicas_used[$k]} to $first although its replica lives"; }
  fi
done
rebuilds_after=0
for i in "${replicas[@]}"; do
  [ "replica-$i" = "$victim" ] && continue
  n=$(curl -fsS "http://127.0.0.1:5007$i/metrics" | awk '$1=="springblend_cache_rebuilds_from_disk_total"{print $2}' || true)
  rebuilds_after=$((rebuilds_after + ${n:-0}))
done
rebuilt=$((rebuilds_after - rebuilds_before))
# (A moved character that lands on the replica which took the uploads may still be in its memory, so the
# rebuild count is reported, not asserted; nothing was uploaded again, so every successful solve of a moved
# character was served from the shared cache.)
if [ "$ok" = 1 ]; then
  pass "(d) after killing $victim: 3 more rounds all succeed without re-upload, its ${#moved[@]} characters moved (each to one live replica; $rebuilt rigs rebuilt from the shared cache dir), the other ${#stayed[@]} stayed"
fi

# (e) the farm's frames equal a local solve of the same frames
ok=1
for name in "${names[@]}"; do
  # shellcheck disable=SC2086
  if ! (cd "$data" && "$client" blend ${args_of[$name]} --sweep 3 --weights "${weights_of[$name]}" \
        --out "$farm/local/$name") >"$farm/local/$name.jsonl" 2>"$farm/local/$name.err"; then
    ok=0; fail "(e) local blend of $name: $(tail -n1 "$farm/local/$name.err")"; continue
  fi
  for dir in "$farm/out/$name.r1" "$farm/out/$name.d3"; do
    if ! report=$(/usr/bin/python3 - "$dir" "$farm/local/$name" <<'EOF'
import glob, os, sys
farm, local = sys.argv[1], sys.argv[2]
def verts(path):
    with open(path) as f:
        return [tuple(map(float, l.split()[1:4])) for l in f if l.startswith("v ")]
files = sorted(os.path.basename(p) for p in glob.glob(os.path.join(local, "frame_*.obj")))
if len(files) != 3 or sorted(os.path.basename(p) for p in glob.glob(os.path.join(farm, "frame_*.obj"))) != files:
    sys.exit(f"frame files differ: {files}")
worst = 0.0
for f in files:
    a, b = verts(os.path.join(farm, f)), verts(os.path.join(local, f))
    if len(a) != len(b) or not a:
        sys.exit(f"{f}: {len(a)} vertices from the farm, {len(b)} local")
    diag = sum((max(v[k] for v in b) - min(v[k] for v in b)) ** 2 for k in range(3)) ** 0.5
    worst = max(worst, max(abs(x - y) for p, q in zip(a, b) for x, y in zip(p, q)) / diag)
print(f"{worst:.2e}")
sys.exit(0 if worst < 1e-5 else 1)
EOF
    ); then
      ok=0; fail "(e) $name: $(basename "$dir") differs from the local solve: $report"
    else
      echo "  $name $(basename "$dir"): max |farm - local| = $report of the bounding-box diagonal"
    fi
  done
done
[ "$ok" = 1 ] && pass "(e) farm frames equal local blend frames (max abs difference < 1e-5 of the bounding box) for ${#names[@]} characters, before and after the kill"

# (f) stateless frames: a bake split into two chunks on two different replicas is byte-identical to the whole
# bake (every frame is a function of its own request)
alive=()
for i in "${replicas[@]}"; do [ "replica-$i" = "$victim" ] || alive+=("127.0.0.1:5006$i"); done
name="${names[0]}"
mkdir -p "$farm/chunks"
/usr/bin/python3 - "$farm/chunks" "${weights_of[$name]}" <<'EOF'
import json, sys
out, end = sys.argv[1], [float(w) for w in sys.argv[2].split(",")]
frames = [{"weights": [((7 * i) % 12) / 11.0 * w for w in end]} for i in range(12)]  # out of order
for file, part in (("whole", frames), ("first", frames[:6]), ("second", frames[6:])):
    json.dump({"frames": part}, open(f"{out}/{file}.json", "w"))
EOF
chunk() {  # replica, scene, output directory
  "$client" solve --server "$1" --character "${id_of[$name]}" --frames "$farm/chunks/$2.json" --out "$3" \
    >"$3.jsonl" 2>"$3.err"
}
if chunk "${alive[0]}" whole "$farm/chunks/whole" && chunk "${alive[1]}" first "$farm/chunks/first" &&
   chunk "${alive[0]}" second "$farm/chunks/second"; then
  same=1
  for i in $(seq 0 11); do
    if [ "$i" -lt 6 ]; then part="$farm/chunks/first/frame_$(printf %04d "$i").obj"
    else part="$farm/chunks/second/frame_$(printf %04d $((i - 6))).obj"; fi
    cmp -s "$farm/chunks/whole/frame_$(printf %04d "$i").obj" "$part" || { same=0; echo "  frame $i differs" >&2; }
  done
  if [ "$same" = 1 ]; then
    pass "(f) a 12-frame bake in two chunks on ${alive[1]} and ${alive[0]} is byte-identical to the whole bake"
  else
    fail "(f) a chunked bake differs from the whole bake (stateless frames)"
  fi
else
  fail "(f) chunked bake: $(tail -qn1 "$farm/chunks/"*.err 2>/dev/null | head -n1)"
fi

timing_test=$(( $(date +%s) - s ))
finished=1
