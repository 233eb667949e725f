#pragma once
// Short whole runs on a small synthetic scene, shared by the suites that train end to end (the method's
// schedule, run control, monitoring, stability). Each suite adjusts the options it is about.
#include <filesystem>

#include <gtest/gtest.h>
#include "gs_trainer/pipeline.h"
#include "gs_trainer/synthetic.h"

namespace gaps::test {

// The synthetic scene, written to dir/scene at width x height.
inline void write_small_scene(const std::filesystem::path& dir, int width = 64, int height = 48, int images = 16) {
  SyntheticSceneOptions s;
  s.images = images;
  s.width = width;
  s.height = height;
  const absl::Status written = write_synthetic_scene(dir / "scene", s);
  ASSERT_TRUE(written.ok()) << written;
}

// The real fern scene (GAPS_DATA_DIR) at its sparse-view protocol, 3 views at -r 8, 300 vanilla iterations from
// 4,000 random points into `out`: a short end-to-end run on benchmark data.
inline RunOptions fern_short_run(const std::filesystem::path& out) {
  RunOptions o;
  o.scene_dir = std::filesystem::path(GAPS_DATA_DIR) / "llff" / "fern";
  o.out_dir = out;
  o.views = 3;
  o.resolution = 8;
  o.init = "random";
  o.random_points = 4000;
  o.config.iterations = 300;
  return o;
}

// 90 iterations from 2,000 random points of dir/scene into dir/out; with a generator, the method's phases
// every 30 iterations after a 30-iteration warmup, 4 pseudo-views each.
inline RunOptions short_run(const std::filesystem::path& dir, Variant variant = Variant::kVanilla,
                            Generator* generator = nullptr) {
  RunOptions o;
  o.scene_dir = dir / "scene";
  o.out_dir = dir / "out";
  o.views = 3;
  o.resolution = 1;
  o.init = "random";
  o.random_points = 2000;
  o.config.iterations = 90;
  o.variant = variant;
  o.generator = generator;
  o.gaps.warmup_iterations = 30;
  o.gaps.phase_interval = 30;
  o.gaps.n_active = 4;
  return o;
}

}  // namespace gaps::test
