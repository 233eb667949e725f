// The initialisation cache's files under concurrent use: runs of one scene started together read an entry
// while another run is still writing it.
#include <atomic>
#include <filesystem>
#include <string>
#include <thread>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include "common/io_util.h"
#include "gs_trainer/init/init_cache.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

InitResult entry(int64_t n, const std::string& method) {
  InitResult r;
  r.points = PointCloud{at::rand({n, 3}), at::rand({n, 3})};
  r.method = method;
  r.notes = {"note of " + method};
  return r;
}

fs::path fresh_dir(const std::string& name) {
  const fs::path dir = fs::path(testing::TempDir()) / name;
  remove_tree(dir);
  return dir;
}

TEST(InitCache, WhatIsWrittenIsReadBack) {
  const fs::path ply = fresh_dir("init_cache_roundtrip") / "scene_3v_sparse.ply";
  EXPECT_FALSE(read_init_cache(ply).has_value());
  const InitResult written = entry(100, "sparse");
  auto stored = write_init_cache(ply, written);
  ASSERT_TRUE(stored.ok()) << stored.status();
  EXPECT_TRUE(at::allclose(stored->xyz, written.points.xyz));
  const std::optional<InitResult> read = read_init_cache(ply);
  ASSERT_TRUE(read.has_value());
  EXPECT_TRUE(read->from_cache);
  EXPECT_EQ(read->method, "sparse");
  EXPECT_EQ(read->notes, written.notes);
  EXPECT_EQ(read->cache_file, ply);
  EXPECT_TRUE(at::equal(read->points.xyz, stored->xyz));
  // Nothing but the entry's two files is left behind.
  int files = 0;
  for ([[maybe_unused]] const auto& f : fs::directory_iterator(ply.parent_path())) ++files;
  EXPECT_EQ(files, 2);
}

TEST(InitCache, AReaderNeverSeesAnEntryHalfRewritten) {
  // A run that missed the cache (it started before the entry existed) rewrites the entry while later runs
  // read it: every read must find a whole entry, never recompute because of the writer.
  const fs::path ply = fresh_dir("init_cache_concurrent") / "scene_24v_sweep.ply";
  InitResult big = entry(20000, "sweep");
  big.notes.assign(200, std::string(200, 'n'));  // a metadata file of ~40 kB takes several writes
  ASSERT_TRUE(write_init_cache(ply, big).ok());
  std::atomic<bool> writing{true};
  std::thread writer([&] {
    for (int i = 0; i < 150; ++i) ASSERT_TRUE(write_init_cache(ply, big).ok());
    writing = false;
  });
  int reads = 0, misses = 0;
  while (writing) {
    const std::optional<InitResult> r = read_init_cache(ply);
    ++reads;
    if (!r || r->method != "sweep" || r->notes.size() != big.notes.size() || r->points.xyz.size(0) != 20000) ++misses;
  }
  writer.join();
  EXPECT_GT(reads, 0);
  EXPECT_EQ(misses, 0) << "of " << reads << " reads during the rewrites";
}

}  // namespace
}  // namespace gaps
