#include "server/trainer_service.h"

#include <unistd.h>

#include <cstdio>

#include <algorithm>
#include <chrono>
#include <fstream>
#include <iostream>
#include <optional>
#include <random>

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_replace.h"
#include "common/io_util.h"
#include "common/limits.h"
#include "common/status_macros.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/model/render.h"
#include "gs_trainer/pipeline.h"
#include "gs_trainer/scene/camera_path.h"
#include "rpc/codec.h"
#include "rpc/security.h"
#include "server/job_config.h"
#include "server/scene_upload.h"

namespace gaps {
namespace {

// One request of a kind that the trainer serves a bounded number of at once (kMaxConcurrentRenders,
// kMaxWatchStreams): taken() is false beyond the limit, and the slot is given back when it goes.
class InFlightSlot {
 public:
  InFlightSlot(std::atomic<int>& count, int limit) : count_(count), taken_(count.fetch_add(1) < limit) {
    if (!taken_) count_.fetch_sub(1);
  }
  ~InFlightSlot() {
    if (taken_) count_.fetch_sub(1);
  }
  InFlightSlot(const InFlightSlot&) = delete;
  InFlightSlot& operator=(const InFlightSlot&) = delete;
  bool taken() const { return taken_; }

 private:
  std::atomic<int>& count_;
  bool taken_;
};

grpc::Status busy(const std::string& what, int limit) {
  return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED, absl::StrCat("the trainer serves ", limit, " ", what,
                                                                         " at once and all are taken; retry in a "
                                                                         "few seconds"));
}

namespace fs = std::filesystem;

double now_seconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

std::string new_job_id() {
  static std::mt19937_64 rng(std::random_device{}());
  static std::mutex mutex;
  std::lock_guard<std::mutex> lock(mutex);
  return absl::StrFormat("job-%012x", rng() & 0xffffffffffffULL);
}

std::string default_replica_id() {
  char host[256] = {0};
  if (gethostname(host, sizeof(host) - 1) != 0) std::snprintf(host, sizeof(host), "trainer");
  static std::mt19937_64 rng(std::random_device{}());
  return absl::StrFormat("%s-%d-%06x", host, static_cast<int>(getpid()), rng() & 0xffffff);
}

// Upload folders not touched for `age`: what a trainer that died while receiving them left behind.
void remove_stale_uploads(const fs::path& uploads, std::chrono::hours age) {
  std::error_code ec;
  const auto now = fs::file_time_type::clock::now();
  for (const auto& entry : fs::directory_iterator(uploads, ec)) {
    const auto written = entry.last_write_time(ec);
    if (!ec && now - written > age) remove_tree(entry.path());
  }
}

absl::Status move_folder(const fs::path& from, const fs::path& to) {
  std::error_code ec;
  fs::create_directories(to.parent_path(), ec);
  if (!ec) fs::rename(from, to, ec);
  if (ec) return absl::ResourceExhaustedError(absl::StrCat("the trainer could not store the upload: ", ec.message()));
  return absl::OkStatus();
}

bool terminal(v1::JobState s) { return s == v1::SUCCEEDED || s == v1::FAILED || s == v1::CANCELLED; }

v1::JobEvent event_for(const std::string& job_id) {
  v1::JobEvent e;
  e.set_job_id(job_id);
  e.set_time(now_seconds());
  return e;
}

// The event that ends a job's history; watchers stop at it.
v1::JobEvent closing_event(const v1::JobStatus& status) {
  v1::JobEvent e = event_for(status.job_id());
  if (status.state() == v1::SUCCEEDED)
    *e.mutable_finished() = status;
  else if (status.state() == v1::CANCELLED)
    *e.mutable_cancelled() = status;
  else
    *e.mutable_failed() = status;
  return e;
}

// What clients get for a job whose end the store refused: the store's code and message, and that the
// stored state is stale.
absl::Status unrecorded_end_error(const v1::JobStatus& status, const absl::Status& store_error) {
  return absl::Status(store_error.code(),
                      absl::StrCat("job ", status.job_id(), " ended (", v1::JobState_Name(status.state()),
                                   ") but the trainer could not record that: ", store_error.message(),
                                   "; it keeps trying, and a trainer restarted on its data folder runs the job again"));
}

std::string event_name(const v1::JobEvent& event) {
  const auto* field = v1::JobEvent::descriptor()->FindFieldByNumber(event.event_case());
  return field ? field->name() : "empty";
}

v1::PhaseEvent phase_event(const nlohmann::json& entry) {
  v1::PhaseEvent p;
  p.set_phase(entry.value("phase", -1));
  p.set_iteration(entry.value("iteration", 0));
  if (entry.contains("selection")) p.set_selected(static_cast<int>(entry["selection"].size()));
  p.set_admitted(entry.value("admitted", 0));
  p.set_skipped(entry.value("skipped", false));
  p.set_skip_reason(entry.value("skip_reason", std::string()));
  p.set_details_json(entry.dump());
  return p;
}

std::vector<JobStore::Artifact> list_artifacts(const fs::path& out_dir) {
  std::vector<JobStore::Artifact> out;
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(out_dir, ec); !ec && it != fs::recursive_directory_iterator();
       it.increment(ec)) {
    if (!it->is_regular_file()) continue;
    out.push_back({fs::relative(it->path(), out_dir).generic_string(), static_cast<int64_t>(it->file_size())});
  }
  std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) { return a.path < b.path; });
  return out;
}

}  // namespace

