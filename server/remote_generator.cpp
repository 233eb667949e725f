#include "server/remote_generator.h"

#include <arpa/inet.h>
#include <netdb.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <set>

#include <condition_variable>
#include <future>
#include <mutex>
#include <thread>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/strip.h"
#include "common/status_macros.h"
#include "common/stopwatch.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "rpc/codec.h"
#include "rpc/generation_codec.h"
#include "rpc/shared_memory.h"
#include "rpc/streamed_send.h"

namespace gaps {

struct RemoteGenerator::Worker {
  std::string address;
  std::shared_ptr<grpc::Channel> channel;
  std::unique_ptr<v1::DiffusionWorker::Stub> stub;
  std::unique_ptr<grpc::health::v1::Health::Stub> health;
  bool healthy = true;  // optimistic until a call fails
  bool probed = false;  // a health check and GetInfo succeeded once
  std::chrono::steady_clock::time_point failed_at;
  std::string last_error;
  std::string scene_handle;
  uint64_t adapted_version = 0;               // views_version_ the handle belongs to
  bool shares_memory = false;                 // its probe was read here (set by probe())
  std::string weights_identity;               // WorkerInfo.weights_identity (set by probe())
  std::unique_ptr<rpc::SharedRegion> region;  // reused by its calls while large enough
  double seconds_per_pose = 0;                // its shards' Generate seconds per pose, smoothed; 0: unmeasured
};

namespace {

// The largest exported adaptation taken from a worker (sdxl's LoRA adapters in float32: about 13 MB at rank 4,
// ~0.4 GB at rank 128).
constexpr uint64_t kMaxExportBytes = uint64_t{1} << 30;

// An answer a worker should not have sent (truncated, the wrong count or shape, non-finite pixels): the
// worker is at fault, not the request, so another worker is asked. generate() names the worker.
absl::Status malformed(const absl::Status& why) {
  return absl::DataLossError(absl::StrCat("malformed answer: ", why.message()));
}

// Cancels `context` once `should_stop` says so, checking every 50 ms from a thread of its own, for as long as
// it lives (the span of one call).
class CancelWhenStopping {
 public:
  CancelWhenStopping(grpc::ClientContext& context, const std::function<bool()>& should_stop) {
    if (!should_stop) return;
    watcher_ = std::thread([this, &context, should_stop] {
      std::unique_lock<std::mutex> lock(mutex_);
      while (!done_) {
        if (should_stop()) {
          context.TryCancel();
          return;
        }
        changed_.wait_for(lock, std::chrono::milliseconds(50));
      }
    });
  }
  ~CancelWhenStopping() {
    if (!watcher_.joinable()) return;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      done_ = true;
    }
    changed_.notify_all();
    watcher_.join();
  }
  CancelWhenStopping(const CancelWhenStopping&) = delete;
  CancelWhenStopping& operator=(const CancelWhenStopping&) = delete;

 private:
  std::mutex mutex_;
  std::condition_variable changed_;
  bool done_ = false;
  std::thread watcher_;
};

bool retryable(absl::StatusCode code) {
  return code == absl::StatusCode::kUnavailable || code == absl::StatusCode::kDeadlineExceeded ||
         code == absl::StatusCode::kResourceExhausted || code == absl::StatusCode::kAborted ||
         code == absl::StatusCode::kCancelled;
}

// The errors after which another worker may succeed: the worker failed or answered malformed, not the request.
bool another_worker_may_help(const absl::Status& st) { return retryable(st.code()) || absl::IsDataLoss(st); }

}  // namespace

