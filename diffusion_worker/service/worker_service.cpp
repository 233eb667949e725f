#include "diffusion_worker/service/worker_service.h"

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <optional>

#include <ATen/Context.h>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "common/stopwatch.h"
#include "rpc/codec.h"
#include "rpc/generation_codec.h"
#include "rpc/security.h"

#if defined(GAPS_CUDA_KERNELS)
#include <cuda_runtime_api.h>
#endif

namespace gaps {
namespace {

struct DeviceMemory {
  uint64_t total = 0, free = 0;  // bytes; 0 when not known
};

// Physical memory for the CPU, the CUDA runtime's figures for "cuda" / "cuda:N".
DeviceMemory device_memory(const std::string& device) {
  DeviceMemory m;
  if (device == "cpu") {
    const long page = sysconf(_SC_PAGE_SIZE), pages = sysconf(_SC_PHYS_PAGES), available = sysconf(_SC_AVPHYS_PAGES);
    if (page > 0 && pages > 0) m.total = static_cast<uint64_t>(page) * static_cast<uint64_t>(pages);
    if (page > 0 && available > 0) m.free = static_cast<uint64_t>(page) * static_cast<uint64_t>(available);
    return m;
  }
#if defined(GAPS_CUDA_KERNELS)
  if (device.rfind("cuda", 0) == 0) {
    const int index = device.size() > 5 ? std::atoi(device.c_str() + 5) : 0;
    int previous = 0;
    size_t free_bytes = 0, total_bytes = 0;
    if (cudaGetDevice(&previous) == cudaSuccess && cudaSetDevice(index) == cudaSuccess &&
        cudaMemGetInfo(&free_bytes, &total_bytes) == cudaSuccess) {
      m.total = total_bytes;
      m.free = free_bytes;
    }
    cudaSetDevice(previous);
  }
#endif
  return m;
}

}  // namespace

// Holds the backend for one call; releasing it wakes the next waiting call.
class WorkerService::BackendTurn {
 public:
  explicit BackendTurn(WorkerService& service) : service_(service) {}
  ~BackendTurn() {
    std::lock_guard<std::mutex> lock(service_.mutex_);
    service_.backend_busy_ = false;
    service_.backend_free_.notify_one();
  }

