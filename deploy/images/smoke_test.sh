#!/usr/bin/env bash
# End to end through the CPU image: builds it with podman (build_image.sh), starts a gaps-worker and a
# gaps-trainer container on the host network (token on both links, TLS between client and trainer, the
# trainer's data in a podman volume), waits for both to report healthy through the image's own health check,
# submits a small job of the paper's method (LLFF fern, 3 views, -r 8, 60 iterations, two diffusion phases
# on the reproject backend) with the image's `gaps` CLI, fetches its artifacts, then stops the
# trainer with SIGTERM and checks that it exits cleanly. Prints the image size and the containers' peak
# memory. Needs root or rootful podman, and fern under GAPS_DATA_DIR (default ../shared/data).
#   bash deploy/images/smoke_test.sh [--keep]        # --keep leaves containers, volume and scratch files
# From ctest (label container) it runs only when GAPS_CONTAINER_TESTS=1; otherwise, or without podman or
# fern, it exits 77 (skipped) saying why.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
export CONTAINERS_CONF=${CONTAINERS_CONF:-$here/containers.conf}
from_ctest=0
keep=0
for arg in "$@"; do
  case $arg in
    --from-ctest) from_ctest=1 ;;
    --keep) keep=1 ;;
    *) echo "smoke_test: unknown argument $arg" >&2; exit 2 ;;
  esac
done
skip() { echo "smoke_test: skipped: $*"; exit 77; }
if [ "$from_ctest" = 1 ] && [ "${GAPS_CONTAINER_TESTS:-0}" != 1 ]; then
  skip "builds the image (tens of minutes the first time); set GAPS_CONTAINER_TESTS=1 to run it"
fi
command -v podman >/dev/null || skip "podman is not installed (apt-get install podman debootstrap)"
scene=${GAPS_DATA_DIR:-$root/../shared/data}/llff/fern
[ -f "$scene/poses_bounds.npy" ] || skip "no LLFF fern scene at $scene (set GAPS_DATA_DIR)"
scene=$(cd "$scene" && pwd)

image=${GAPS_IMAGE:-gaps:cpu}
name=gaps-smoke-$$
scratch=$(mktemp -d)
stats_pid=
cleanup() {
  [ -z "$stats_pid" ] || kill "$stats_pid" 2>/dev/null || true
  if [ "$keep" = 0 ]; then
    podman rm -f -v -t 0 "$name-worker" "$name-trainer" >/dev/null 2>&1 || true
    podman volume rm -f "$name-data" >/dev/null 2>&1 || true
    rm -rf "$scratch"
  else
    echo "smoke_test: kept containers $name-worker, $name-trainer, volume $name-data, files in $scratch"
  fi
}
trap cleanup EXIT
step() { echo "smoke_test: [$(date +%T)] $*"; }

step "building $image"
start=$(date +%s)
if [ -z "${GAPS_IMAGE:-}" ]; then bash "$here/build_image.sh" --tag "$image" 2>&1 | tail -3; fi
step "image ready after $(($(date +%s) - start)) s: $(podman image inspect --format '{{.Size}}' "$image" |
  awk '{printf "%.0f MB (%.2f GiB)", $1 / 1e6, $1 / 2^30}')"

