"""check_compose.py's checks on a merged compose configuration made here: silent on the good one, naming
the fault in a copy broken in one place. No docker-compose needed."""
import copy
import pathlib
import sys
import unittest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import check_compose as cc  # noqa: E402

GPU = {"resources": {"reservations": {"devices": [{"driver": "nvidia", "device_ids": ["0"], "capabilities": ["gpu"]}]}}}


def trainer(port):
    return {
        "command": ["gaps-trainer", "--listen=0.0.0.0:50051", "--device=cuda", "--tls_cert=/run/secrets/tls_cert",
                    "--gpu_memory_gib=4", "--tryfromenv=workers,job_store"],
        "environment": {"FLAGS_workers": "worker:50052", "GAPS_HEALTH_ADDRESS": "127.0.0.1:50051",
                        "GAPS_HEALTH_TLS_CA": "/run/secrets/tls_ca"},
        "secrets": [{"source": "tls_cert"}, {"source": "tls_ca"}],
        "healthcheck": {"test": ["CMD", "gaps-health-check"]},
        "depends_on": {"worker": {"condition": "service_healthy"}},
        "ports": [{"published": port, "target": 50051}],
        "volumes": ["trainer-data:/var/lib/gaps:rw"],
        "deploy": copy.deepcopy(GPU),
        "stop_grace_period": "6m",
    }


def good():
    return {"services": {
        "worker": {"command": ["gaps-worker", "--listen=0.0.0.0:50052", "--device=cuda", "--gpu_memory_gib=17"],
                   "environment": {"GAPS_HEALTH_ADDRESS": "127.0.0.1:50052"},
                   "healthcheck": {"test": ["CMD", "gaps-health-check"]}, "deploy": copy.deepcopy(GPU)},
        "trainer": trainer(50051),
    }}


class ChecksTest(unittest.TestCase):

    def assertFault(self, change, *words):
        config = good()
        change(config["services"])
        problems = cc.check_config(config)
        self.assertTrue(any(all(w in p for w in words) for p in problems),
                        f"expected a problem naming {words}, got {problems}")

    def test_good_configuration_passes(self):
        self.assertEqual(cc.check_config(good()), [])

    def test_services_sharing_a_gpu_must_cap_their_memory_to_fit_a_24_gb_card(self):
        def uncap(services):
            services["worker"]["command"].remove("--gpu_memory_gib=17")
        self.assertFault(uncap, "worker", "without a --gpu_memory_gib cap")

        def overcommit(services):
            services["worker"]["command"][-1] = "--gpu_memory_gib=19"
        self.assertFault(overcommit, "caps and contexts add up to 24.0 GiB")

        def separate(services):  # a GPU each: no cap needed
            services["worker"]["command"].remove("--gpu_memory_gib=17")
            services["worker"]["deploy"]["resources"]["reservations"]["devices"][0]["device_ids"] = ["1"]
            services["trainer"]["deploy"]["resources"]["reservations"]["devices"][0]["device_ids"] = ["0"]
        config = good()
        separate(config["services"])
        self.assertEqual(cc.check_config(config), [])

    def test_worker_address(self):
        self.assertFault(lambda s: s["trainer"]["environment"].update(FLAGS_workers="wrker:50052"),
                         "names no gaps-worker service")
        self.assertFault(lambda s: s["trainer"]["environment"].update(FLAGS_workers="worker:50051"),
                         "listens on another port")
        self.assertFault(lambda s: s["trainer"].pop("depends_on"), "does not wait for worker")

    def test_health_check(self):
        self.assertFault(lambda s: s["worker"].pop("healthcheck"), "worker: no healthcheck")
        self.assertFault(lambda s: s["worker"]["environment"].pop("GAPS_HEALTH_ADDRESS"), "not the port")
        self.assertFault(lambda s: s["trainer"]["environment"].pop("GAPS_HEALTH_TLS_CA"), "serves TLS")

    def test_secret_attached(self):
        self.assertFault(lambda s: s["trainer"]["secrets"].pop(0), "/run/secrets/tls_cert")

    def test_grace_period_covers_a_generation_call(self):
        self.assertEqual(cc.seconds("1m30s"), 90)
        self.assertFault(lambda s: s["trainer"].pop("stop_grace_period"), "stop_grace_period 10s")
        self.assertFault(lambda s: s["trainer"].update(stop_grace_period="120s"), "stop_grace_period 120s")

    def test_gpu_reserved(self):
        self.assertFault(lambda s: s["worker"].pop("deploy"), "without a GPU reservation")

    def test_ports_unique(self):
        self.assertFault(lambda s: s.update({"trainer-2": trainer(50051)}), "host port 50051")

    def test_trainers_sharing_data_need_postgres(self):
        self.assertFault(lambda s: s.update({"trainer-2": trainer(50061)}), "no PostgreSQL job store")

        def scale_out(s):
            s["trainer-2"] = trainer(50061)
            s["trainer-2"]["deploy"]["resources"]["reservations"]["devices"][0]["device_ids"] = ["1"]
            for t in ("trainer", "trainer-2"):
                s[t]["environment"]["FLAGS_job_store"] = "postgresql://gaps@postgres:5432/gaps"

        config = good()
        scale_out(config["services"])
        self.assertEqual(cc.check_config(config), [])


if __name__ == "__main__":
    unittest.main()