TrainerService::TrainerService(TrainerServiceOptions options, std::unique_ptr<DataDirLock> lock,
                               std::unique_ptr<JobStore> store)
    : options_(std::move(options)), lock_(std::move(lock)), store_(std::move(store)) {}

TrainerService::~TrainerService() { shutdown(); }

absl::StatusOr<std::unique_ptr<TrainerService>> TrainerService::create(TrainerServiceOptions options) {
  if (options.data_dir.empty()) return absl::InvalidArgumentError("the trainer needs a data folder");
  if (options.concurrency < 1) return absl::InvalidArgumentError("concurrency must be at least 1");
  if (!(options.lease_seconds > 0)) return absl::InvalidArgumentError("the lease must last longer than 0 seconds");
  if (options.replica_id.empty()) options.replica_id = default_replica_id();
  std::error_code ec;
  fs::create_directories(options.data_dir / "jobs", ec);
  if (ec) return absl::PermissionDeniedError(absl::StrCat(options.data_dir.string(), ": ", ec.message()));
  const bool shared = !options.job_store.empty();
  GAPS_ASSIGN_OR_RETURN(std::unique_ptr<DataDirLock> lock, DataDirLock::acquire(options.data_dir, shared));
  GAPS_ASSIGN_OR_RETURN(std::unique_ptr<JobStore> store, JobStore::open_location(options.job_store, options.data_dir));
  return std::unique_ptr<TrainerService>(new TrainerService(std::move(options), std::move(lock), std::move(store)));
}

fs::path TrainerService::job_dir(const std::string& job_id) const { return options_.data_dir / "jobs" / job_id; }

absl::Status TrainerService::start() {
  if (store_->shared()) {
    // Other replicas may be receiving uploads right now: only what no upload can still be using goes.
    remove_stale_uploads(options_.data_dir / "uploads", std::chrono::hours(24));
  } else {
    // This process holds the folder alone: uploads being received when an earlier one stopped never
    // became jobs, and the leases of jobs it ran died with it (they are taken over at once).
    remove_tree(options_.data_dir / "uploads");
    GAPS_RETURN_IF_ERROR(store_->expire_leases());
  }
  for (int i = 0; i < options_.concurrency; ++i) threads_.emplace_back([this] { job_loop(); });
  threads_.emplace_back([this] { retry_loop(); });
  threads_.emplace_back([this] { heartbeat_loop(); });
  return absl::OkStatus();
}

