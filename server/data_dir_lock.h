#pragma once
// One trainer per data folder, unless the trainers share a PostgreSQL job store: an SQLite store and its job
// folders belong to one process (a second gaps-trainer on the folder would take over jobs the first is
// running and train them into the same folders), so it holds the folder exclusively and another trainer is
// refused at start-up, naming the process that holds it. Replicas of a shared store hold it together.
#include <filesystem>
#include <memory>

#include "absl/status/statusor.h"

namespace gaps {

class DataDirLock {
 public:
  // A non-blocking lock on DIR/trainer.lock: exclusive (recording the holder's pid) or `shared`;
  // FAILED_PRECONDITION when a process holds it the other way. The lock goes with the process, so a killed
  // trainer leaves none behind.
  static absl::StatusOr<std::unique_ptr<DataDirLock>> acquire(const std::filesystem::path& data_dir,
                                                              bool shared = false);
  ~DataDirLock();
  DataDirLock(const DataDirLock&) = delete;
  DataDirLock& operator=(const DataDirLock&) = delete;

 private:
  explicit DataDirLock(int fd) : fd_(fd) {}
  int fd_;
};

}  // namespace gaps