 private:
  WorkerService& service_;
};

WorkerService::WorkerService(std::unique_ptr<Generator> generator, WorkerServiceOptions options)
    : generator_(std::move(generator)), options_(std::move(options)) {
  if (!options_.shared_memory) return;
  // Without a probe (no writable /dev/shm) trainers simply use the socket.
  if (auto probe = rpc::SharedMemoryProbe::create(); probe.ok()) probe_ = *std::move(probe);
}

grpc::Status WorkerService::wait_for_backend(grpc::ServerContext* context, std::unique_ptr<BackendTurn>* turn) {
  std::unique_lock<std::mutex> lock(mutex_);
  if (backend_busy_ && waiting_ >= options_.queue_capacity)
    return grpc::Status(
        grpc::StatusCode::RESOURCE_EXHAUSTED,
        absl::StrCat("worker queue full (", waiting_, " calls waiting, capacity ", options_.queue_capacity, ")"));
  ++waiting_;
  const auto deadline = context->deadline();
  while (backend_busy_) {
    if (context->IsCancelled()) {
      --waiting_;
      return grpc::Status(grpc::StatusCode::CANCELLED, "call cancelled while queued");
    }
    // Wake periodically: cancellation has no notification here.
    const auto until = std::min(deadline, std::chrono::system_clock::now() + std::chrono::milliseconds(100));
    backend_free_.wait_until(lock, until);
    if (backend_busy_ && std::chrono::system_clock::now() >= deadline) {
      --waiting_;
      return grpc::Status(grpc::StatusCode::DEADLINE_EXCEEDED, "deadline passed while queued for the backend");
    }
  }
  --waiting_;
  backend_busy_ = true;
  *turn = std::make_unique<BackendTurn>(*this);
  return grpc::Status::OK;
}

void WorkerService::forget_oldest_scenes() {
  while (scenes_.size() > static_cast<size_t>(options_.max_scenes)) {
    const auto oldest = std::min_element(last_use_.begin(), last_use_.end(),
                                         [](const auto& x, const auto& y) { return x.second < y.second; });
    forget_scene(std::string(oldest->first));
  }
}

bool WorkerService::forget_scene(const std::string& handle) {
  learnt_.erase(handle);
  last_use_.erase(handle);
  return scenes_.erase(handle) > 0;
}

absl::StatusOr<WorkerService::Readaptation> WorkerService::ensure_adapted(const std::string& handle) {
  if (!handle.empty()) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (const auto it = last_use_.find(handle); it != last_use_.end()) it->second = ++use_clock_;
  }
  if (handle.empty() || handle == adapted_handle_) return Readaptation::kNone;
  rpc::AdaptRequest scene;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    const auto it = scenes_.find(handle);
    if (it == scenes_.end()) return absl::NotFoundError(absl::StrCat("unknown scene handle '", handle, "'"));
    scene = it->second;
  }
  std::string learnt;
  if (scene.exported.empty() && options_.keep_scene_adaptations) {
    std::lock_guard<std::mutex> lock(mutex_);
    if (const auto it = learnt_.find(handle); it != learnt_.end()) learnt = it->second;
  }
  Readaptation done = Readaptation::kInstalled;
  if (!scene.exported.empty()) {
    GAPS_RETURN_IF_ERROR(generator_->install_adaptation(scene.views, scene.adaptation, std::move(scene.exported)));
  } else if (!learnt.empty()) {
    GAPS_RETURN_IF_ERROR(generator_->install_adaptation(scene.views, scene.adaptation, std::move(learnt)));
  } else {
    done = Readaptation::kAdapted;
    GAPS_RETURN_IF_ERROR(generator_->adapt(scene.views, scene.adaptation));
    // Kept for the scene: other workers may install it (ExportAdaptation), and when scenes alternate on this
    // worker, coming back to this one installs it instead of learning it again.
    GAPS_ASSIGN_OR_RETURN(learnt, generator_->export_adaptation());
    std::lock_guard<std::mutex> lock(mutex_);
    if (scenes_.count(handle)) learnt_[handle] = std::move(learnt);
  }
  adapted_handle_ = handle;
  return done;
}

grpc::Status WorkerService::GetInfo(grpc::ServerContext* context, const v1::GetInfoRequest*, v1::WorkerInfo* info) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  info->set_backend(options_.backend);
  info->set_backend_version(generator_->name());
  info->set_max_batch(options_.max_batch);
  info->set_max_request_bytes(options_.max_request_bytes);
  info->set_queue_capacity(options_.queue_capacity);
  info->set_device(options_.device);
  const DeviceMemory memory = device_memory(options_.device);
  info->set_device_memory_total(memory.total);
  info->set_device_memory_free(memory.free);
  info->set_weights_identity(generator_->weights_identity());
  {
    std::lock_guard<std::mutex> lock(mutex_);
    info->set_scenes_kept(static_cast<int32_t>(scenes_.size()));
  }
  if (probe_) {
    info->set_shared_memory_probe(probe_->name());
    info->set_shared_memory_token(probe_->token());
  }
  for (const char* c : {"render_rgb", "render_depth", "render_alpha", "references", "strength", "control_scale",
                        "ip_adapter_scale", "prompt", "seed"})
    info->add_supported_constraints(c);
  return grpc::Status::OK;
}