void TrainerService::run_claimed(v1::JobStatus job) {
  if (job.state() != v1::RUNNING) return run_job(std::move(job));
  job.set_resumes(job.resumes() + 1);
  if (!job.stopped_cleanly()) job.set_crashes(job.crashes() + 1);
  job.set_stopped_cleanly(false);
  if (job.crashes() >= options_.max_crashes) {
    job.set_state(v1::FAILED);
    job.set_finished_at(now_seconds());
    job.set_error(absl::StrCat("the trainer died ", job.crashes(),
                               " times while running this job (last seen at iteration ", job.iteration(),
                               "); it is not run again, as it may be what killed the trainer. The "
                               "trainer's log has the cause; resubmit the job to try again"));
    write_log_line(STDERR_FILENO, absl::StrCat("gaps-trainer: job ", job.job_id(), " quarantined: ", job.error()));
    end_job({job, list_artifacts(job_dir(job.job_id()) / "out"), absl::OkStatus()});
    return;
  }
  v1::JobEvent e = event_for(job.job_id());
  e.set_log(absl::StrCat("trainer ", options_.replica_id,
                         " takes the job over: it resumes from its last checkpoint, or from the start without one "
                         "(resume ",
                         job.resumes(), job.crashes() > 0 ? absl::StrCat(", after ", job.crashes(), " crash(es)") : "",
                         ")"));
  publish(e);
  run_job(std::move(job));
}

void TrainerService::shutdown() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (stopping_) return;
    stopping_ = true;
  }
  stop_training_ = true;
  queue_changed_.notify_all();
  events_changed_.notify_all();
  stopping_changed_.notify_all();
  for (auto& t : threads_) t.join();
  threads_.clear();
  retry_unrecorded_ends();
  std::lock_guard<std::mutex> lock(mutex_);
  for (const auto& [job_id, end] : unrecorded_ends_)
    write_log_line(STDERR_FILENO,
                   absl::StrCat("gaps-trainer: job ", job_id, ": its end was never recorded in the job store (",
                                end.error.message(), ")"));
}

void TrainerService::publish(v1::JobEvent event) {
  if (const absl::StatusOr<int64_t> seq = store_->append_event(event); !seq.ok())
    log_store_error(event.job_id(), absl::StrCat("its ", event_name(event), " event"), seq.status());
  events_changed_.notify_all();
}

void TrainerService::log_store_error(const std::string& job_id, const std::string& what,
                                     const absl::Status& error) const {
  write_log_line(STDERR_FILENO, absl::StrCat("gaps-trainer: job ", job_id, ": the job store did not record ", what,
                                             ": ", error.ToString()));
}

void TrainerService::job_loop() {
  std::string last_error;
  while (true) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (stopping_) return;
    }
    absl::StatusOr<std::optional<v1::JobStatus>> claimed = store_->claim(options_.replica_id, options_.lease_seconds);
    if (claimed.ok() && claimed->has_value()) {
      last_error.clear();
      run_claimed(std::move(**claimed));
      continue;
    }
    if (!claimed.ok() && claimed.status().ToString() != last_error) {  // once per distinct failure
      last_error = claimed.status().ToString();
      write_log_line(STDERR_FILENO,
                     absl::StrCat("gaps-trainer: cannot take jobs from the job store (trying again): ", last_error));
    }
    std::unique_lock<std::mutex> lock(mutex_);
    queue_changed_.wait_for(lock, options_.claim_interval);
  }
}

void TrainerService::run_job(v1::JobStatus status) {
  const std::string job_id = status.job_id();
  const auto flags = std::make_shared<RunFlags>();
  {
    std::lock_guard<std::mutex> lock(mutex_);
    running_[job_id] = flags;
  }
  const auto done = [&] {
    std::lock_guard<std::mutex> lock(mutex_);
    running_.erase(job_id);
  };
  status.set_state(v1::RUNNING);
  status.set_started_at(now_seconds());
  status.set_runner(options_.replica_id);
  // The job runs anyway: a store that recovers records its end, and one that does not lets the lease lapse,
  // so that the job is taken over.
  if (absl::Status st = store_->update(status, options_.replica_id); !st.ok()) {
    if (st.code() == absl::StatusCode::kAborted) return done();
    log_store_error(job_id, "that it started", st);
  }
  v1::JobEvent started = event_for(job_id);
  started.set_state_changed(v1::RUNNING);
  publish(started);

  v1::JobStatus final_status = train(status, *flags);
  if (flags->lease_lost) {
    write_log_line(STDERR_FILENO, absl::StrCat("gaps-trainer: job ", job_id,
                                               ": another trainer took it over; this run stops unrecorded"));
    return done();
  }
  if (!terminal(final_status.state())) {  // interrupted by shutdown: RUNNING for the next process or replica
    final_status.set_stopped_cleanly(true);
    if (absl::Status st = store_->update(final_status, options_.replica_id); !st.ok())
      log_store_error(job_id, "its progress before the shutdown (it resumes from its last recorded checkpoint)", st);
    if (absl::Status st = store_->release(job_id, options_.replica_id); !st.ok())
      log_store_error(job_id, "the release of its lease (it is taken over when the lease expires)", st);
    return done();
  }
  final_status.set_finished_at(now_seconds());
  const auto artifacts = list_artifacts(job_dir(job_id) / "out");
  for (const auto& a : artifacts) final_status.add_artifacts(a.path);
  end_job({final_status, artifacts, absl::OkStatus()});
  done();
}

