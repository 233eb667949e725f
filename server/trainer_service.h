#pragma once
// The Trainer gRPC service: validates and stores uploaded scenes, runs training jobs from a queue with a
// configurable number of concurrent jobs, records everything in the SQLite job store (so a restarted
// trainer knows its jobs, replays their events and re-runs the ones that were running) and serves events,
// artifacts and renders. Jobs of the method variants get pseudo-views from a pool of diffusion workers
// (server/remote_generator.h); a phase no worker answers is skipped and reported, never fatal.
// A write the job store refuses is never dropped silently: a submission or cancellation fails with the
// store's error, a lost event or progress update of a running job is logged with the job id, and a job end
// the store refused is retried in the background while GetJob/ListJobs/WatchJob report it as unrecorded.
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "gaps/v1/trainer.grpc.pb.h"
#include "server/data_dir_lock.h"
#include "server/job_store.h"
#include "server/remote_generator.h"

namespace gaps {

struct TrainerServiceOptions {
  std::filesystem::path data_dir;  // jobs.db, jobs/<id>/{scene,out}, the initialiser cache
  std::string device = "cpu";      // training device of every job
  int concurrency = 1;             // jobs trained at once
  // A job found RUNNING at start-up whose trainer died (no clean stop) this many times is FAILED, not run
  // again: it may be what killed the trainer.
  int max_crashes = 2;
  WorkerPoolOptions workers;  // diffusion workers (addresses may be empty: vanilla jobs only)
  std::string token;          // required bearer token (empty: none)
  uint64_t max_upload_bytes = uint64_t{8} << 30;
  std::chrono::milliseconds store_retry_interval{10000};  // between attempts to record a refused job end
};

class TrainerService final : public v1::Trainer::Service {
 public:
  static absl::StatusOr<std::unique_ptr<TrainerService>> create(TrainerServiceOptions options);
  ~TrainerService() override;

  // Starts the job threads; jobs left RUNNING or QUEUED by a previous process are queued again.
  absl::Status start();
  // Stops taking jobs, interrupts running ones without marking them finished (they run again after a
  // restart) and joins the threads.
  void shutdown();

  grpc::Status SubmitJob(grpc::ServerContext* context, grpc::ServerReader<v1::SubmitJobRequest>* reader,
                         v1::SubmitJobResponse* response) override;
  grpc::Status WatchJob(grpc::ServerContext* context, const v1::WatchJobRequest* request,
                        grpc::ServerWriter<v1::JobEvent>* writer) override;
  grpc::Status GetJob(grpc::ServerContext* context, const v1::GetJobRequest* request, v1::JobStatus* response) override;
  grpc::Status ListJobs(grpc::ServerContext* context, const v1::ListJobsRequest* request,
                        v1::ListJobsResponse* response) override;
  grpc::Status CancelJob(grpc::ServerContext* context, const v1::CancelJobRequest* request,
                         v1::JobStatus* response) override;
  grpc::Status FetchArtifacts(grpc::ServerContext* context, const v1::FetchArtifactsRequest* request,
                              grpc::ServerWriter<v1::ArtifactChunk>* writer) override;
  grpc::Status RenderView(grpc::ServerContext* context, const v1::RenderViewRequest* request,
                          v1::RenderViewResponse* response) override;

 private:
  TrainerService(TrainerServiceOptions options, std::unique_ptr<DataDirLock> lock, std::unique_ptr<JobStore> store);
  std::filesystem::path job_dir(const std::string& job_id) const;
  void job_loop();
  void run_job(const std::string& job_id);
  // Runs the pipeline for a job; returns its final status (or the status to keep when shutting down).
  v1::JobStatus train(v1::JobStatus status, const std::atomic<bool>& cancelled);
  // Stores the event (logging a refusal) and wakes the watchers.
  void publish(v1::JobEvent event);
  void enqueue(const std::string& job_id);
  void log_store_error(const std::string& job_id, const std::string& what, const absl::Status& error) const;

  // A job that ended but whose end the store refused: retried by retry_loop, and reported by the RPCs
  // instead of the stale state the store still holds.
  struct UnrecordedEnd {
    v1::JobStatus status;  // the final status to record
    std::vector<JobStore::Artifact> artifacts;
    absl::Status error;  // for clients: the store's latest refusal, naming the job and its outcome
  };
  // A job a previous process left RUNNING: counted as a resume (and a crash unless it stopped cleanly) and
  // queued again; false when it reached max_crashes and was FAILED instead.
  bool requeue_interrupted(v1::JobStatus& job);
  // Records the end (status, artifacts, closing event) or keeps it as unrecorded.
  void end_job(UnrecordedEnd end);
  absl::Status record_end(const UnrecordedEnd& end);
  void retry_loop();
  void retry_unrecorded_ends();
  // OK, or the error of the job's unrecorded end.
  absl::Status unrecorded_end(const std::string& job_id);
  // Puts the store's refusal into a status read from it whose end is unrecorded.
  void note_unrecorded_end(v1::JobStatus& status);

  TrainerServiceOptions options_;
  std::unique_ptr<DataDirLock> lock_;  // held for the service's lifetime
  std::unique_ptr<JobStore> store_;
  std::mutex mutex_;
  std::condition_variable queue_changed_;
  std::condition_variable events_changed_;
  std::condition_variable stopping_changed_;
  std::deque<std::string> queue_;
  std::map<std::string, std::shared_ptr<std::atomic<bool>>> cancel_flags_;  // queued and running jobs
  std::map<std::string, UnrecordedEnd> unrecorded_ends_;
  bool stopping_ = false;
  std::atomic<bool> stop_training_{false};
  std::vector<std::thread> threads_;
};

}  // namespace gaps