std::vector<std::string> resolve_worker_addresses(const std::vector<std::string>& targets) {
  std::vector<std::string> out;
  for (const std::string& target : targets) {
    if (!absl::StartsWith(target, "dns:")) {
      out.push_back(target);
      continue;
    }
    // dns:[//authority]/NAME:PORT or dns:NAME:PORT; the authority (a DNS server) is left to the system.
    absl::string_view name = absl::StripPrefix(target, "dns:");
    if (absl::ConsumePrefix(&name, "//")) name = name.substr(std::min(name.size(), name.find('/') + 1));
    const size_t colon = name.rfind(':');
    const std::string host(name.substr(0, colon)), port(colon == absl::string_view::npos ? "" : name.substr(colon + 1));
    addrinfo hints{};
    hints.ai_family = AF_UNSPEC;
    hints.ai_socktype = SOCK_STREAM;
    addrinfo* found = nullptr;
    std::set<std::string> addresses;
    if (!host.empty() && !port.empty() && getaddrinfo(host.c_str(), port.c_str(), &hints, &found) == 0) {
      for (const addrinfo* a = found; a != nullptr; a = a->ai_next) {
        char ip[INET6_ADDRSTRLEN] = {0};
        const void* bytes =
            a->ai_family == AF_INET6
                ? static_cast<const void*>(&reinterpret_cast<const sockaddr_in6*>(a->ai_addr)->sin6_addr)
                : static_cast<const void*>(&reinterpret_cast<const sockaddr_in*>(a->ai_addr)->sin_addr);
        if (inet_ntop(a->ai_family, bytes, ip, sizeof(ip)) == nullptr) continue;
        addresses.insert(a->ai_family == AF_INET6 ? absl::StrCat("[", ip, "]:", port) : absl::StrCat(ip, ":", port));
      }
      freeaddrinfo(found);
    }
    if (addresses.empty()) out.push_back(target);
    out.insert(out.end(), addresses.begin(), addresses.end());
  }
  return out;
}

std::vector<size_t> shard_sizes(size_t poses, const std::vector<double>& seconds_per_pose) {
  const size_t shards = seconds_per_pose.size();
  double measured_sum = 0;
  size_t measured = 0;
  for (const double s : seconds_per_pose)
    if (s > 0) measured_sum += s, ++measured;
  const double unmeasured = measured > 0 ? measured_sum / static_cast<double>(measured) : 1.0;
  std::vector<double> speed;
  double total = 0;
  for (const double s : seconds_per_pose) total += speed.emplace_back(1.0 / (s > 0 ? s : unmeasured));
  std::vector<size_t> sizes(shards);
  size_t begin = 0;
  double cumulative = 0;
  for (size_t k = 0; k < shards; ++k) {
    cumulative += speed[k];
    size_t end = k + 1 == shards
                     ? poses
                     : static_cast<size_t>(std::floor(static_cast<double>(poses) * cumulative / total + 1e-9));
    // At least one pose for this shard, and one left for each later one.
    end = std::clamp(end, begin + 1, poses - (shards - k - 1));
    sizes[k] = end - begin;
    begin = end;
  }
  return sizes;
}

RemoteGenerator::RemoteGenerator(WorkerPoolOptions options) : options_(std::move(options)) {}
RemoteGenerator::~RemoteGenerator() {
  join_adaptation(nullptr, true);
  // The job is over: its workers may forget its scene (views, adaptation) now rather than when they run out of room.
  for (auto& w : workers_)
    if (w->healthy && !w->scene_handle.empty()) release_scene(*w, w->scene_handle);
}

void RemoteGenerator::release_scene(Worker& w, const std::string& handle) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + options_.probe_timeout);
  rpc::attach_token(context, options_.security.token);
  v1::ReleaseSceneRequest request;
  request.set_scene_handle(handle);
  v1::ReleaseSceneResponse response;
  // Best effort: a worker that restarted or forgot the scene has nothing to free.
  (void)w.stub->ReleaseScene(&context, request, &response);
}

absl::StatusOr<std::unique_ptr<RemoteGenerator>> RemoteGenerator::create(WorkerPoolOptions options) {
  if (options.addresses.empty()) return absl::InvalidArgumentError("the worker pool needs at least one address");
  if (options.max_rounds < 1) return absl::InvalidArgumentError("max_rounds must be at least 1");
  std::unique_ptr<RemoteGenerator> g(new RemoteGenerator(std::move(options)));
  for (const auto& address : g->options_.addresses) {
    auto w = std::make_unique<Worker>();
    w->address = address;
    GAPS_ASSIGN_OR_RETURN(w->channel, rpc::make_channel(address, g->options_.security));
    w->stub = v1::DiffusionWorker::NewStub(w->channel);
    w->health = grpc::health::v1::Health::NewStub(w->channel);
    g->workers_.push_back(std::move(w));
  }
  return g;
}

