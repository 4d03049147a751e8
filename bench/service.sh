#!/usr/bin/env bash
# Service throughput: frames per second through springblend-server with 1, 2 and 4 concurrent streams on the
# bundled ICT face (neutral to jawOpen, the paper's protocol: a sweep of STEPS frames per stream, every frame stateless),
# and the server's overhead over the same sweep solved locally by `springblend blend`.
#   bash bench/service.sh [BUILD_DIR (default build/bench)] [OUT_DIR (default bench-results)]
# Environment: STEPS (default 36), STREAMS (default "1 2 4").
set -euo pipefail
cd "$(dirname "$0")/.."
build="${1:-build/bench}"
out="${2:-bench-results}"
steps="${STEPS:-36}"
streams_list="${STREAMS:-1 2 4}"
cli="$build/client/springblend"
server="$build/server/springblend-server"
for b in "$cli" "$server"; do
  [ -x "$b" ] || { echo "service.sh: $b is missing; build the bench preset first (see README, Benchmark)" >&2; exit 2; }
done
mkdir -p "$out"
work=$(mktemp -d)
trap 'kill "$server_pid" 2>/dev/null || true; wait 2>/dev/null || true; rm -rf "$work"' EXIT
face=tests/data/face
rest="$face/generic_neutral_mesh.obj"
target="$face/jawOpen.obj"

now() { date +%s.%N; }

# Local: the same sweep in one process; the per-frame solve times exclude loading and the rig build.
"$cli" blend --rest "$rest" --target "$target" --sweep "$steps" --out "$work/local" > "$work/local.jsonl"
local_ms=$(/usr/bin/python3 -c "import json,sys; print(sum(json.loads(l)['solve_ms'] for l in open(sys.argv[1]) if l.strip()))" "$work/local.jsonl")

"$server" --listen 127.0.0.1:0 --cache-dir "$work/cache" > "$work/server.out" 2> "$work/server.err" &
server_pid=$!
for _ in $(seq 200); do grep -q "listening on" "$work/server.out" 2>/dev/null && break; sleep 0.05; done
address=$(sed -n 's/.*listening on //p' "$work/server.out")
"$cli" upload --server "$address" --rest "$rest" --target "$target" --name face > "$work/character.json"
id=$(sed -n 's/.*"id":"\([0-9a-f]*\)".*/\1/p' "$work/character.json")

rows=()
one_stream_s=""
for streams in $streams_list; do
  start=$(now)
  pids=()
  for s in $(seq "$streams"); do
    "$cli" solve --server "$address" --character "$id" --sweep "$steps" --weights 1 --out "$work/s$streams-$s" \
      > "$work/s$streams-$s.jsonl" &
    pids+=($!)
  done
  for p in "${pids[@]}"; do wait "$p"; done
  wall=$(/usr/bin/python3 -c "import sys; print(float(sys.argv[2]) - float(sys.argv[1]))" "$start" "$(now)")
  frames=$(cat "$work"/s"$streams"-*.jsonl | grep -c '"frame"' || true)
  if [ "$streams" = 1 ]; then
    one_stream_s="$wall"
    # The same run seen from both ends: the client's time to the last frame against the server's solve times.
    read -r served_solve_ms last_received_ms < <(/usr/bin/python3 -c "
import json, sys
lines = [json.loads(l) for l in open(sys.argv[1]) if l.strip()]
print(sum(l['solve_ms'] for l in lines), max(l['received_ms'] for l in lines))" "$work/s1-1.jsonl")
  fi
  rows+=("$(/usr/bin/python3 -c "
import sys
streams, frames, wall = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3])
print(f'| {streams} | {frames} | {wall:.2f} | {frames / wall:.2f} | {1000 * wall * streams / frames:.0f} |')
" "$streams" "$frames" "$wall")")
done

served_overhead=$(/usr/bin/python3 -c "
import sys
solve, received = float(sys.argv[1]), float(sys.argv[2])
print(f'{100 * (received - solve) / solve:.1f} % ({received - solve:.0f} ms over {solve:.0f} ms)')
" "${served_solve_ms:-1}" "${last_received_ms:-0}")
overhead=$(/usr/bin/python3 -c "
import sys
local_ms, one = float(sys.argv[1]), sys.argv[2]
print(f'{100 * (float(one) * 1000 - local_ms) / local_ms:.1f} %' if one else '-')
" "$local_ms" "$one_stream_s")

{
  echo "# springblend service throughput"
  echo
  echo "machine: nproc $(nproc), $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | sed 's/^ //'), $(date -u '+%Y-%m-%d %H:%M UTC'), git $(git describe --always --dirty 2>/dev/null || echo n/a)"
  echo
  echo "Bundled ICT face (neutral to jawOpen), $steps-frame sweeps, one per stream, through a server on"
  echo "loopback (default workers = cores). Wall time from starting the clients to the last frame."
  echo
  echo "| streams | frames | wall s | frames/s | ms per frame per stream |"
  echo "|---|---|---|---|---|"
  printf '%s\n' "${rows[@]}"
  echo
  echo "Local solve of the same sweep (sum of per-frame solve times): $(printf '%.0f' "$local_ms") ms."
  echo "Server overhead with one stream (client process start, connection, transfer, server work around the"
  echo "solve) over the local solve: $overhead. The two runs are separate solves on a shared machine, so this"
  echo "also holds their difference in solve time."
  echo
  echo "Service overhead in one run (one stream): the client's time from the call to the last frame against the"
  echo "sum of the server's per-frame solve times (request decoding, queueing, encoding, transfer and the"
  echo "client's decoding, with the solve itself taken out): $served_overhead. Frames are stateless, so the"
  echo "server's workers solve several frames of one stream at once: where the solve times add up to more than"
  echo "the wall time this is negative, the gain of that parallelism rather than an overhead."
} | tee "$out/service.md"
