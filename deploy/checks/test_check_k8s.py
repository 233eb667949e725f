"""Each of check_k8s.py's checks, on a small deployment made here: silent on the good one, and naming
the fault in a copy broken in one place. No kubectl needed."""
import copy
import pathlib
import sys
import unittest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import check_k8s as cm  # noqa: E402

NS = "gaps"


def meta(name, **extra):
    return {"name": name, "namespace": NS, **extra}


def deployment(name, command, env=None, replicas=1, strategy="Recreate", grace=30, volumes=(), mounts=(),
               gpu=1, image="gaps:cuda", probe=None):
    labels = {"app": name}
    probe = probe or {"grpc": {"port": 50052}}
    container = {
        "name": "main", "image": image, "command": command, "env": env or [],
        "ports": [{"name": "grpc", "containerPort": 50051 if "trainer" in name else 50052}],
        "readinessProbe": probe, "livenessProbe": probe,
        "resources": {"requests": {"cpu": "1", "memory": "1Gi", cm.GPU: gpu},
                      "limits": {"memory": "2Gi", cm.GPU: gpu}},
        "volumeMounts": list(mounts),
    }
    return {"apiVersion": "apps/v1", "kind": "Deployment", "metadata": meta(name),
            "spec": {"replicas": replicas, "strategy": {"type": strategy}, "selector": {"matchLabels": labels},
                     "template": {"metadata": {"labels": dict(labels)},
                                  "spec": {"terminationGracePeriodSeconds": grace, "containers": [container],
                                           "volumes": list(volumes)}}}}


def good():
    exec_probe = {"exec": {"command": ["gaps-health-check"]}}
    trainer = deployment(
        "gaps-trainer",
        ["gaps-trainer", "--data_dir=/var/lib/gaps/data", "--device=cuda", "--tls_cert=/tls/tls.crt",
         "--tryfromenv=workers,job_store"],
        env=[{"name": "FLAGS_workers", "value": "dns:///gaps-worker:50052"},
             {"name": "PGPASSWORD", "valueFrom": {"secretKeyRef": {"name": "pg", "key": "password"}}}],
        grace=360, probe=exec_probe,
        volumes=[{"name": "data", "persistentVolumeClaim": {"claimName": "gaps-data"}},
                 {"name": "tls", "secret": {"secretName": "tls"}}],
        mounts=[{"name": "data", "mountPath": "/var/lib/gaps"}, {"name": "tls", "mountPath": "/tls"}])
    worker = deployment("gaps-worker", ["gaps-worker", "--device=cuda"], replicas=2, strategy="RollingUpdate")
    return [
        {"apiVersion": "v1", "kind": "Namespace", "metadata": {"name": NS}},
        trainer, worker,
        {"apiVersion": "v1", "kind": "Service", "metadata": meta("gaps-worker"),
         "spec": {"clusterIP": "None", "selector": {"app": "gaps-worker"},
                  "ports": [{"port": 50052, "targetPort": "grpc"}]}},
        {"apiVersion": "v1", "kind": "Service", "metadata": meta("gaps-trainer"),
         "spec": {"selector": {"app": "gaps-trainer"}, "ports": [{"port": 50051, "targetPort": 50051}]}},
        {"apiVersion": "v1", "kind": "PersistentVolumeClaim", "metadata": meta("gaps-data"),
         "spec": {"accessModes": ["ReadWriteOnce"]}},
        {"apiVersion": "v1", "kind": "Secret", "metadata": meta("tls"), "data": {"tls.crt": ""}},
        {"apiVersion": "v1", "kind": "Secret", "metadata": meta("pg"), "data": {"password": ""}},
        {"apiVersion": "policy/v1", "kind": "PodDisruptionBudget", "metadata": meta("gaps-worker"),
         "spec": {"maxUnavailable": 1, "selector": {"matchLabels": {"app": "gaps-worker"}}}},
        {"apiVersion": "networking.k8s.io/v1", "kind": "NetworkPolicy", "metadata": meta("gaps-worker"),
         "spec": {"podSelector": {"matchLabels": {"app": "gaps-worker"}},
                  "ingress": [{"from": [{"podSelector": {"matchLabels": {"app": "gaps-trainer"}}}]}]}},
    ]


def find(objs, kind, name):
    return next(o for o in objs if o["kind"] == kind and o["metadata"]["name"] == name)


def container(objs, name):
    return find(objs, "Deployment", name)["spec"]["template"]["spec"]["containers"][0]


def env(objs, name, variable):
    return next(e for e in container(objs, name)["env"] if e["name"] == variable)


