// The RPC path's cost: pseudo-view generation through a DiffusionWorker on loopback vs the same backend
// in process (overhead per pseudo-view), for each hand-over (float32 or compact payloads, in the messages or
// through shared memory) with the round trip's stages and bytes; and scene upload throughput into a Trainer
// service (SubmitJob including the server's validation and writing). Services run in this process on
// 127.0.0.1, so the figures hold serialization, HTTP/2 transfer and decoding, not network latency.
// --busy_threads N keeps N more threads spinning meanwhile: a host whose cores other runs occupy. The
// "-converted-at-once" cases convert every payload before sending (both sides), the others convert while sending.
// The cases' calls take turns (round robin), each case's median reported.
//   rpc_bench [--scene DIR] [--resolution 8] [--batch 16] [--repeats 5] [--busy_threads 0] [--work_dir DIR]
#include <algorithm>
#include <atomic>
#include <chrono>
#include <iostream>
#include <optional>
#include <thread>

#include <ATen/ATen.h>
#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include <nlohmann/json.hpp>
#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "client/remote_client.h"
#include "diffusion_worker/backend_registry.h"
#include "diffusion_worker/service/worker_service.h"
#include "gs_trainer/scene/scene.h"
#include "server/remote_generator.h"
#include "server/trainer_service.h"

ABSL_FLAG(std::string, scene, GAPS_DATA_DIR "/llff/fern", "scene folder");
ABSL_FLAG(int, resolution, 8, "downscale factor");
ABSL_FLAG(int, batch, 16, "pseudo-views per Generate call (the paper's phase size on LLFF)");
ABSL_FLAG(int, repeats, 5, "timed repetitions (the median is reported)");
ABSL_FLAG(std::string, work_dir, "/tmp/gaps_rpc_bench", "folder for the trainer's data");
ABSL_FLAG(int, busy_threads, 0, "threads kept spinning while the round trips are timed (a busy host)");

namespace {

using Clock = std::chrono::steady_clock;

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

template <typename F>
double median_seconds(int repeats, F&& f) {
  std::vector<double> times;
  for (int i = 0; i < repeats; ++i) {
    const auto start = Clock::now();
    f();
    times.push_back(std::chrono::duration<double>(Clock::now() - start).count());
  }
  return median(times);
}

// A server on a free loopback port with `service` registered; the port is written to *port.
std::unique_ptr<grpc::Server> serve(grpc::Service* service, int* port) {
  grpc::ServerBuilder builder;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), port);
  builder.RegisterService(service);
  return builder.BuildAndStart();
}

// Threads that spin until destroyed: the other runs of a busy host.
class BusyThreads {
 public:
  explicit BusyThreads(int n) {
    for (int i = 0; i < n; ++i)
      threads_.emplace_back([this] {
        volatile double x = 1.0;
        while (!stop_.load(std::memory_order_relaxed)) x = x * 1.0000001 + 1e-9;
      });
  }
  ~BusyThreads() {
    stop_ = true;
    for (auto& t : threads_) t.join();
  }

 private:
  std::atomic<bool> stop_{false};
  std::vector<std::thread> threads_;
};

int fail(const absl::Status& st) {
  std::cerr << "rpc_bench: " << st << "\n";
  return 1;
}

}  // namespace

