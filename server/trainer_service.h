#pragma once
// The Trainer gRPC service: validates and stores uploaded scenes, runs training jobs it claims from the job
// store's queue (a configurable number at once, each under a lease it renews), records everything in the
// store (so a restarted trainer, or another replica of a shared PostgreSQL store, knows every job, replays
// its events and takes over the ones whose runner died) and serves events, artifacts and renders. Jobs of the method
// variants get pseudo-views from a pool of diffusion workers (server/remote_generator.h); a phase no worker answers is
// skipped and reported, never fatal. A write the job store refuses is never dropped silently: a submission or
// cancellation fails with the store's error, a lost event or progress update of a running job is logged with the job
// id, and a job end the store refused is retried in the background while GetJob/ListJobs/WatchJob report it as
// unrecorded.
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "gaps/v1/trainer.grpc.pb.h"
#include "gs_trainer/model/gaussians.h"
#include "gs_trainer/pipeline.h"
#include "server/data_dir_lock.h"
#include "server/job_store.h"
#include "server/remote_generator.h"

namespace gaps {

struct TrainerServiceOptions {
  std::filesystem::path data_dir;  // jobs.db, jobs/<id>/{scene,out}, uploads/, the initialiser cache
  // "" (SQLite in data_dir, this process alone) or a PostgreSQL URI shared by replicas (server/job_store.h).
  std::string job_store;
  // This process in leases and logs; empty: host name, pid and a random suffix.
  std::string replica_id;
  double lease_seconds = 30;                       // a job whose runner stops renewing for this long is taken over
  std::chrono::milliseconds claim_interval{1000};  // how often idle job threads look for work
  std::string device = "cpu";                      // training device of every job
  int concurrency = 1;                             // jobs trained at once
  double checkpoint_seconds = 120;  // a job's state is saved at least this often (0: phases and shutdown only)
  // A job found RUNNING at start-up whose trainer died (no clean stop) this many times is FAILED, not run
  // again: it may be what killed the trainer.
  int max_crashes = 2;
  std::filesystem::path lpips_weights;  // the jobs' LPIPS-VGG weights (safetensors); empty: LPIPS is null
  WorkerPoolOptions workers;            // diffusion workers (addresses may be empty: vanilla jobs only)
  std::string token;                    // required bearer token (empty: none)
  uint64_t max_upload_bytes = uint64_t{8} << 30;
  std::chrono::milliseconds store_retry_interval{10000};  // between attempts to record a refused job end
};

class TrainerService final : public v1::Trainer::Service {
 public:
  static absl::StatusOr<std::unique_ptr<TrainerService>> create(TrainerServiceOptions options);
  ~TrainerService() override;

  // Starts the job threads, which claim queued jobs and jobs whose runner died (with SQLite: every job a
  // previous process left running).
  absl::Status start();
  // Stops taking jobs, interrupts running ones without marking them finished (they go on after a restart or
  // on another replica, from their checkpoint) and joins the threads.
  void shutdown();
  const std::string& replica_id() const { return options_.replica_id; }
  std::string store_description() const { return store_->describe(); }

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
  grpc::Status GetJobCameras(grpc::ServerContext* context, const v1::GetJobCamerasRequest* request,
                             v1::JobCameras* response) override;

 private:
  TrainerService(TrainerServiceOptions options, std::unique_ptr<DataDirLock> lock, std::unique_ptr<JobStore> store);
  std::filesystem::path job_dir(const std::string& job_id) const;
  // The model of a SUCCEEDED job on the service's device, and its run's options. The last job's model is kept,
  // so that the frames of a camera path (one RenderView each) do not each read its PLY again.
  struct FinishedModel {
    std::shared_ptr<const GaussianModel> model;
    RunOptions options;
  };
  absl::StatusOr<FinishedModel> finished_model(const std::string& job_id);
  void job_loop();
  // Takes over a job a dead or stopped runner left RUNNING (counting a resume, and a crash unless it
  // stopped cleanly) and runs it; a job that reached max_crashes is FAILED instead.
  void run_claimed(v1::JobStatus job);
  void run_job(v1::JobStatus status);
  // What stops a running job: a cancel, or the loss of its lease to another replica.
  struct RunFlags {
    std::atomic<bool> cancelled{false};
    std::atomic<bool> lease_lost{false};
  };
  // Runs the pipeline for a job; returns its final status (or the status to keep when shutting down).
  v1::JobStatus train(v1::JobStatus status, const RunFlags& flags);
  // Renews the leases of the running jobs and passes on cancel requests and lost leases.
  void heartbeat_loop();
  // Stores the event (logging a refusal) and wakes the watchers.
  void publish(v1::JobEvent event);
  void log_store_error(const std::string& job_id, const std::string& what, const absl::Status& error) const;

  // A job that ended but whose end the store refused: retried by retry_loop, and reported by the RPCs
  // instead of the stale state the store still holds.
  struct UnrecordedEnd {
    v1::JobStatus status;  // the final status to record
    std::vector<JobStore::Artifact> artifacts;
    absl::Status error;  // for clients: the store's latest refusal, naming the job and its outcome
  };
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
  std::map<std::string, std::shared_ptr<RunFlags>> running_;  // the jobs this process runs
  std::map<std::string, UnrecordedEnd> unrecorded_ends_;
  bool stopping_ = false;
  std::atomic<bool> stop_training_{false};
  std::atomic<int> renders_in_flight_{0};  // RenderView calls being served (at most kMaxConcurrentRenders)
  std::atomic<int> watch_streams_{0};      // open WatchJob streams (at most kMaxWatchStreams)
  std::vector<std::thread> threads_;
  std::mutex model_mutex_;  // guards the two below
  std::string cached_job_;
  std::shared_ptr<const GaussianModel> cached_model_;
};

}  // namespace gaps
