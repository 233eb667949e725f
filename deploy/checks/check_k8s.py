#!/usr/bin/env python3
"""Renders the Kubernetes overlays and checks them offline.

For each overlay: `kubectl kustomize` (secrets made by make_secrets.sh in a scratch copy of deploy/, so the
real secrets/ folders are neither needed nor touched), then PyPI's kubernetes-validate in strict mode (every
field known and of the right type for the Kubernetes release given), then the checks below for what a
schema cannot see: that the objects refer to each other correctly and that the gaps services are wired
as the project needs.

    python3 deploy/checks/check_k8s.py [--kubernetes-version V]... [OVERLAY...]  # default: every overlay
    python3 deploy/checks/check_k8s.py --rendered FILE.yaml                       # checks only

Exit status 0 when every overlay passes; 1 with one line per problem otherwise. Needs kubectl (any
release with `kustomize`, Debian's kubernetes-client included), openssl, PyYAML and kubernetes-validate.
"""
import argparse
import pathlib
import shutil
import subprocess
import sys
import tempfile

import yaml

from gaps_flags import effective_flags as flags_of, program as program_of, uses_cuda

DEPLOY = pathlib.Path(__file__).resolve().parent.parent
K8S = DEPLOY / "k8s"
WORKLOADS = ("Deployment", "StatefulSet", "DaemonSet", "Job")
CLUSTER_SCOPED = ("Namespace", "PersistentVolume", "StorageClass", "ClusterRole", "ClusterRoleBinding",
                  "PriorityClass", "CustomResourceDefinition")
GPU = "nvidia.com/gpu"
# The trainer's default --worker_timeout_s (server/trainer_main.cpp): the longest an iteration can wait on
# one generation call, so the least time a stopping trainer may need before it can checkpoint.
DEFAULT_WORKER_TIMEOUT_S = 300


# ---------------------------------------------------------------------------------------------- the model
def key(obj):
    return obj["kind"], obj["metadata"].get("namespace"), obj["metadata"]["name"]


def pod_spec(obj):
    return obj["spec"]["template"]["spec"]


def pod_labels(obj):
    return obj["spec"]["template"]["metadata"].get("labels", {})


def selects(selector, labels):
    """True when a matchLabels-style selector (a plain map, as Services use) picks these labels."""
    return bool(selector) and all(labels.get(k) == v for k, v in selector.items())


def containers(obj):
    spec = pod_spec(obj)
    return spec.get("initContainers", []) + spec.get("containers", [])


def argv(container):
    return container.get("command", []) + container.get("args", [])


def program(container):
    return program_of(argv(container))


def effective_flags(container):
    return flags_of(argv(container), {e["name"]: e.get("value") for e in container.get("env", []) if "value" in e})


# ----------------------------------------------------------------------------------------------- checks
def check_namespaces(objs):
    """Every namespaced object in one namespace, which the output creates when it creates any."""
    problems = []
    spaces = {o["metadata"].get("namespace") for o in objs if o["kind"] not in CLUSTER_SCOPED}
    if None in spaces:
        missing = [f"{o['kind']}/{o['metadata']['name']}" for o in objs
                   if o["kind"] not in CLUSTER_SCOPED and not o["metadata"].get("namespace")]
        problems.append(f"objects without a namespace (they would land in kubectl's current one): {missing}")
    if len(spaces - {None}) > 1:
        problems.append(f"objects spread over several namespaces: {sorted(spaces - {None})}")
    created = {o["metadata"]["name"] for o in objs if o["kind"] == "Namespace"}
    if created and not (spaces - {None}) <= created:
        problems.append(f"namespaces used but not created: {sorted(spaces - {None} - created)}")
    return problems