std::string RemoteGenerator::name() const {
  std::lock_guard<std::mutex> lock(name_mutex_);
  return backend_version_.empty() ? "remote (no worker reached yet)" : "remote " + backend_version_;
}

void RemoteGenerator::mark_failed(Worker& w) {
  w.healthy = false;
  w.failed_at = std::chrono::steady_clock::now();
  // A restarted worker forgot its scenes: adapt it again before it generates.
  w.scene_handle.clear();
  w.adapted_version = 0;
}

absl::Status RemoteGenerator::probe(Worker& w) {
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + options_.probe_timeout);
  grpc::health::v1::HealthCheckRequest request;
  grpc::health::v1::HealthCheckResponse response;
  GAPS_RETURN_IF_ERROR(rpc::from_grpc(w.health->Check(&context, request, &response), w.address + " health check"));
  if (response.status() != grpc::health::v1::HealthCheckResponse::SERVING)
    return absl::UnavailableError(absl::StrCat(w.address, " is not serving"));
  // Learn the backend's identity (and check the token) before relying on the worker.
  grpc::ClientContext info_context;
  info_context.set_deadline(std::chrono::system_clock::now() + options_.probe_timeout);
  rpc::attach_token(info_context, options_.security.token);
  v1::WorkerInfo info;
  GAPS_RETURN_IF_ERROR(
      rpc::from_grpc(w.stub->GetInfo(&info_context, v1::GetInfoRequest(), &info), w.address + " GetInfo"));
  w.shares_memory = options_.shared_memory && !info.shared_memory_probe().empty() &&
                    rpc::shares_memory_with(info.shared_memory_probe(), info.shared_memory_token());
  w.weights_identity = info.weights_identity();
  std::lock_guard<std::mutex> lock(name_mutex_);
  backend_version_ = info.backend_version();
  return absl::OkStatus();
}

bool RemoteGenerator::usable(Worker& w) {
  if (w.healthy && w.probed) return true;
  if (!w.healthy && std::chrono::steady_clock::now() - w.failed_at < options_.failure_cooldown) return false;
  const absl::Status st = probe(w);
  if (!st.ok()) {
    w.last_error = std::string(st.message());
    mark_failed(w);
    return false;
  }
  w.healthy = true;
  w.probed = true;
  return true;
}

namespace {

void add_worker_notes(const std::string& address, const google::protobuf::RepeatedPtrField<std::string>& from,
                      std::vector<std::string>* to) {
  for (const std::string& note : from) to->push_back(absl::StrCat(address, ": ", note));
}

}  // namespace

absl::Status RemoteGenerator::adapt(const std::vector<ReferenceView>& views,
                                    const std::optional<SceneAdaptation>& adaptation) {
  join_adaptation(nullptr, true);  // calls for earlier views read views_
  views_ = views;
  adaptation_ = adaptation;
  ++views_version_;
  notes_.clear();
  start_adaptation();
  return absl::OkStatus();
}

void RemoteGenerator::start_adaptation() {
  {
    std::lock_guard<std::mutex> lock(adaptation_mutex_);
    first_adaptation_end_.reset();
    shared_export_.reset();
  }
  if (views_.empty() || workers_.empty() || stopping()) return;
  std::vector<Worker*> targets;
  if (options_.fan_out) {
    for (auto& w : workers_) targets.push_back(w.get());
  } else {
    targets.push_back(workers_[next_ % workers_.size()].get());
  }
  // With sharing, the first worker adapts and exports what it learnt; the others wait for that and install it.
  const bool share = options_.share_adaptation && targets.size() > 1;
  std::shared_future<void> leader_done;
  for (Worker* target : targets) {
    auto adaptation = std::make_unique<Adaptation>();
    adaptation->worker = target;
    const bool leader = share && target == targets.front();
    std::promise<void> done;
    if (leader) leader_done = done.get_future().share();
    adaptation->call = std::async(
        std::launch::async, [this, &a = *adaptation, leader, share, leader_done, done = std::move(done)]() mutable {
          if (share && !leader) leader_done.wait_for(options_.share_wait);
          adapt_in_background(a);
          if (leader) {
            fetch_export(*a.worker, a.attempt);
            done.set_value();
          }
          std::lock_guard<std::mutex> lock(adaptation_mutex_);
          a.ended = true;
          if (!first_adaptation_end_) first_adaptation_end_ = std::chrono::steady_clock::now();
          adaptation_ended_.notify_all();
        });
    adaptations_.push_back(std::move(adaptation));
  }
}