grpc::Status WorkerService::AdaptScene(grpc::ServerContext* context,
                                       grpc::ServerReaderWriter<v1::AdaptSceneProgress, v1::Chunk>* stream) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  v1::AdaptSceneBatch batch;
  if (auto st = rpc::read_chunked([&](v1::Chunk* c) { return stream->Read(c); }, options_.max_request_bytes, &batch);
      !st.ok())
    return rpc::to_grpc(st);
  absl::StatusOr<rpc::AdaptRequest> scene = rpc::decode_adapt_batch(batch);
  if (!scene.ok()) return rpc::to_grpc(scene.status());
  if (scene->views.empty()) return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "AdaptScene needs reference views");
  std::unique_ptr<BackendTurn> turn;
  if (auto st = wait_for_backend(context, &turn); !st.ok()) return st;
  std::string handle;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    handle = absl::StrCat(batch.scene_id().empty() ? "scene" : batch.scene_id(), "#", next_handle_++);
    scenes_[handle] = *scene;
    last_use_[handle] = ++use_clock_;
    forget_oldest_scenes();
  }
  v1::AdaptSceneProgress progress;
  progress.set_message(absl::StrCat("adapting ", generator_->name(), " to ", scene->views.size(), " views"));
  stream->Write(progress);
  if (auto st = ensure_adapted(handle).status(); !st.ok()) {
    std::lock_guard<std::mutex> lock(mutex_);
    forget_scene(handle);
    return rpc::to_grpc(st);
  }
  progress.set_fraction(1.0);
  progress.set_message("adapted");
  progress.set_scene_handle(handle);
  for (const std::string& note : generator_->notes()) progress.add_notes(note);
  stream->Write(progress);
  return grpc::Status::OK;
}

absl::StatusOr<std::unique_ptr<rpc::SharedRegion>> WorkerService::open_region(const v1::GenerateBatch& batch) {
  if (!batch.has_shared_region()) return nullptr;
  if (!probe_)
    return absl::FailedPreconditionError(
        "this worker takes no shared memory (--shared_memory=false); send payloads "
        "in the message");
  const v1::SharedRegion& r = batch.shared_region();
  if (r.answer_offset() > r.size())
    return absl::InvalidArgumentError(absl::StrCat("shared region ", r.name(), ": answer_offset ", r.answer_offset(),
                                                   " lies beyond its ", r.size(), " bytes"));
  return rpc::SharedRegion::open(r.name(), r.size());
}

namespace {

// The backend, not the request, produced what cannot be sent: the caller asks another worker.
grpc::Status malformed_answer(const absl::Status& why) {
  return rpc::to_grpc(absl::DataLossError(absl::StrCat("malformed answer: ", why.message())));
}

}  // namespace

