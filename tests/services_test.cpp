// The client-server building blocks in one process: message codecs and chunking (with the generation
// controls), the worker service (remote generation equals in-process generation, the backend's notes,
// bounded queue, deadlines, tokens, float32 / compact hand-over through the socket or shared memory), the worker pool's
// give-up path, the SQLite job store across reopening and when it refuses writes, the trainer service's answers to a
// job store that refuses writes, a job whose worker cannot honour its controls, and upload validation.
#include <fcntl.h>
#include <sqlite3.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <fstream>
#include <functional>
#include <iterator>
#include <mutex>
#include <optional>
#include <regex>
#include <set>
#include <thread>

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include <gtest/gtest.h>
#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "client/remote_client.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/limits.h"
#include "common/ply.h"
#include "common/status_macros.h"
#include "diffusion_worker/backend_registry.h"
#include "diffusion_worker/service/worker_service.h"
#include "rpc/codec.h"
#include "rpc/config_codec.h"
#include "rpc/generation_codec.h"
#include "rpc/security.h"
#include "rpc/shared_memory.h"
#include "server/job_config.h"
#include "server/job_store.h"
#include "server/remote_generator.h"
#include "server/scene_upload.h"
#include "server/trainer_service.h"
#include "tests/camera_test_util.h"
#include "tests/synthetic_scene_util.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

ReferenceView test_reference(double x, uint64_t seed) {
  at::manual_seed(seed);
  const Camera c = test::camera_on_x_axis(x);
  return {c, at::rand({c.height, c.width, 3}), at::full({c.height, c.width}, 2.0), at::ones({c.height, c.width})};
}

std::vector<GenerationRequest> test_requests() {
  std::vector<ReferenceView> refs = {test_reference(0.0, 1), test_reference(0.5, 2)};
  std::vector<GenerationRequest> out;
  for (double x : {0.2, 0.3}) {
    GenerationRequest q;
    q.camera = test::camera_on_x_axis(x);
    at::manual_seed(static_cast<uint64_t>(x * 100));
    q.render_rgb = at::rand({18, 24, 3});
    q.render_depth = at::full({18, 24}, 2.0);
    q.render_alpha = at::rand({18, 24});
    q.coverage = 0.6;
    q.strength = 0.5;
    q.control_scale = 0.8;
    q.references = x < 0.25 ? refs : std::vector<ReferenceView>{refs[1], refs[0]};
    q.seed = 7;
    out.push_back(q);
  }
  return out;
}

// The services' threads log to one file (stdout and stderr share it): each line must arrive whole, or a
// reader looking for "port N" misses the port (a test once did, when a job's log line landed mid-line).
TEST(ServiceLog, LinesFromManyThreadsArriveWhole) {
  const fs::path log = fs::path(::testing::TempDir()) / "service_log_lines.txt";
  const int fd = ::open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  ASSERT_GE(fd, 0);
  const int threads = 4, lines = 200;
  std::vector<std::thread> writers;
  for (int t = 0; t < threads; ++t)
    writers.emplace_back([&, t] {
      for (int i = 0; i < lines; ++i)
        write_log_line(fd, absl::StrCat("thread ", t, " line ", i, " ", std::string(500, 'a' + t), " end"));
    });
  for (auto& w : writers) w.join();
  ::close(fd);
  std::ifstream in(log);
  std::string line;
  int count = 0;
  while (std::getline(in, line)) {
    ++count;
    ASSERT_TRUE(absl::StartsWith(line, "thread ") && absl::EndsWith(line, " end")) << line;
    const char letter = 'a' + (line[7] - '0');
    EXPECT_EQ(line.find_first_not_of(letter, line.find(' ', line.find(" line ") + 6) + 1), line.size() - 4) << line;
  }
  EXPECT_EQ(count, threads * lines);
}

TEST(Codec, TensorsAndCamerasRoundTrip) {
  const at::Tensor t = at::rand({5, 4, 3});
  v1::Tensor raw;
  rpc::encode_raw(t, &raw);
  auto back = rpc::decode_tensor_shaped(raw, {5, 4, 3}, "t");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_TRUE(at::equal(*back, t));
  v1::Tensor png;
  ASSERT_TRUE(rpc::encode_png(t, &png).ok());
  auto decoded = rpc::decode_tensor(png, "png");
  ASSERT_TRUE(decoded.ok());
  EXPECT_LE((*decoded - t).abs().max().item<float>(), 0.5f / 255 + 1e-6);
  raw.mutable_shape()->Set(0, 6);
  EXPECT_EQ(rpc::decode_tensor(raw, "t").status().code(), absl::StatusCode::kInvalidArgument);
  // No data, but extents whose strides overflow (found by fuzz/generation_request_fuzz.cpp: LibTorch threw).
  v1::Tensor empty;
  empty.set_encoding(v1::Tensor::RAW_F32);
  for (int64_t extent : {int64_t{0}, int64_t{10000000}, int64_t{10000000}}) empty.add_shape(extent);
  const auto refused = rpc::decode_tensor(empty, "reference rgb");
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "reference rgb: shape is too large")) << refused.status();
  // A small empty shape decodes to an empty tensor (fuzzing found the copy into its null storage).
  v1::Tensor none;
  none.set_encoding(v1::Tensor::RAW_F32);
  for (int64_t extent : {0, 3}) none.add_shape(extent);
  const auto empty_tensor = rpc::decode_tensor(none, "t");
  ASSERT_TRUE(empty_tensor.ok()) << empty_tensor.status();
  EXPECT_EQ(empty_tensor->sizes(), at::IntArrayRef({0, 3}));

  Camera c = test::camera_on_x_axis(0.3);
  c.R = Eigen::AngleAxisd(0.4, Eigen::Vector3d(0, 1, 0)).toRotationMatrix();
  v1::Camera pc;
  rpc::encode_camera(c, &pc);
  auto cb = rpc::decode_camera(pc, "c");
  ASSERT_TRUE(cb.ok());
  EXPECT_TRUE(cb->R.isApprox(c.R));
  EXPECT_TRUE(cb->t.isApprox(c.t));
  pc.set_translation(1, std::nan(""));
  const auto nan = rpc::decode_camera(pc, "camera 3");
  EXPECT_EQ(nan.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(nan.status().message().find("camera 3"), std::string_view::npos);
  EXPECT_NE(nan.status().message().find("not finite"), std::string_view::npos);
}