void RemoteGenerator::fetch_export(Worker& w, Attempt& attempt) {
  if (w.adapted_version != views_version_ || stopping()) return;  // its adaptation failed: the others adapt
  const auto start = std::chrono::steady_clock::now();
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + options_.generate_timeout);
  rpc::attach_token(context, options_.security.token);
  const CancelWhenStopping cancel(context, options_.should_stop);
  v1::ExportAdaptationRequest request;
  request.set_scene_handle(w.scene_handle);
  auto reader = w.stub->ExportAdaptation(&context, request);
  v1::AdaptationExport answer;
  absl::Status read = rpc::read_chunked([&](v1::Chunk* c) { return reader->Read(c); }, kMaxExportBytes, &answer);
  const absl::Status finished = rpc::from_grpc(reader->Finish(), w.address + " ExportAdaptation");
  if (!finished.ok() || !read.ok()) {
    // Not fatal: every worker then adapts itself, as without sharing.
    attempt.notes.push_back(absl::StrCat(w.address, ": its adaptation could not be shared, so each worker adapts ",
                                         "itself: ", (finished.ok() ? read : finished).message()));
    return;
  }
  attempt.stages["adaptation_export"] +=
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (answer.adaptation().empty()) return;  // the backend learnt nothing to hand over (e.g. reproject)
  attempt.counters["adaptation_export_bytes"] += static_cast<double>(answer.adaptation().size());
  std::lock_guard<std::mutex> lock(adaptation_mutex_);
  shared_export_ = SharedExport{views_version_, answer.weights_identity(), std::move(*answer.mutable_adaptation())};
}

void RemoteGenerator::adapt_in_background(Adaptation& a) {
  Worker& w = *a.worker;
  if (!usable(w)) return;
  const absl::Status adapted = adapt_on(w, a.attempt);
  // A worker that failed sits out its cooldown, as after a failed call in generate(); an error of the request
  // (the views, the adaptation asked for) is left for generate(), whose adaptation of the worker reports it.
  if (adapted.ok() || stopping() || !another_worker_may_help(adapted)) return;
  w.last_error = std::string(adapted.message());
  mark_failed(w);
}

void RemoteGenerator::join_adaptation(Attempt* into, bool all) {
  adapting_.clear();
  if (adaptations_.empty()) return;
  auto start = std::chrono::steady_clock::now();
  std::vector<std::unique_ptr<Adaptation>> running, ended;
  {
    std::unique_lock<std::mutex> lock(adaptation_mutex_);
    const auto all_ended = [&] {
      return std::all_of(adaptations_.begin(), adaptations_.end(), [](const auto& a) { return a->ended; });
    };
    if (all) {
      adaptation_ended_.wait(lock, all_ended);
    } else {
      adaptation_ended_.wait(lock, [&] { return first_adaptation_end_.has_value(); });
      adaptation_ended_.wait_until(lock, *first_adaptation_end_ + options_.adaptation_grace, all_ended);
    }
    for (auto& a : adaptations_) (a->ended ? ended : running).push_back(std::move(a));
  }
  for (auto& a : running) adapting_.insert(a->worker);
  for (auto& a : ended) {
    a->call.get();
    if (into != nullptr) into->add(a->attempt);
  }
  adaptations_ = std::move(running);
  if (into != nullptr) into->stages["adaptation_wait"] += lap_seconds(&start);
}

