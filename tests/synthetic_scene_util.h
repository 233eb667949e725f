#pragma once
// The small synthetic scene that the service tests upload (services_test.cpp, services_e2e_test.cpp,
// scale_out_test.cpp, gpu/services_cuda_test.cpp): written to disk, then read as the client reads a scene.
#include <filesystem>

#include "absl/status/statusor.h"
#include "client/remote_client.h"
#include "gs_trainer/synthetic.h"

namespace gaps::test {

// Nine views of width x height in `dir`, read back at full resolution.
inline absl::StatusOr<client::PreparedScene> prepared_synthetic_scene(const std::filesystem::path& dir, int width,
                                                                      int height) {
  SyntheticSceneOptions options;
  options.images = 9;
  options.width = width;
  options.height = height;
  if (absl::Status written = write_synthetic_scene(dir, options); !written.ok()) return written;
  return client::prepare_scene(dir, 1);
}

}  // namespace gaps::test
