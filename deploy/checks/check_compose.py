#!/usr/bin/env python3
"""Validates the compose files offline: `docker-compose config -q` on each combination the files are meant
for (compose.yaml alone, with the two-GPU file, with the PostgreSQL file, with both), then checks on the
merged result that the gaps services are wired as the project needs.

    python3 deploy/checks/check_compose.py [--docker-compose PATH]

Runs on a scratch copy of deploy/compose without secrets/ or .env (the variables a file requires are set
to stand-ins), so a checkout's own secrets neither help nor hurt. Exit status 0 when every combination
passes; 1 with one line per problem otherwise. Needs docker-compose (Debian's 1.29) and PyPI's PyYAML.
"""
import argparse
import os
import pathlib
import re
import shutil
import subprocess
import sys
import tempfile

import yaml

from gaps_flags import effective_flags, listen_port, program, uses_cuda

COMPOSE = pathlib.Path(__file__).resolve().parent.parent / "compose"
COMBINATIONS = (
    ("compose.yaml",),
    ("compose.yaml", "compose.two-gpus.yaml"),
    ("compose.yaml", "compose.postgres.yaml"),
    ("compose.yaml", "compose.two-gpus.yaml", "compose.postgres.yaml"),
)
# What the files interpolate and make_secrets.sh would provide.
STAND_INS = {"GAPS_POSTGRES_PASSWORD": "stand-in"}
DEFAULT_PORTS = {"gaps-trainer": 50051, "gaps-worker": 50052}
# The trainer's default --worker_timeout_s (server/trainer_main.cpp): the longest an iteration can wait on
# one generation call, so the least time a stopping trainer may need before it can checkpoint.
DEFAULT_WORKER_TIMEOUT_S = 300
# Services that share a GPU must fit the card the one-host files are made for, a 24 GB card (23.99 GiB, a
# little of it the driver's): their --gpu_memory_gib caps plus a CUDA context each (docs/deploy.md, "What
# hardware do I need", measured with bench/placements_bench.py).
SHARED_CARD_GIB = 23.0
CONTEXT_GIB = 0.5


def seconds(duration):
    """Compose's durations ("360s", "6m", "1m30s", "1h"); compose's default grace period is 10 s."""
    if duration is None:
        return 10
    parts = re.findall(r"(\d+(?:\.\d+)?)(h|ms|m|s|us)", str(duration))
    scale = {"h": 3600, "m": 60, "s": 1, "ms": 1e-3, "us": 1e-6}
    return sum(float(n) * scale[unit] for n, unit in parts)


def gaps_services(config):
    """(name, service, program, flags) of each service that runs a gaps binary."""
    for name, s in config["services"].items():
        argv = (s.get("entrypoint") or []) + (s.get("command") or [])
        env = s.get("environment") or {}
        if program(argv) in DEFAULT_PORTS:
            yield name, s, program(argv), effective_flags(argv, env)


def check_workers(config):
    """Each trainer's workers are services of this file that run gaps-worker on that port, awaited healthy."""
    problems = []
    workers = {name: flags for name, _, prog, flags in gaps_services(config) if prog == "gaps-worker"}
    for name, s, prog, flags in gaps_services(config):
        if prog != "gaps-trainer":
            continue
        addresses = list(filter(None, flags.get("workers", "").split(",")))
        if not addresses:
            problems.append(f"{name}: no --workers")
        for address in addresses:
            host, _, port = address.rpartition(":")
            if host not in workers:
                problems.append(f"{name}: worker address {address} names no gaps-worker service")
                continue
            if not port.isdigit() or int(port) != listen_port(workers[host], DEFAULT_PORTS["gaps-worker"]):
                problems.append(f"{name}: worker address {address}: {host} listens on another port")
            if (s.get("depends_on") or {}).get(host, {}).get("condition") != "service_healthy":
                problems.append(f"{name}: does not wait for {host} to be healthy")
    return problems


def check_service(name, s, prog, flags):
    problems = []
    port = listen_port(flags, DEFAULT_PORTS[prog])
    env = s.get("environment") or {}
    if "healthcheck" not in s:
        problems.append(f"{name}: no healthcheck")
    health = env.get("GAPS_HEALTH_ADDRESS", "127.0.0.1:50051")
    if int(health.rpartition(":")[2]) != port:
        problems.append(f"{name}: GAPS_HEALTH_ADDRESS {health} is not the port it listens on ({port})")
    if flags.get("tls_cert") and not env.get("GAPS_HEALTH_TLS_CA"):
        problems.append(f"{name}: serves TLS but its health check has no GAPS_HEALTH_TLS_CA")
    attached = {sec["source"] for sec in s.get("secrets", [])}
    argv = (s.get("entrypoint") or []) + (s.get("command") or []) + [str(v) for v in env.values()]
    for secret in sorted({m for a in argv for m in re.findall(r"/run/secrets/([\w.-]+)", a)} - attached):
        problems.append(f"{name}: reads /run/secrets/{secret} but the secret is not attached")
    if prog == "gaps-trainer":
        timeout = int(flags.get("worker_timeout_s", DEFAULT_WORKER_TIMEOUT_S))
        if seconds(s.get("stop_grace_period")) <= timeout:
            problems.append(f"{name}: stop_grace_period {s.get('stop_grace_period', '10s')} leaves no time to "
                            f"checkpoint after a generation call of up to --worker_timeout_s={timeout}")
    devices = s.get("deploy", {}).get("resources", {}).get("reservations", {}).get("devices", [])
    if uses_cuda(flags) and not any("gpu" in d.get("capabilities", []) for d in devices):
        problems.append(f"{name}: --device={flags['device']} without a GPU reservation")
    return problems