void TrainerService::heartbeat_loop() {
  const auto interval = std::chrono::duration<double>(options_.lease_seconds / 4);
  std::unique_lock<std::mutex> lock(mutex_);
  while (!stopping_changed_.wait_for(lock, interval, [this] { return stopping_; })) {
    const auto running = running_;
    lock.unlock();
    for (const auto& [job_id, flags] : running) {
      const absl::StatusOr<bool> renewed = store_->renew(job_id, options_.replica_id, options_.lease_seconds);
      if (renewed.ok()) {
        if (*renewed) flags->cancelled = true;
      } else if (renewed.status().code() == absl::StatusCode::kAborted) {
        flags->lease_lost = true;
      } else {
        log_store_error(job_id, "the renewal of its lease", renewed.status());
      }
    }
    lock.lock();
  }
}

void TrainerService::end_job(UnrecordedEnd end) {
  const std::string job_id = end.status.job_id();
  const absl::Status st = record_end(end);
  if (!st.ok()) {
    log_store_error(job_id,
                    absl::StrCat("its end (", v1::JobState_Name(end.status.state()), "), retrying every ",
                                 options_.store_retry_interval.count(), " ms"),
                    st);
    end.error = unrecorded_end_error(end.status, st);
  }
  if (!st.ok() && st.code() != absl::StatusCode::kAborted) {
    std::lock_guard<std::mutex> lock(mutex_);
    unrecorded_ends_[job_id] = std::move(end);
  }
  events_changed_.notify_all();  // watchers get the closing event or the refusal
}

absl::Status TrainerService::record_end(const UnrecordedEnd& end) {
  v1::JobEvent closing = closing_event(end.status);
  // Only while this process holds the lease: a job another replica took over ends there, once.
  return store_->end_job(end.status, end.artifacts, closing, options_.replica_id);
}

void TrainerService::retry_loop() {
  std::unique_lock<std::mutex> lock(mutex_);
  while (!stopping_changed_.wait_for(lock, options_.store_retry_interval, [this] { return stopping_; })) {
    if (unrecorded_ends_.empty()) continue;
    lock.unlock();
    retry_unrecorded_ends();
    lock.lock();
  }
}

void TrainerService::retry_unrecorded_ends() {
  std::vector<UnrecordedEnd> ends;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& [job_id, end] : unrecorded_ends_) ends.push_back(end);
  }
  for (const UnrecordedEnd& end : ends) {
    const absl::Status st = record_end(end);
    std::lock_guard<std::mutex> lock(mutex_);
    if (st.ok() || st.code() == absl::StatusCode::kAborted) {
      unrecorded_ends_.erase(end.status.job_id());
      write_log_line(STDERR_FILENO, absl::StrCat("gaps-trainer: job ", end.status.job_id(), ": ",
                                                 st.ok() ? "its end is recorded now"
                                                         : "another trainer took it over; its end here is dropped"));
    } else {
      unrecorded_ends_[end.status.job_id()].error = unrecorded_end_error(end.status, st);
    }
  }
  events_changed_.notify_all();
}

absl::Status TrainerService::unrecorded_end(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = unrecorded_ends_.find(job_id);
  return it == unrecorded_ends_.end() ? absl::OkStatus() : it->second.error;
}

void TrainerService::note_unrecorded_end(v1::JobStatus& status) {
  if (absl::Status st = unrecorded_end(status.job_id()); !st.ok()) status.set_error(std::string(st.message()));
}