// Bytes for images and alpha: an 8-bit photograph round-trips exactly, values outside [0, 1] are clamped,
// non-finite values are refused naming the tensor, and a payload of the wrong size is refused.
TEST(Codec, CompactTensorsAreBytes) {
  const at::Tensor photo = at::randint(0, 256, {5, 4, 3}).to(at::kFloat).div(255);
  v1::Tensor compact;
  ASSERT_TRUE(rpc::encode_tensor(photo, rpc::TensorEncoding::kUint8, nullptr, "photo", &compact).ok());
  EXPECT_EQ(compact.encoding(), v1::Tensor::RAW_U8);
  EXPECT_EQ(compact.data().size(), 60u);
  auto back = rpc::decode_tensor_shaped(compact, {5, 4, 3}, "photo");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_TRUE(at::equal(*back, photo));
  ASSERT_TRUE(
      rpc::encode_tensor(at::tensor({-0.5f, 0.25f, 1.5f}), rpc::TensorEncoding::kUint8, nullptr, "t", &compact).ok());
  back = rpc::decode_tensor(compact, "t");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_TRUE(at::allclose(*back, at::tensor({0.0f, 64.0f / 255, 1.0f})));
  compact.mutable_data()->pop_back();
  const auto short_payload = rpc::decode_tensor(compact, "t");
  EXPECT_EQ(short_payload.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(short_payload.status().message(), "needs 3 bytes, got 2")) << short_payload.status();
  const absl::Status nan =
      rpc::encode_tensor(at::tensor({0.5f, NAN}), rpc::TensorEncoding::kUint8, nullptr, "pose 2 render_rgb", &compact);
  EXPECT_EQ(nan.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(nan.message(), "pose 2 render_rgb: contains NaN or infinite values");
  compact.set_encoding(v1::Tensor::PNG);
  EXPECT_EQ(rpc::tensor_encoding(compact.encoding(), "answer_encoding").status().code(),
            absl::StatusCode::kInvalidArgument);
}

// Half precision for depth maps: two bytes a value, each within 2^-11 of the float (rounded to nearest even, as
// at::Tensor::to(kHalf) rounds); a map with a magnitude beyond 65504 travels as float32, non-finite values are
// refused naming the tensor, and a payload of the wrong size is refused.
TEST(Codec, DepthTravelsInHalfPrecision) {
  const at::Tensor depth = at::rand({6, 5}).mul(100).add(0.01);
  v1::Tensor half;
  ASSERT_TRUE(rpc::encode_tensor(depth, rpc::TensorEncoding::kFloat16, nullptr, "depth", &half).ok());
  EXPECT_EQ(half.encoding(), v1::Tensor::RAW_F16);
  EXPECT_EQ(half.data().size(), 60u);
  auto back = rpc::decode_tensor_shaped(half, {6, 5}, "depth");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_TRUE(at::equal(*back, depth.to(at::kHalf).to(at::kFloat)));
  EXPECT_LE(((*back - depth).abs() / depth).max().item<float>(), std::ldexp(1.0f, -11));
  EXPECT_EQ(*rpc::tensor_encoding(v1::Tensor::RAW_F16, "depth"), rpc::TensorEncoding::kFloat16);

  const at::Tensor far = at::tensor({1.0f, 70000.0f});
  ASSERT_TRUE(rpc::encode_tensor(far, rpc::TensorEncoding::kFloat16, nullptr, "depth", &half).ok());
  EXPECT_EQ(half.encoding(), v1::Tensor::RAW_F32);
  back = rpc::decode_tensor(half, "depth");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_TRUE(at::equal(*back, far));

  const absl::Status inf = rpc::encode_tensor(at::tensor({1.0f, INFINITY}), rpc::TensorEncoding::kFloat16, nullptr,
                                              "pose 1 render_depth", &half);
  EXPECT_EQ(inf.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(inf.message(), "pose 1 render_depth: contains NaN or infinite values");
  ASSERT_TRUE(rpc::encode_tensor(depth, rpc::TensorEncoding::kFloat16, nullptr, "depth", &half).ok());
  half.mutable_data()->pop_back();
  const auto odd = rpc::decode_tensor(half, "reference 2 render_depth");
  EXPECT_EQ(odd.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(
      absl::StrContains(odd.status().message(), "reference 2 render_depth: shape [6, 5] needs 60 bytes, got 59"))
      << odd.status();
  // A half-precision infinity in a payload (another sender's) is refused where the shape is checked.
  half.mutable_data()->push_back('\0');
  half.mutable_data()->replace(0, 2, std::string("\x00\x7c", 2));
  const auto infinite = rpc::decode_tensor_shaped(half, {6, 5}, "depth");
  EXPECT_EQ(infinite.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(absl::StrContains(infinite.status().message(), "NaN or infinite")) << infinite.status();
}

// Shared-memory regions: opened only by the names the module creates and at their size, slices checked, gone
// once their owner is; a probe is recognised by its token only; regions of dead processes are removed.
TEST(SharedMemory, RegionsProbesAndStaleRegions) {
  auto region = rpc::SharedRegion::create(1000);
  ASSERT_TRUE(region.ok()) << region.status();
  (*region)->data()[999] = 42;
  auto seen = rpc::SharedRegion::open((*region)->name(), 1000);
  ASSERT_TRUE(seen.ok()) << seen.status();
  EXPECT_EQ((*seen)->data()[999], 42);
  EXPECT_EQ(rpc::SharedRegion::open((*region)->name(), 999).status().code(), absl::StatusCode::kInvalidArgument);
  for (const char* name : {"/etc", "/gaps-region-1", "/gaps-region-1-2/../x", "gaps-region-1-2", "/gaps-region-a-2"})
    EXPECT_EQ(rpc::SharedRegion::open(name, 1000).status().code(), absl::StatusCode::kInvalidArgument) << name;
  EXPECT_TRUE((*region)->check_slice(900, 100, "t").ok());
  EXPECT_EQ((*region)->check_slice(901, 100, "t").code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ((*region)->check_slice(~uint64_t{0}, 2, "t").code(), absl::StatusCode::kInvalidArgument);
  rpc::SharedArena arena(**region);
  EXPECT_EQ(*arena.allocate(10), 0u);
  EXPECT_EQ(*arena.allocate(10), 64u);  // aligned
  EXPECT_EQ(arena.allocate(900).status().code(), absl::StatusCode::kResourceExhausted);
  const std::string name = (*region)->name();
  region->reset();
  EXPECT_EQ(rpc::SharedRegion::open(name, 1000).status().code(), absl::StatusCode::kFailedPrecondition);

  auto probe = rpc::SharedMemoryProbe::create();
  ASSERT_TRUE(probe.ok()) << probe.status();
  EXPECT_TRUE(rpc::shares_memory_with((*probe)->name(), (*probe)->token()));
  EXPECT_FALSE(rpc::shares_memory_with((*probe)->name(), (*probe)->token() + "0"));
  EXPECT_FALSE(rpc::shares_memory_with("/gaps-region-1-1", (*probe)->token()));
  const std::string probe_name = (*probe)->name(), token = (*probe)->token();
  probe->reset();
  EXPECT_FALSE(rpc::shares_memory_with(probe_name, token));

  const pid_t child = fork();
  if (child == 0) _exit(0);
  ASSERT_GT(child, 0);
  waitpid(child, nullptr, 0);
  const std::string stale = "/gaps-region-" + std::to_string(child) + "-0";
  const int fd = shm_open(stale.c_str(), O_CREAT | O_RDWR, 0600);
  ASSERT_GE(fd, 0);
  close(fd);
  auto mine = rpc::SharedRegion::create(64);
  ASSERT_TRUE(mine.ok());
  EXPECT_GE(rpc::remove_stale_regions(), 1);
  EXPECT_LT(shm_open(stale.c_str(), O_RDONLY, 0), 0) << "the dead process's region is gone";
  EXPECT_TRUE(rpc::SharedRegion::open((*mine)->name(), 64).ok()) << "a live process's region stays";
}

TEST(Codec, ChunkedMessagesReassembleAndRespectTheLimit) {
  v1::GenerateBatch batch;
  ASSERT_TRUE(rpc::encode_generation_batch(test_requests(), &batch).ok());
  EXPECT_EQ(batch.references_size(), 2);  // shared by both poses, sent once
  std::vector<v1::Chunk> chunks;
  ASSERT_TRUE(rpc::write_chunked(batch, [&](const v1::Chunk& c) {
    chunks.push_back(c);
    return true;
  }));
  size_t i = 0;
  const auto read = [&](v1::Chunk* c) {
    if (i == chunks.size()) return false;
    *c = chunks[i++];
    return true;
  };
  v1::GenerateBatch back;
  ASSERT_TRUE(rpc::read_chunked(read, 1 << 30, &back).ok());
  auto requests = rpc::decode_generation_batch(back);
  ASSERT_TRUE(requests.ok()) << requests.status();
  ASSERT_EQ(requests->size(), 2u);
  EXPECT_EQ((*requests)[1].references[0].camera.name, test_requests()[1].references[0].camera.name);
  EXPECT_TRUE(at::equal((*requests)[0].render_rgb, test_requests()[0].render_rgb));
  i = 0;
  EXPECT_EQ(rpc::read_chunked(read, 100, &back).code(), absl::StatusCode::kResourceExhausted);
}

// The trainer's two-stage settings travel with each pose: all three fields or none.
TEST(Codec, InpaintSettingsTravelWithThePose) {
  std::vector<GenerationRequest> requests = test_requests();
  requests[0].inpaint = InpaintSettings{0.25, 0.1, 7};
  v1::GenerateBatch batch;
  ASSERT_TRUE(rpc::encode_generation_batch(requests, &batch).ok());
  auto back = rpc::decode_generation_batch(batch);
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_TRUE((*back)[0].inpaint.has_value());
  EXPECT_EQ((*back)[0].inpaint->depth_threshold, 0.25);
  EXPECT_EQ((*back)[0].inpaint->uncovered_fraction, 0.1);
  EXPECT_EQ((*back)[0].inpaint->dilation, 7);
  EXPECT_FALSE((*back)[1].inpaint.has_value());
  batch.mutable_poses(0)->clear_inpaint_dilation();
  const absl::Status partial = rpc::decode_generation_batch(batch).status();
  EXPECT_EQ(partial.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(partial.message().find("inpaint_dilation"), std::string_view::npos);
  batch.mutable_poses(0)->set_inpaint_dilation(8);
  EXPECT_EQ(rpc::decode_generation_batch(batch).status().code(), absl::StatusCode::kInvalidArgument);
}

// The job's generation controls travel: the IP-Adapter scale with each pose, the scene adaptation with
// AdaptScene (both fields or none); values out of range are INVALID_ARGUMENT naming the field.
TEST(Codec, GenerationControlsTravelAndAreChecked) {
  std::vector<GenerationRequest> requests = test_requests();
  requests[0].ip_adapter_scale = 0.35;
  v1::GenerateBatch batch;
  ASSERT_TRUE(rpc::encode_generation_batch(requests, &batch).ok());
  auto back = rpc::decode_generation_batch(batch);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ((*back)[0].ip_adapter_scale, std::optional<double>(0.35));
  EXPECT_FALSE((*back)[1].ip_adapter_scale.has_value());
  for (double bad : {-0.5, std::nan("")}) {
    batch.mutable_poses(1)->set_ip_adapter_scale(bad);
    const absl::Status refused = rpc::decode_generation_batch(batch).status();
    EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument) << bad;
    EXPECT_TRUE(absl::StrContains(refused.message(), "pose 1: ip_adapter_scale")) << refused;
  }

  v1::AdaptSceneBatch adapt;
  rpc::encode_adapt_batch("job-1", requests[0].references, SceneAdaptation{2, 7}, &adapt);
  auto scene = rpc::decode_adapt_batch(adapt);
  ASSERT_TRUE(scene.ok()) << scene.status();
  EXPECT_EQ(adapt.scene_id(), "job-1");
  ASSERT_EQ(scene->views.size(), 2u);
  EXPECT_TRUE(at::equal(scene->views[1].image, requests[0].references[1].image));
  ASSERT_TRUE(scene->adaptation.has_value());
  EXPECT_EQ(scene->adaptation->lora_rank, 2);
  EXPECT_EQ(scene->adaptation->lora_steps, 7);
  v1::AdaptSceneBatch without;
  rpc::encode_adapt_batch("job-1", requests[0].references, std::nullopt, &without);
  EXPECT_FALSE(rpc::decode_adapt_batch(without)->adaptation.has_value());
  const auto refusal = [](v1::AdaptSceneBatch b, const std::function<void(v1::AdaptSceneBatch&)>& change) {
    change(b);
    const absl::Status s = rpc::decode_adapt_batch(b).status();
    EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << s;
    return std::string(s.message());
  };
  EXPECT_TRUE(absl::StrContains(refusal(adapt, [](auto& b) { b.clear_lora_steps(); }), "lora_rank and lora_steps"));
  EXPECT_TRUE(absl::StrContains(refusal(adapt, [](auto& b) { b.set_lora_steps(-1); }), "lora_steps must be >= 0"));
  EXPECT_TRUE(absl::StrContains(refusal(adapt, [](auto& b) { b.set_lora_rank(0); }), "lora_rank must be >= 1"));
}

TEST(ConfigCodec, JsonAndProtoAgreeAndUnsetFieldsKeepDefaults) {
  v1::TrainConfig config;
  ASSERT_TRUE(rpc::set_fields({{"iterations", 123}, {"lambda_dssim", 0.3}}, config.mutable_training()).ok());
  ASSERT_TRUE(
      rpc::set_fields({{"warmup_iterations", 40}, {"tier_alpha_min", {0.0, -0.1}}, {"tier_alpha_max", {1.0, 1.1}}},
                      config.mutable_gaps())
          .ok());
  EXPECT_EQ(rpc::set_fields({{"no_such_option", 1}}, config.mutable_training()).code(),
            absl::StatusCode::kInvalidArgument);
  config.set_views(3);
  auto o = run_options_from_proto(config, false, "", "cpu");
  ASSERT_TRUE(o.ok()) << o.status();
  EXPECT_EQ(o->config.iterations, 123);
  EXPECT_DOUBLE_EQ(o->config.lambda_dssim, 0.3);
  EXPECT_DOUBLE_EQ(o->config.feature_lr, TrainConfig().feature_lr);
  EXPECT_EQ(o->gaps.warmup_iterations, 40);
  EXPECT_EQ(o->gaps.phase_interval, GapsConfig().phase_interval);
  EXPECT_EQ(o->variant, Variant::kFull);
  EXPECT_EQ(o->init, "auto");  // unset: PatchMatch, or the sparse points where it covers too little
  config.set_init("sparse");
  EXPECT_EQ(run_options_from_proto(config, false, "", "cpu")->init, "sparse");
  config.set_init("points");
  EXPECT_EQ(run_options_from_proto(config, false, "", "cpu").status().code(), absl::StatusCode::kInvalidArgument);
  // A point count that would not fit any machine's memory is refused at submission, naming field and limit.
  config.set_init("random");
  config.set_random_points(100'000'000'000);
  const auto too_many = run_options_from_proto(config, false, "", "cpu");
  EXPECT_EQ(too_many.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(too_many.status().message().find("random_points 100000000000 is over the limit of 67108864"),
            std::string_view::npos)
      << too_many.status();
  config.set_random_points(0);
  config.set_init("colmap");
  const auto unknown = run_options_from_proto(config, false, "", "cpu");
  EXPECT_EQ(unknown.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(unknown.status().message().find("unknown init 'colmap' (auto, mvs"), std::string_view::npos);

  // PatchMatch and fusion settings: those set arrive, the others keep the defaults, ranges are checked.
  config.set_init("mvs");
  ASSERT_TRUE(rpc::set_fields({{"patchmatch_best_views", 3},
                               {"fusion_max_normal_error", 25.0},
                               {"fusion_add_sparse", true},
                               {"sparse_max_image_side", 504}},
                              config.mutable_init_settings())
                  .ok());
  o = run_options_from_proto(config, false, "", "cpu");
  ASSERT_TRUE(o.ok()) << o.status();
  EXPECT_EQ(o->patchmatch.best_views, 3);
  EXPECT_DOUBLE_EQ(o->fusion.max_normal_error_deg, 25.0);
  EXPECT_TRUE(o->fusion.add_sparse_points);
  EXPECT_FALSE(FusionOptions{}.add_sparse_points);
  EXPECT_EQ(o->sparse.max_image_side, 504);
  EXPECT_EQ(SparseOptions{}.max_image_side, 0);
  EXPECT_DOUBLE_EQ(o->patchmatch.max_cost, PatchMatchOptions{}.max_cost);
  EXPECT_EQ(o->fusion.min_views, FusionOptions{}.min_views);
  config.mutable_init_settings()->set_fusion_min_views(0);
  const auto refused = run_options_from_proto(config, false, "", "cpu");
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(refused.status().message().find("config: fusion: min_views must be >= 1, got 0"), std::string_view::npos)
      << refused.status();
}

// Blocks in generate() until released, so tests can fill the worker's queue.
class GatedGenerator : public Generator {
 public:
  std::string name() const override { return "gated (test)"; }
  absl::Status adapt(const std::vector<ReferenceView>&, const std::optional<SceneAdaptation>&) override {
    return absl::OkStatus();
  }
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override {
    std::unique_lock<std::mutex> lock(mutex);
    ++entered;
    changed.notify_all();
    changed.wait(lock, [&] { return open; });
    std::vector<at::Tensor> out;
    for (const auto& r : requests) out.push_back(r.render_rgb);
    return out;
  }
  void release() {
    std::lock_guard<std::mutex> lock(mutex);
    open = true;
    changed.notify_all();
  }
  void wait_entered(int n) {
    std::unique_lock<std::mutex> lock(mutex);
    changed.wait(lock, [&] { return entered >= n; });
  }
  std::mutex mutex;
  std::condition_variable changed;
  bool open = false;
  int entered = 0;
};

struct RunningWorker {
  RunningWorker(std::unique_ptr<Generator> generator, WorkerServiceOptions options,
                std::shared_ptr<grpc::ServerCredentials> credentials = grpc::InsecureServerCredentials(),
                int wanted_port = 0)
      : service(std::move(generator), options) {
    grpc::EnableDefaultHealthCheckService(true);
    grpc::ServerBuilder builder;
    builder.AddListeningPort("127.0.0.1:" + std::to_string(wanted_port), credentials, &port);
    builder.RegisterService(&service);
    server = builder.BuildAndStart();
  }
  ~RunningWorker() { server->Shutdown(std::chrono::system_clock::now()); }
  std::string address() const { return "127.0.0.1:" + std::to_string(port); }
  WorkerService service;
  int port = 0;
  std::unique_ptr<grpc::Server> server;
};

// How a pool hands tensors over (the defaults: compact, shared memory when the worker shares it).
struct Transfer {
  rpc::TensorEncoding encoding = rpc::TensorEncoding::kUint8;
  bool shared_memory = true;
};

absl::StatusOr<std::unique_ptr<RemoteGenerator>> pool(const std::vector<std::string>& addresses,
                                                      const std::string& token = "", Transfer transfer = {}) {
  WorkerPoolOptions o;
  o.addresses = addresses;
  o.security.token = token;
  o.encoding = transfer.encoding;
  o.shared_memory = transfer.shared_memory;
  o.probe_timeout = std::chrono::milliseconds(500);
  o.generate_timeout = std::chrono::milliseconds(20000);
  o.max_rounds = 2;
  o.backoff_initial = std::chrono::milliseconds(20);
  return RemoteGenerator::create(o);
}

// One Generate call of `batch` straight to a worker (no pool): the status the worker answered.
grpc::Status generate_call(v1::DiffusionWorker::Stub& stub, const v1::GenerateBatch& batch,
                           std::chrono::milliseconds timeout) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + timeout);
  auto stream = stub.Generate(&context);
  rpc::write_chunked(batch, [&](const v1::Chunk& c) { return stream->Write(c); });
  stream->WritesDone();
  v1::GenerateResult result;
  (void)rpc::read_chunked([&](v1::Chunk* c) { return stream->Read(c); }, 1 << 30, &result);
  return stream->Finish();
}

// Float32 hands over exactly what an in-process backend sees, through the socket and through shared memory.
TEST(WorkerService, RemoteGenerationEqualsInProcess) {
  auto local = make_generator("reproject", "");
  auto hosted = make_generator("reproject", "");
  ASSERT_TRUE(local.ok() && hosted.ok());
  WorkerServiceOptions options;
  options.backend = "reproject";
  RunningWorker worker(std::move(*hosted), options);
  ASSERT_GT(worker.port, 0);
  const auto requests = test_requests();
  auto want = (*local)->generate(requests);
  ASSERT_TRUE(want.ok()) << want.status();
  for (const bool shared : {false, true}) {
    auto remote = pool({worker.address()}, "", {rpc::TensorEncoding::kFloat32, shared});
    ASSERT_TRUE(remote.ok()) << remote.status();
    ASSERT_TRUE((*remote)->adapt(requests[0].references, std::nullopt).ok());
    auto got = (*remote)->generate(requests);
    ASSERT_TRUE(got.ok()) << got.status();
    ASSERT_EQ(got->size(), want->size());
    for (size_t k = 0; k < got->size(); ++k)
      EXPECT_TRUE(at::equal((*got)[k], (*want)[k])) << "pose " << k << ", shared memory " << shared;
    EXPECT_EQ((*remote)->counters().at("shared_memory"), shared ? 1.0 : 0.0);
    EXPECT_EQ((*remote)->name(), "remote " + (*local)->name());
  }
}

// Renders with 8-bit values (as the photographs are) and depths with half-precision values travel compact without
// loss, in a quarter of the bytes for colour and alpha and half for depth; the answer is the in-process one rounded
// to bytes. Shared memory leaves the message
// with the cameras and controls only.
TEST(WorkerService, CompactTransferIsTheInProcessAnswerInBytes) {
  auto local = make_generator("reproject", "");
  auto hosted = make_generator("reproject", "");
  ASSERT_TRUE(local.ok() && hosted.ok());
  WorkerServiceOptions options;
  options.backend = "reproject";
  RunningWorker worker(std::move(*hosted), options);
  auto requests = test_requests();
  const auto bytes = [](const at::Tensor& t) { return t.mul(255).round().div(255); };
  const auto halves = [](const at::Tensor& t) { return t.to(at::kHalf).to(at::kFloat); };
  for (auto& q : requests) {
    q.render_rgb = bytes(q.render_rgb);
    q.render_alpha = bytes(q.render_alpha);
    q.render_depth = halves(q.render_depth);
    for (auto& r : q.references) {
      r.image = bytes(r.image);
      r.render_depth = halves(r.render_depth);
    }
  }
  auto want = (*local)->generate(requests);
  ASSERT_TRUE(want.ok()) << want.status();
  double request_bytes[2][2] = {};  // [compact][shared]: bytes in the message
  for (const bool compact : {false, true})
    for (const bool shared : {false, true}) {
      auto remote =
          pool({worker.address()}, "", {compact ? rpc::TensorEncoding::kUint8 : rpc::TensorEncoding::kFloat32, shared});
      ASSERT_TRUE(remote.ok()) << remote.status();
      ASSERT_TRUE((*remote)->adapt(requests[0].references, std::nullopt).ok());
      auto got = (*remote)->generate(requests);
      ASSERT_TRUE(got.ok()) << got.status();
      for (size_t k = 0; k < got->size(); ++k) {
        const at::Tensor expected = compact ? bytes((*want)[k].clamp(0, 1)) : (*want)[k];
        EXPECT_TRUE(at::allclose((*got)[k], expected, 0, 1e-6)) << "pose " << k << " compact " << compact;
      }
      const std::map<std::string, double> counters = (*remote)->counters();
      request_bytes[compact][shared] = counters.at("request_bytes");
      EXPECT_EQ(counters.at("shared_memory"), shared ? 1.0 : 0.0);
      EXPECT_EQ(counters.count("shared_memory_bytes"), shared ? 1u : 0u);
      const std::map<std::string, double> stages = (*remote)->stage_seconds();
      for (const char* stage : {"client_encode", "client_send", "client_receive", "client_decode", "worker_receive",
                                "worker_decode", "worker_queue", "worker_encode"})
        EXPECT_EQ(stages.count(stage), 1u) << stage;
    }
  // Per pixel: float32 colour 12 + depth 4 + alpha 4 bytes, compact 3 + 2 + 1; through shared memory the message
  // keeps the cameras and controls (most of it at this tiny image size).
  EXPECT_LT(request_bytes[1][0], 0.4 * request_bytes[0][0]);
  EXPECT_LT(request_bytes[1][1], 0.1 * request_bytes[1][0]);
  EXPECT_LT(request_bytes[0][1], 0.1 * request_bytes[1][0]);
}

// A worker started without shared memory offers none, and its callers use the socket.
TEST(WorkerService, AWorkerWithoutSharedMemoryGetsPayloadsInTheMessages) {
  auto hosted = make_generator("reproject", "");
  ASSERT_TRUE(hosted.ok());
  WorkerServiceOptions options;
  options.backend = "reproject";
  options.shared_memory = false;
  RunningWorker worker(std::move(*hosted), options);
  auto remote = pool({worker.address()});
  ASSERT_TRUE(remote.ok()) << remote.status();
  const auto requests = test_requests();
  ASSERT_TRUE((*remote)->adapt(requests[0].references, std::nullopt).ok());
  ASSERT_TRUE((*remote)->generate(requests).ok());
  EXPECT_EQ((*remote)->counters().at("shared_memory"), 0.0);
}

// What a worker does with shared-memory regions it is handed: only names a trainer creates, only slices inside
// the region, only when it offers shared memory; each refusal names the problem.
TEST(WorkerService, SharedRegionsAreCheckedBeforeUse) {
  auto hosted = make_generator("reproject", "");
  ASSERT_TRUE(hosted.ok());
  WorkerServiceOptions options;
  options.backend = "reproject";
  RunningWorker worker(std::move(*hosted), options);
  auto closed = make_generator("reproject", "");
  ASSERT_TRUE(closed.ok());
  options.shared_memory = false;
  RunningWorker without(std::move(*closed), options);
  const auto call = [](const RunningWorker& w, const v1::GenerateBatch& batch) {
    auto stub = v1::DiffusionWorker::NewStub(grpc::CreateChannel(w.address(), grpc::InsecureChannelCredentials()));
    return generate_call(*stub, batch, std::chrono::seconds(20));
  };
  const auto requests = test_requests();
  const rpc::SharedLayout layout = rpc::shared_layout(requests, rpc::TensorEncoding::kUint8);
  auto region = rpc::SharedRegion::create(layout.request_bytes + layout.answer_bytes);
  ASSERT_TRUE(region.ok()) << region.status();
  rpc::SharedArena arena(**region);
  v1::GenerateBatch good;
  ASSERT_TRUE(rpc::encode_generation_batch(requests, &good, {rpc::TensorEncoding::kUint8, &arena}).ok());
  good.mutable_shared_region()->set_name((*region)->name());
  good.mutable_shared_region()->set_size((*region)->size());
  good.mutable_shared_region()->set_answer_offset(layout.request_bytes);
  EXPECT_TRUE(call(worker, good).ok());

  const auto refused = [&](const RunningWorker& w, const v1::GenerateBatch& batch, grpc::StatusCode code,
                           const std::string& words) {
    const grpc::Status st = call(w, batch);
    EXPECT_EQ(st.error_code(), code) << st.error_message();
    EXPECT_TRUE(absl::StrContains(st.error_message(), words)) << st.error_message();
  };
  refused(without, good, grpc::StatusCode::FAILED_PRECONDITION, "takes no shared memory");
  v1::GenerateBatch bad = good;
  bad.mutable_shared_region()->set_name("/etc-passwd");
  refused(worker, bad, grpc::StatusCode::INVALID_ARGUMENT, "is not one a gaps trainer creates");
  bad.mutable_shared_region()->set_name("/gaps-region-1-999999999");
  refused(worker, bad, grpc::StatusCode::FAILED_PRECONDITION, "/gaps-region-1-999999999");
  bad = good;
  bad.mutable_shared_region()->set_size((*region)->size() + 64);
  refused(worker, bad, grpc::StatusCode::INVALID_ARGUMENT, "the request says");
  bad = good;
  bad.mutable_poses(1)->mutable_render_rgb()->mutable_shared()->set_offset((*region)->size() - 8);
  refused(worker, bad, grpc::StatusCode::INVALID_ARGUMENT, "pose 1 render_rgb: bytes");
  bad = good;
  bad.clear_shared_region();
  refused(worker, bad, grpc::StatusCode::INVALID_ARGUMENT, "refers to shared memory, but the call has no region");
}

// Answers every request with NaN pixels: a worker with a broken backend.
class NanGenerator : public Generator {
 public:
  std::string name() const override { return "nan (test)"; }
  absl::Status adapt(const std::vector<ReferenceView>&, const std::optional<SceneAdaptation>&) override {
    return absl::OkStatus();
  }
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override {
    std::vector<at::Tensor> out;
    for (const auto& r : requests) out.push_back(at::full_like(r.render_rgb, std::nan("")));
    return out;
  }
};

// A malformed answer is the worker's fault, not the request's: the next worker is asked, and when none answers
// well the error names each worker and what was wrong with its answer.
TEST(WorkerPool, AMalformedAnswerMovesOnToTheNextWorker) {
  WorkerServiceOptions options;
  options.backend = "nan";
  RunningWorker broken(std::make_unique<NanGenerator>(), options);
  auto hosted = make_generator("reproject", "");
  ASSERT_TRUE(hosted.ok());
  options.backend = "reproject";
  RunningWorker healthy(std::move(*hosted), options);
  const auto requests = test_requests();

  // Float32 answers carry the NaN to the trainer, which refuses them; bytes cannot, so the worker refuses.
  for (const auto encoding : {rpc::TensorEncoding::kFloat32, rpc::TensorEncoding::kUint8}) {
    auto both = pool({broken.address(), healthy.address()}, "", {encoding, false});
    ASSERT_TRUE(both.ok()) << both.status();
    ASSERT_TRUE((*both)->adapt(requests[0].references, std::nullopt).ok());
    const auto images = (*both)->generate(requests);
    ASSERT_TRUE(images.ok()) << images.status();
    for (const at::Tensor& image : *images) EXPECT_TRUE(at::isfinite(image).all().item<bool>());

    auto alone = pool({broken.address()}, "", {encoding, false});
    ASSERT_TRUE(alone.ok()) << alone.status();
    ASSERT_TRUE((*alone)->adapt(requests[0].references, std::nullopt).ok());
    const absl::Status refused = (*alone)->generate(requests).status();
    EXPECT_EQ(refused.code(), absl::StatusCode::kUnavailable) << refused;
    EXPECT_TRUE(absl::StrContains(refused.message(), broken.address() + ": ")) << refused;
    EXPECT_TRUE(absl::StrContains(refused.message(), "malformed answer: image 0: contains NaN or infinite values"))
        << refused;
  }
}

// A cancelled job or a stopping trainer does not wait for a worker that never answers: the call is cancelled
// and generate() says why (the phase is then skipped), long before the call's deadline would have ended it.
TEST(WorkerPool, AStopRequestCancelsACallToAWorkerThatNeverAnswers) {
  auto gated = std::make_unique<GatedGenerator>();
  GatedGenerator* gate = gated.get();
  WorkerServiceOptions options;
  options.backend = "gated";
  RunningWorker worker(std::move(gated), options);
  WorkerPoolOptions o;
  o.addresses = {worker.address()};
  o.probe_timeout = std::chrono::milliseconds(500);
  o.generate_timeout = std::chrono::hours(1);
  o.max_rounds = 3;
  std::atomic<bool> stop{false};
  o.should_stop = [&] { return stop.load(); };
  auto remote = RemoteGenerator::create(o);
  ASSERT_TRUE(remote.ok()) << remote.status();
  const auto requests = test_requests();
  ASSERT_TRUE((*remote)->adapt(requests[0].references, std::nullopt).ok());
  std::thread stopper([&] {
    gate->wait_entered(1);  // the call is in the worker's backend, which never answers on its own
    stop = true;
  });
  const absl::Status stopped = (*remote)->generate(requests).status();
  stopper.join();
  gate->release();
  EXPECT_EQ(stopped.code(), absl::StatusCode::kUnavailable) << stopped;
  EXPECT_TRUE(absl::StrContains(stopped.message(), "the job is stopping")) << stopped;
}

// A dns:/// name stands for every address it resolves to (one worker each); a name that resolves to nothing
// stays in the pool as itself, to be reported unreachable like any worker that is down.
TEST(WorkerPool, DnsNamesResolveToOneWorkerPerAddress) {
  const auto resolved =
      resolve_worker_addresses({"dns:///localhost:1234", "10.0.0.7:50052", "dns:no-such-host.invalid:9"});
  EXPECT_NE(std::find(resolved.begin(), resolved.end(), "127.0.0.1:1234"), resolved.end())
      << absl::StrJoin(resolved, " ");
  EXPECT_NE(std::find(resolved.begin(), resolved.end(), "10.0.0.7:50052"), resolved.end());
  EXPECT_NE(std::find(resolved.begin(), resolved.end(), "dns:no-such-host.invalid:9"), resolved.end());
  EXPECT_EQ(std::count_if(resolved.begin(), resolved.end(),
                          [](const std::string& a) { return absl::StrContains(a, "dns:"); }),
            1);

  auto hosted = make_generator("reproject", "");
  ASSERT_TRUE(hosted.ok());
  WorkerServiceOptions options;
  options.backend = "reproject";
  RunningWorker worker(std::move(*hosted), options);
  auto remote = pool(resolve_worker_addresses({"dns:///localhost:" + std::to_string(worker.port)}));
  ASSERT_TRUE(remote.ok()) << remote.status();
  const auto requests = test_requests();
  ASSERT_TRUE((*remote)->adapt(requests[0].references, std::nullopt).ok());
  auto got = (*remote)->generate(requests);  // through 127.0.0.1 (and past ::1, where nothing listens)
  ASSERT_TRUE(got.ok()) << got.status();
  EXPECT_EQ(got->size(), requests.size());
}

// What the hosted backend cannot honour comes back with the answer that asked for it: the adaptation's notes
// with the Generate call that adapted the worker, each generation's with its own.
TEST(WorkerService, BackendNotesReachTheCaller) {
  auto hosted = make_generator("reproject", "");
  ASSERT_TRUE(hosted.ok());
  WorkerServiceOptions options;
  options.backend = "reproject";
  RunningWorker worker(std::move(*hosted), options);
  auto remote = pool({worker.address()});
  ASSERT_TRUE(remote.ok()) << remote.status();
  std::vector<GenerationRequest> requests = test_requests();
  ASSERT_TRUE((*remote)->adapt(requests[0].references, SceneAdaptation{4, 50}).ok());
  EXPECT_TRUE((*remote)->notes().empty()) << "nothing reached a worker yet";
  ASSERT_TRUE((*remote)->generate(requests).ok());
  EXPECT_EQ((*remote)->notes(),
            std::vector<std::string>{worker.address() + ": reproject has no model to adapt: the 50 LoRA steps (rank 4) "
                                                        "asked for were not run"});
  requests[1].ip_adapter_scale = 0.5;
  ASSERT_TRUE((*remote)->generate(requests).ok());
  EXPECT_EQ((*remote)->notes(),
            std::vector<std::string>{worker.address() + ": reproject has no IP-Adapter: 1/2 requests asked for "
                                                        "ip_adapter_scale 0.5, generated without an image prompt"});
}

TEST(WorkerService, FullQueueIsResourceExhaustedAndQueuedCallsHonourDeadlines) {
  auto gated = std::make_unique<GatedGenerator>();
  GatedGenerator* gate = gated.get();
  WorkerServiceOptions options;
  options.backend = "gated";
  options.queue_capacity = 1;
  RunningWorker worker(std::move(gated), options);
  auto channel = grpc::CreateChannel(worker.address(), grpc::InsecureChannelCredentials());
  auto stub = v1::DiffusionWorker::NewStub(channel);
  v1::GenerateBatch batch;
  ASSERT_TRUE(rpc::encode_generation_batch(test_requests(), &batch).ok());
  const auto call = [&](std::chrono::milliseconds timeout) { return generate_call(*stub, batch, timeout); };
  std::thread running([&] { EXPECT_TRUE(call(std::chrono::seconds(30)).ok()); });
  gate->wait_entered(1);
  // Waits in the queue (capacity 1) past its deadline.
  grpc::Status queued_status;
  std::thread queued([&] { queued_status = call(std::chrono::milliseconds(1500)); });
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  const grpc::Status overflow = call(std::chrono::seconds(10));  // backend busy, queue full
  EXPECT_EQ(overflow.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED) << overflow.error_message();
  queued.join();
  EXPECT_EQ(queued_status.error_code(), grpc::StatusCode::DEADLINE_EXCEEDED) << queued_status.error_message();
  gate->release();
  running.join();
}

TEST(WorkerService, WrongTokenIsUnauthenticated) {
  auto hosted = make_generator("reproject", "");
  ASSERT_TRUE(hosted.ok());
  WorkerServiceOptions options;
  options.backend = "reproject";
  options.token = "correct-token";
  RunningWorker worker(std::move(*hosted), options);
  auto stub = v1::DiffusionWorker::NewStub(grpc::CreateChannel(worker.address(), grpc::InsecureChannelCredentials()));
  for (const std::string token : {"", "wrong-token"}) {
    grpc::ClientContext context;
    rpc::attach_token(context, token);
    v1::WorkerInfo info;
    EXPECT_EQ(stub->GetInfo(&context, v1::GetInfoRequest(), &info).error_code(), grpc::StatusCode::UNAUTHENTICATED);
  }
  grpc::ClientContext context;
  rpc::attach_token(context, "correct-token");
  v1::WorkerInfo info;
  ASSERT_TRUE(stub->GetInfo(&context, v1::GetInfoRequest(), &info).ok());
  EXPECT_EQ(info.backend(), "reproject");
  EXPECT_EQ(info.device(), "cpu");
  EXPECT_GT(info.device_memory_total(), 0u);  // the host's physical memory
  EXPECT_LE(info.device_memory_free(), info.device_memory_total());
  // The pool with the right token generates; with a wrong one it reports the refusal, not a skip.
  auto good = pool({worker.address()}, "correct-token");
  ASSERT_TRUE(good.ok());
  EXPECT_TRUE((*good)->generate(test_requests()).ok());
}

// Mutual TLS: a CA signs the server's and one client's certificate; a client without a certificate, or with
// one the CA did not sign, never gets through the handshake.
using MutualTls = test::TempDirTest;

TEST_F(MutualTls, OnlyClientsWithACertificateSignedByTheClientCaGetIn) {
  if (std::system("openssl version > /dev/null 2>&1") != 0) GTEST_SKIP() << "openssl not found: no test certificates";
  const std::string d = dir_.string() + "/";
  ASSERT_TRUE(test::make_test_certificates(dir_));

  auto credentials = rpc::server_credentials({"", d + "localhost.pem", d + "localhost.key", d + "ca.pem"});
  ASSERT_TRUE(credentials.ok()) << credentials.status();
  auto hosted = make_generator("reproject", "");
  ASSERT_TRUE(hosted.ok());
  WorkerServiceOptions options;
  options.backend = "reproject";
  RunningWorker worker(std::move(*hosted), options, *credentials);
  ASSERT_GT(worker.port, 0);
  auto get_info = [&](const rpc::ClientSecurity& security) {
    auto channel = rpc::make_channel(worker.address(), security);
    EXPECT_TRUE(channel.ok()) << channel.status();
    auto stub = v1::DiffusionWorker::NewStub(*channel);
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
    v1::WorkerInfo info;
    return stub->GetInfo(&context, v1::GetInfoRequest(), &info);
  };
  EXPECT_TRUE(get_info({"", d + "ca.pem", "localhost", d + "client.pem", d + "client.key"}).ok());
  EXPECT_FALSE(get_info({"", d + "ca.pem", "localhost"}).ok()) << "no client certificate";
  EXPECT_FALSE(get_info({"", d + "ca.pem", "localhost", d + "rogue.pem", d + "rogue.key"}).ok())
      << "unsigned certificate";
  EXPECT_FALSE(get_info({}).ok()) << "plaintext";
  // Half-given settings are errors that say what is missing.
  EXPECT_EQ(rpc::server_credentials({"", "", "", d + "ca.pem"}).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(rpc::make_channel(worker.address(), {"", d + "ca.pem", "", d + "client.pem", ""}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(rpc::make_channel(worker.address(), {"", "", "", d + "client.pem", d + "client.key"}).status().code(),
            absl::StatusCode::kInvalidArgument);
  // A key that belongs to another certificate is named with both files, on either side, before gRPC sees it
  // (which would only say that the server "cannot listen" or that a handshake failed).
  const auto mismatch = [&](const absl::Status& st) {
    EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << st;
    EXPECT_TRUE(absl::StrContains(st.message(), "the TLS private key " + d +
                                                    "rogue.key does not belong to the "
                                                    "certificate " +
                                                    d + "localhost.pem"))
        << st;
  };
  mismatch(rpc::server_credentials({"", d + "localhost.pem", d + "rogue.key", ""}).status());
  mismatch(rpc::make_channel(worker.address(), {"", d + "ca.pem", "", d + "localhost.pem", d + "rogue.key"}).status());
  std::ofstream(d + "truncated.key") << "-----BEGIN PRIVATE KEY-----\nAAAA\n-----END PRIVATE KEY-----\n";
  const auto unreadable = rpc::server_credentials({"", d + "localhost.pem", d + "truncated.key", ""}).status();
  EXPECT_TRUE(absl::StrContains(unreadable.message(), d + "truncated.key: the private key cannot be read"))
      << unreadable;
}

// A file that holds no PEM block is named as such when it is read, not later by gRPC as "empty address
// list" or "cannot listen".
TEST(Security, FilesWithoutAPemBlockAreRefusedNamingTheFile) {
  const std::filesystem::path garbage = std::filesystem::temp_directory_path() / "gaps_garbage.pem";
  std::ofstream(garbage) << "this is not a certificate\n";
  const auto channel = rpc::make_channel("127.0.0.1:1", {"", garbage.string(), ""});
  ASSERT_FALSE(channel.ok());
  EXPECT_EQ(channel.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(channel.status().message().find(garbage.string() + ": not a PEM certificate"), std::string_view::npos)
      << channel.status();
  rpc::ServerSecurity server{"", garbage.string(), garbage.string(), ""};
  const auto credentials = rpc::server_credentials(server);
  ASSERT_FALSE(credentials.ok());
  EXPECT_NE(credentials.status().message().find("not a PEM"), std::string_view::npos) << credentials.status();
  std::filesystem::remove(garbage);
}

TEST(WorkerPool, NoReachableWorkerIsUnavailableNamingEachAddress) {
  auto remote = pool({"127.0.0.1:1", "127.0.0.1:2"});
  ASSERT_TRUE(remote.ok());
  const auto result = (*remote)->generate(test_requests());
  ASSERT_FALSE(result.ok());
  EXPECT_EQ(result.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_NE(result.status().message().find("127.0.0.1:1"), std::string_view::npos);
  EXPECT_NE(result.status().message().find("127.0.0.1:2"), std::string_view::npos);
}

// Echoes each render and counts the poses and adaptations it was asked for.
class EchoGenerator : public Generator {
 public:
  std::string name() const override { return "echo (test)"; }
  absl::Status adapt(const std::vector<ReferenceView>&, const std::optional<SceneAdaptation>&) override {
    ++adaptations;
    return absl::OkStatus();
  }
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override {
    poses += static_cast<int>(requests.size());
    std::vector<at::Tensor> out;
    for (const auto& r : requests) out.push_back(r.render_rgb);
    return out;
  }
  std::atomic<int> adaptations{0}, poses{0};
};

// Fails its first generate() with UNAVAILABLE, as a worker going away would, then echoes.
class FlakyGenerator : public EchoGenerator {
 public:
  std::string name() const override { return "flaky (test)"; }
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override {
    if (++generations == 1) return absl::UnavailableError("going away (test)");
    return EchoGenerator::generate(requests);
  }
  std::atomic<int> generations{0};
};

// A worker that failed may have restarted and forgotten the scene: it is adapted again before it generates.
TEST(WorkerPool, AWorkerThatFailedIsAdaptedAgainBeforeItGenerates) {
  auto flaky = std::make_unique<FlakyGenerator>();
  const FlakyGenerator& backend = *flaky;
  WorkerServiceOptions options;
  options.backend = "flaky";
  RunningWorker worker(std::move(flaky), options);
  auto remote = pool({worker.address()});
  ASSERT_TRUE(remote.ok()) << remote.status();
  const auto requests = test_requests();
  ASSERT_TRUE((*remote)->adapt(requests[0].references, SceneAdaptation{4, 50}).ok());
  const auto images = (*remote)->generate(requests);
  ASSERT_TRUE(images.ok()) << images.status();
  EXPECT_EQ(backend.generations, 2);
  EXPECT_EQ(backend.adaptations, 2);
}

// A worker restarted between two phases (no call failed, so the pool still holds its old scene handle)
// answers NOT_FOUND for that handle: the pool adapts it again and the phase gets its images.
TEST(WorkerPool, AWorkerRestartedBetweenCallsIsAdaptedAgain) {
  WorkerServiceOptions options;
  options.backend = "reproject";
  auto first = make_generator("reproject", "");
  ASSERT_TRUE(first.ok());
  auto worker = std::make_unique<RunningWorker>(std::move(*first), options);
  const int port = worker->port;
  auto remote = pool({worker->address()});
  ASSERT_TRUE(remote.ok()) << remote.status();
  const auto requests = test_requests();
  ASSERT_TRUE((*remote)->adapt(requests[0].references, std::nullopt).ok());
  ASSERT_TRUE((*remote)->generate(requests).ok());

  worker.reset();
  auto second = make_generator("reproject", "");
  ASSERT_TRUE(second.ok());
  worker = std::make_unique<RunningWorker>(std::move(*second), options, grpc::InsecureServerCredentials(), port);
  ASSERT_EQ(worker->port, port);
  const auto images = (*remote)->generate(requests);
  EXPECT_TRUE(images.ok()) << images.status();
}

std::vector<GenerationRequest> many_requests(int count) {
  const std::vector<GenerationRequest> pair = test_requests();
  std::vector<GenerationRequest> out;
  for (int k = 0; k < count; ++k) {
    GenerationRequest q = pair[k % 2];
    q.render_rgb = at::full_like(q.render_rgb, k / 16.0);
    out.push_back(q);
  }
  return out;
}

// Each image must be the answer to its own pose (EchoGenerator: the render), in the order asked.
void expect_in_order(const std::vector<at::Tensor>& images, const std::vector<GenerationRequest>& requests) {
  ASSERT_EQ(images.size(), requests.size());
  for (size_t k = 0; k < images.size(); ++k) EXPECT_TRUE(at::equal(images[k], requests[k].render_rgb)) << "pose " << k;
}

// A phase's poses are shared among the pool's workers (each adapted to the scene first) and come back in order;
// with fan_out off one worker makes them all.
TEST(WorkerPool, APhaseIsSharedAmongTheWorkersAndAnsweredInOrder) {
  WorkerServiceOptions options;
  options.backend = "echo";
  auto a = std::make_unique<EchoGenerator>(), b = std::make_unique<EchoGenerator>();
  const EchoGenerator &first = *a, &second = *b;
  RunningWorker wa(std::move(a), options), wb(std::move(b), options);
  const auto requests = many_requests(5);
  for (const bool fan_out : {true, false}) {
    WorkerPoolOptions o;
    o.addresses = {wa.address(), wb.address()};
    o.encoding = rpc::TensorEncoding::kFloat32;
    o.fan_out = fan_out;
    auto remote = RemoteGenerator::create(o);
    ASSERT_TRUE(remote.ok()) << remote.status();
    ASSERT_TRUE((*remote)->adapt(requests[0].references, SceneAdaptation{4, 50}).ok());
    const int poses_before = first.poses + second.poses, first_before = first.poses;
    const int adaptations_before = first.adaptations + second.adaptations;
    const auto images = (*remote)->generate(requests);
    ASSERT_TRUE(images.ok()) << images.status();
    expect_in_order(*images, requests);
    EXPECT_EQ(first.poses + second.poses - poses_before, 5);
    EXPECT_EQ((*remote)->counters().at("workers"), fan_out ? 2.0 : 1.0);
    EXPECT_EQ(first.adaptations + second.adaptations - adaptations_before, fan_out ? 2 : 1);
    if (fan_out) EXPECT_EQ(first.poses - first_before, 2) << "contiguous shards: 2 poses, then 3";
  }
}

// Shards follow the workers' speeds: even while none is measured, in proportion once they are, never empty.
TEST(WorkerPool, ShardsAreSizedByEachWorkersSpeed) {
  EXPECT_EQ(shard_sizes(5, {0, 0}), (std::vector<size_t>{2, 3}));
  EXPECT_EQ(shard_sizes(16, {0, 0, 0}), (std::vector<size_t>{5, 5, 6}));
  EXPECT_EQ(shard_sizes(16, {0.1, 0.3}), (std::vector<size_t>{12, 4})) << "three times as fast: three times the poses";
  EXPECT_EQ(shard_sizes(16, {0.1, 0}), (std::vector<size_t>{8, 8})) << "unmeasured counts as the measured mean";
  EXPECT_EQ(shard_sizes(10, {10, 0.01}), (std::vector<size_t>{1, 9})) << "the slow one keeps one pose";
  EXPECT_EQ(shard_sizes(4, {0.01, 10, 10, 10}), (std::vector<size_t>{1, 1, 1, 1}));
  EXPECT_EQ(shard_sizes(7, {2.5}), (std::vector<size_t>{7}));
  for (size_t poses = 3; poses < 40; poses += 3) {
    const std::vector<size_t> sizes = shard_sizes(poses, {0.3, 0.01, 1.7});
    EXPECT_EQ(sizes[0] + sizes[1] + sizes[2], poses);
    EXPECT_GE(*std::min_element(sizes.begin(), sizes.end()), 1u);
    EXPECT_GE(sizes[1], sizes[0]);
    EXPECT_GE(sizes[0], sizes[2]);
  }
}

// Echoes after `delay` per pose, as a worker on a slower (or busier) GPU would.
class SlowEchoGenerator : public EchoGenerator {
 public:
  explicit SlowEchoGenerator(std::chrono::milliseconds delay) : delay_(delay) {}
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override {
    std::this_thread::sleep_for(delay_ * static_cast<int>(requests.size()));
    return EchoGenerator::generate(requests);
  }

 private:
  std::chrono::milliseconds delay_;
};

// The first shared phase splits evenly; once the pool has seen that one worker takes far longer per pose, it
// gives that worker fewer poses (still at least one), and the answers stay in order.
TEST(WorkerPool, ASlowerWorkerIsGivenFewerPosesOnceItsSpeedIsKnown) {
  WorkerServiceOptions options;
  options.backend = "echo";
  auto slow = std::make_unique<SlowEchoGenerator>(std::chrono::milliseconds(200));
  auto fast = std::make_unique<EchoGenerator>();
  const EchoGenerator& slower = *slow;
  RunningWorker ws(std::move(slow), options), wf(std::move(fast), options);
  auto remote = pool({ws.address(), wf.address()}, "", {rpc::TensorEncoding::kFloat32, true});
  ASSERT_TRUE(remote.ok()) << remote.status();
  const auto requests = many_requests(8);
  ASSERT_TRUE((*remote)->adapt(requests[0].references, std::nullopt).ok());
  const std::string slow_shard = "shard " + ws.address();
  for (const int expected_at_most : {4, 1}) {
    const int before = slower.poses;
    const auto images = (*remote)->generate(requests);
    ASSERT_TRUE(images.ok()) << images.status();
    expect_in_order(*images, requests);
    EXPECT_LE(slower.poses - before, expected_at_most);
    EXPECT_GE(slower.poses - before, 1);
    EXPECT_EQ((*remote)->counters().at(slow_shard), slower.poses - before);
  }
}

// A worker that fails its shard hands it to the others: the phase still gets every image, in order.
TEST(WorkerPool, AShardWhoseWorkerFailsIsAnsweredByAnother) {
  WorkerServiceOptions options;
  options.backend = "flaky";
  auto flaky = std::make_unique<FlakyGenerator>();
  const FlakyGenerator& failing = *flaky;
  RunningWorker broken(std::move(flaky), options);
  auto echo = std::make_unique<EchoGenerator>();
  const EchoGenerator& healthy = *echo;
  options.backend = "echo";
  RunningWorker good(std::move(echo), options);
  auto remote = pool({broken.address(), good.address()}, "", {rpc::TensorEncoding::kFloat32, true});
  ASSERT_TRUE(remote.ok()) << remote.status();
  const auto requests = many_requests(4);
  ASSERT_TRUE((*remote)->adapt(requests[0].references, std::nullopt).ok());
  const auto images = (*remote)->generate(requests);
  ASSERT_TRUE(images.ok()) << images.status();
  expect_in_order(*images, requests);
  EXPECT_EQ(failing.generations, 1) << "its shard failed once and went elsewhere";
  EXPECT_EQ(healthy.poses, 4);
}

// The pool reports where a call's time went: the AdaptScene call when this call adapted the worker, the
// backend's seconds and the transfer around them.
TEST(WorkerPool, GenerateReportsTheAdaptationAndTheWorkersSecondsByStage) {
  WorkerServiceOptions options;
  options.backend = "reproject";
  auto generator = make_generator("reproject", "");
  ASSERT_TRUE(generator.ok());
  RunningWorker worker(std::move(*generator), options);
  auto remote = pool({worker.address()});
  ASSERT_TRUE(remote.ok()) << remote.status();
  const auto requests = test_requests();
  ASSERT_TRUE((*remote)->adapt(requests[0].references, std::nullopt).ok());
  ASSERT_TRUE((*remote)->generate(requests).ok());
  const std::map<std::string, double> first = (*remote)->stage_seconds();
  for (const char* stage : {"adapt_scene", "worker_generate", "transfer"}) {
    ASSERT_EQ(first.count(stage), 1u) << stage;
    EXPECT_GE(first.at(stage), 0.0) << stage;
  }
  ASSERT_TRUE((*remote)->generate(requests).ok());
  const std::map<std::string, double> second = (*remote)->stage_seconds();
  EXPECT_EQ(second.count("adapt_scene"), 0u) << "adapted once, by the first call";
  EXPECT_EQ(second.count("worker_generate"), 1u);
}

// Echoes; its adapt() holds until the test releases it (or 20 s pass), and says whether it was released.
class GatedAdaptGenerator : public EchoGenerator {
 public:
  absl::Status adapt(const std::vector<ReferenceView>& views, const std::optional<SceneAdaptation>& a) override {
    std::unique_lock<std::mutex> lock(mutex_);
    released_in_time = changed_.wait_for(lock, std::chrono::seconds(20), [this] { return released_; });
    return EchoGenerator::adapt(views, a);
  }
  void release() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      released_ = true;
    }
    changed_.notify_all();
  }
  std::atomic<bool> released_in_time{false};

 private:
  std::mutex mutex_;
  std::condition_variable changed_;
  bool released_ = false;
};

// adapt() starts the workers' adaptation and returns while it runs (so a LoRA trains while the model does);
// generate() waits for it and reports it: its AdaptScene seconds and how long generate() waited.
TEST(WorkerPool, AdaptReturnsAtOnceAndGenerateWaitsForTheWorkersAdaptation) {
  WorkerServiceOptions options;
  options.backend = "gated";
  auto gated = std::make_unique<GatedAdaptGenerator>();
  GatedAdaptGenerator& backend = *gated;
  RunningWorker worker(std::move(gated), options);
  auto remote = pool({worker.address()}, "", {rpc::TensorEncoding::kFloat32, true});
  ASSERT_TRUE(remote.ok()) << remote.status();
  const auto requests = many_requests(3);
  // Were adapt() to wait for the worker, it would return only when the gate gave up, unreleased.
  ASSERT_TRUE((*remote)->adapt(requests[0].references, SceneAdaptation{4, 50}).ok());
  backend.release();
  const auto images = (*remote)->generate(requests);
  ASSERT_TRUE(images.ok()) << images.status();
  expect_in_order(*images, requests);
  EXPECT_TRUE(backend.released_in_time) << "adapt() waited for the worker's adaptation";
  EXPECT_EQ(backend.adaptations, 1);
  const std::map<std::string, double> stages = (*remote)->stage_seconds();
  for (const char* stage : {"adapt_scene", "adaptation_wait"}) {
    ASSERT_EQ(stages.count(stage), 1u) << stage;
    EXPECT_GE(stages.at(stage), 0.0) << stage;
  }
  ASSERT_TRUE((*remote)->generate(requests).ok());
  EXPECT_EQ((*remote)->stage_seconds().count("adaptation_wait"), 0u) << "waited for once";
  EXPECT_EQ(backend.adaptations, 1);
}

// With fan_out, a worker whose adaptation is still running once another's has ended (and the grace after it
// passed) sits out the calls, which the adapted worker answers alone; once its adaptation ends, it shares them.
TEST(WorkerPool, AWorkerStillAdaptingSitsOutTheCallsUntilItsAdaptationEnds) {
  WorkerServiceOptions options;
  options.backend = "echo";
  auto quick = std::make_unique<EchoGenerator>();
  auto gated = std::make_unique<GatedAdaptGenerator>();
  const EchoGenerator& first = *quick;
  GatedAdaptGenerator& slow = *gated;
  RunningWorker wa(std::move(quick), options), wb(std::move(gated), options);
  WorkerPoolOptions o;
  o.addresses = {wa.address(), wb.address()};
  o.encoding = rpc::TensorEncoding::kFloat32;
  o.adaptation_grace = std::chrono::milliseconds(100);
  auto remote = RemoteGenerator::create(o);
  ASSERT_TRUE(remote.ok()) << remote.status();
  const auto requests = many_requests(5);
  ASSERT_TRUE((*remote)->adapt(requests[0].references, SceneAdaptation{4, 50}).ok());
  auto images = (*remote)->generate(requests);
  ASSERT_TRUE(images.ok()) << images.status();
  expect_in_order(*images, requests);
  // Had the call waited for the gated worker, the gate would have given up (unreleased) and that worker shared it.
  EXPECT_EQ((*remote)->counters().at("workers"), 1.0);
  EXPECT_EQ(first.poses, 5);
  EXPECT_EQ(slow.poses, 0);
  EXPECT_EQ((*remote)->stage_seconds().count("adaptation_wait"), 1u);
  slow.release();
  bool shared = false;
  for (int i = 0; i < 100 && !shared; ++i) {
    images = (*remote)->generate(requests);
    ASSERT_TRUE(images.ok()) << images.status();
    expect_in_order(*images, requests);
    shared = (*remote)->counters().at("workers") == 2.0;
    if (!shared) std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  EXPECT_TRUE(shared) << "the worker whose adaptation ended was not called again";
  EXPECT_TRUE(slow.released_in_time);
  EXPECT_EQ(slow.adaptations, 1) << "adapted once, in the background";
  EXPECT_GT(slow.poses, 0);
}

// Refuses every adaptation as a request error (the views, the settings), not as a failing worker.
class RefusingAdaptGenerator : public EchoGenerator {
 public:
  absl::Status adapt(const std::vector<ReferenceView>&, const std::optional<SceneAdaptation>&) override {
    return absl::InvalidArgumentError("these views cannot be adapted to (test)");
  }
};

// The background adaptation does not turn a refused request into an unreachable worker: generate() reports the
// worker's own error, as when it adapted the worker itself.
TEST(WorkerPool, AnAdaptationRefusedInTheBackgroundIsReportedByGenerate) {
  WorkerServiceOptions options;
  options.backend = "refusing";
  RunningWorker worker(std::make_unique<RefusingAdaptGenerator>(), options);
  WorkerPoolOptions o;
  o.addresses = {worker.address()};
  o.encoding = rpc::TensorEncoding::kFloat32;
  o.max_rounds = 1;  // one pass: a worker wrongly set aside as failed would leave only UNAVAILABLE
  auto remote = RemoteGenerator::create(o);
  ASSERT_TRUE(remote.ok()) << remote.status();
  const auto requests = many_requests(2);
  ASSERT_TRUE((*remote)->adapt(requests[0].references, std::nullopt).ok());
  const auto images = (*remote)->generate(requests);
  ASSERT_FALSE(images.ok());
  EXPECT_TRUE(absl::IsInvalidArgument(images.status())) << images.status();
  EXPECT_TRUE(absl::StrContains(images.status().message(), "cannot be adapted to (test)")) << images.status();
}

// Learns a number per adaptation (1, 2, ...), exports it as its adaptation and adds what it learnt or installed
// to every echoed render: an image says which adaptation made it. Its weights are `weights`.
class LearningGenerator : public EchoGenerator {
 public:
  explicit LearningGenerator(std::string weights = "w") : weights_(std::move(weights)) {}
  std::string name() const override { return "learning (test)"; }
  std::string weights_identity() const override { return weights_; }
  absl::Status adapt(const std::vector<ReferenceView>& views, const std::optional<SceneAdaptation>& a) override {
    learnt_ = ++trained;
    return EchoGenerator::adapt(views, a);
  }
  absl::StatusOr<std::string> export_adaptation() const override { return absl::StrCat("learnt ", learnt_); }
  absl::Status install_adaptation(const std::vector<ReferenceView>&, const std::optional<SceneAdaptation>&,
                                  std::string exported) override {
    if (refuse_installs) return absl::InvalidArgumentError("cannot install (test)");
    if (!absl::SimpleAtoi(exported.substr(exported.find(' ') + 1), &learnt_))
      return absl::InvalidArgumentError("not an export of this backend (test)");
    ++installed;
    return absl::OkStatus();
  }
  absl::StatusOr<std::vector<at::Tensor>> generate(const std::vector<GenerationRequest>& requests) override {
    GAPS_ASSIGN_OR_RETURN(std::vector<at::Tensor> out, EchoGenerator::generate(requests));
    for (at::Tensor& image : out) image = image + learnt_;
    return out;
  }
  std::atomic<int> trained{0}, installed{0};
  std::atomic<bool> refuse_installs{false};

 private:
  std::string weights_;
  int learnt_ = 0;
};

// Two workers on a phase (fan_out): what the first learnt from the scene, the second installs, and every
// image comes from that one adaptation.
std::unique_ptr<RemoteGenerator> two_worker_pool(const RunningWorker& a, const RunningWorker& b, bool share) {
  WorkerPoolOptions o;
  o.addresses = {a.address(), b.address()};
  o.encoding = rpc::TensorEncoding::kFloat32;
  o.share_adaptation = share;
  o.adaptation_grace = std::chrono::seconds(20);  // both join the first call
  auto remote = RemoteGenerator::create(o);
  EXPECT_TRUE(remote.ok()) << remote.status();
  return remote.ok() ? *std::move(remote) : nullptr;
}

TEST(WorkerPool, TheFirstWorkerAdaptsAndTheOthersInstallWhatItLearnt) {
  WorkerServiceOptions options;
  options.backend = "learning";
  auto a = std::make_unique<LearningGenerator>(), b = std::make_unique<LearningGenerator>();
  LearningGenerator &first = *a, &second = *b;
  RunningWorker wa(std::move(a), options), wb(std::move(b), options);
  const auto requests = many_requests(6);
  auto remote = two_worker_pool(wa, wb, true);
  ASSERT_NE(remote, nullptr);
  ASSERT_TRUE(remote->adapt(requests[0].references, SceneAdaptation{4, 50}).ok());
  const auto images = remote->generate(requests);
  ASSERT_TRUE(images.ok()) << images.status();
  EXPECT_EQ(remote->counters().at("workers"), 2.0);
  EXPECT_EQ(first.trained, 1);
  EXPECT_EQ(second.trained, 0);
  EXPECT_EQ(second.installed, 1);
  for (size_t k = 0; k < images->size(); ++k)
    EXPECT_TRUE(at::equal((*images)[k], requests[k].render_rgb + 1)) << "pose " << k << ": not adaptation 1's";
  EXPECT_EQ(remote->counters().at("adaptations_made"), 1.0);
  EXPECT_EQ(remote->counters().at("adaptations_installed"), 1.0);
  EXPECT_EQ(remote->counters().at("adaptation_export_bytes"), 8.0);  // "learnt 1"
  EXPECT_EQ(remote->stage_seconds().count("adaptation_export"), 1u);

  // New views: adapted anew, shared anew (adaptation 2 of the first worker).
  ASSERT_TRUE(remote->adapt(requests[1].references, SceneAdaptation{4, 50}).ok());
  ASSERT_TRUE(remote->generate(requests).ok());
  EXPECT_EQ(first.trained, 2);
  EXPECT_EQ(second.trained, 0);
  EXPECT_EQ(second.installed, 2);

  // Without sharing every worker adapts itself.
  auto own = two_worker_pool(wa, wb, false);
  ASSERT_NE(own, nullptr);
  ASSERT_TRUE(own->adapt(requests[0].references, SceneAdaptation{4, 50}).ok());
  ASSERT_TRUE(own->generate(requests).ok());
  EXPECT_EQ(first.trained, 3);
  EXPECT_EQ(second.trained, 1);
  EXPECT_EQ(own->counters().at("adaptations_made"), 2.0);
  EXPECT_EQ(own->counters().count("adaptations_installed"), 0u);
}

// A worker with other weights never installs another's adaptation; one that cannot install it adapts itself
// (a note says so); a backend that learns nothing to hand over (its export empty) has every worker adapt.
TEST(WorkerPool, AWorkerThatCannotUseTheSharedAdaptationAdaptsItself) {
  WorkerServiceOptions options;
  options.backend = "learning";
  auto a = std::make_unique<LearningGenerator>("w"), b = std::make_unique<LearningGenerator>("other weights");
  auto c = std::make_unique<LearningGenerator>("w");
  LearningGenerator &other = *b, &refusing = *c;
  refusing.refuse_installs = true;
  RunningWorker wa(std::move(a), options), wb(std::move(b), options), wc(std::move(c), options);
  const auto requests = many_requests(6);
  for (const RunningWorker* follower : {&wb, &wc}) {
    auto remote = two_worker_pool(wa, *follower, true);
    ASSERT_NE(remote, nullptr);
    ASSERT_TRUE(remote->adapt(requests[0].references, SceneAdaptation{4, 50}).ok());
    ASSERT_TRUE(remote->generate(requests).ok());
    EXPECT_EQ(remote->counters().at("adaptations_made"), 2.0);
    EXPECT_EQ(remote->counters().count("adaptations_installed"), 0u);
    const std::vector<std::string> notes = remote->notes();
    const bool noted = std::any_of(notes.begin(), notes.end(), [](const std::string& n) {
      return absl::StrContains(n, "could not install the shared adaptation") &&
             absl::StrContains(n, "cannot install (test)");
    });
    EXPECT_EQ(noted, follower == &wc) << absl::StrJoin(notes, "\n");
  }
  EXPECT_EQ(other.trained, 1);
  EXPECT_EQ(other.installed, 0);
  EXPECT_EQ(refusing.trained, 1);

  options.backend = "echo";
  auto d = std::make_unique<EchoGenerator>(), e = std::make_unique<EchoGenerator>();
  const EchoGenerator &echo_first = *d, &echo_second = *e;
  RunningWorker wd(std::move(d), options), we(std::move(e), options);
  auto remote = two_worker_pool(wd, we, true);
  ASSERT_NE(remote, nullptr);
  ASSERT_TRUE(remote->adapt(requests[0].references, std::nullopt).ok());
  ASSERT_TRUE(remote->generate(requests).ok());
  EXPECT_EQ(echo_first.adaptations + echo_second.adaptations, 2);
  EXPECT_EQ(remote->counters().count("adaptations_installed"), 0u);
}

// A first worker whose adaptation hangs holds the others only for share_wait: they then adapt themselves and
// answer the phase while it sits out.
TEST(WorkerPool, TheOthersAdaptThemselvesWhenTheFirstWorkersAdaptationTakesTooLong) {
  WorkerServiceOptions options;
  options.backend = "learning";
  auto gated = std::make_unique<GatedAdaptGenerator>();
  auto other = std::make_unique<LearningGenerator>();
  GatedAdaptGenerator& first = *gated;
  const LearningGenerator& second = *other;
  RunningWorker wa(std::move(gated), options), wb(std::move(other), options);
  WorkerPoolOptions o;
  o.addresses = {wa.address(), wb.address()};
  o.encoding = rpc::TensorEncoding::kFloat32;
  o.share_wait = std::chrono::milliseconds(200);
  o.adaptation_grace = std::chrono::milliseconds(100);
  auto remote = RemoteGenerator::create(o);
  ASSERT_TRUE(remote.ok()) << remote.status();
  const auto requests = many_requests(4);
  ASSERT_TRUE((*remote)->adapt(requests[0].references, SceneAdaptation{4, 50}).ok());
  const auto images = (*remote)->generate(requests);
  ASSERT_TRUE(images.ok()) << images.status();
  EXPECT_EQ((*remote)->counters().at("workers"), 1.0);
  EXPECT_EQ(second.trained, 1);
  EXPECT_EQ(second.installed, 0);
  EXPECT_EQ(first.poses, 0);
  first.release();
}

// How many scenes a worker keeps (GetInfo).
int scenes_kept(const RunningWorker& worker) {
  auto stub = v1::DiffusionWorker::NewStub(grpc::CreateChannel(worker.address(), grpc::InsecureChannelCredentials()));
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  v1::WorkerInfo info;
  EXPECT_TRUE(stub->GetInfo(&context, v1::GetInfoRequest(), &info).ok());
  return info.scenes_kept();
}

// A job's pool releases its scene on each worker when the job ends, and an earlier scene when it adapts anew; a
// worker keeps at most max_scenes (the least recently used forgotten) and a job whose scene it forgot is adapted
// again, without an error.
TEST(WorkerPool, ScenesAreReleasedWhenJobsEndAndForgottenBeyondTheWorkersRoom) {
  WorkerServiceOptions options;
  options.backend = "learning";
  options.max_scenes = 2;
  auto g = std::make_unique<LearningGenerator>();
  const LearningGenerator& backend = *g;
  RunningWorker worker(std::move(g), options);
  const auto requests = many_requests(2);
  {
    auto job = pool({worker.address()});
    ASSERT_TRUE(job.ok());
    ASSERT_TRUE((*job)->adapt(requests[0].references, std::nullopt).ok());
    ASSERT_TRUE((*job)->generate(requests).ok());
    ASSERT_TRUE((*job)->adapt(requests[1].references, std::nullopt).ok());
    ASSERT_TRUE((*job)->generate(requests).ok());
    EXPECT_EQ(scenes_kept(worker), 1) << "the first views' scene released once the second was adapted";
  }
  EXPECT_EQ(scenes_kept(worker), 0) << "released when the job ended";

  std::vector<std::unique_ptr<RemoteGenerator>> jobs;
  for (int k = 0; k < 3; ++k) {
    auto job = pool({worker.address()});
    ASSERT_TRUE(job.ok());
    jobs.push_back(*std::move(job));
    ASSERT_TRUE(jobs.back()->adapt(requests[0].references, std::nullopt).ok());
    ASSERT_TRUE(jobs.back()->generate(requests).ok());
  }
  EXPECT_EQ(scenes_kept(worker), 2);
  const int trained = backend.trained;
  EXPECT_TRUE(jobs[0]->generate(requests).ok()) << "the forgotten scene is adapted again";
  EXPECT_EQ(backend.trained, trained + 1);
  EXPECT_EQ(scenes_kept(worker), 2);
}

// Two jobs' pools on one LearningGenerator worker, job a adapted and served first (it learns 1), then job b (2).
struct TwoJobsOnOneWorker {
  explicit TwoJobsOnOneWorker(bool keep_scene_adaptations) {
    WorkerServiceOptions options;
    options.backend = "learning";
    options.keep_scene_adaptations = keep_scene_adaptations;
    auto g = std::make_unique<LearningGenerator>();
    backend = g.get();
    worker = std::make_unique<RunningWorker>(std::move(g), options);
    // In float32: the images' values (render + adaptation) lie beyond a byte's [0, 1].
    const Transfer exact{rpc::TensorEncoding::kFloat32, true};
    auto job_a = pool({worker->address()}, "", exact), job_b = pool({worker->address()}, "", exact);
    EXPECT_TRUE(job_a.ok() && job_b.ok());
    if (!job_a.ok() || !job_b.ok()) return;
    a = *std::move(job_a);
    b = *std::move(job_b);
    EXPECT_TRUE(a->adapt(requests[0].references, std::nullopt).ok());
    EXPECT_TRUE(a->generate(requests).ok());
    EXPECT_TRUE(b->adapt(requests[1].references, std::nullopt).ok());
    EXPECT_TRUE(b->generate(requests).ok());
  }
  // What `job` adds to a render now (its first image less its render), or NaN when the call failed.
  double added_by(RemoteGenerator& job) {
    auto images = job.generate(requests);
    EXPECT_TRUE(images.ok()) << images.status();
    return images.ok() ? ((*images)[0] - requests[0].render_rgb).max().item<double>() : std::nan("");
  }
  const std::vector<GenerationRequest> requests = many_requests(2);
  LearningGenerator* backend = nullptr;
  std::unique_ptr<RunningWorker> worker;
  std::unique_ptr<RemoteGenerator> a, b;
};

// On one worker, scenes that alternate (two jobs sharing it) are adapted once each: coming back to a scene
// installs what its adaptation learnt instead of learning it again.
TEST(WorkerPool, AWorkerComingBackToAnAdaptedSceneInstallsItsAdaptation) {
  TwoJobsOnOneWorker jobs(true);
  ASSERT_TRUE(jobs.a && jobs.b);
  for (int round = 0; round < 2; ++round) {
    EXPECT_EQ(jobs.added_by(*jobs.a), 1.0) << "round " << round << ": job a's adaptation";
    EXPECT_EQ(jobs.added_by(*jobs.b), 2.0) << "round " << round << ": job b's adaptation";
  }
  EXPECT_EQ(jobs.backend->trained, 2) << "each scene learnt once";
  EXPECT_EQ(jobs.backend->installed, 4) << "a and b again in each of the two rounds";
  // The switch back is reported with the call it preceded.
  EXPECT_EQ(jobs.b->counters().at("scene_switch_installs"), 1.0);
  EXPECT_EQ(jobs.b->stage_seconds().count("scene_switch"), 1u);
}

// With --nokeep_scene_adaptations a scene that comes back is adapted anew, as each phase once retrained the LoRA.
TEST(WorkerPool, AWorkerThatKeepsNoAdaptationLearnsAComingBackSceneAgain) {
  TwoJobsOnOneWorker jobs(false);
  ASSERT_TRUE(jobs.a && jobs.b);
  EXPECT_EQ(jobs.added_by(*jobs.a), 3.0) << "job a's scene learnt a third time";
  EXPECT_EQ(jobs.backend->trained, 3);
  EXPECT_EQ(jobs.backend->installed, 0);
  EXPECT_EQ(jobs.a->counters().at("scene_switch_adaptations"), 1.0);
}

// The SQLite backend's own failure modes (the contract of both backends: job_store_test.cpp).
using JobStoreTest = test::TempDirTest;

constexpr char kRefusal[] = "database or disk is full (test)";

// A second connection to a job database that makes it refuse writes as a full disk would: each refusal is
// a trigger that aborts the matching statements with kRefusal until it is lifted.
class StoreSabotage {
 public:
  explicit StoreSabotage(const std::filesystem::path& file) {
    EXPECT_EQ(sqlite3_open(file.c_str(), &db_), SQLITE_OK);
    sqlite3_busy_timeout(db_, 5000);
  }
  ~StoreSabotage() { sqlite3_close(db_); }
  // `on` is the trigger's event and condition, e.g. "UPDATE ON jobs WHEN NEW.state = 3".
  void refuse(const std::string& name, const std::string& on) {
    exec("CREATE TRIGGER " + name + " BEFORE " + on + " BEGIN SELECT RAISE(ABORT, '" + kRefusal + "'); END");
  }
  void lift(const std::string& name) { exec("DROP TRIGGER " + name); }
  void exec(const std::string& sql) {
    char* error = nullptr;
    EXPECT_EQ(sqlite3_exec(db_, sql.c_str(), nullptr, nullptr, &error), SQLITE_OK)
        << sql << ": " << (error ? error : "");
    sqlite3_free(error);
  }

 private:
  sqlite3* db_ = nullptr;
};

TEST_F(JobStoreTest, AJobEndIsRecordedWholeOrNotAtAll) {
  auto store = JobStore::open(dir_ / "jobs.db");
  ASSERT_TRUE(store.ok()) << store.status();
  v1::JobStatus status;
  status.set_job_id("job-1");
  status.set_state(v1::RUNNING);
  ASSERT_TRUE((*store)->insert(status, v1::JobSpec()).ok());
  status.set_state(v1::SUCCEEDED);
  v1::JobEvent closing;
  closing.set_job_id("job-1");
  *closing.mutable_finished() = status;
  StoreSabotage sabotage(dir_ / "jobs.db");
  sabotage.refuse("no_events", "INSERT ON events");
  const absl::Status refused = (*store)->end_job(status, {{"point_cloud.ply", 2000}}, closing);
  EXPECT_EQ(refused.code(), absl::StatusCode::kInternal) << refused;
  EXPECT_TRUE(absl::StrContains(refused.message(), kRefusal)) << refused;
  EXPECT_EQ((*store)->get("job-1")->state(), v1::RUNNING);
  EXPECT_TRUE((*store)->artifacts("job-1")->empty());
  sabotage.lift("no_events");
  ASSERT_TRUE((*store)->end_job(status, {{"point_cloud.ply", 2000}}, closing).ok());
  EXPECT_EQ((*store)->get("job-1")->state(), v1::SUCCEEDED);
  EXPECT_EQ((*store)->artifacts("job-1")->size(), 1u);
  auto events = (*store)->events("job-1", 0);
  ASSERT_TRUE(events.ok()) << events.status();
  ASSERT_EQ(events->size(), 1u);
  EXPECT_TRUE((*events)[0].has_finished());
}

// One corrupt status row: the others still list; it lists as FAILED naming itself and the store's file.
TEST_F(JobStoreTest, ACorruptStatusRowHidesNoOtherJob) {
  auto store = JobStore::open(dir_ / "jobs.db");
  ASSERT_TRUE(store.ok()) << store.status();
  for (const char* id : {"job-a", "job-b", "job-c"}) {
    v1::JobStatus status;
    status.set_job_id(id);
    status.set_state(v1::SUCCEEDED);
    ASSERT_TRUE((*store)->insert(status, v1::JobSpec()).ok());
  }
  StoreSabotage(dir_ / "jobs.db").exec("UPDATE jobs SET status = x'ffffffff0a' WHERE id = 'job-b'");
  const auto listed = (*store)->list();
  ASSERT_TRUE(listed.ok()) << listed.status();
  ASSERT_EQ(listed->size(), 3u);
  EXPECT_EQ((*listed)[0].state(), v1::SUCCEEDED);
  EXPECT_EQ((*listed)[2].state(), v1::SUCCEEDED);
  const v1::JobStatus& broken = (*listed)[1];
  EXPECT_EQ(broken.job_id(), "job-b");
  EXPECT_EQ(broken.state(), v1::FAILED);
  EXPECT_TRUE(absl::StrContains(broken.error(), "corrupt status record of job job-b")) << broken.error();
  EXPECT_TRUE(absl::StrContains(broken.error(), (dir_ / "jobs.db").string())) << broken.error();
  const auto got = (*store)->get("job-b");
  EXPECT_EQ(got.status().code(), absl::StatusCode::kDataLoss);
  EXPECT_TRUE(absl::StrContains(got.status().message(), (dir_ / "jobs.db").string())) << got.status();
}

TEST_F(JobStoreTest, ADatabaseLockedByAnotherProcessIsUnavailable) {
  auto store = JobStore::open(dir_ / "jobs.db");
  ASSERT_TRUE(store.ok()) << store.status();
  v1::JobStatus status;
  status.set_job_id("job-1");
  status.set_state(v1::QUEUED);
  ASSERT_TRUE((*store)->insert(status, v1::JobSpec()).ok());
  StoreSabotage other(dir_ / "jobs.db");
  other.exec("BEGIN EXCLUSIVE");
  status.set_state(v1::RUNNING);
  const absl::Status locked = (*store)->update(status);  // after the store's busy timeout
  EXPECT_EQ(locked.code(), absl::StatusCode::kUnavailable) << locked;
  v1::JobEvent event;
  event.set_job_id("job-1");
  EXPECT_EQ((*store)->append_event(event).status().code(), absl::StatusCode::kUnavailable);
  other.exec("COMMIT");
  EXPECT_TRUE((*store)->update(status).ok());
  EXPECT_TRUE((*store)->append_event(event).ok());
}

TEST_F(JobStoreTest, AReadOnlyDatabaseIsRefusedAtOpening) {
  ASSERT_TRUE(JobStore::open(dir_ / "jobs.db").ok());
  ASSERT_EQ(chmod((dir_ / "jobs.db").c_str(), 0444), 0);
  if (access((dir_ / "jobs.db").c_str(), W_OK) == 0) GTEST_SKIP() << "file permissions do not bind this user";
  const auto store = JobStore::open(dir_ / "jobs.db");
  EXPECT_FALSE(store.ok());
  EXPECT_TRUE(absl::StrContains(store.status().message(), (dir_ / "jobs.db").string())) << store.status();
}

// A trainer service in this process, its client and a small scene to submit.
struct TrainerInProcess : test::TempDirTest {
  // Starts the service with `options` (its data folder set here).
  void start(TrainerServiceOptions options) {
    options.data_dir = dir_ / "data";
    auto made = TrainerService::create(options);
    ASSERT_TRUE(made.ok()) << made.status();
    service = std::move(*made);
    ASSERT_TRUE(service->start().ok());
    grpc::ServerBuilder builder;
    builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
    builder.RegisterService(service.get());
    server = builder.BuildAndStart();
    ASSERT_GT(port, 0);
    auto connected = client::TrainerClient::connect("127.0.0.1:" + std::to_string(port), {});
    ASSERT_TRUE(connected.ok()) << connected.status();
    trainer = std::make_unique<client::TrainerClient>(std::move(*connected));
    auto prepared = test::prepared_synthetic_scene(dir_ / "source", 32, 24);
    ASSERT_TRUE(prepared.ok()) << prepared.status();
    scene = *prepared;
  }
  void TearDown() override {
    if (service) service->shutdown();
    if (server) server->Shutdown(std::chrono::system_clock::now());
    test::TempDirTest::TearDown();
  }

  static v1::JobSpec spec(int iterations) {
    v1::JobSpec s;
    s.set_name("store errors");
    s.mutable_config()->set_views(3);
    s.mutable_config()->set_init("random");
    s.mutable_config()->set_random_points(300);
    s.mutable_config()->set_variant("vanilla");
    s.mutable_config()->mutable_training()->set_iterations(iterations);
    return s;
  }

  // Polls GetJob until `done` holds or a minute passed; returns the last answer.
  absl::StatusOr<v1::JobStatus> get_until(const std::string& job_id,
                                          const std::function<bool(const v1::JobStatus&)>& done) {
    absl::StatusOr<v1::JobStatus> job = trainer->get(job_id);
    for (int i = 0; i < 600 && job.ok() && !done(*job); ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      job = trainer->get(job_id);
    }
    return job;
  }

  std::unique_ptr<TrainerService> service;
  std::unique_ptr<grpc::Server> server;
  int port = 0;
  std::unique_ptr<client::TrainerClient> trainer;
  client::PreparedScene scene;
};

// ... and a saboteur of its job store.
struct TrainerStoreErrors : TrainerInProcess {
  void SetUp() override {
    TrainerInProcess::SetUp();
    TrainerServiceOptions options;
    options.store_retry_interval = std::chrono::milliseconds(100);
    ASSERT_NO_FATAL_FAILURE(start(options));
    sabotage = std::make_unique<StoreSabotage>(dir_ / "data" / "jobs.db");
  }
  std::unique_ptr<StoreSabotage> sabotage;
};

TEST_F(TrainerStoreErrors, ARefusedSubmissionFailsAndLeavesNoJobFolder) {
  sabotage->refuse("no_jobs", "INSERT ON jobs");
  const auto job = trainer->submit(spec(20), scene);
  ASSERT_FALSE(job.ok());
  EXPECT_EQ(job.status().code(), absl::StatusCode::kInternal) << job.status();
  EXPECT_TRUE(absl::StrContains(job.status().message(), kRefusal)) << job.status();
  EXPECT_TRUE(std::filesystem::is_empty(dir_ / "data" / "jobs"));
  const auto listed = trainer->list();
  ASSERT_TRUE(listed.ok()) << listed.status();
  EXPECT_TRUE(listed->empty());
}

TEST_F(TrainerStoreErrors, StoreRefusalsWhileAJobRunsAreLoggedAndItsEndIsRecordedOnceTheStoreRecovers) {
  // Nothing after the submission is recorded: neither the running state, nor progress, nor any event.
  sabotage->refuse("no_running", "UPDATE ON jobs WHEN NEW.state = 2");
  sabotage->refuse("no_events", "INSERT ON events WHEN NEW.seq > 0");
  testing::internal::CaptureStderr();
  const auto job = trainer->submit(spec(20), scene);
  ASSERT_TRUE(job.ok()) << job.status();
  const auto unrecorded = get_until(*job, [](const v1::JobStatus& s) { return !s.error().empty(); });
  const std::string log = testing::internal::GetCapturedStderr();
  ASSERT_TRUE(unrecorded.ok()) << unrecorded.status();
  // The state the store holds, with the reason it is stale; never the end the store did not take.
  EXPECT_EQ(unrecorded->state(), v1::QUEUED);
  EXPECT_TRUE(absl::StrContains(unrecorded->error(), "SUCCEEDED")) << unrecorded->error();
  EXPECT_TRUE(absl::StrContains(unrecorded->error(), kRefusal)) << unrecorded->error();
  const auto listed = trainer->list();
  ASSERT_TRUE(listed.ok()) << listed.status();
  ASSERT_EQ(listed->size(), 1u);
  EXPECT_EQ((*listed)[0].error(), unrecorded->error());
  int events = 0;
  const auto watched = trainer->watch(*job, [&](const v1::JobEvent&) { ++events; });
  EXPECT_EQ(watched.status().code(), absl::StatusCode::kInternal) << watched.status();
  EXPECT_TRUE(absl::StrContains(watched.status().message(), kRefusal)) << watched.status();
  EXPECT_EQ(events, 1);  // QUEUED
  for (const std::string& what :
       {"that it started", "its progress at iteration 10", "its progress event", "its end (SUCCEEDED)"})
    EXPECT_TRUE(absl::StrContains(log, "job " + *job + ": the job store did not record " + what)) << what << "\n"
                                                                                                  << log;
  EXPECT_TRUE(absl::StrContains(log, kRefusal)) << log;

  sabotage->lift("no_running");
  sabotage->lift("no_events");
  const auto recorded = get_until(*job, [](const v1::JobStatus& s) { return s.state() == v1::SUCCEEDED; });
  ASSERT_TRUE(recorded.ok()) << recorded.status();
  EXPECT_EQ(recorded->state(), v1::SUCCEEDED);
  EXPECT_TRUE(recorded->error().empty()) << recorded->error();
  const auto finished = trainer->watch(*job, [](const v1::JobEvent&) {});
  ASSERT_TRUE(finished.ok()) << finished.status();
  EXPECT_EQ(finished->state(), v1::SUCCEEDED);
  const auto files = trainer->fetch(*job, dir_ / "fetched");
  ASSERT_TRUE(files.ok()) << files.status();
  EXPECT_TRUE(std::filesystem::exists(dir_ / "fetched" / "point_cloud.ply"));
}

TEST_F(TrainerStoreErrors, ARefusedCancellationKeepsTheJobQueued) {
  const auto running = trainer->submit(spec(1000000), scene);  // occupies the only job thread
  const auto queued = trainer->submit(spec(20), scene);
  ASSERT_TRUE(running.ok() && queued.ok());
  sabotage->refuse("no_cancel", "UPDATE ON jobs WHEN NEW.state = 5");
  const auto refused = trainer->cancel(*queued);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInternal) << refused.status();
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "stays queued")) << refused.status();
  const auto still_queued = trainer->get(*queued);
  ASSERT_TRUE(still_queued.ok()) << still_queued.status();
  EXPECT_EQ(still_queued->state(), v1::QUEUED);
  sabotage->lift("no_cancel");
  const auto cancelled = trainer->cancel(*queued);
  ASSERT_TRUE(cancelled.ok()) << cancelled.status();
  EXPECT_EQ(cancelled->state(), v1::CANCELLED);
  const auto watched = trainer->watch(*queued, [](const v1::JobEvent&) {});
  ASSERT_TRUE(watched.ok()) << watched.status();
  EXPECT_EQ(watched->state(), v1::CANCELLED);
}

// The CPU threads each concurrent job's parallel regions get, as its log reports them (read in the job's thread).
std::vector<std::string> thread_counts_of_jobs(TrainerInProcess& t, int jobs) {
  std::vector<std::string> ids;
  for (int i = 0; i < jobs; ++i) {
    const auto job = t.trainer->submit(TrainerInProcess::spec(20), t.scene);
    EXPECT_TRUE(job.ok()) << job.status();
    if (job.ok()) ids.push_back(*job);
  }
  std::vector<std::string> counts;
  const std::regex line("trains with ([0-9]+) CPU thread");
  for (const std::string& id : ids) {
    std::string count = "none";
    const auto end = t.trainer->watch(id, [&](const v1::JobEvent& e) {
      std::smatch m;
      if (e.has_log() && std::regex_search(e.log(), m, line)) count = m[1];
    });
    EXPECT_TRUE(end.ok()) << end.status();
    if (end.ok()) EXPECT_EQ(end->state(), v1::SUCCEEDED) << end->error();
    counts.push_back(count);
  }
  return counts;
}

// Jobs trained at once share the process's CPU threads out instead of each taking all of them (which
// oversubscribed a busy trainer's cores); an explicit count holds whatever the concurrency.
TEST_F(TrainerInProcess, EachJobTrainsWithItsShareOfTheCpuThreads) {
  const int process_threads = at::get_num_threads();
  TrainerServiceOptions options;
  options.concurrency = 2;
  ASSERT_NO_FATAL_FAILURE(start(options));
  const std::string share = std::to_string(std::max(1, process_threads / 2));
  EXPECT_EQ(thread_counts_of_jobs(*this, 2), std::vector<std::string>({share, share}));
}

TEST_F(TrainerInProcess, AnExplicitThreadCountHoldsForEveryJob) {
  TrainerServiceOptions options;
  options.threads_per_job = 3;
  ASSERT_NO_FATAL_FAILURE(start(options));
  EXPECT_EQ(thread_counts_of_jobs(*this, 1), std::vector<std::string>({"3"}));
  options.threads_per_job = -1;
  options.data_dir = dir_ / "other";
  const auto refused = TrainerService::create(options);
  ASSERT_FALSE(refused.ok());
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "threads_per_job")) << refused.status();
}

// A vanilla trainer with no worker.
struct TrainerAlone : TrainerInProcess {
  void SetUp() override {
    TrainerInProcess::SetUp();
    ASSERT_NO_FATAL_FAILURE(start(TrainerServiceOptions{}));
  }
};

// Each WatchJob stream holds a thread of the trainer for as long as its job runs: past kMaxWatchStreams the
// next one is refused at once with RESOURCE_EXHAUSTED and a retry hint, and a slot given back serves again.
TEST_F(TrainerAlone, WatchStreamsBeyondTheLimitAreRefusedWithARetryHint) {
  const auto job = trainer->submit(spec(1000000), scene);
  ASSERT_TRUE(job.ok()) << job.status();
  auto stub = v1::Trainer::NewStub(
      grpc::CreateChannel("127.0.0.1:" + std::to_string(port), grpc::InsecureChannelCredentials()));
  std::vector<std::unique_ptr<grpc::ClientContext>> contexts;
  std::vector<std::unique_ptr<grpc::ClientReader<v1::JobEvent>>> streams;
  v1::WatchJobRequest request;
  request.set_job_id(*job);
  for (int i = 0; i < kMaxWatchStreams; ++i) {
    contexts.push_back(std::make_unique<grpc::ClientContext>());
    streams.push_back(stub->WatchJob(contexts.back().get(), request));
    v1::JobEvent first;
    ASSERT_TRUE(streams.back()->Read(&first)) << "stream " << i << " was refused";  // it holds its slot now
  }
  const auto refused = trainer->watch(*job, [](const v1::JobEvent&) {});
  ASSERT_FALSE(refused.ok());
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted) << refused.status();
  EXPECT_TRUE(absl::StrContains(refused.status().message(), "retry")) << refused.status();
  contexts[0]->TryCancel();
  (void)streams[0]->Finish();
  ASSERT_TRUE(trainer->cancel(*job).ok());
  // The handler notices the cancelled stream at its next look at the store, then gives its slot back.
  auto served = trainer->watch(*job, [](const v1::JobEvent&) {});
  for (int i = 0; i < 100 && absl::IsResourceExhausted(served.status()); ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    served = trainer->watch(*job, [](const v1::JobEvent&) {});
  }
  EXPECT_TRUE(served.ok()) << served.status();
  for (size_t i = 1; i < streams.size(); ++i) {
    contexts[i]->TryCancel();
    (void)streams[i]->Finish();
  }
}

// ... with a reproject worker in this process (it has neither LoRA nor an IP-Adapter).
struct TrainerWithWorker : TrainerInProcess {
  void SetUp() override {
    TrainerInProcess::SetUp();
    auto backend = make_generator("reproject", "");
    ASSERT_TRUE(backend.ok()) << backend.status();
    WorkerServiceOptions w;
    w.backend = "reproject";
    worker = std::make_unique<RunningWorker>(std::move(*backend), w);
    ASSERT_GT(worker->port, 0);
    TrainerServiceOptions options;
    options.workers.addresses = {worker->address()};
    ASSERT_NO_FATAL_FAILURE(start(options));
  }
  void TearDown() override {
    TrainerInProcess::TearDown();  // the jobs first: they call the worker
    worker.reset();
  }
  std::unique_ptr<RunningWorker> worker;
};

// The job's generation controls reach the worker; what its backend cannot honour comes back as notes, which
// land in the phase's entry (PhaseEvent.details_json, phases.json) and, once each, in the job's log.
TEST_F(TrainerWithWorker, BackendNotesReachThePhaseEntryAndTheJobLog) {
  v1::JobSpec s = spec(40);
  s.mutable_config()->set_variant("full");
  ASSERT_TRUE(rpc::set_fields({{"warmup_iterations", 20},
                               {"phase_interval", 10},
                               {"n_active", 2},
                               {"lora_steps", 30},
                               {"ip_adapter_scale", 0.4}},
                              s.mutable_config()->mutable_gaps())
                  .ok());
  const auto job = trainer->submit(s, scene);
  ASSERT_TRUE(job.ok()) << job.status();
  std::vector<nlohmann::json> phases;
  std::vector<std::string> note_lines;
  const auto final_status = trainer->watch(*job, [&](const v1::JobEvent& e) {
    if (e.has_phase_finished()) phases.push_back(nlohmann::json::parse(e.phase_finished().details_json()));
    if (e.has_log() && absl::StrContains(e.log(), "generator note")) note_lines.push_back(e.log());
  });
  ASSERT_TRUE(final_status.ok()) << final_status.status();
  ASSERT_EQ(final_status->state(), v1::SUCCEEDED) << final_status->error();
  ASSERT_EQ(phases.size(), 2u);  // iterations 20 and 30
  const auto notes = [](const nlohmann::json& phase) {
    return phase.value("generator_notes", nlohmann::json::array()).dump();
  };
  // Phase 0 adapted the worker (LoRA asked, none run) and generated (an image prompt asked, none given).
  for (const std::string part : {worker->address() + ": reproject has no model to adapt: the 30 LoRA steps",
                                 std::string("asked for ip_adapter_scale 0.4")})
    EXPECT_TRUE(absl::StrContains(notes(phases[0]), part)) << notes(phases[0]);
  EXPECT_FALSE(absl::StrContains(notes(phases[1]), "LoRA")) << notes(phases[1]);
  EXPECT_TRUE(absl::StrContains(notes(phases[1]), "asked for ip_adapter_scale 0.4")) << notes(phases[1]);
  std::set<std::string> distinct;
  for (const auto& phase : phases)
    for (const auto& note : phase["generator_notes"]) distinct.insert(note.get<std::string>());
  EXPECT_EQ(note_lines.size(), distinct.size()) << "one log line per distinct note";
  ASSERT_FALSE(note_lines.empty());
  EXPECT_TRUE(absl::StrContains(note_lines[0], "generator note (phase 0): " + worker->address())) << note_lines[0];
  const auto fetched = trainer->fetch(*job, dir_ / "fetched");
  ASSERT_TRUE(fetched.ok()) << fetched.status();
  std::ifstream phases_file(dir_ / "fetched" / "phases.json");
  EXPECT_EQ(nlohmann::json::parse(phases_file)[0]["generator_notes"], phases[0]["generator_notes"]);
}

// Asynchronous phases through a worker: the remote generation runs beside training and its views are judged a
// fixed number of iterations later, as in process; the hand-over's stages still reach the phase's entry.
TEST_F(TrainerWithWorker, AsynchronousPhasesJoinAFixedNumberOfIterationsLater) {
  v1::JobSpec s = spec(40);
  s.mutable_config()->set_variant("full");
  ASSERT_TRUE(
      rpc::set_fields({{"warmup_iterations", 20}, {"phase_interval", 10}, {"n_active", 2}, {"async_iterations", 4}},
                      s.mutable_config()->mutable_gaps())
          .ok());
  const auto job = trainer->submit(s, scene);
  ASSERT_TRUE(job.ok()) << job.status();
  std::vector<nlohmann::json> phases;
  const auto final_status = trainer->watch(*job, [&](const v1::JobEvent& e) {
    if (e.has_phase_finished()) phases.push_back(nlohmann::json::parse(e.phase_finished().details_json()));
  });
  ASSERT_TRUE(final_status.ok()) << final_status.status();
  ASSERT_EQ(final_status->state(), v1::SUCCEEDED) << final_status->error();
  ASSERT_EQ(phases.size(), 2u);  // after 20 and 30 iterations, each joined 4 iterations after its launch
  for (size_t k = 0; k < phases.size(); ++k) {
    const nlohmann::json& p = phases[k];
    ASSERT_TRUE(p.contains("async")) << p.dump();
    EXPECT_EQ(p["iteration"].get<int>(), 19 + 10 * static_cast<int>(k)) << p.dump();  // counted from 0
    EXPECT_EQ(p["async"]["launched_before"].get<int>(), p["iteration"].get<int>() + 1) << p.dump();
    EXPECT_EQ(p["async"]["joined_before"].get<int>(), p["async"]["launched_before"].get<int>() + 4) << p.dump();
    EXPECT_TRUE(p.contains("generator_stages") && p["generator_stages"].contains("transfer")) << p.dump();
    EXPECT_FALSE(p.value("skipped", false)) << p.dump();
  }
}

// ... with a worker whose backend never answers until released, and an hour's deadline on each call.
struct TrainerWithHungWorker : TrainerInProcess {
  void SetUp() override {
    TrainerInProcess::SetUp();
    auto gated = std::make_unique<GatedGenerator>();
    gate = gated.get();
    WorkerServiceOptions w;
    w.backend = "gated";
    worker = std::make_unique<RunningWorker>(std::move(gated), w);
    TrainerServiceOptions options;
    options.workers.addresses = {worker->address()};
    options.workers.generate_timeout = std::chrono::hours(1);
    ASSERT_NO_FATAL_FAILURE(start(options));
  }
  void TearDown() override {
    gate->release();
    TrainerInProcess::TearDown();
    worker.reset();
  }
  // A full job whose first phase (iteration 20) calls the worker; returns once the call is in its backend.
  std::string submit_and_wait_for_the_call() {
    v1::JobSpec s = spec(1000);
    s.mutable_config()->set_variant("full");
    EXPECT_TRUE(rpc::set_fields({{"warmup_iterations", 20}, {"phase_interval", 100}, {"n_active", 2}},
                                s.mutable_config()->mutable_gaps())
                    .ok());
    const auto job = trainer->submit(s, scene);
    EXPECT_TRUE(job.ok()) << job.status();
    gate->wait_entered(1);
    return job.ok() ? *job : "";
  }
  GatedGenerator* gate = nullptr;
  std::unique_ptr<RunningWorker> worker;
};

// gaps cancel ends a job whose generation call hangs: the call is cancelled rather than waited for (an hour).
TEST_F(TrainerWithHungWorker, CancelEndsAJobWaitingForAWorkerThatNeverAnswers) {
  const std::string job = submit_and_wait_for_the_call();
  ASSERT_FALSE(job.empty());
  ASSERT_TRUE(trainer->cancel(job).ok());
  const auto ended = get_until(job, [](const v1::JobStatus& s) { return s.state() == v1::CANCELLED; });
  ASSERT_TRUE(ended.ok()) << ended.status();
  EXPECT_EQ(ended->state(), v1::CANCELLED) << ended->error();
  EXPECT_EQ(gate->entered, 1) << "the worker was still holding the call: the job did not wait for it";
}

// A shutdown (SIGTERM) does not wait for a worker that never answers either: it returns, and the job is left
// to resume on the next start rather than failed.
TEST_F(TrainerWithHungWorker, ShutdownDoesNotWaitForAWorkerThatNeverAnswers) {
  const std::string job = submit_and_wait_for_the_call();
  ASSERT_FALSE(job.empty());
  service->shutdown();
  EXPECT_EQ(gate->entered, 1);
  {
    std::lock_guard<std::mutex> lock(gate->mutex);
    EXPECT_FALSE(gate->open) << "shutdown returned only because the worker answered";
  }
  service.reset();
  auto store = JobStore::open(dir_ / "data" / "jobs.db");
  ASSERT_TRUE(store.ok()) << store.status();
  const auto status = (*store)->get(job);
  ASSERT_TRUE(status.ok()) << status.status();
  EXPECT_NE(status->state(), v1::FAILED) << status->error();
}

// What a client sends through SubmitJob, before it is cut into messages.
struct UploadParts {
  v1::JobSpec spec;
  std::vector<std::string> images;
  std::vector<std::pair<int, std::string>> larger_images;  // by camera index
  std::string points_ply;
};

std::vector<v1::SubmitJobRequest> submit_messages(const UploadParts& parts, size_t chunk_bytes) {
  std::vector<v1::SubmitJobRequest> messages(1);
  *messages[0].mutable_spec() = parts.spec;
  const auto keep = [&](const v1::SubmitJobRequest& m) {
    messages.push_back(m);
    return true;
  };
  for (size_t i = 0; i < parts.images.size(); ++i)
    rpc::write_file_chunks(v1::FileChunk::IMAGE, static_cast<int>(i), parts.images[i], keep, chunk_bytes);
  for (const auto& [index, image] : parts.larger_images)
    rpc::write_file_chunks(v1::FileChunk::LARGER_IMAGE, index, image, keep, chunk_bytes);
  if (!parts.points_ply.empty()) rpc::write_file_chunks(v1::FileChunk::POINTS, 0, parts.points_ply, keep, chunk_bytes);
  return messages;
}

absl::StatusOr<SceneUpload> receive(const std::vector<v1::SubmitJobRequest>& messages, const fs::path& dir,
                                    uint64_t max_bytes = uint64_t{1} << 30) {
  size_t next = 0;
  return receive_upload(
      [&](v1::SubmitJobRequest* m) {
        if (next == messages.size()) return false;
        *m = messages[next++];
        return true;
      },
      max_bytes, dir);
}

struct UploadTest : test::TempDirTest {
  void SetUp() override {
    test::TempDirTest::SetUp();
    auto scene = test::prepared_synthetic_scene(dir_ / "source", 32, 24);
    ASSERT_TRUE(scene.ok()) << scene.status();
    upload.spec.mutable_config()->set_views(3);
    for (const auto& c : scene->cameras) *upload.spec.add_cameras() = c;
    upload.images = scene->images;
  }
  absl::Status write(const std::string& folder = "scene") {
    GAPS_ASSIGN_OR_RETURN(SceneUpload received, receive(submit_messages(upload, 700), dir_ / folder));
    return write_uploaded_scene(received);
  }
  UploadParts upload;
};

TEST_F(UploadTest, AValidUploadLoadsAsTheSameScene) {
  ASSERT_TRUE(write().ok()) << write();
  auto original = load_scene(dir_ / "source");
  auto uploaded = load_scene(dir_ / "scene");
  ASSERT_TRUE(uploaded.ok()) << uploaded.status();
  ASSERT_EQ(uploaded->cameras.size(), original->cameras.size());
  for (size_t i = 0; i < original->cameras.size(); ++i) {
    const Camera &a = original->cameras[i], &b = uploaded->cameras[i];
    EXPECT_TRUE(a.R.isApprox(b.R, 1e-9)) << i;
    EXPECT_TRUE(a.t.isApprox(b.t, 1e-9)) << i;
    EXPECT_NEAR(a.fx, b.fx, 1e-9);
    EXPECT_EQ(a.width, b.width);
    auto ia = load_camera_image(a), ib = load_camera_image(b);
    EXPECT_LE((*ia - *ib).abs().max().item<float>(), 0.5f / 255 + 1e-6);
  }
}

TEST_F(UploadTest, FilesStreamToDiskAsTheyArriveAndBecomeTheScene) {
  // Chunks of 100 bytes: every image arrives in several pieces, each appended to its file as it comes.
  auto received = receive(submit_messages(upload, 100), dir_ / "streamed");
  ASSERT_TRUE(received.ok()) << received.status();
  EXPECT_EQ(received->images, 9);
  for (int i = 0; i < 9; ++i) {
    ASSERT_GT(upload.images[i].size(), 200u);
    EXPECT_EQ(*read_file_bytes(received->image_file(i)), upload.images[i]) << i;
  }
  ASSERT_TRUE(write_uploaded_scene(*received).ok());
  EXPECT_FALSE(fs::exists(dir_ / "streamed" / "upload")) << "the staging files are gone once the scene is made";
  EXPECT_EQ(*read_file_bytes(dir_ / "streamed" / "images" / upload.spec.cameras(0).name()), upload.images[0]);
}

TEST_F(UploadTest, MalformedStreamsAreRefusedNamingTheProblem) {
  const auto refused = [&](std::vector<v1::SubmitJobRequest> messages, absl::StatusCode code, const std::string& needle,
                           uint64_t max_bytes = uint64_t{1} << 30) {
    const auto st = receive(messages, dir_ / "bad", max_bytes).status();
    EXPECT_EQ(st.code(), code) << st;
    EXPECT_TRUE(absl::StrContains(st.message(), needle)) << st;
    EXPECT_FALSE(absl::StrContains(st.message(), dir_.string())) << "the server's path leaks: " << st;
  };
  const auto good = submit_messages(upload, 500);
  refused({good.begin() + 1, good.end()}, absl::StatusCode::kInvalidArgument, "first message must carry the JobSpec");
  auto spec_twice = good;
  spec_twice.insert(spec_twice.begin() + 2, good[0]);
  refused(spec_twice, absl::StatusCode::kInvalidArgument, "only file chunks may follow");
  auto out_of_order = good;
  out_of_order[1].mutable_file()->set_index(3);
  refused(out_of_order, absl::StatusCode::kInvalidArgument, "image chunk for index 3 while image 0 is expected");
  refused({good.begin(), good.end() - 1}, absl::StatusCode::kInvalidArgument, "image 8 is incomplete");
  auto stray_points = good;
  stray_points.back().mutable_file()->set_kind(v1::FileChunk::POINTS);
  refused(stray_points, absl::StatusCode::kInvalidArgument, "point cloud sent but the spec announced none");
  auto too_many = upload;
  too_many.images.push_back(upload.images[0]);
  refused(submit_messages(too_many, 500), absl::StatusCode::kInvalidArgument, "image 9 has no camera (9 cameras)");
  refused(good, absl::StatusCode::kResourceExhausted, "upload exceeds the limit of 1000 bytes", 1000);
}

TEST_F(UploadTest, CorruptUploadsAreInvalidArgumentsNamingTheProblem) {
  const auto expect_invalid = [&](const std::string& needle) {
    const absl::Status st = write();
    EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << st;
    EXPECT_NE(st.message().find(needle), std::string_view::npos) << st;
  };
  const UploadParts good = upload;
  upload.images[4] = "definitely not an image";
  expect_invalid("image 4");
  upload = good;
  upload.images.pop_back();
  expect_invalid("camera count mismatch");
  upload = good;
  upload.spec.mutable_cameras(2)->set_rotation(4, std::nan(""));
  expect_invalid("camera 2");
  upload = good;
  upload.spec.mutable_config()->set_views(20);
  expect_invalid("views");
  // Finite as a double, infinite as the float32 training uses: refused before any job exists.
  upload = good;
  upload.spec.mutable_cameras(1)->set_translation(0, 1e300);
  expect_invalid("translation not finite or beyond");
  upload = good;
  upload.spec.mutable_cameras(3)->set_near(5);
  upload.spec.mutable_cameras(3)->set_far(1);
  expect_invalid("near bound 5 beyond far bound 1");
  upload = good;
  upload.spec.mutable_cameras(3)->set_near(-1);
  expect_invalid("depth bounds must be finite and not negative");
  upload = good;
  upload.spec.mutable_cameras(0)->set_fx(1e30);
  expect_invalid("focal lengths");
  // Names reach other users' terminals and become file names: no control characters, no endless names.
  upload = good;
  upload.spec.set_name("job\x1b[2J\x1b[31mred");
  expect_invalid("job name 'job\\x1b[2J\\x1b[31mred' has control characters");
  upload = good;
  upload.spec.set_name(std::string(300, 'n'));
  expect_invalid("job name of 300 bytes, over the limit of 255");
  upload = good;
  upload.spec.mutable_cameras(5)->set_name("img\x1b]0;title\x07.png");
  expect_invalid("camera 5 (img\\x1b]0;title\\x07.png): image name must be a plain file name");
  upload = good;
  upload.spec.mutable_cameras(6)->set_name(std::string(300, 'c') + ".png");
  expect_invalid("camera 6: image name of 304 bytes, over the limit of 255");
}

// A scene's depth bounds (LLFF's poses_bounds.npy) survive the upload: random points are drawn between them,
// so without them a submitted job would start elsewhere than gaps train on the same scene.
TEST_F(UploadTest, DepthBoundsSurviveTheUpload) {
  for (int i = 0; i < upload.spec.cameras_size(); ++i) {
    upload.spec.mutable_cameras(i)->set_near(0.5 + i);
    upload.spec.mutable_cameras(i)->set_far(40.0 + i);
  }
  ASSERT_TRUE(write().ok()) << write();
  absl::StatusOr<Scene> uploaded = load_scene(dir_ / "scene");
  ASSERT_TRUE(uploaded.ok()) << uploaded.status();
  for (int i = 0; i < upload.spec.cameras_size(); ++i) {
    EXPECT_DOUBLE_EQ(uploaded->cameras[i].near, 0.5 + i) << i;
    EXPECT_DOUBLE_EQ(uploaded->cameras[i].far, 40.0 + i) << i;
  }
}

// A PNG of random pixels, width x height.
std::string random_png(int width, int height) {
  absl::StatusOr<std::string> png = encode_png(at::rand({height, width, 3}), "random");
  EXPECT_TRUE(png.ok()) << png.status();
  return png.ok() ? *png : std::string();
}

// FileChunk::LARGER_IMAGE: views at twice their camera's size (within a pixel) land in the scene's larger-views
// folder under the cameras' image names; anything else is refused, naming the camera.
TEST_F(UploadTest, LargerViewsAreKeptUnderTheCamerasNamesAndChecked) {
  upload.larger_images = {{1, random_png(64, 48)}, {4, random_png(65, 47)}};
  ASSERT_TRUE(write().ok()) << write();
  for (const auto& [index, image] : upload.larger_images)
    EXPECT_EQ(*read_file_bytes(dir_ / "scene" / kLargerViewsFolder / upload.spec.cameras(index).name()), image);
  EXPECT_EQ(std::distance(fs::directory_iterator(dir_ / "scene" / kLargerViewsFolder), fs::directory_iterator()), 2);
  EXPECT_TRUE(load_scene(dir_ / "scene").ok()) << "the folder is beside the scene, not in it";

  const UploadParts good = upload;
  const auto refused = [&](const std::string& folder, const std::string& needle) {
    const absl::Status st = write(folder);
    EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << st;
    EXPECT_TRUE(absl::StrContains(st.message(), needle)) << st;
  };
  upload.larger_images = {{1, random_png(64, 50)}};
  refused("wrong_size", "larger image of camera 1 (" + upload.spec.cameras(1).name() +
                            "): image is 64x50 but twice its camera's size is 64x48");
  upload.larger_images = {{2, "not an image"}};
  refused("corrupt", "larger image of camera 2");
  upload.larger_images = {{4, random_png(64, 48)}, {1, random_png(64, 48)}};
  refused("out_of_order", "larger image for camera 1 out of order or range (9 cameras, last sent 4)");
  upload.larger_images = {{9, random_png(64, 48)}};
  refused("out_of_range", "larger image for camera 9 out of order or range");

  upload = good;
  std::vector<v1::SubmitJobRequest> early = submit_messages(upload, 100000);
  std::rotate(early.begin() + 1, early.end() - 2, early.end());  // the two larger images before the images
  const absl::Status st = receive(early, dir_ / "early").status();
  EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << st;
  EXPECT_TRUE(absl::StrContains(st.message(), "larger image for camera 1 before every image arrived")) << st;
  std::vector<v1::SubmitJobRequest> cut = submit_messages(upload, 100);
  cut.pop_back();
  const absl::Status incomplete = receive(cut, dir_ / "cut").status();
  EXPECT_TRUE(absl::StrContains(incomplete.message(), "larger image 4 is incomplete")) << incomplete;
}

TEST_F(UploadTest, AnUploadedPointCloudIsKeptAndABrokenOneRefused) {
  PointCloud points{at::rand({50, 3}), at::rand({50, 3})};
  ASSERT_TRUE(write_point_cloud_ply(points, dir_ / "points.ply").ok());
  upload.spec.set_has_points(true);
  upload.spec.mutable_config()->set_init("points");
  upload.points_ply = *read_file_bytes(dir_ / "points.ply");
  ASSERT_TRUE(write().ok()) << write();
  auto back = read_point_cloud_ply(dir_ / "scene" / "points.ply");
  ASSERT_TRUE(back.ok());
  EXPECT_TRUE(at::allclose(back->xyz, points.xyz));
  const std::string ply_header =
      "ply\nformat binary_little_endian 1.0\nelement vertex COUNT\nproperty float x\nproperty float y\n"
      "property float z\nend_header\n";
  const auto refused = [&](const std::string& ply, const std::string& needle) {
    upload.points_ply = ply;
    const absl::Status st = write("scene2");
    EXPECT_EQ(st.code(), absl::StatusCode::kInvalidArgument) << st;
    EXPECT_NE(st.message().find("uploaded point cloud"), std::string_view::npos) << st;
    EXPECT_NE(st.message().find(needle), std::string_view::npos) << st;
    EXPECT_EQ(st.message().find(dir_.string()), std::string_view::npos) << "the server's path leaks: " << st;
  };
  refused("ply\nnot really", "end_header");
  refused("ply\nformat binary_little_endian 1.0\nelement vertex 5999999999999\nend_header\n",
          "the vertex element has no properties");
  const std::string one_point(12, '\0');
  for (const char* count : {"-5", "abc", "4294967296"}) {
    std::string ply = ply_header;
    ply.replace(ply.find("COUNT"), 5, count);
    refused(ply + one_point, count[0] == '4' ? "announces 4294967296 vertices" : "is not a non-negative integer");
  }
  std::string far_point = ply_header;
  far_point.replace(far_point.find("COUNT"), 5, "1");
  const float coordinates[3] = {1e38f, 0.f, 0.f};
  refused(far_point + std::string(reinterpret_cast<const char*>(coordinates), 12), "point 0 has a coordinate beyond");
}

}  // namespace
}  // namespace gaps
