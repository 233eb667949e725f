#include "server/job_runner.h"

#include <unistd.h>

#include <chrono>
#include <functional>
#include <optional>
#include <utility>

#include <ATen/Parallel.h>
#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"
#include "common/io_util.h"
#include "server/artifacts.h"
#include "server/job_config.h"
#include "server/job_events.h"
#include "server/scene_upload.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

// What clients get for a job whose end the store refused: the store's code and message, and that the
// stored state is stale.
absl::Status unrecorded_end_error(const v1::JobStatus& status, const absl::Status& store_error) {
  return absl::Status(store_error.code(),
                      absl::StrCat("job ", status.job_id(), " ended (", v1::JobState_Name(status.state()),
                                   ") but the trainer could not record that: ", store_error.message(),
                                   "; it keeps trying, and a trainer restarted on its data folder runs the job again"));
}

v1::JobStatus failed(v1::JobStatus status, const absl::Status& error, const fs::path& data_dir) {
  status.set_state(v1::FAILED);
  // Where the trainer keeps its data is its own business: the client learns what failed and why.
  status.set_error(absl::StrReplaceAll(error.message(), {{data_dir.string() + "/", ""}}));
  return status;
}

// The status a run leaves: its outcome, or RUNNING when a shutdown (not a cancel) stopped it, for the next
// process to go on with.
v1::JobStatus run_outcome(v1::JobStatus status, const absl::StatusOr<RunResult>& result, bool cancelled,
                          const fs::path& data_dir) {
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
  if (result.status().code() != absl::StatusCode::kCancelled)
    return failed(std::move(status), result.status(), data_dir);
  if (cancelled) {
    status.set_state(v1::CANCELLED);
    status.set_error(absl::StrCat("cancelled: ", result.status().message()));
  } else {
    status.set_state(v1::RUNNING);
  }
  return status;
}

}  // namespace

void JobRunner::start() {
  const int cpu_threads = cpu_threads_per_job();
  for (int i = 0; i < options_.concurrency; ++i) threads_.emplace_back([this, cpu_threads] { job_loop(cpu_threads); });
  threads_.emplace_back([this] { retry_loop(); });
  threads_.emplace_back([this] { heartbeat_loop(); });
}

void JobRunner::shutdown() {
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

void JobRunner::publish(v1::JobEvent event) {
  // The trainer's own log says when a job arrives and starts; its end is logged by end_job.
  if (event.has_state_changed())
    write_log_line(STDERR_FILENO,
                   absl::StrCat("gaps-trainer: job ", event.job_id(), ": ", v1::JobState_Name(event.state_changed())));
  if (const absl::StatusOr<int64_t> seq = store_.append_event(event); !seq.ok())
    log_store_error(event.job_id(), absl::StrCat("its ", event_name(event), " event"), seq.status());
  events_changed_.notify_all();
}

void JobRunner::job_queued() { queue_changed_.notify_one(); }

void JobRunner::job_ended() { events_changed_.notify_all(); }

void JobRunner::cancel_if_running(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mutex_);
  if (auto it = running_.find(job_id); it != running_.end()) it->second->cancelled = true;
}

bool JobRunner::wait_for_events(std::chrono::milliseconds timeout) {
  std::unique_lock<std::mutex> lock(mutex_);
  if (stopping_) return false;
  events_changed_.wait_for(lock, timeout);
  return true;
}

void JobRunner::log_store_error(const std::string& job_id, const std::string& what, const absl::Status& error) const {
  write_log_line(STDERR_FILENO, absl::StrCat("gaps-trainer: job ", job_id, ": the job store did not record ", what,
                                             ": ", error.ToString()));
}

int JobRunner::cpu_threads_per_job() const {
  if (options_.threads_per_job > 0) return options_.threads_per_job;
  // Read before any job thread changed it: the process's default (OMP_NUM_THREADS, else its cores).
  static const int process_threads = at::get_num_threads();
  return std::max(1, process_threads / options_.concurrency);
}