v1::JobStatus TrainerService::train(v1::JobStatus status, const RunFlags& flags) {
  const std::string job_id = status.job_id();
  const fs::path dir = job_dir(job_id);
  const auto fail = [&](const absl::Status& error) {
    status.set_state(v1::FAILED);
    // Where the trainer keeps its data is its own business: the client learns what failed and why.
    status.set_error(absl::StrReplaceAll(error.message(), {{options_.data_dir.string() + "/", ""}}));
    return status;
  };
  absl::StatusOr<v1::JobSpec> spec = store_->spec(job_id);
  if (!spec.ok()) return fail(spec.status());
  absl::StatusOr<RunOptions> options =
      run_options_from_proto(spec->config(), spec->has_points(), dir / "scene" / "points.ply", options_.device);
  if (!options.ok()) return fail(options.status());
  RunOptions& o = *options;
  o.scene_dir = dir / "scene";
  if (std::error_code ec; fs::is_directory(o.scene_dir / kLargerViewsFolder, ec))
    o.larger_views_dir = o.scene_dir / kLargerViewsFolder;
  o.out_dir = dir / "out";
  o.init_cache_dir = options_.data_dir / "init_cache";
  o.lpips_weights = options_.lpips_weights;
  const std::function<bool()> should_stop = [&] {
    return flags.cancelled.load() || flags.lease_lost.load() || stop_training_.load();
  };
  std::unique_ptr<RemoteGenerator> generator;
  if (o.variant != Variant::kVanilla) {
    if (options_.workers.addresses.empty())
      return fail(absl::FailedPreconditionError(absl::StrCat(
          "variant ", variant_name(o.variant), " needs diffusion workers (start the trainer with --workers)")));
    WorkerPoolOptions pool = options_.workers;
    pool.addresses = resolve_worker_addresses(pool.addresses);  // per job: workers come and go
    pool.scene_id = job_id;
    // A cancel or a shutdown does not wait for a worker that never answers: the call is cancelled.
    pool.should_stop = should_stop;
    absl::StatusOr<std::unique_ptr<RemoteGenerator>> made = RemoteGenerator::create(pool);
    if (!made.ok()) return fail(made.status());
    generator = std::move(*made);
    o.generator = generator.get();
  }
  o.checkpoint_dir = dir / "checkpoint";
  o.checkpoint_every_seconds = options_.checkpoint_seconds;
  o.on_checkpoint = [&](int iteration) {
    v1::JobEvent e = event_for(job_id);
    e.set_checkpoint_written(iteration);
    publish(e);
  };
  o.should_stop = should_stop;
  o.on_phase = [&](const std::string& what, const nlohmann::json& entry) {
    v1::JobEvent e = event_for(job_id);
    if (what == "started")
      *e.mutable_phase_started() = phase_event(entry);
    else
      *e.mutable_phase_finished() = phase_event(entry);
    publish(e);
    if (what == "skipped") {
      v1::JobEvent warning = event_for(job_id);
      warning.set_log(absl::StrCat("warning: diffusion phase ", entry.value("phase", -1),
                                   " skipped, training continues: ", entry.value("skip_reason", std::string())));
      publish(warning);
    }
  };
  const auto on_progress = [&](const TrainProgress& p) {
    v1::JobEvent e = event_for(job_id);
    v1::Progress* q = e.mutable_progress();
    q->set_iteration(p.iteration);
    q->set_iterations(p.iterations);
    q->set_loss(p.loss);
    q->set_num_gaussians(p.num_gaussians);
    q->set_iterations_per_second(p.iterations_per_second);
    q->set_elapsed_seconds(p.elapsed_seconds);
    publish(e);
    status.set_iteration(p.iteration);
    status.set_iterations(p.iterations);
    status.set_num_gaussians(p.num_gaussians);
    if (absl::Status st = store_->update(status, options_.replica_id);
        !st.ok() && st.code() != absl::StatusCode::kAborted)
      log_store_error(job_id, absl::StrCat("its progress at iteration ", p.iteration), st);
  };
  const auto log = [&](const std::string& line) {
    v1::JobEvent e = event_for(job_id);
    e.set_log(line);
    publish(e);
  };
  absl::StatusOr<RunResult> result = run_pipeline(o, on_progress, log);
  if (result.ok()) {
    status.set_state(v1::SUCCEEDED);
    status.set_psnr(result->metrics.psnr);
    status.set_ssim(result->metrics.ssim);
    if (result->metrics.lpips) status.set_lpips(*result->metrics.lpips);
    status.set_num_gaussians(result->num_gaussians);
    status.set_phases(result->phases);
    status.set_phases_skipped(result->phases_skipped);
    status.set_degraded(result->degraded());
    return status;
  }
  if (result.status().code() == absl::StatusCode::kCancelled) {
    if (flags.cancelled) {
      status.set_state(v1::CANCELLED);
      status.set_error(absl::StrCat("cancelled: ", result.status().message()));
    } else {
      status.set_state(v1::RUNNING);  // shutdown: left for the next process
    }
    return status;
  }
  return fail(result.status());
}