std::vector<RemoteGenerator::Worker*> RemoteGenerator::ready_workers() {
  std::vector<Worker*> ready;
  for (auto& w : workers_)
    if (!adapting_.count(w.get()) && !stopping() && usable(*w)) ready.push_back(w.get());
  return ready;
}

void RemoteGenerator::Attempt::add(const Attempt& other) {
  for (const auto& [stage, seconds] : other.stages) stages[stage] += seconds;
  for (const auto& [name, value] : other.counters)
    counters[name] = name == "shared_memory" ? std::max(counters[name], value) : counters[name] + value;
  notes.insert(notes.end(), other.notes.begin(), other.notes.end());
}

std::string RemoteGenerator::export_for(const Worker& w) {
  std::lock_guard<std::mutex> lock(adaptation_mutex_);
  const bool fits = shared_export_ && shared_export_->views_version == views_version_ && w.probed &&
                    shared_export_->weights_identity == w.weights_identity;
  return fits ? shared_export_->adaptation : std::string();
}

absl::Status RemoteGenerator::adapt_on(Worker& w, Attempt& attempt) {
  if (views_.empty() || w.adapted_version == views_version_) return absl::OkStatus();
  std::string exported = export_for(w);
  if (!exported.empty()) {
    const absl::Status installed = call_adapt_scene(w, attempt, std::move(exported));
    if (installed.ok() || stopping()) return installed;
    // A worker that cannot install another's adaptation can still make its own.
    attempt.notes.push_back(absl::StrCat(w.address, ": could not install the shared adaptation (", installed.message(),
                                         "), so it adapted itself"));
  }
  return call_adapt_scene(w, attempt, "");
}

absl::Status RemoteGenerator::call_adapt_scene(Worker& w, Attempt& attempt, const std::string& exported) {
  v1::AdaptSceneBatch batch;
  rpc::encode_adapt_batch(options_.scene_id, views_, adaptation_, &batch, exported);
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + options_.generate_timeout);
  rpc::attach_token(context, options_.security.token);
  const CancelWhenStopping cancel(context, options_.should_stop);
  const auto start = std::chrono::steady_clock::now();
  auto stream = w.stub->AdaptScene(&context);
  rpc::write_chunked(batch, [&](const v1::Chunk& c) { return stream->Write(c); });
  stream->WritesDone();
  v1::AdaptSceneProgress progress;
  std::string handle;
  std::vector<std::string> adapt_notes;
  while (stream->Read(&progress)) {
    if (!progress.scene_handle().empty()) handle = progress.scene_handle();
    add_worker_notes(w.address, progress.notes(), &adapt_notes);
  }
  GAPS_RETURN_IF_ERROR(rpc::from_grpc(stream->Finish(), w.address + " AdaptScene"));
  if (handle.empty()) return absl::InternalError(absl::StrCat(w.address, " AdaptScene returned no scene handle"));
  attempt.notes.insert(attempt.notes.end(), adapt_notes.begin(), adapt_notes.end());
  attempt.stages["adapt_scene"] += std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  attempt.counters[exported.empty() ? "adaptations_made" : "adaptations_installed"] += 1;
  if (!w.scene_handle.empty() && w.scene_handle != handle) release_scene(w, w.scene_handle);  // earlier views'
  w.scene_handle = handle;
  w.adapted_version = views_version_;
  return absl::OkStatus();
}