def check_shared_gpus(config):
    """CUDA services reserving the same GPU (no device_ids: all of them) each cap their allocator, and the caps
    with a CUDA context each fit SHARED_CARD_GIB."""
    by_gpu = {}
    for name, s, prog, flags in gaps_services(config):
        if not uses_cuda(flags):
            continue
        devices = s.get("deploy", {}).get("resources", {}).get("reservations", {}).get("devices", [])
        ids = [str(i) for d in devices for i in (d.get("device_ids") or ["all"])]
        for gpu in ids or ["all"]:
            by_gpu.setdefault(gpu, []).append((name, flags))
    if "all" in by_gpu:  # a service on every GPU shares each with the others
        for gpu in [g for g in by_gpu if g != "all"]:
            by_gpu[gpu] += by_gpu["all"]
    problems = []
    for gpu, services in sorted(by_gpu.items()):
        if len(services) < 2:
            continue
        names = ", ".join(sorted(name for name, _ in services))
        caps = [float(flags.get("gpu_memory_gib", 0)) for _, flags in services]
        for (name, _), cap in zip(services, caps):
            if cap <= 0:
                problems.append(f"{name}: shares GPU {gpu} ({names}) without a --gpu_memory_gib cap")
        total = sum(caps) + CONTEXT_GIB * len(services)
        if all(c > 0 for c in caps) and total > SHARED_CARD_GIB:
            problems.append(f"GPU {gpu} ({names}): caps and contexts add up to {total:.1f} GiB, more than a "
                            f"24 GB card's {SHARED_CARD_GIB} GiB")
    return problems


def check_shared_data(config):
    """Trainers that share a data volume must share a PostgreSQL job store (SQLite has one owner)."""
    by_volume = {}
    for name, s, prog, flags in gaps_services(config):
        if prog == "gaps-trainer":
            for v in s.get("volumes", []):
                source = v.split(":")[0] if isinstance(v, str) else v.get("source")
                by_volume.setdefault(source, []).append((name, flags))
    problems = []
    for volume, trainers in by_volume.items():
        if len(trainers) > 1:
            for name, flags in trainers:
                if not flags.get("job_store", "").startswith(("postgresql://", "postgres://")):
                    problems.append(f"{name}: shares volume {volume} with other trainers but has no PostgreSQL "
                                    f"job store")
    return problems


def check_ports(config):
    seen, problems = {}, []
    for name, s in config["services"].items():
        for p in s.get("ports", []):
            published = p.get("published") if isinstance(p, dict) else str(p).split(":")[0]
            if published in seen:
                problems.append(f"{name}: host port {published} is also published by {seen[published]}")
            seen[published] = name
    return problems


def check_config(config):
    problems = check_workers(config) + check_shared_data(config) + check_ports(config) + check_shared_gpus(config)
    for name, s, prog, flags in gaps_services(config):
        problems += check_service(name, s, prog, flags)
    if not any(prog == "gaps-trainer" for _, _, prog, _ in gaps_services(config)):
        problems.append("no gaps-trainer service")
    return problems


def compose(tool, folder, files, env, *args):
    command = [tool] + [a for f in files for a in ("-f", str(folder / f))] + ["config", *args]
    return subprocess.run(command, capture_output=True, text=True, env=env, cwd=folder)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--docker-compose", default=shutil.which("docker-compose"))
    args = parser.parse_args(argv)
    if not args.docker_compose:
        print("check_compose: docker-compose not found (scripts/setup.sh installs Debian's docker-compose)")
        return 1
    problems = []
    listed = {f for combination in COMBINATIONS for f in combination}
    for path in sorted(COMPOSE.glob("*.yaml")):
        extended = any(f"file: {path.name}" in (COMPOSE / f).read_text() for f in listed)
        if path.name not in listed and not extended:
            problems.append(f"{path.name}: in no checked combination (add it to COMBINATIONS)")
    with tempfile.TemporaryDirectory() as scratch:
        folder = pathlib.Path(scratch) / "compose"
        shutil.copytree(COMPOSE, folder, ignore=shutil.ignore_patterns("secrets", ".env"))
        env = {k: v for k, v in os.environ.items() if not k.startswith(("GAPS_", "COMPOSE_"))}
        for files in COMBINATIONS:
            label = " + ".join(files)
            result = compose(args.docker_compose, folder, files, {**env, **STAND_INS}, "-q")
            if result.returncode != 0:
                problems.append(f"{label}: docker-compose config -q failed: {result.stderr.strip()}")
                continue
            # A value a file requires (`${VAR:?...}`) must stop the rendering when missing, not become "".
            required = [v for v in STAND_INS if any(v in (folder / f).read_text() for f in files)]
            if required and compose(args.docker_compose, folder, files, env, "-q").returncode == 0:
                problems.append(f"{label}: renders without {', '.join(required)}")
            config = yaml.safe_load(compose(args.docker_compose, folder, files, {**env, **STAND_INS}).stdout)
            found = check_config(config)
            problems += [f"{label}: {p}" for p in found]
            print(f"check_compose: {label}: {len(config['services'])} services "
                  f"({', '.join(sorted(config['services']))}), {'OK' if not found else 'problems'}")
    for p in problems:
        print(f"  {p}")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
