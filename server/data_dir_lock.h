#pragma once
// One trainer per data folder: its SQLite job store and job folders belong to one process. A second
// gaps-trainer on the same folder would take over jobs the first is running and train them into the same
// folders, so it is refused at start-up, naming the process that holds the folder.
#include <filesystem>
#include <memory>

#include "absl/status/statusor.h"

namespace gaps {

class DataDirLock {
 public:
  // An exclusive, non-blocking lock on DIR/trainer.lock (which records the holder's pid); FAILED_PRECONDITION
  // when another process holds it. The lock goes with the process, so a killed trainer leaves none behind.
  static absl::StatusOr<std::unique_ptr<DataDirLock>> acquire(const std::filesystem::path& data_dir);
  ~DataDirLock();
  DataDirLock(const DataDirLock&) = delete;
  DataDirLock& operator=(const DataDirLock&) = delete;

 private:
  explicit DataDirLock(int fd) : fd_(fd) {}
  int fd_;
};

}  // namespace gaps