grpc::Status TrainerService::SubmitJob(grpc::ServerContext* context, grpc::ServerReader<v1::SubmitJobRequest>* reader,
                                       v1::SubmitJobResponse* response) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  // The upload streams into a staging folder and becomes the job's scene only once checked whole, so a
  // trainer that dies mid-upload leaves no half-written job behind (start() clears what it left, with a
  // shared store once it is a day old).
  const std::string job_id = new_job_id();
  const fs::path staging = options_.data_dir / "uploads" / job_id;
  const fs::path dir = job_dir(job_id);
  absl::StatusOr<SceneUpload> received = receive_upload(
      [reader](v1::SubmitJobRequest* part) { return reader->Read(part); }, options_.max_upload_bytes, staging);
  absl::Status stored_scene = received.ok() ? write_uploaded_scene(*received) : received.status();
  if (stored_scene.ok()) stored_scene = move_folder(staging, dir / "scene");
  if (!stored_scene.ok()) {
    remove_tree(staging);
    remove_tree(dir);
    return rpc::to_grpc(stored_scene);
  }
  const SceneUpload& upload = *received;
  v1::JobStatus status;
  status.set_job_id(job_id);
  status.set_name(upload.spec.name());
  status.set_state(v1::QUEUED);
  status.set_submitted_at(now_seconds());
  absl::StatusOr<RunOptions> o =
      run_options_from_proto(upload.spec.config(), upload.spec.has_points(), "", options_.device);
  status.set_iterations(o.ok() ? o->config.iterations : 0);
  if (auto st = store_->insert(status, upload.spec); !st.ok()) {
    remove_tree(dir);
    return rpc::to_grpc(st);
  }
  v1::JobEvent queued = event_for(job_id);
  queued.set_state_changed(v1::QUEUED);
  publish(queued);
  queue_changed_.notify_one();  // an idle job thread of this process claims it at once
  response->set_job_id(job_id);
  return grpc::Status::OK;
}

grpc::Status TrainerService::WatchJob(grpc::ServerContext* context, const v1::WatchJobRequest* request,
                                      grpc::ServerWriter<v1::JobEvent>* writer) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  if (auto job = store_->get(request->job_id()); !job.ok()) return rpc::to_grpc(job.status());
  const InFlightSlot slot(watch_streams_, kMaxWatchStreams);
  if (!slot.taken()) return busy("WatchJob streams", kMaxWatchStreams);
  int64_t next = std::max<int64_t>(0, request->from_sequence());
  while (!context->IsCancelled()) {
    absl::StatusOr<std::vector<v1::JobEvent>> events = store_->events(request->job_id(), next);
    if (!events.ok()) return rpc::to_grpc(events.status());
    for (const auto& e : *events) {
      if (!writer->Write(e)) return grpc::Status(grpc::StatusCode::CANCELLED, "watcher went away");
      next = e.sequence() + 1;
      if (e.has_finished() || e.has_failed() || e.has_cancelled()) return grpc::Status::OK;
    }
    // Its end will not be in the events until the store takes it.
    if (auto st = unrecorded_end(request->job_id()); !st.ok()) return rpc::to_grpc(st);
    std::unique_lock<std::mutex> lock(mutex_);
    if (stopping_) return grpc::Status(grpc::StatusCode::UNAVAILABLE, "trainer shutting down");
    events_changed_.wait_for(lock, std::chrono::milliseconds(250));
  }
  return grpc::Status(grpc::StatusCode::CANCELLED, "watcher went away");
}

