#!/usr/bin/env bash
# Makes the secrets a deployment reads, as files that git ignores (never commit them):
#   token          bearer token clients must send to the trainer (gaps --token_file)
#   worker_token   bearer token the trainer sends to the workers (the trainer's own token is never sent)
#   ca.crt ca.key  a private CA; ca.crt is what clients pass as --tls_ca (keep ca.key off the cluster)
#   tls.crt tls.key the trainer's TLS certificate (signed by the CA) and key
#   postgres_password  the job store's database password (the scale-out deployments)
# Existing files are kept, so running it again changes nothing; --force makes new ones.
#
#   bash deploy/make_secrets.sh compose [--dns NAME]... [--force]   # deploy/compose/secrets/ and .env
#   bash deploy/make_secrets.sh k8s [--dns NAME]... [--force]       # deploy/k8s/base/secrets/ (+ scale-out's)
#   bash deploy/make_secrets.sh DIR [--dns NAME]... [--force]       # all of them into DIR
# --dns adds a name the trainer's certificate is valid for (the address clients use from outside, e.g.
# gaps.example.org); the certificate always names localhost, 127.0.0.1 and the trainer's in-cluster names.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
[ $# -ge 1 ] || { sed -n '2,15p' "$0" >&2; exit 2; }
target=$1
shift
force=0
names=(localhost gaps-trainer trainer gaps-trainer.gaps.svc gaps-trainer.gaps.svc.cluster.local)
while [ $# -gt 0 ]; do
  case $1 in
    --force) force=1 ;;
    --dns) names+=("$2"); shift ;;
    *) echo "make_secrets: unknown argument $1" >&2; exit 2 ;;
  esac
  shift
done
command -v openssl >/dev/null || { echo "make_secrets: needs openssl" >&2; exit 1; }
umask 077

fresh() { [ "$force" = 1 ] || [ ! -s "$1" ]; }

random_token() {
  local file=$1
  fresh "$file" || return 0
  openssl rand -hex 32 >"$file"
  echo "make_secrets: wrote $file"
}

# A CA (kept if present) and a server certificate for the trainer's names, valid for a year (ECDSA P-256).
tls_files() {
  local dir=$1
  if fresh "$dir/ca.crt" || fresh "$dir/ca.key"; then
    openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 3650 -subj "/CN=gaps CA" \
      -keyout "$dir/ca.key" -out "$dir/ca.crt" 2>/dev/null
    rm -f "$dir/tls.crt"
    echo "make_secrets: wrote $dir/ca.crt and ca.key"
  fi
  fresh "$dir/tls.crt" || [ ! -s "$dir/tls.key" ] || return 0
  local san="IP:127.0.0.1" name
  for name in "${names[@]}"; do san+=",DNS:$name"; done
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=gaps-trainer" \
    -keyout "$dir/tls.key" -out "$dir/tls.csr" 2>/dev/null
  openssl x509 -req -in "$dir/tls.csr" -CA "$dir/ca.crt" -CAkey "$dir/ca.key" -CAcreateserial -days 365 \
    -extfile <(printf 'subjectAltName=%s\nextendedKeyUsage=serverAuth\n' "$san") -out "$dir/tls.crt" 2>/dev/null
  rm -f "$dir/tls.csr" "$dir/ca.srl"
  echo "make_secrets: wrote $dir/tls.crt and tls.key ($san)"
}

all_into() {
  local dir=$1
  mkdir -p "$dir"
  random_token "$dir/token"
  random_token "$dir/worker_token"
  random_token "$dir/postgres_password"
  tls_files "$dir"
}

case $target in
  compose)
    dir=$here/compose/secrets
    all_into "$dir"
    # Compose mounts secrets as they are on the host: the services' user (uid 10001) must be able to read
    # them, so the files are world-readable inside a folder only the owner can enter.
    chmod 0700 "$dir"
    chmod 0644 "$dir"/token "$dir"/worker_token "$dir"/tls.crt "$dir"/tls.key "$dir"/ca.crt
    # PostgreSQL's password reaches both the database and libpq (PGPASSWORD) through the environment.
    if fresh "$here/compose/.env" || ! grep -q '^GAPS_POSTGRES_PASSWORD=' "$here/compose/.env"; then
      echo "GAPS_POSTGRES_PASSWORD=$(cat "$dir/postgres_password")" >"$here/compose/.env"
      echo "make_secrets: wrote $here/compose/.env"
    fi
    ;;
  k8s)
    dir=$here/k8s/base/secrets
    mkdir -p "$dir"
    random_token "$dir/token"
    random_token "$dir/worker_token"
    tls_files "$dir"
    # The CA's key is not part of any Secret; it stays with whoever issues certificates.
    mkdir -p "$here/k8s/overlays/scale-out/secrets"
    random_token "$here/k8s/overlays/scale-out/secrets/postgres_password"
    ;;
  *) all_into "$target" ;;
esac
