#pragma once
// A synthetic scene with known cameras, rendered by the project itself: a textured backdrop and a few
// coloured objects in front of it, seen by a forward-facing arc of cameras (like an LLFF capture).
// Written to disk as a nerfstudio transforms.json scene, so it goes through the ordinary loader.
#include <filesystem>

#include "absl/status/status.h"
#include "gs_trainer/model/gaussians.h"

namespace gaps {

struct SyntheticSceneOptions {
  int images = 16;
  int width = 160;
  int height = 120;
  uint64_t seed = 0;
};

// The ground-truth model behind the synthetic images.
GaussianModel synthetic_ground_truth(uint64_t seed);

absl::Status write_synthetic_scene(const std::filesystem::path& dir, const SyntheticSceneOptions& options);

}  // namespace gaps