grpc::Status TrainerService::GetJob(grpc::ServerContext* context, const v1::GetJobRequest* request,
                                    v1::JobStatus* response) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  absl::StatusOr<v1::JobStatus> job = store_->get(request->job_id());
  if (!job.ok()) return rpc::to_grpc(job.status());
  *response = *job;
  note_unrecorded_end(*response);
  return grpc::Status::OK;
}

grpc::Status TrainerService::ListJobs(grpc::ServerContext* context, const v1::ListJobsRequest*,
                                      v1::ListJobsResponse* response) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  absl::StatusOr<std::vector<v1::JobStatus>> jobs = store_->list();
  if (!jobs.ok()) return rpc::to_grpc(jobs.status());
  for (auto& j : *jobs) {
    note_unrecorded_end(j);
    *response->add_jobs() = std::move(j);
  }
  return grpc::Status::OK;
}

grpc::Status TrainerService::CancelJob(grpc::ServerContext* context, const v1::CancelJobRequest* request,
                                       v1::JobStatus* response) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  absl::StatusOr<v1::JobStatus> job = store_->get(request->job_id());
  if (!job.ok()) return rpc::to_grpc(job.status());
  if (terminal(job->state()))
    return grpc::Status(
        grpc::StatusCode::FAILED_PRECONDITION,
        absl::StrCat("job ", request->job_id(), " already ended (", v1::JobState_Name(job->state()), ")"));
  if (auto st = unrecorded_end(request->job_id()); !st.ok())
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION, std::string(st.message()));
  v1::JobStatus cancelled = *job;
  cancelled.set_state(v1::CANCELLED);
  cancelled.set_error("cancelled before it started");
  cancelled.set_finished_at(now_seconds());
  v1::JobEvent closing = closing_event(cancelled);
  // A job nobody runs ends here; a running one (here or on another replica) gets the request and stops at
  // its next iteration, in its own thread.
  const absl::StatusOr<bool> ended = store_->cancel(cancelled, closing);
  if (!ended.ok()) {
    if (ended.status().code() == absl::StatusCode::kFailedPrecondition) return rpc::to_grpc(ended.status());
    return rpc::to_grpc(absl::Status(
        ended.status().code(), absl::StrCat("job ", request->job_id(), " stays queued: ", ended.status().message())));
  }
  if (*ended) {
    events_changed_.notify_all();
    *response = cancelled;
    return grpc::Status::OK;
  }
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (auto it = running_.find(request->job_id()); it != running_.end()) it->second->cancelled = true;
  }
  *response = *job;
  return grpc::Status::OK;
}

grpc::Status TrainerService::FetchArtifacts(grpc::ServerContext* context, const v1::FetchArtifactsRequest* request,
                                            grpc::ServerWriter<v1::ArtifactChunk>* writer) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  absl::StatusOr<v1::JobStatus> job = store_->get(request->job_id());
  if (!job.ok()) return rpc::to_grpc(job.status());
  if (!terminal(job->state()))
    return grpc::Status(grpc::StatusCode::FAILED_PRECONDITION,
                        absl::StrCat("job ", request->job_id(), " is ", v1::JobState_Name(job->state()),
                                     "; artifacts are served once it ends"));
  absl::StatusOr<std::vector<JobStore::Artifact>> artifacts = store_->artifacts(request->job_id());
  if (!artifacts.ok()) return rpc::to_grpc(artifacts.status());
  const fs::path out = job_dir(request->job_id()) / "out";
  for (const auto& a : *artifacts) {
    std::ifstream file(out / a.path, std::ios::binary);
    if (!file)
      return grpc::Status(grpc::StatusCode::DATA_LOSS, absl::StrCat("artifact ", a.path, " is missing on disk"));
    std::string buffer(rpc::kChunkBytes, '\0');
    do {
      file.read(buffer.data(), buffer.size());
      v1::ArtifactChunk chunk;
      chunk.set_path(a.path);
      chunk.set_data(buffer.data(), file.gcount());
      chunk.set_last(file.eof());
      if (!writer->Write(chunk)) return grpc::Status(grpc::StatusCode::CANCELLED, "reader went away");
    } while (!file.eof());
  }
  return grpc::Status::OK;
}