absl::StatusOr<std::vector<at::Tensor>> RemoteGenerator::call_generate(Worker& w,
                                                                       const std::vector<GenerationRequest>& requests,
                                                                       bool shared, Attempt& attempt,
                                                                       std::vector<std::string>* worker_notes) {
  const auto start = std::chrono::steady_clock::now();
  auto clock = start;
  v1::GenerateBatch batch;
  std::optional<rpc::SharedArena> arena;
  if (shared) {
    const rpc::SharedLayout layout = rpc::shared_layout(requests, options_.encoding);
    if (!w.region || w.region->size() < layout.request_bytes + layout.answer_bytes) {
      w.region.reset();
      auto created = rpc::SharedRegion::create(layout.request_bytes + layout.answer_bytes);
      // generate_on falls back to the messages for this.
      if (!created.ok()) return absl::FailedPreconditionError(created.status().message());
      w.region = *std::move(created);
    }
    arena.emplace(*w.region);
    v1::SharedRegion* region = batch.mutable_shared_region();
    region->set_name(w.region->name());
    region->set_size(w.region->size());
    region->set_answer_offset(layout.request_bytes);
  }
  const rpc::TensorEncoding depths =
      options_.depth_encoding.value_or(rpc::depth_encoding_for(options_.encoding, arena.has_value()));
  const rpc::TensorTransfer transfer{options_.encoding, arena ? &*arena : nullptr, depths};
  // Laid out now, converted while the converted parts are sent (rpc/streamed_send.h); or converted at once.
  std::vector<rpc::MessagePart> parts;
  GAPS_RETURN_IF_ERROR(
      rpc::encode_generation_batch(requests, &batch, transfer, options_.convert_while_sending ? &parts : nullptr));
  if (!w.scene_handle.empty()) batch.set_scene_handle(w.scene_handle);
  const double lay_out_seconds = lap_seconds(&clock);
  attempt.counters["request_bytes"] += static_cast<double>(batch.ByteSizeLong());
  attempt.counters["shared_memory"] = shared ? 1.0 : 0.0;

  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + options_.generate_timeout);
  rpc::attach_token(context, options_.security.token);
  const CancelWhenStopping cancel(context, options_.should_stop);
  auto stream = w.stub->Generate(&context);
  rpc::StreamedSendTimes sent;
  const absl::Status converted = rpc::write_streamed(
      batch, parts, [&](const v1::Chunk& c) { return stream->Write(c); }, nullptr, &sent);
  if (!converted.ok() && !absl::IsUnavailable(converted)) {
    // A tensor the encoding refuses (the stream is incomplete): the request is at fault, not the worker.
    context.TryCancel();
    (void)stream->Finish();
    return converted;
  }
  stream->WritesDone();
  attempt.stages["client_encode"] += lay_out_seconds + sent.convert_seconds;
  attempt.stages["client_send"] += lap_seconds(&clock);
  v1::GenerateResult result;
  const absl::Status read =
      rpc::read_chunked([&](v1::Chunk* c) { return stream->Read(c); }, uint64_t{1} << 34, &result);
  GAPS_RETURN_IF_ERROR(rpc::from_grpc(stream->Finish(), w.address + " Generate"));
  attempt.stages["client_receive"] += lap_seconds(&clock);
  if (!read.ok()) return malformed(read);
  if (static_cast<size_t>(result.images_size()) != requests.size())
    return malformed(
        absl::InvalidArgumentError(absl::StrCat(result.images_size(), " images for ", requests.size(), " poses")));
  std::vector<at::Tensor> images;
  for (int k = 0; k < result.images_size(); ++k) {
    const Camera& pose = requests[k].camera;
    absl::StatusOr<at::Tensor> image = rpc::decode_tensor_shaped(
        result.images(k), {pose.height, pose.width, 3}, absl::StrCat("image ", k), shared ? w.region.get() : nullptr);
    if (!image.ok()) return malformed(image.status());  // the decoder refuses NaN and infinite pixels too
    images.push_back(*std::move(image));
  }
  attempt.stages["client_decode"] += lap_seconds(&clock);
  attempt.counters["answer_bytes"] += static_cast<double>(result.ByteSizeLong());
  if (arena) attempt.counters["shared_memory_bytes"] += static_cast<double>(w.region->size());
  for (const auto& [stage, seconds] : result.stage_seconds()) attempt.stages[stage] += seconds;
  for (const auto& [stage, seconds] : result.transfer_seconds()) attempt.stages[stage] += seconds;
  for (const auto& [name, count] : result.backend_counters()) attempt.counters[name] += count;
  attempt.stages["worker_generate"] += result.backend_seconds();
  // The rest of the call, less the worker's re-adaptation to this scene where jobs alternate on it.
  const auto switched = result.stage_seconds().find("scene_switch");
  const double switch_seconds = switched != result.stage_seconds().end() ? switched->second : 0.0;
  attempt.stages["transfer"] += std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() -
                                result.backend_seconds() - switch_seconds;
  add_worker_notes(w.address, result.notes(), worker_notes);
  return images;
}

