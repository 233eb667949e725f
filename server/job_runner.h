#pragma once
// The Trainer service's job execution: threads that claim jobs from the job store's queue (or take over one
// whose runner died), hold each under a lease a heartbeat renews, run the pipeline (gs_trainer/pipeline.h)
// with its events and checkpoints going to the store, and record the job's end. An end the store refuses is
// kept and retried, and reported meanwhile (unrecorded_end), never dropped.
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json_fwd.hpp>
#include "gaps/v1/trainer.pb.h"
#include "gs_trainer/pipeline.h"
#include "server/job_store.h"
#include "server/remote_generator.h"
#include "server/trainer_options.h"

namespace gaps {

class JobRunner {
 public:
  JobRunner(const TrainerServiceOptions& options, JobStore& store) : options_(options), store_(store) {}
  ~JobRunner() { shutdown(); }
  JobRunner(const JobRunner&) = delete;
  JobRunner& operator=(const JobRunner&) = delete;

  // Starts the job threads, the heartbeat and the retries of refused job ends.
  void start();
  // Stops taking jobs, interrupts running ones without marking them finished (they go on after a restart or
  // on another replica, from their checkpoint) and joins the threads.
  void shutdown();

  // Stores the event (logging a refusal) and wakes the watchers.
  void publish(v1::JobEvent event);
  // Wakes an idle job thread, so that a job submitted here starts without waiting for the next claim.
  void job_queued();
  // Wakes the watchers of a job that ended outside a run (cancelled while nobody ran it).
  void job_ended();
  // A cancel request for a job this process runs reaches its run at once, not at the next renewal.
  void cancel_if_running(const std::string& job_id);
  // Waits up to `timeout` for new events; false once the runner is shutting down.
  bool wait_for_events(std::chrono::milliseconds timeout);
  // OK, or the error of the job's unrecorded end.
  absl::Status unrecorded_end(const std::string& job_id);
  // Puts the store's refusal into a status read from it whose end is unrecorded.
  void note_unrecorded_end(v1::JobStatus& status);

 private:
  // What stops a running job: a cancel, or the loss of its lease to another replica.
  struct RunFlags {
    std::atomic<bool> cancelled{false};
    std::atomic<bool> lease_lost{false};
  };
  // A job that ended but whose end the store refused: retried by retry_loop, and reported by the RPCs
  // instead of the stale state the store still holds.
  struct UnrecordedEnd {
    v1::JobStatus status;  // the final status to record
    std::vector<JobStore::Artifact> artifacts;
    absl::Status error;  // for clients: the store's latest refusal, naming the job and its outcome
  };

  void job_loop(int cpu_threads);
  // Takes over a job a dead or stopped runner left RUNNING (counting a resume, and a crash unless it
  // stopped cleanly) and runs it; a job that reached max_crashes is FAILED instead.
  void run_claimed(v1::JobStatus job);
  void run_job(v1::JobStatus status);
  // The CPU threads each job thread's parallel regions use (TrainerServiceOptions::threads_per_job resolved).
  int cpu_threads_per_job() const;
  // Leaves a job interrupted by shutdown RUNNING, stopped cleanly, for the next process or replica.
  void leave_for_later(v1::JobStatus status);
  // Runs the pipeline for a job; returns its final status (or the status to keep when shutting down).
  v1::JobStatus train(v1::JobStatus status, const RunFlags& flags);
  // The job's run options, its folders and the service's settings filled in.
  absl::StatusOr<RunOptions> run_options(const std::string& job_id);
  // The diffusion workers' generator of a method variant's job.
  absl::StatusOr<std::unique_ptr<RemoteGenerator>> make_generator(const RunOptions& o, const std::string& job_id,
                                                                  const std::function<bool()>& should_stop) const;
  // A progress report becomes an event and the job's stored progress, which `status` keeps for the run's end.
  void on_progress(const TrainProgress& p, v1::JobStatus& status);
  // A skipped phase also gets a warning in the log: training goes on without it, which a client should see.
  void on_phase(const std::string& job_id, const std::string& what, const nlohmann::json& entry);
  // Renews the leases of the running jobs and passes on cancel requests and lost leases.
  void heartbeat_loop();
  void log_store_error(const std::string& job_id, const std::string& what, const absl::Status& error) const;
  // Records the end (status, artifacts, closing event) or keeps it as unrecorded.
  void end_job(UnrecordedEnd end);
  absl::Status record_end(const UnrecordedEnd& end);
  void retry_loop();
  void retry_unrecorded_ends();

  const TrainerServiceOptions& options_;
  JobStore& store_;
  std::mutex mutex_;
  std::condition_variable queue_changed_;
  std::condition_variable events_changed_;
  std::condition_variable stopping_changed_;
  std::map<std::string, std::shared_ptr<RunFlags>> running_;  // the jobs this process runs
  std::map<std::string, UnrecordedEnd> unrecorded_ends_;
  bool stopping_ = false;
  std::atomic<bool> stop_training_{false};
  std::vector<std::thread> threads_;
};

}  // namespace gaps
