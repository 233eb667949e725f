#pragma once
// The random-weight SDXL folder the SDXL benchmarks time (sdxl_bench, generator_bench) and diffusers loads
// on the other side: written once, with the SDXL base 1.0 configs or another folder's.
#include <chrono>
#include <filesystem>
#include <iostream>
#include <string>

#include "diffusion_worker/sdxl/model_folder.h"
#include "diffusion_worker/sdxl/random_model.h"

namespace gaps::bench {

// Writes the folder when write is set and dir has no model_index.json; configs_from ("" = SDXL base 1.0)
// names a folder whose component configs to use instead. False, with a message naming program, on failure.
inline bool ensure_random_sdxl(const std::string& dir, bool write, const std::string& configs_from, uint64_t seed,
                               const char* program) {
  if (std::filesystem::exists(std::filesystem::path(dir) / "model_index.json")) return true;
  if (!write) {
    std::cerr << program << ": " << dir << " holds no model; pass --write_model to write the random-weight SDXL\n";
    return false;
  }
  sdxl::SdxlConfigs configs = sdxl::SdxlConfigs::base();
  if (!configs_from.empty()) {
    auto folder = sdxl::ModelFolder::open(configs_from);
    if (!folder.ok()) {
      std::cerr << program << ": " << folder.status() << "\n";
      return false;
    }
    configs = {*folder->read_json("unet"), *folder->read_json("vae"), *folder->read_json("text_encoder"),
               *folder->read_json("text_encoder_2"), *folder->read_json("scheduler", "scheduler_config.json")};
  }
  const auto t0 = std::chrono::steady_clock::now();
  const absl::Status written = sdxl::write_random_sdxl_model(dir, configs, seed, "float16");
  if (!written.ok()) {
    std::cerr << program << ": " << written << "\n";
    return false;
  }
  std::cerr << program << ": wrote " << dir << " in "
            << std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() << " s\n";
  return true;
}

}  // namespace gaps::bench