absl::StatusOr<std::vector<at::Tensor>> RemoteGenerator::generate_on(Worker& w,
                                                                     const std::vector<GenerationRequest>& requests,
                                                                     Attempt& attempt) {
  std::vector<std::string> worker_notes;
  auto images = call_generate(w, requests, w.shares_memory, attempt, &worker_notes);
  if (w.shares_memory && !images.ok() &&
      (absl::IsFailedPrecondition(images.status()) || absl::IsResourceExhausted(images.status()))) {
    // The probe said the memory is shared, but the region could not be made or opened: the socket still works.
    attempt.notes.push_back(absl::StrCat(w.address, ": shared memory unusable (", images.status().message(),
                                         "); payloads travel in the messages"));
    w.shares_memory = false;
    w.region.reset();
    worker_notes.clear();
    images = call_generate(w, requests, false, attempt, &worker_notes);
  }
  attempt.notes.insert(attempt.notes.end(), worker_notes.begin(), worker_notes.end());
  return images;
}

absl::StatusOr<std::vector<at::Tensor>> RemoteGenerator::adapt_and_generate_on(
    Worker& w, const std::vector<GenerationRequest>& requests, Attempt& attempt) {
  for (int tries = 0;; ++tries) {
    GAPS_RETURN_IF_ERROR(adapt_on(w, attempt));
    const bool had_handle = !w.scene_handle.empty();
    auto images = generate_on(w, requests, attempt);
    if (images.ok() || tries > 0 || !had_handle || !absl::IsNotFound(images.status())) return images;
    w.scene_handle.clear();
    w.adapted_version = 0;
  }
}

absl::StatusOr<std::vector<at::Tensor>> RemoteGenerator::generate(const std::vector<GenerationRequest>& requests) {
  notes_.clear();
  stage_seconds_.clear();
  counters_.clear();
  if (requests.empty()) return std::vector<at::Tensor>{};
  // The background adaptation's stages and notes come first in this call's report.
  Attempt attempt;
  const bool shared_out = options_.fan_out && requests.size() > 1;
  join_adaptation(&attempt, !shared_out);
  std::vector<Worker*> ready;
  if (shared_out) ready = ready_workers();
  if (ready.empty() && !adapting_.empty()) {
    // No adapted worker to start with: wait for the others after all.
    join_adaptation(&attempt, true);
    ready = ready_workers();
  }
  Attempt generation;
  auto images = ready.size() > 1 ? generate_fanned_out(requests, ready, generation)
                                 : generate_with_failover(requests, generation);
  if (!images.ok() && !adapting_.empty() && another_worker_may_help(images.status()) && !stopping()) {
    // The adapted workers failed; those still adapting may answer once they are done.
    join_adaptation(&attempt, true);
    generation = Attempt();
    images = generate_with_failover(requests, generation);
  }
  if (!images.ok()) return images;
  attempt.add(generation);
  notes_ = std::move(attempt.notes);
  stage_seconds_ = std::move(attempt.stages);
  counters_ = std::move(attempt.counters);
  if (!counters_.count("workers")) counters_["workers"] = 1;
  return images;
}

namespace {

absl::Status stopped_status() {
  return absl::UnavailableError("the job is stopping: the generation call was cancelled");
}

}  // namespace