absl::StatusOr<TrainerService::FinishedModel> TrainerService::finished_model(const std::string& job_id) {
  GAPS_ASSIGN_OR_RETURN(const v1::JobStatus job, store_->get(job_id));
  if (job.state() != v1::SUCCEEDED)
    return absl::FailedPreconditionError(absl::StrCat("job ", job_id, " has no finished model"));
  GAPS_ASSIGN_OR_RETURN(const v1::JobSpec spec, store_->spec(job_id));
  FinishedModel out;
  GAPS_ASSIGN_OR_RETURN(out.options, run_options_from_proto(spec.config(), spec.has_points(), "", ""));
  out.options.scene_dir = job_dir(job_id) / "scene";
  std::lock_guard<std::mutex> lock(model_mutex_);
  if (cached_job_ != job_id || !cached_model_) {
    GAPS_ASSIGN_OR_RETURN(const GaussianModel model, load_gaussians_ply(job_dir(job_id) / "out" / "point_cloud.ply"));
    cached_model_ = std::make_shared<const GaussianModel>(model.to(at::Device(options_.device)));
    cached_job_ = job_id;
  }
  out.model = cached_model_;
  return out;
}

grpc::Status TrainerService::RenderView(grpc::ServerContext* context, const v1::RenderViewRequest* request,
                                        v1::RenderViewResponse* response) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  // Before anything is decoded or allocated: a render's memory grows with its pixels.
  if (auto st = check_render_size("camera", request->camera().width(), request->camera().height()); !st.ok())
    return rpc::to_grpc(st);
  absl::StatusOr<Camera> camera = rpc::decode_camera(request->camera(), "camera");
  if (!camera.ok()) return rpc::to_grpc(camera.status());
  const InFlightSlot slot(renders_in_flight_, kMaxConcurrentRenders);
  if (!slot.taken()) return busy("renders", kMaxConcurrentRenders);
  absl::StatusOr<FinishedModel> finished = finished_model(request->job_id());
  if (!finished.ok()) return rpc::to_grpc(finished.status());
  at::AutoGradMode no_grad(false);
  const GaussianModel& model = *finished->model;
  RenderOptions render_options;
  render_options.background = at::full({3}, finished->options.config.background, model.means.options());
  const at::Tensor rgb = render(model, *camera, render_options).rgb.clamp(0, 1).cpu();
  return rpc::to_grpc(rpc::encode_png(rgb, response->mutable_image()));
}

grpc::Status TrainerService::GetJobCameras(grpc::ServerContext* context, const v1::GetJobCamerasRequest* request,
                                           v1::JobCameras* response) {
  if (auto st = rpc::check_token(*context, options_.token); !st.ok()) return st;
  absl::StatusOr<FinishedModel> finished = finished_model(request->job_id());
  if (!finished.ok()) return rpc::to_grpc(finished.status());
  const RunOptions& o = finished->options;
  SceneLoadOptions load;
  load.resolution = o.resolution;
  absl::StatusOr<Scene> scene = load_scene(o.scene_dir, load);
  if (!scene.ok()) return rpc::to_grpc(scene.status());
  absl::StatusOr<Split> split = benchmark_split(static_cast<int>(scene->cameras.size()), o.views);
  if (!split.ok()) return rpc::to_grpc(split.status());
  std::vector<Camera> train;
  for (int i : split->train) {
    train.push_back(scene->cameras[i]);
    rpc::encode_camera(scene->cameras[i], response->add_train());
  }
  for (int i : split->test) rpc::encode_camera(scene->cameras[i], response->add_test());
  absl::StatusOr<std::pair<double, double>> bounds = path_depth_bounds(train, finished->model->means);
  if (!bounds.ok()) return rpc::to_grpc(bounds.status());
  response->set_background(o.config.background);
  response->set_near(bounds->first);
  response->set_far(bounds->second);
  return grpc::Status::OK;
}

}  // namespace gaps