def check_selectors(objs):
    """Workload selectors pick their own pods; Services, PodDisruptionBudgets and NetworkPolicies pick some."""
    problems = []
    workloads = [o for o in objs if o["kind"] in WORKLOADS]
    for w in workloads:
        selector = w["spec"].get("selector", {}).get("matchLabels", {})
        if w["kind"] != "Job" and not selects(selector, pod_labels(w)):
            problems.append(f"{w['kind']}/{w['metadata']['name']}: selector {selector} does not match its pod "
                            f"labels {pod_labels(w)}")

    def picked(ns, selector):
        return [w for w in workloads if w["metadata"].get("namespace") == ns and selects(selector, pod_labels(w))]

    for o in objs:
        ns, name = o["metadata"].get("namespace"), f"{o['kind']}/{o['metadata']['name']}"
        if o["kind"] == "Service" and o["spec"].get("selector"):
            targets = picked(ns, o["spec"]["selector"])
            if not targets:
                problems.append(f"{name}: selector {o['spec']['selector']} matches no pods")
            ports = {p.get("name") for w in targets for c in containers(w) for p in c.get("ports", [])}
            ports |= {p["containerPort"] for w in targets for c in containers(w) for p in c.get("ports", [])}
            for port in o["spec"].get("ports", []):
                target = port.get("targetPort", port["port"])
                if targets and target not in ports:
                    problems.append(f"{name}: targetPort {target} is not a port of the pods it selects")
        elif o["kind"] == "PodDisruptionBudget":
            if not picked(ns, o["spec"]["selector"].get("matchLabels", {})):
                problems.append(f"{name}: selector matches no pods")
        elif o["kind"] == "NetworkPolicy":
            if not picked(ns, o["spec"]["podSelector"].get("matchLabels", {})):
                problems.append(f"{name}: podSelector matches no pods")
            for rule in o["spec"].get("ingress", []):
                for peer in rule.get("from", []):
                    if "podSelector" in peer and "namespaceSelector" not in peer and \
                            not picked(ns, peer["podSelector"].get("matchLabels", {})):
                        problems.append(f"{name}: ingress from {peer['podSelector']} matches no pods")
    return problems


def check_references(objs):
    """Every Secret, ConfigMap and PersistentVolumeClaim a pod names exists in its namespace (with the key)."""
    problems = []
    have = {key(o): o for o in objs}

    def need(kind, ns, name, where, data_key=None):
        obj = have.get((kind, ns, name))
        if obj is None:
            problems.append(f"{where}: {kind} {name} is not in the output (namespace {ns})")
        elif data_key and data_key not in {**obj.get("data", {}), **obj.get("stringData", {})}:
            problems.append(f"{where}: {kind} {name} has no key {data_key}")

    for w in (o for o in objs if o["kind"] in WORKLOADS):
        ns, where = w["metadata"].get("namespace"), f"{w['kind']}/{w['metadata']['name']}"
        spec = pod_spec(w)
        claims = {t["metadata"]["name"] for t in w["spec"].get("volumeClaimTemplates", [])}
        for v in spec.get("volumes", []):
            if "secret" in v:
                need("Secret", ns, v["secret"]["secretName"], where)
            if "configMap" in v:
                need("ConfigMap", ns, v["configMap"]["name"], where)
            if "persistentVolumeClaim" in v:
                need("PersistentVolumeClaim", ns, v["persistentVolumeClaim"]["claimName"], where)
        for s in spec.get("imagePullSecrets", []):
            need("Secret", ns, s["name"], where)
        for c in containers(w):
            mounted = {v["name"] for v in spec.get("volumes", [])} | claims
            for m in c.get("volumeMounts", []):
                if m["name"] not in mounted:
                    problems.append(f"{where}: container {c['name']} mounts undeclared volume {m['name']}")
            for e in c.get("env", []):
                ref = e.get("valueFrom", {})
                if "secretKeyRef" in ref:
                    need("Secret", ns, ref["secretKeyRef"]["name"], where, ref["secretKeyRef"]["key"])
                if "configMapKeyRef" in ref:
                    need("ConfigMap", ns, ref["configMapKeyRef"]["name"], where, ref["configMapKeyRef"]["key"])
            for e in c.get("envFrom", []):
                if "secretRef" in e:
                    need("Secret", ns, e["secretRef"]["name"], where)
                if "configMapRef" in e:
                    need("ConfigMap", ns, e["configMapRef"]["name"], where)
    return problems


