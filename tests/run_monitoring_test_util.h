#pragma once
// The short runs of the monitoring tests (run_monitoring_test.cpp, and gpu/ for the CUDA peak memory),
// with an evaluation curve, and the JSON they write.
#include <filesystem>
#include <fstream>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include "gs_trainer/pipeline.h"
#include "tests/synthetic_run.h"
#include "tests/test_util.h"

namespace gaps::test {

// 60 iterations on the small synthetic scene, evaluated every 20.
struct RunMonitoring : TempDirTest {
  RunOptions options() {
    RunOptions o = short_run(dir_);
    o.config.iterations = 60;
    o.eval_every = 20;
    return o;
  }
  void SetUp() override {
    TempDirTest::SetUp();
    write_small_scene(dir_);
  }
};

}  // namespace gaps::test
