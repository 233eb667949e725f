#pragma once
// What a Trainer service is started with: its data folder and job store, how it runs jobs, and what reaches
// it (token, upload limit). Shared by the service (server/trainer_service.h) and its job runner
// (server/job_runner.h).
#include <chrono>
#include <cstdint>
#include <filesystem>
#include <string>

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
  // The CPU threads of each job's parallel regions (ATen's intra-op threads); 0: the process's threads
  // (OMP_NUM_THREADS, else its cores) shared out among the `concurrency` jobs, at least one each.
  int threads_per_job = 0;
  double checkpoint_seconds = 120;  // a job's state is saved at least this often (0: phases and shutdown only)
  // A job found RUNNING at start-up whose trainer died (no clean stop) this many times is FAILED, not run
  // again: it may be what killed the trainer.
  int max_crashes = 2;
  std::filesystem::path init_cache_dir;  // the jobs' initial-point cache; empty: data_dir/init_cache
  std::filesystem::path lpips_weights;   // the jobs' LPIPS-VGG weights (safetensors); empty: LPIPS is null
  WorkerPoolOptions workers;             // diffusion workers (addresses may be empty: vanilla jobs only)
  std::string token;                     // required bearer token (empty: none)
  uint64_t max_upload_bytes = uint64_t{8} << 30;
  std::chrono::milliseconds store_retry_interval{10000};  // between attempts to record a refused job end
};

// A job's folder: scene/ (the checked upload), out/ (its artifacts), checkpoint/.
inline std::filesystem::path job_dir(const TrainerServiceOptions& options, const std::string& job_id) {
  return options.data_dir / "jobs" / job_id;
}

}  // namespace gaps