grpc::Status WorkerService::Generate(grpc::ServerContext* context,
                                     grpc::ServerReaderWriter<v1::Chunk, v1::Chunk>* stream) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  auto clock = std::chrono::steady_clock::now();
  v1::GenerateResult result;
  auto& transfer = *result.mutable_transfer_seconds();
  v1::GenerateBatch batch;
  if (auto st = rpc::read_chunked([&](v1::Chunk* c) { return stream->Read(c); }, options_.max_request_bytes, &batch);
      !st.ok())
    return rpc::to_grpc(st);
  transfer["worker_receive"] = lap_seconds(&clock);
  if (batch.poses_size() == 0)
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "Generate needs at least one pose");
  if (batch.poses_size() > options_.max_batch)
    return grpc::Status(
        grpc::StatusCode::INVALID_ARGUMENT,
        absl::StrCat(batch.poses_size(), " poses exceed this worker's max batch of ", options_.max_batch));
  auto answer_encoding = rpc::tensor_encoding(batch.answer_encoding(), "answer_encoding");
  if (!answer_encoding.ok()) return rpc::to_grpc(answer_encoding.status());
  auto region = open_region(batch);
  if (!region.ok()) return rpc::to_grpc(region.status());
  auto requests = rpc::decode_generation_batch(batch, region->get());
  if (!requests.ok()) return rpc::to_grpc(requests.status());
  transfer["worker_decode"] = lap_seconds(&clock);
  std::unique_ptr<BackendTurn> turn;
  if (auto st = wait_for_backend(context, &turn); !st.ok()) return st;
  transfer["worker_queue"] = lap_seconds(&clock);
  const absl::StatusOr<Readaptation> switched = ensure_adapted(batch.scene_handle());
  if (!switched.ok()) return rpc::to_grpc(switched.status());
  // Another scene was adapted since this one's last call (jobs sharing the worker): reported as a stage.
  const double switch_seconds = lap_seconds(&clock);
  const auto start = std::chrono::steady_clock::now();
  auto images = generator_->generate(*requests);
  if (!images.ok()) return rpc::to_grpc(images.status());
  // Re-adapting above repeats what this scene's AdaptScene already reported; only generate()'s notes are new.
  const std::vector<std::string> notes = generator_->notes();
  const std::map<std::string, double> stages = generator_->stage_seconds();
  const std::map<std::string, double> counters = generator_->counters();
  turn.reset();
  if (context->IsCancelled()) return grpc::Status(grpc::StatusCode::CANCELLED, "caller gave up during generation");
  result.set_backend_seconds(std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count());
  clock = std::chrono::steady_clock::now();
  std::optional<rpc::SharedArena> arena;
  if (*region) arena.emplace(**region, batch.shared_region().answer_offset());
  // The images are laid out now and converted while the converted ones are sent (rpc/streamed_send.h), or
  // converted at once.
  std::vector<rpc::MessagePart> parts;
  if (auto st = rpc::encode_answer(*images, {*answer_encoding, arena ? &*arena : nullptr}, &result,
                                   options_.convert_while_sending ? &parts : nullptr);
      !st.ok())
    return malformed_answer(st);
  const double lay_out_seconds = lap_seconds(&clock);
  for (const std::string& note : notes) result.add_notes(note);
  result.mutable_stage_seconds()->insert(stages.begin(), stages.end());
  result.mutable_backend_counters()->insert(counters.begin(), counters.end());
  if (*switched != Readaptation::kNone) {
    (*result.mutable_stage_seconds())["scene_switch"] = switch_seconds;
    (*result.mutable_backend_counters())[*switched == Readaptation::kAdapted ? "scene_switch_adaptations"
                                                                             : "scene_switch_installs"] = 1;
  }
  // The message's size is announced before the conversions run, so worker_encode holds a value now (a double: the
  // same serialised size as the real one), which write_streamed's finish replaces with the measured seconds.
  transfer["worker_encode"] = -1.0;
  const absl::Status sent = rpc::write_streamed(
      result, parts, [&](const v1::Chunk& c) { return stream->Write(c); },
      [&](double convert_seconds) { transfer["worker_encode"] = lay_out_seconds + convert_seconds; });
  if (absl::IsUnavailable(sent)) return grpc::Status(grpc::StatusCode::UNAVAILABLE, "result stream broke");
  if (!sent.ok()) return malformed_answer(sent);
  return grpc::Status::OK;
}

grpc::Status WorkerService::ExportAdaptation(grpc::ServerContext* context, const v1::ExportAdaptationRequest* request,
                                             grpc::ServerWriter<v1::Chunk>* writer) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  v1::AdaptationExport answer;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    const auto it = scenes_.find(request->scene_handle());
    if (it == scenes_.end())
      return grpc::Status(grpc::StatusCode::NOT_FOUND,
                          absl::StrCat("unknown scene handle '", request->scene_handle(), "'"));
    // What it learnt itself, else what it installed from another worker.
    const auto learnt = learnt_.find(request->scene_handle());
    answer.set_adaptation(learnt != learnt_.end() ? learnt->second : it->second.exported);
  }
  answer.set_weights_identity(generator_->weights_identity());
  if (!rpc::write_chunked(answer, [&](const v1::Chunk& c) { return writer->Write(c); }))
    return grpc::Status(grpc::StatusCode::CANCELLED, "the caller went away during ExportAdaptation");
  return grpc::Status::OK;
}

grpc::Status WorkerService::ReleaseScene(grpc::ServerContext* context, const v1::ReleaseSceneRequest* request,
                                         v1::ReleaseSceneResponse*) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  std::lock_guard<std::mutex> lock(mutex_);
  if (!forget_scene(request->scene_handle()))
    return grpc::Status(grpc::StatusCode::NOT_FOUND,
                        absl::StrCat("unknown scene handle '", request->scene_handle(), "'"));
  return grpc::Status::OK;
}

}  // namespace gaps