absl::StatusOr<std::vector<at::Tensor>> RemoteGenerator::generate_fanned_out(
    const std::vector<GenerationRequest>& requests, const std::vector<Worker*>& ready, Attempt& attempt) {
  const size_t shards = std::min(ready.size(), requests.size());
  std::vector<double> seconds_per_pose;
  for (size_t s = 0; s < shards; ++s) seconds_per_pose.push_back(ready[s]->seconds_per_pose);
  const std::vector<size_t> sizes = shard_sizes(requests.size(), seconds_per_pose);
  std::vector<std::vector<GenerationRequest>> parts(shards);
  for (size_t s = 0, begin = 0; s < shards; begin += sizes[s], ++s)
    parts[s].assign(requests.begin() + begin, requests.begin() + begin + sizes[s]);
  std::vector<Attempt> attempts(shards);
  // Each shard runs on its own worker, so each thread updates only its worker's speed.
  const auto shard = [&](size_t s) {
    auto start = std::chrono::steady_clock::now();
    auto images = adapt_and_generate_on(*ready[s], parts[s], attempts[s]);
    if (images.ok()) {
      const auto adapting = attempts[s].stages.find("adapt_scene");
      const double seconds = lap_seconds(&start) - (adapting != attempts[s].stages.end() ? adapting->second : 0.0);
      const double measured = seconds / static_cast<double>(parts[s].size());
      double& smoothed = ready[s]->seconds_per_pose;
      smoothed = smoothed > 0 ? 0.5 * (smoothed + measured) : measured;
    }
    return images;
  };
  std::vector<std::future<absl::StatusOr<std::vector<at::Tensor>>>> calls;
  for (size_t s = 1; s < shards; ++s) calls.push_back(std::async(std::launch::async, shard, s));
  std::vector<absl::StatusOr<std::vector<at::Tensor>>> answers;
  answers.push_back(shard(0));
  for (auto& call : calls) answers.push_back(call.get());

  std::vector<at::Tensor> images;
  for (size_t s = 0; s < shards; ++s) {
    if (!answers[s].ok()) {
      const absl::Status st = answers[s].status();
      if (stopping()) return stopped_status();
      if (!another_worker_may_help(st)) return st;
      ready[s]->last_error = std::string(st.message());
      mark_failed(*ready[s]);
      attempts[s] = Attempt();
      answers[s] = generate_with_failover(parts[s], attempts[s]);
      if (!answers[s].ok()) return answers[s].status();
    }
    attempt.add(attempts[s]);
    images.insert(images.end(), answers[s]->begin(), answers[s]->end());
  }
  attempt.counters["workers"] = static_cast<double>(shards);
  for (size_t s = 0; s < shards; ++s)
    attempt.counters[absl::StrCat("shard ", ready[s]->address)] += static_cast<double>(sizes[s]);
  return images;
}

absl::StatusOr<std::vector<at::Tensor>> RemoteGenerator::generate_with_failover(
    const std::vector<GenerationRequest>& requests, Attempt& attempt) {
  auto backoff = options_.backoff_initial;
  const absl::Status stopped = stopped_status();
  for (int round = 0; round < options_.max_rounds; ++round) {
    for (size_t k = 0; k < workers_.size(); ++k) {
      if (stopping()) return stopped;
      Worker& w = *workers_[(next_ + k) % workers_.size()];
      // A worker adapting in the background is not to be called beside that call.
      if (adapting_.count(&w) || !usable(w)) continue;
      Attempt tried;  // of this worker only: a failed one's notes and seconds are not this call's
      auto images = adapt_and_generate_on(w, requests, tried);
      if (images.ok()) {
        next_ = (next_ + k + 1) % workers_.size();
        attempt = std::move(tried);
        return images;
      }
      const absl::Status st = images.status();
      if (stopping()) return stopped;
      if (!another_worker_may_help(st)) return st;
      w.last_error = std::string(st.message());
      mark_failed(w);
    }
    if (round + 1 < options_.max_rounds) {
      if (stopping()) return stopped;
      std::this_thread::sleep_for(backoff);
      backoff = std::min(backoff * 2, options_.backoff_max);
      // After a full failed pass, give every worker another chance at the next probe.
      for (auto& w : workers_) w->failed_at = {};
    }
  }
  std::vector<std::string> reasons;
  for (const auto& w : workers_)
    reasons.push_back(absl::StrCat(w->address, ": ", w->last_error.empty() ? "not reached" : w->last_error));
  return absl::UnavailableError(absl::StrCat("no diffusion worker answered after ", options_.max_rounds, " rounds (",
                                             absl::StrJoin(reasons, "; "), ")"));
}

}  // namespace gaps
