#!/usr/bin/env bash
# The server's resident memory as a process, with the ICT face's 16 expressions uploaded to a server with a fresh
# cache directory (each target's path spooled as it is solved, then read from the character's file), and after a
# restart on that directory with its first frame. Prints a table and writes OUT/server_memory.md. About four
# minutes on two cores.
#   bash bench/server_memory.sh [BUILD_DIR (build/release)] [OUT (bench-results)] [SHARED (../shared/meshes)]
# Skips cleanly (exit 0, a note in the table) when the face is not there.
set -euo pipefail
cd "$(dirname "$0")/.."
build="${1:-build/release}"
out="${2:-bench-results}"
shared="${3:-$(cd .. && pwd)/shared/meshes}"
face="$shared/face6706"
mkdir -p "$out"
report="$out/server_memory.md"
if [ ! -f "$face/generic_neutral_mesh.obj" ]; then
  echo "server_memory: skipped ($face not found)" | tee "$report"
  exit 0
fi
server="$build/server/springblend-server"
cli="$build/client/springblend"
work="$(mktemp -d)"
pid=""
cleanup() {
  if [ -n "$pid" ]; then kill "$pid" 2> /dev/null || true; wait "$pid" 2> /dev/null || true; fi
  rm -rf "$work"
}
trap cleanup EXIT
targets=()
for t in browDown_L browDown_R browInnerUp_L browInnerUp_R cheekPuff_L cheekPuff_R eyeBlink_L eyeBlink_R jawOpen \
  mouthClose mouthFunnel mouthPucker mouthSmile_L mouthSmile_R noseSneer_L noseSneer_R; do
  targets+=(--target "$face/$t.obj")
done
weights="0,0,0,0,0,0,0,0,0.55,0,0,0,0,0,0,0"  # jawOpen at 0.55
port=$((20000 + RANDOM % 20000))
address="127.0.0.1:$port"
mb() { awk -v key="$2:" '$1 == key {printf "%.0f", $2 / 1024}' "/proc/$1/status"; }
serve() {  # cache directory ("" for none), log name
  "$server" --listen "$address" --cache-dir "$1" --workers 1 > "$work/server-$2.log" 2>&1 &
  pid=$!
  for _ in $(seq 150); do
    if "$cli" health --server "$address" > /dev/null 2>&1; then return 0; fi
    sleep 0.2
  done
  echo "server_memory: the server did not start (see $work/server-$2.log)" >&2
  exit 1
}
stop() { kill "$pid"; wait "$pid" 2> /dev/null || true; pid=""; }
now() { date +%s.%N; }
rows=()
mkdir -p "$work/cache"
serve "$work/cache" upload
echo 5 > "/proc/$pid/clear_refs" || true  # resets VmHWM where the kernel allows it
before=$(mb "$pid" VmRSS)
start=$(now)
"$cli" upload --server "$address" --rest "$face/generic_neutral_mesh.obj" "${targets[@]}" --name face16 \
  > "$work/upload.json" 2> "$work/upload.err"
upload_s=$(echo "$(now) - $start" | bc)
uploaded=$(mb "$pid" VmRSS)
peak=$(mb "$pid" VmHWM)
"$cli" solve --server "$address" --character face16 --weights "$weights" --out "$work/frame-upload" \
  > "$work/solve-upload.json"
rows+=("| uploaded | $before | $(printf '%.0f' "$upload_s") | $uploaded | $peak | $(mb "$pid" VmRSS) | |")
stop
serve "$work/cache" restart
start=$(now)
"$cli" solve --server "$address" --character face16 --weights "$weights" --out "$work/frame-restart" \
  > "$work/solve-restart.json"
first_s=$(echo "$(now) - $start" | bc)
rows+=("| restarted on the cache directory | | | | | $(mb "$pid" VmRSS) | $(printf '%.2f' "$first_s") |")
stop
same="the frame is the same bytes after the upload and after the restart"
if ! diff -r "$work/frame-upload" "$work/frame-restart" > /dev/null; then
  same="THE FRAMES DIFFER between the upload and the restart"
fi
{
  echo "# Server memory: the ICT face's 16 expressions ($(date -u +%Y-%m-%d), $(nproc) cores)"
  echo
  echo "| server | resident MB at start | upload s | resident MB after the upload | peak MB | resident MB after a frame (jawOpen 0.55) | first frame s |"
  echo "|---|---:|---:|---:|---:|---:|---:|"
  printf '%s\n' "${rows[@]}"
  echo
  echo "$same."
} | tee "$report"