# Secrets the containers' user (uid 10001) can read: a scratch copy, removed at the end.
bash "$root/deploy/make_secrets.sh" "$scratch/secrets" >/dev/null
chmod 0755 "$scratch" "$scratch/secrets" && chmod 0644 "$scratch"/secrets/*
mkdir -m 0777 "$scratch/out"
free_port() { python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }
worker_port=$(free_port)
trainer_port=$(free_port)
# podman without systemd cannot schedule the HEALTHCHECK (it says so on stderr, kept in podman.err); the
# checks below run it on demand with `podman healthcheck run`.
run=(podman run -d --network host -v "$scratch/secrets:/secrets:ro")

step "starting the worker on 127.0.0.1:$worker_port and the trainer on 127.0.0.1:$trainer_port"
"${run[@]}" --name "$name-worker" -e GAPS_HEALTH_ADDRESS="127.0.0.1:$worker_port" "$image" \
  gaps-worker --listen="127.0.0.1:$worker_port" --backend=reproject --token_file=/secrets/worker_token \
  >/dev/null 2>>"$scratch/podman.err"
podman volume create "$name-data" >/dev/null
"${run[@]}" --name "$name-trainer" -v "$name-data:/var/lib/gaps" -e GAPS_HEALTH_ADDRESS="127.0.0.1:$trainer_port" \
  -e GAPS_HEALTH_TLS_CA=/secrets/ca.crt "$image" \
  gaps-trainer --listen="127.0.0.1:$trainer_port" --data_dir=/var/lib/gaps/data --device=cpu \
  --workers="127.0.0.1:$worker_port" --token_file=/secrets/token --worker_token_file=/secrets/worker_token \
  --tls_cert=/secrets/tls.crt --tls_key=/secrets/tls.key >/dev/null 2>>"$scratch/podman.err"

# Peak memory of each container, sampled every 2 s while they run.
(while true; do podman stats --no-stream --format '{{.Name}} {{.MemUsage}}' "$name-worker" "$name-trainer" \
   2>/dev/null >>"$scratch/stats"; sleep 2; done) &
stats_pid=$!

wait_healthy() {
  for _ in $(seq 60); do
    if podman healthcheck run "$1" >/dev/null 2>&1; then
      step "$1 healthy (the image's HEALTHCHECK: $(podman exec "$1" gaps-health-check 2>&1))"
      return 0
    fi
    sleep 1
  done
  echo "smoke_test: $1 never became healthy; its log:"
  podman logs "$1"
  exit 1
}
wait_healthy "$name-worker"
wait_healthy "$name-trainer"

step "submitting fern (3 views, -r 8, 60 iterations, method 'full', two diffusion phases) with the image's gaps CLI"
start=$(date +%s)
client=(podman run --rm --no-healthcheck --network host -v "$scratch/secrets:/secrets:ro" "$image" gaps)
remote=(--trainer="127.0.0.1:$trainer_port" --token_file=/secrets/token --tls_ca=/secrets/ca.crt)
podman run --rm --no-healthcheck --network host -v "$scratch/secrets:/secrets:ro" -v "$scene:/scene:ro" "$image" \
  gaps submit /scene --views=3 --resolution=8 --iterations=60 --variant=full --init=random --random_points=5000 \
  --warmup_iterations=20 --phase_interval=20 --n_active=4 --name=smoke --quiet --watch \
  "${remote[@]}" >"$scratch/submit.out" 2>"$scratch/submit.err" || {
  echo "smoke_test: the job failed:"; cat "$scratch/submit.out" "$scratch/submit.err"
  podman logs "$name-trainer" | tail -20
  exit 1
}
sed 's/^/  /' "$scratch/submit.err" "$scratch/submit.out"
job=$(head -1 "$scratch/submit.out")
step "job $job succeeded in $(($(date +%s) - start)) s (upload, training, evaluation)"
grep -q "phase 1 finished" "$scratch/submit.err" || { echo "smoke_test: no diffusion phase ran"; exit 1; }

podman run --rm --no-healthcheck --network host -v "$scratch/secrets:/secrets:ro" -v "$scratch/out:/out" "$image" \
  gaps fetch "$job" -o "/out/$job" "${remote[@]}" >"$scratch/fetch.out"
step "fetched $(wc -l <"$scratch/fetch.out") files: $(xargs -n1 basename <"$scratch/fetch.out" | sort | tr '\n' ' ')"
[ -s "$scratch/out/$job/metrics.json" ] || { echo "smoke_test: no metrics.json among the artifacts"; exit 1; }
"${client[@]}" list "${remote[@]}" | sed 's/^/  /'

step "stopping the trainer with SIGTERM"
podman stop -t 60 "$name-trainer" >/dev/null 2>>"$scratch/podman.err"
code=$(podman inspect --format '{{.State.ExitCode}}' "$name-trainer")
podman logs "$name-trainer" 2>&1 | sed 's/^/  trainer: /'
[ "$code" = 0 ] || { echo "smoke_test: the trainer exited with $code after SIGTERM"; exit 1; }
podman stop -t 30 "$name-worker" >/dev/null 2>>"$scratch/podman.err"
kill "$stats_pid" 2>/dev/null || true
stats_pid=
if [ -s "$scratch/stats" ]; then
  step "peak memory (podman stats every 2 s):"
  python3 - "$scratch/stats" <<'EOF'
import re, sys
units = {"b": 1, "kb": 1e3, "mb": 1e6, "gb": 1e9, "kib": 2**10, "mib": 2**20, "gib": 2**30}
peak = {}
for line in open(sys.argv[1]):
    m = re.match(r"(\S+) ([\d.]+)([a-zA-Z]+) /", line)
    if m:
        peak[m[1]] = max(peak.get(m[1], 0), float(m[2]) * units[m[3].lower()])
for name, value in sorted(peak.items()):
    print(f"  {name.rsplit('-', 1)[1]}: {value / 2**20:.0f} MiB")
EOF
fi
step "passed"