int main(int argc, char** argv) {
  absl::ParseCommandLine(argc, argv);
  const int resolution = absl::GetFlag(FLAGS_resolution), batch = absl::GetFlag(FLAGS_batch);
  const int repeats = absl::GetFlag(FLAGS_repeats);
  gaps::SceneLoadOptions load;
  load.resolution = resolution;
  auto scene = gaps::load_scene(absl::GetFlag(FLAGS_scene), load);
  if (!scene.ok()) return fail(scene.status());

  // Requests as a phase makes them: 3 references with renders, poses between them. The render at a pose is
  // its nearest photo, and depth a constant plane, which is what the backend's cost depends on (sizes).
  std::vector<gaps::ReferenceView> refs;
  for (int i : {1, 9, 17}) {
    const gaps::Camera& c = scene->cameras[i];
    auto image = gaps::load_camera_image(c);
    if (!image.ok()) return fail(image.status());
    refs.push_back({c, *image, at::full({c.height, c.width}, 4.0), at::ones({c.height, c.width})});
  }
  std::vector<gaps::GenerationRequest> requests;
  for (int k = 0; k < batch; ++k) {
    gaps::GenerationRequest q;
    const auto& a = refs[k % 2].camera;
    const auto& b = refs[k % 2 + 1].camera;
    q.camera = a;
    q.camera.t = a.t + (b.t - a.t) * ((k + 1.0) / (batch + 1.0));
    q.render_rgb = refs[k % 2].image;
    q.render_depth = refs[k % 2].render_depth;
    q.render_alpha = refs[k % 2].render_alpha * 0.9;
    q.coverage = 0.9;
    q.strength = 0.4;
    q.control_scale = 0.8;
    q.references = refs;
    q.seed = k;
    requests.push_back(std::move(q));
  }
  auto local = gaps::make_generator("reproject", "");
  auto hosted = gaps::make_generator("reproject", "");
  if (!local.ok() || !hosted.ok()) return fail(local.status());
  if (absl::GetFlag(FLAGS_busy_threads) < 0) return fail(absl::InvalidArgumentError("--busy_threads must be >= 0"));
  gaps::WorkerServiceOptions worker_options;
  worker_options.backend = "reproject";
  worker_options.max_batch = batch;
  gaps::WorkerService worker(std::move(*hosted), worker_options);
  // A second worker that converts its answers at once, then sends them: the hand-over before streaming.
  auto hosted_at_once = gaps::make_generator("reproject", "");
  if (!hosted_at_once.ok()) return fail(hosted_at_once.status());
  worker_options.convert_while_sending = false;
  gaps::WorkerService worker_at_once(std::move(*hosted_at_once), worker_options);
  grpc::EnableDefaultHealthCheckService(true);
  int worker_port = 0, worker_at_once_port = 0;
  auto worker_server = serve(&worker, &worker_port);
  auto worker_at_once_server = serve(&worker_at_once, &worker_at_once_port);
  const auto& c0 = requests[0].camera;
  (void)(*local)->adapt(refs, std::nullopt);
  struct Case {
    const char* name;
    gaps::rpc::TensorEncoding encoding;
    bool shared_memory;
    std::optional<gaps::rpc::TensorEncoding> depth;  // unset: the pool's choice (float16 with compact on a socket)
    bool convert_while_sending = true;               // false: both sides convert everything, then send
  };
  using gaps::rpc::TensorEncoding;
  const std::vector<Case> cases = {
      {"float32-socket", TensorEncoding::kFloat32, false, std::nullopt},
      {"float32-socket-converted-at-once", TensorEncoding::kFloat32, false, std::nullopt, false},
      {"compact-socket", TensorEncoding::kUint8, false, std::nullopt},
      {"compact-socket-converted-at-once", TensorEncoding::kUint8, false, std::nullopt, false},
      {"compact-socket-float32-depth", TensorEncoding::kUint8, false, TensorEncoding::kFloat32},
      {"compact-shared", TensorEncoding::kUint8, true, std::nullopt},
      {"compact-shared-converted-at-once", TensorEncoding::kUint8, true, std::nullopt, false},
      {"compact-shared-half-depth", TensorEncoding::kUint8, true, TensorEncoding::kFloat16},
      {"float32-shared", TensorEncoding::kFloat32, true, std::nullopt}};
  std::vector<std::unique_ptr<gaps::RemoteGenerator>> remotes;
  for (const Case& c : cases) {
    gaps::WorkerPoolOptions pool;
    pool.addresses = {"127.0.0.1:" + std::to_string(c.convert_while_sending ? worker_port : worker_at_once_port)};
    pool.encoding = c.encoding;
    pool.depth_encoding = c.depth;
    pool.shared_memory = c.shared_memory;
    pool.convert_while_sending = c.convert_while_sending;
    auto remote = gaps::RemoteGenerator::create(pool);
    if (!remote.ok()) return fail(remote.status());
    (void)(*remote)->adapt(refs, std::nullopt);
    if (auto warm = (*remote)->generate(requests); !warm.ok()) return fail(warm.status());  // connects, adapts
    remotes.push_back(*std::move(remote));
  }
  const BusyThreads busy(absl::GetFlag(FLAGS_busy_threads));
  // Round robin over the in-process call and the cases, so that a drift of the host touches them alike.
  std::vector<std::vector<double>> times(cases.size() + 1);
  for (int r = 0; r < repeats; ++r)
    for (size_t k = 0; k <= cases.size(); ++k)
      times[k].push_back(median_seconds(1, [&] {
        if (k == cases.size())
          (void)(*local)->generate(requests);
        else
          (void)remotes[k]->generate(requests);
      }));
  const double in_process = median(times[cases.size()]);
  for (size_t k = 0; k < cases.size(); ++k) {
    gaps::RemoteGenerator& remote = *remotes[k];
    const double over_rpc = median(times[k]);
    std::cout << nlohmann::json{{"bench", "generation_round_trip"},
                                {"backend", "reproject"},
                                {"hand_over", cases[k].name},
                                {"width", c0.width},
                                {"height", c0.height},
                                {"batch", batch},
                                {"references", refs.size()},
                                {"busy_threads", absl::GetFlag(FLAGS_busy_threads)},
                                {"in_process_s", in_process},
                                {"rpc_s", over_rpc},
                                {"ratio", over_rpc / in_process},
                                {"overhead_per_view_ms", 1000.0 * (over_rpc - in_process) / batch},
                                {"last_call_stage_seconds", remote.stage_seconds()},
                                {"last_call_counters", remote.counters()},
                                {"repeats", repeats}}
                     .dump()
              << std::endl;
  }

  // Upload throughput: the whole scene (every image, as the client sends it) into a trainer whose job
  // threads are not started, so only SubmitJob is timed.
  gaps::TrainerServiceOptions trainer_options;
  trainer_options.data_dir = absl::GetFlag(FLAGS_work_dir);
  auto trainer = gaps::TrainerService::create(trainer_options);
  if (!trainer.ok()) return fail(trainer.status());
  int trainer_port = 0;
  auto trainer_server = serve(trainer->get(), &trainer_port);
  auto client = gaps::client::TrainerClient::connect("127.0.0.1:" + std::to_string(trainer_port), {});
  if (!client.ok()) return fail(client.status());
  const auto prepare_start = Clock::now();
  auto prepared = gaps::client::prepare_scene(absl::GetFlag(FLAGS_scene), resolution);
  if (!prepared.ok()) return fail(prepared.status());
  const double prepare_s = std::chrono::duration<double>(Clock::now() - prepare_start).count();
  size_t bytes = 0;
  for (const auto& image : prepared->images) bytes += image.size();
  gaps::v1::JobSpec spec;
  spec.set_name("upload bench");
  spec.mutable_config()->set_views(3);
  const double submit_s = median_seconds(repeats, [&] {
    auto job = client->submit(spec, *prepared);
    if (!job.ok()) std::cerr << job.status() << "\n";
  });
  std::cout << nlohmann::json{{"bench", "scene_upload"},
                              {"images", prepared->images.size()},
                              {"bytes", bytes},
                              {"width", prepared->cameras[0].width()},
                              {"height", prepared->cameras[0].height()},
                              {"client_prepare_s", prepare_s},
                              {"submit_s", submit_s},
                              {"throughput_mb_per_s", bytes / 1e6 / submit_s},
                              {"repeats", repeats}}
                   .dump()
            << std::endl;
  trainer_server->Shutdown(std::chrono::system_clock::now());
  worker_server->Shutdown(std::chrono::system_clock::now());
  return 0;
}