def check_containers(objs):
    """Resource limits everywhere; GPUs where CUDA is used; probes on every serving gaps container."""
    problems = []
    for w in (o for o in objs if o["kind"] in WORKLOADS):
        for c in containers(w):
            where = f"{w['kind']}/{w['metadata']['name']} container {c['name']}"
            limits = c.get("resources", {}).get("limits", {})
            requests = c.get("resources", {}).get("requests", {})
            if "memory" not in limits:
                problems.append(f"{where}: no memory limit")
            if not {"cpu", "memory"} <= set(requests):
                problems.append(f"{where}: no cpu and memory requests")
            flags = effective_flags(c)
            cuda = uses_cuda(flags)
            cuda_image = "cuda" in c.get("image", "").rsplit("/", 1)[-1]
            if (cuda or cuda_image) and int(limits.get(GPU, 0)) < 1:
                problems.append(f"{where}: runs CUDA ({c.get('image')}, --device={flags.get('device', 'cpu')}) "
                                f"without a {GPU} limit")
            if GPU in requests and requests[GPU] != limits.get(GPU):
                problems.append(f"{where}: {GPU} request {requests[GPU]} differs from its limit")
            if cuda and not cuda_image:
                problems.append(f"{where}: --device={flags['device']} needs the CUDA image, not {c.get('image')}")
            if program(c) in ("gaps-trainer", "gaps-worker"):
                problems += check_probes(where, c)
    return problems


def check_probes(where, container):
    problems = []
    ports = {p["containerPort"] for p in container.get("ports", [])}
    for probe in ("readinessProbe", "livenessProbe"):
        spec = container.get(probe)
        if not spec:
            problems.append(f"{where}: no {probe}")
        elif "grpc" in spec and spec["grpc"]["port"] not in ports:
            problems.append(f"{where}: {probe} asks port {spec['grpc']['port']}, not a port of the container")
        elif "grpc" in spec and effective_flags(container).get("tls_cert"):
            problems.append(f"{where}: {probe} is the kubelet's plaintext gRPC probe but the service serves TLS")
    return problems


def check_gaps_wiring(objs):
    """The trainer reaches the workers through a headless Service; its stop has time to checkpoint; an SQLite
    trainer is alone on its volume and a PostgreSQL one shares a ReadWriteMany volume."""
    problems = []
    services = {(o["metadata"].get("namespace"), o["metadata"]["name"]): o for o in objs if o["kind"] == "Service"}
    claims = {(o["metadata"].get("namespace"), o["metadata"]["name"]): o for o in objs
              if o["kind"] == "PersistentVolumeClaim"}
    workloads = [o for o in objs if o["kind"] in WORKLOADS]
    trainers = [(w, c) for w in workloads for c in containers(w) if program(c) == "gaps-trainer"]
    if not trainers:
        problems.append("no gaps-trainer container")
    if not any(program(c) == "gaps-worker" for w in workloads for c in containers(w)):
        problems.append("no gaps-worker container")
    for w, c in trainers:
        ns, where = w["metadata"].get("namespace"), f"{w['kind']}/{w['metadata']['name']}"
        flags = effective_flags(c)
        for target in filter(None, flags.get("workers", "").split(",")):
            problems += check_worker_target(where, ns, target, services, workloads)
        timeout = int(flags.get("worker_timeout_s", DEFAULT_WORKER_TIMEOUT_S))
        grace = pod_spec(w).get("terminationGracePeriodSeconds", 30)
        if grace <= timeout:
            problems.append(f"{where}: terminationGracePeriodSeconds {grace} leaves no time to checkpoint after a "
                            f"generation call of up to --worker_timeout_s={timeout}")
        replicas = w["spec"].get("replicas", 1)
        data = [v["persistentVolumeClaim"]["claimName"] for v in pod_spec(w).get("volumes", [])
                if "persistentVolumeClaim" in v and any(m["name"] == v["name"] and
                                                        flags.get("data_dir", "").startswith(m["mountPath"])
                                                        for m in c.get("volumeMounts", []))]
        if not data:
            problems.append(f"{where}: --data_dir={flags.get('data_dir')} is not on a persistent volume")
        modes = {m for name in data for m in claims.get((ns, name), {}).get("spec", {}).get("accessModes", [])}
        if not flags.get("job_store", "").startswith(("postgresql://", "postgres://")):
            if replicas != 1 or w["spec"].get("strategy", {}).get("type") != "Recreate":
                problems.append(f"{where}: an SQLite job store needs exactly one replica and the Recreate strategy "
                                f"(replicas {replicas}, strategy {w['spec'].get('strategy', {}).get('type')})")
        elif replicas > 1 and "ReadWriteMany" not in modes:
            problems.append(f"{where}: {replicas} replicas share --data_dir but its volume is {sorted(modes)}, "
                            f"not ReadWriteMany")
    return problems