class ChecksTest(unittest.TestCase):

    def problems_after(self, change):
        objs = copy.deepcopy(good())
        change(objs)
        return cm.check_objects(objs)

    def assertFault(self, change, *words):
        problems = self.problems_after(change)
        self.assertTrue(any(all(w in p for w in words) for p in problems),
                        f"expected a problem naming {words}, got {problems}")

    def test_good_deployment_passes(self):
        self.assertEqual(cm.check_objects(good()), [])

    def test_effective_flags_read_tryfromenv(self):
        flags = cm.effective_flags(container(good(), "gaps-trainer"))
        self.assertEqual(flags["workers"], "dns:///gaps-worker:50052")
        self.assertNotIn("job_store", flags)  # listed, but its variable is not set

    def test_object_without_namespace(self):
        self.assertFault(lambda o: find(o, "Secret", "tls")["metadata"].pop("namespace"), "without a namespace")

    def test_namespace_not_created(self):
        self.assertFault(lambda o: o.remove(find(o, "Namespace", NS)) or o.append(
            {"kind": "Namespace", "metadata": {"name": "other"}}), "not created")

    def test_workload_selector_misses_its_pods(self):
        self.assertFault(lambda o: find(o, "Deployment", "gaps-worker")["spec"]["selector"]["matchLabels"].update(
            app="typo"), "does not match its pod labels")

    def test_service_selects_nothing(self):
        self.assertFault(lambda o: find(o, "Service", "gaps-trainer")["spec"].update(selector={"app": "x"}),
                         "matches no pods")

    def test_service_target_port_missing(self):
        self.assertFault(lambda o: find(o, "Service", "gaps-worker")["spec"]["ports"][0].update(targetPort="http"),
                         "targetPort http")

    def test_pdb_and_network_policy_select_nothing(self):
        self.assertFault(lambda o: find(o, "PodDisruptionBudget", "gaps-worker")["spec"]["selector"].update(
            matchLabels={"app": "x"}), "PodDisruptionBudget", "matches no pods")
        self.assertFault(lambda o: find(o, "NetworkPolicy", "gaps-worker")["spec"]["ingress"][0]["from"][0].update(
            podSelector={"matchLabels": {"app": "x"}}), "ingress from")

    def test_missing_secret_pvc_and_key(self):
        self.assertFault(lambda o: o.remove(find(o, "Secret", "tls")), "Secret tls is not in the output")
        self.assertFault(lambda o: o.remove(find(o, "PersistentVolumeClaim", "gaps-data")),
                         "PersistentVolumeClaim gaps-data is not in the output")
        self.assertFault(lambda o: find(o, "Secret", "pg").update(data={"pass": ""}), "has no key password")

    def test_gpu_limit_required_for_cuda(self):
        self.assertFault(lambda o: container(o, "gaps-worker")["resources"]["limits"].pop(cm.GPU), "without a")
        self.assertFault(lambda o: container(o, "gaps-worker").update(image="gaps:cpu"), "needs the CUDA image")

    def test_memory_limit_required(self):
        self.assertFault(lambda o: container(o, "gaps-worker")["resources"]["limits"].pop("memory"), "no memory limit")

    def test_probes(self):
        self.assertFault(lambda o: container(o, "gaps-worker").pop("livenessProbe"), "no livenessProbe")
        self.assertFault(lambda o: container(o, "gaps-worker").update(readinessProbe={"grpc": {"port": 1}}),
                         "asks port 1")
        self.assertFault(lambda o: container(o, "gaps-trainer").update(readinessProbe={"grpc": {"port": 50051}}),
                         "serves TLS")

    def test_worker_service_must_be_headless(self):
        self.assertFault(lambda o: find(o, "Service", "gaps-worker")["spec"].pop("clusterIP"), "not headless")

    def test_worker_target_names_the_worker_service(self):
        self.assertFault(lambda o: env(o, "gaps-trainer", "FLAGS_workers").update(value="dns:///gaps-wrker:50052"),
                         "names no Service")
        self.assertFault(lambda o: env(o, "gaps-trainer", "FLAGS_workers").update(
            value="dns:///gaps-worker.elsewhere.svc:50052"), "names namespace elsewhere")
        self.assertFault(lambda o: env(o, "gaps-trainer", "FLAGS_workers").update(value="dns:///gaps-worker:9"),
                         "port 9")
        self.assertFault(lambda o: env(o, "gaps-trainer", "FLAGS_workers").update(value="dns:///gaps-trainer:50051"),
                         "does not select gaps-worker pods")
        self.assertFault(lambda o: env(o, "gaps-trainer", "FLAGS_workers").update(value="10.0.0.1:50052"),
                         "not a dns:/// target")

    def test_grace_period_covers_a_generation_call(self):
        self.assertFault(lambda o: find(o, "Deployment", "gaps-trainer")["spec"]["template"]["spec"].update(
            terminationGracePeriodSeconds=30), "terminationGracePeriodSeconds 30")

    def test_sqlite_trainer_is_alone(self):
        self.assertFault(lambda o: find(o, "Deployment", "gaps-trainer")["spec"].update(replicas=2),
                         "SQLite job store needs exactly one replica")
        self.assertFault(lambda o: find(o, "Deployment", "gaps-trainer")["spec"]["strategy"].update(
            type="RollingUpdate"), "Recreate")

    def test_postgres_replicas_share_a_read_write_many_volume(self):
        def scale_out(o, mode):
            container(o, "gaps-trainer")["env"].append({"name": "FLAGS_job_store", "value": "postgresql://db/gaps"})
            find(o, "Deployment", "gaps-trainer")["spec"].update(replicas=3, strategy={"type": "RollingUpdate"})
            find(o, "PersistentVolumeClaim", "gaps-data")["spec"]["accessModes"] = [mode]

        self.assertEqual(self.problems_after(lambda o: scale_out(o, "ReadWriteMany")), [])
        self.assertFault(lambda o: scale_out(o, "ReadWriteOnce"), "not ReadWriteMany")

    def test_data_dir_on_a_volume(self):
        self.assertFault(lambda o: container(o, "gaps-trainer").update(
            command=["gaps-trainer", "--data_dir=/tmp/data", "--device=cuda"]), "not on a persistent volume")


if __name__ == "__main__":
    unittest.main()
