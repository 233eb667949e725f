// Files are written whole or not at all (common/io_util.h): a reader never sees a partial file, and a failed
// write (a full disk, a file-size limit) leaves nothing behind and says why.
#include "common/io_util.h"

#include <signal.h>
#include <sys/resource.h>

#include <filesystem>
#include <string>

#include <gtest/gtest.h>
#include "absl/strings/match.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

using IoUtil = test::TempDirTest;

TEST_F(IoUtil, AFileIsWrittenWholeAndReplacesTheOldOneOnlyWhenComplete) {
  const std::filesystem::path file = dir_ / "metrics.json";
  ASSERT_TRUE(write_file_bytes(file, "first").ok());
  ASSERT_TRUE(write_file_bytes(file, "second, longer").ok());
  EXPECT_EQ(*read_file_bytes(file), "second, longer");
  EXPECT_EQ(std::distance(std::filesystem::directory_iterator(dir_), {}), 1) << "no temporary file stays behind";
}

TEST_F(IoUtil, AFailedWriteLeavesNeitherAPartialFileNorTheTemporaryOne) {
  const std::filesystem::path file = dir_ / "point_cloud.ply";
  ASSERT_TRUE(write_file_bytes(file, "the old model").ok());
  // A file-size limit makes the write fail part way, as a full disk would.
  struct rlimit before {};
  ASSERT_EQ(getrlimit(RLIMIT_FSIZE, &before), 0);
  const auto old_handler = signal(SIGXFSZ, SIG_IGN);
  struct rlimit small = before;
  small.rlim_cur = 4096;
  ASSERT_EQ(setrlimit(RLIMIT_FSIZE, &small), 0);
  const absl::Status failed = write_file_bytes(file, std::string(1 << 20, 'x'));
  setrlimit(RLIMIT_FSIZE, &before);
  signal(SIGXFSZ, old_handler);
  ASSERT_FALSE(failed.ok());
  EXPECT_TRUE(absl::StrContains(failed.message(), file.string() + ": cannot be written (")) << failed;
  EXPECT_EQ(*read_file_bytes(file), "the old model") << "the complete file stays as it was";
  EXPECT_EQ(std::distance(std::filesystem::directory_iterator(dir_), {}), 1) << "no partial file stays behind";
}

TEST_F(IoUtil, AnUnwritableFolderIsNamed) {
  const absl::Status st = write_file_bytes(dir_ / "no_such_folder" / "a.json", "{}");
  EXPECT_FALSE(st.ok());
  EXPECT_TRUE(absl::StrContains(st.message(), "no_such_folder/a.json: cannot be written")) << st;
}

}  // namespace
}  // namespace gaps