void JobRunner::job_loop(int cpu_threads) {
  // Concurrent jobs whose parallel regions each ask for every core oversubscribe the host, and a job's speed then
  // depends on what else runs (docs/deploy.md has the measurements). The bound holds for this thread's regions
  // and for the threads a run starts (asynchronous phases), which begin with the last bound set.
  at::set_num_threads(cpu_threads);
  std::string last_error;
  while (true) {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (stopping_) return;
    }
    absl::StatusOr<std::optional<v1::JobStatus>> claimed = store_.claim(options_.replica_id, options_.lease_seconds);
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

void JobRunner::run_claimed(v1::JobStatus job) {
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
    end_job({job, list_artifacts(job_dir(options_, job.job_id()) / "out"), absl::OkStatus()});
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

void JobRunner::run_job(v1::JobStatus status) {
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
  status.set_stage("initialising");
  status.set_started_at(now_seconds());
  status.set_runner(options_.replica_id);
  // The job runs anyway: a store that recovers records its end, and one that does not lets the lease lapse,
  // so that the job is taken over.
  if (absl::Status st = store_.update(status, options_.replica_id); !st.ok()) {
    if (st.code() == absl::StatusCode::kAborted) return done();
    log_store_error(job_id, "that it started", st);
  }
  v1::JobEvent started = event_for(job_id);
  started.set_state_changed(v1::RUNNING);
  publish(started);
  v1::JobEvent threads = event_for(job_id);
  threads.set_log(absl::StrCat("trains with ", at::get_num_threads(), " CPU thread(s) on ", options_.device, " (",
                               options_.concurrency, " job(s) at once on this trainer)"));
  publish(threads);

  v1::JobStatus final_status = train(status, *flags);
  if (flags->lease_lost) {
    write_log_line(STDERR_FILENO, absl::StrCat("gaps-trainer: job ", job_id,
                                               ": another trainer took it over; this run stops unrecorded"));
    return done();
  }
  if (!terminal(final_status.state())) {
    leave_for_later(std::move(final_status));
    return done();
  }
  final_status.set_finished_at(now_seconds());
  const auto artifacts = list_artifacts(job_dir(options_, job_id) / "out");
  for (const auto& a : artifacts) final_status.add_artifacts(a.path);
  end_job({final_status, artifacts, absl::OkStatus()});
  done();
}

void JobRunner::leave_for_later(v1::JobStatus status) {
  const std::string& job_id = status.job_id();
  status.set_stopped_cleanly(true);
  if (absl::Status st = store_.update(status, options_.replica_id); !st.ok())
    log_store_error(job_id, "its progress before the shutdown (it resumes from its last recorded checkpoint)", st);
  if (absl::Status st = store_.release(job_id, options_.replica_id); !st.ok())
    log_store_error(job_id, "the release of its lease (it is taken over when the lease expires)", st);
}

v1::JobStatus JobRunner::train(v1::JobStatus status, const RunFlags& flags) {
  const std::string job_id = status.job_id();
  absl::StatusOr<RunOptions> options = run_options(job_id);
  if (!options.ok()) return failed(std::move(status), options.status(), options_.data_dir);
  RunOptions& o = *options;
  const std::function<bool()> should_stop = [&] {
    return flags.cancelled.load() || flags.lease_lost.load() || stop_training_.load();
  };
  std::unique_ptr<RemoteGenerator> generator;
  if (o.variant != Variant::kVanilla) {
    absl::StatusOr<std::unique_ptr<RemoteGenerator>> made = make_generator(o, job_id, should_stop);
    if (!made.ok()) return failed(std::move(status), made.status(), options_.data_dir);
    generator = std::move(*made);
    o.generator = generator.get();
  }
  o.should_stop = should_stop;
  o.on_checkpoint = [this, &job_id](int iteration) {
    v1::JobEvent e = event_for(job_id);
    e.set_checkpoint_written(iteration);
    publish(e);
  };
  o.on_phase = [this, &job_id](const std::string& what, const nlohmann::json& entry) { on_phase(job_id, what, entry); };
  const auto progress = [&](const TrainProgress& p) { on_progress(p, status); };
  const auto log = [&](const std::string& line) {
    v1::JobEvent e = event_for(job_id);
    e.set_log(line);
    publish(e);
  };
  // Sequenced before run_outcome takes `status`: the progress reports update it while the pipeline runs.
  const absl::StatusOr<RunResult> result = run_pipeline(o, progress, log);
  return run_outcome(std::move(status), result, flags.cancelled, options_.data_dir);
}

absl::StatusOr<RunOptions> JobRunner::run_options(const std::string& job_id) {
  const fs::path dir = job_dir(options_, job_id);
  absl::StatusOr<v1::JobSpec> spec = store_.spec(job_id);
  if (!spec.ok()) return spec.status();
  absl::StatusOr<RunOptions> o =
      run_options_from_proto(spec->config(), spec->has_points(), dir / "scene" / "points.ply", options_.device);
  if (!o.ok()) return o.status();
  o->scene_dir = dir / "scene";
  if (std::error_code ec; fs::is_directory(o->scene_dir / kLargerViewsFolder, ec))
    o->larger_views_dir = o->scene_dir / kLargerViewsFolder;
  o->out_dir = dir / "out";
  o->init_cache_dir = options_.init_cache_dir.empty() ? options_.data_dir / "init_cache" : options_.init_cache_dir;
  o->lpips_weights = options_.lpips_weights;
  o->checkpoint_dir = dir / "checkpoint";
  o->checkpoint_every_seconds = options_.checkpoint_seconds;
  return o;
}

absl::StatusOr<std::unique_ptr<RemoteGenerator>> JobRunner::make_generator(
    const RunOptions& o, const std::string& job_id, const std::function<bool()>& should_stop) const {
  if (options_.workers.addresses.empty())
    return absl::FailedPreconditionError(absl::StrCat("variant ", variant_name(o.variant),
                                                      " needs diffusion workers (start the trainer with --workers)"));
  WorkerPoolOptions pool = options_.workers;
  pool.addresses = resolve_worker_addresses(pool.addresses);  // per job: workers come and go
  pool.scene_id = job_id;
  // A cancel or a shutdown does not wait for a worker that never answers: the call is cancelled.
  pool.should_stop = should_stop;
  return RemoteGenerator::create(pool);
}

void JobRunner::on_phase(const std::string& job_id, const std::string& what, const nlohmann::json& entry) {
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
}

void JobRunner::on_progress(const TrainProgress& p, v1::JobStatus& status) {
  v1::JobEvent e = event_for(status.job_id());
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
  status.set_stage("training");
  if (absl::Status st = store_.update(status, options_.replica_id); !st.ok() && st.code() != absl::StatusCode::kAborted)
    log_store_error(status.job_id(), absl::StrCat("its progress at iteration ", p.iteration), st);
}

void JobRunner::heartbeat_loop() {
  const auto interval = std::chrono::duration<double>(options_.lease_seconds / 4);
  std::unique_lock<std::mutex> lock(mutex_);
  while (!stopping_changed_.wait_for(lock, interval, [this] { return stopping_; })) {
    const auto running = running_;
    lock.unlock();
    for (const auto& [job_id, flags] : running) {
      const absl::StatusOr<bool> renewed = store_.renew(job_id, options_.replica_id, options_.lease_seconds);
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

void JobRunner::end_job(UnrecordedEnd end) {
  const std::string job_id = end.status.job_id();
  end.status.clear_stage();
  write_log_line(STDERR_FILENO, absl::StrCat("gaps-trainer: job ", job_id, ": ", v1::JobState_Name(end.status.state()),
                                             end.status.error().empty() ? "" : ": ", end.status.error()));
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

absl::Status JobRunner::record_end(const UnrecordedEnd& end) {
  v1::JobEvent closing = closing_event(end.status);
  // Only while this process holds the lease: a job another replica took over ends there, once.
  return store_.end_job(end.status, end.artifacts, closing, options_.replica_id);
}

void JobRunner::retry_loop() {
  std::unique_lock<std::mutex> lock(mutex_);
  while (!stopping_changed_.wait_for(lock, options_.store_retry_interval, [this] { return stopping_; })) {
    if (unrecorded_ends_.empty()) continue;
    lock.unlock();
    retry_unrecorded_ends();
    lock.lock();
  }
}

void JobRunner::retry_unrecorded_ends() {
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

absl::Status JobRunner::unrecorded_end(const std::string& job_id) {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = unrecorded_ends_.find(job_id);
  return it == unrecorded_ends_.end() ? absl::OkStatus() : it->second.error;
}

void JobRunner::note_unrecorded_end(v1::JobStatus& status) {
  std::lock_guard<std::mutex> lock(mutex_);
  const auto it = unrecorded_ends_.find(status.job_id());
  // A status read from the store after a retry recorded the end, but before the retry dropped it here, already
  // holds that end: the error no longer applies.
  if (it == unrecorded_ends_.end() || status.state() == it->second.status.state()) return;
  status.set_error(std::string(it->second.error.message()));
}

}  // namespace gaps