def check_worker_target(where, ns, target, services, workloads):
    """dns:///NAME[.NAMESPACE[...]]:PORT names a headless Service of this namespace that selects gaps-worker pods."""
    if not target.startswith("dns:///"):
        return [f"{where}: worker address {target} is not a dns:/// target (one address per pod, never rediscovered)"]
    host, _, port = target[len("dns:///"):].rpartition(":")
    labels = host.split(".")
    if len(labels) > 1 and labels[1] != ns:
        return [f"{where}: {target} names namespace {labels[1]}, but the trainer runs in {ns}"]
    service = services.get((ns, labels[0]))
    if service is None:
        return [f"{where}: {target} names no Service of namespace {ns}"]
    problems = []
    if service["spec"].get("clusterIP") != "None":
        problems.append(f"{where}: Service {labels[0]} is not headless (clusterIP: None): DNS would give one "
                        f"virtual IP and gRPC could not balance over the workers")
    if not port.isdigit() or int(port) not in {p["port"] for p in service["spec"].get("ports", [])}:
        problems.append(f"{where}: {target}: port {port} is not a port of Service {labels[0]}")
    picked = [w for w in workloads if w["metadata"].get("namespace") == ns and
              selects(service["spec"].get("selector", {}), pod_labels(w))]
    if not any(program(c) == "gaps-worker" for w in picked for c in containers(w)):
        problems.append(f"{where}: Service {labels[0]} does not select gaps-worker pods")
    return problems


CHECKS = (check_namespaces, check_selectors, check_references, check_containers, check_gaps_wiring)


def check_objects(objs):
    return [p for check in CHECKS for p in check(objs)]


# --------------------------------------------------------------------------------------- render, validate
def validate_schema(objs, versions):
    try:
        import kubernetes_validate
    except ImportError:
        sys.exit("check_k8s: this Python has no kubernetes_validate (scripts/setup.sh installs PyPI's "
                 "kubernetes-validate into ~/.cache/gaps/venv)")
    problems = []
    for version in versions:
        for o in objs:
            try:
                kubernetes_validate.validate(o, version, strict=True)
            except kubernetes_validate.ValidationError as e:
                problems.append(f"{o['kind']}/{o['metadata']['name']} (Kubernetes {version}): {e.message} at "
                                f"{'.'.join(map(str, e.path))}")
    return problems


def render(overlay: pathlib.Path, kubectl: str) -> str:
    result = subprocess.run([kubectl, "kustomize", str(overlay)], capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"kubectl kustomize {overlay} failed:\n{result.stderr}")
    return result.stdout


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("overlays", nargs="*", help="overlay names under overlays/ (default: all)")
    parser.add_argument("--kubernetes-version", action="append", dest="versions",
                        help="validate against this release's schemas (repeatable; default: 1.27.0, the first with "
                        "native gRPC probes as a stable feature, and 1.37.0, the newest kubernetes-validate knows)")
    parser.add_argument("--rendered", type=pathlib.Path, help="check this rendered file instead of rendering")
    parser.add_argument("--kubectl", default=shutil.which("kubectl"))
    args = parser.parse_args(argv)

    rendered = {}
    if args.rendered:
        rendered[str(args.rendered)] = args.rendered.read_text()
    else:
        if not args.kubectl:
            print("check_k8s: kubectl not found (scripts/setup.sh installs Debian's kubernetes-client)")
            return 1
        overlays = args.overlays or sorted(p.name for p in (K8S / "overlays").iterdir() if p.is_dir())
        with tempfile.TemporaryDirectory() as scratch:
            copy = pathlib.Path(scratch) / "deploy"
            shutil.copytree(DEPLOY, copy, ignore=shutil.ignore_patterns("secrets", ".env"))
            subprocess.run(["bash", str(copy / "make_secrets.sh"), "k8s"], check=True, capture_output=True)
            for name in overlays:
                rendered[name] = render(copy / "k8s" / "overlays" / name, args.kubectl)

    failed = False
    for name, text in rendered.items():
        objs = [o for o in yaml.safe_load_all(text) if o]
        problems = validate_schema(objs, args.versions or ["1.27.0", "1.37.0"]) + check_objects(objs)
        kinds = sorted({o["kind"] for o in objs})
        print(f"check_k8s: {name}: {len(objs)} objects ({', '.join(kinds)}), "
              f"{'OK' if not problems else f'{len(problems)} problem(s)'}")
        for p in problems:
            print(f"  {name}: {p}")
        failed |= bool(problems)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
