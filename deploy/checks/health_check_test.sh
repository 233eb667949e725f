#!/usr/bin/env bash
# The image's health check (deploy/images/gaps_health_check.py) against a real gaps-worker: SERVING over
# plaintext and over TLS with a certificate from make_secrets.sh (so the certificates it makes are ones the
# services accept), a failure without the CA, and a failure once the worker has stopped.
#   bash deploy/checks/health_check_test.sh path/to/gaps-worker
# Runs the check with Debian's python3 and python3-grpcio, as the image does.
set -euo pipefail
worker_bin=$1
deploy=$(cd "$(dirname "$0")/.." && pwd)
check=(/usr/bin/python3 "$deploy/images/gaps_health_check.py" --timeout 5)
if ! /usr/bin/python3 -c 'import grpc' 2>/dev/null; then
  echo "health_check_test: /usr/bin/python3 cannot import grpc (scripts/setup.sh installs python3-grpcio)"
  exit 1
fi
scratch=$(mktemp -d)
pid=
cleanup() {
  if [ -n "$pid" ]; then kill "$pid" 2>/dev/null || true; wait "$pid" 2>/dev/null || true; fi
  rm -rf "$scratch"
}
trap cleanup EXIT
bash "$deploy/make_secrets.sh" "$scratch/secrets" >/dev/null

# Starts the worker on a free port (it prints the one it got) and sets $pid and $port.
start_worker() {
  "$worker_bin" --listen 127.0.0.1:0 --token_file "$scratch/secrets/worker_token" "$@" >"$scratch/worker.log" 2>&1 &
  pid=$!
  for _ in $(seq 100); do
    port=$(sed -n 's/.* on port \([0-9]*\).*/\1/p' "$scratch/worker.log")
    [ -n "$port" ] && return 0
    kill -0 "$pid" 2>/dev/null || break
    sleep 0.1
  done
  echo "health_check_test: the worker did not start:"; cat "$scratch/worker.log"
  exit 1
}
stop_worker() { kill "$pid"; wait "$pid" || true; pid=; }
expect() {  # expect STATUS DESCRIPTION COMMAND...
  local want=$1 what=$2 got=0
  shift 2
  "$@" >"$scratch/out" 2>&1 || got=$?
  if [ "$got" != "$want" ]; then
    echo "health_check_test: FAILED: $what: exit $got, expected $want:"; cat "$scratch/out"
    exit 1
  fi
  echo "health_check_test: ok: $what: $(head -1 "$scratch/out")"
}

start_worker
expect 0 "plaintext worker is SERVING" "${check[@]}" --address "127.0.0.1:$port"
GAPS_HEALTH_ADDRESS="127.0.0.1:$port" expect 0 "address from GAPS_HEALTH_ADDRESS" "${check[@]}"
stop_worker
expect 1 "stopped worker" "${check[@]}" --address "127.0.0.1:$port"

start_worker --tls_cert "$scratch/secrets/tls.crt" --tls_key "$scratch/secrets/tls.key"
expect 0 "TLS worker with the CA" "${check[@]}" --address "127.0.0.1:$port" --tls_ca "$scratch/secrets/ca.crt"
expect 0 "TLS worker by a name of its certificate" "${check[@]}" --address "127.0.0.1:$port" \
  --tls_ca "$scratch/secrets/ca.crt" --tls_server_name gaps-trainer
expect 1 "TLS worker by a name not in its certificate" "${check[@]}" --address "127.0.0.1:$port" \
  --tls_ca "$scratch/secrets/ca.crt" --tls_server_name elsewhere.example.org
expect 1 "TLS worker asked in plaintext" "${check[@]}" --address "127.0.0.1:$port"
echo "health_check_test: passed"
