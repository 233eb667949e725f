// The fuzz targets' seed corpora (fuzz/corpus) hold inputs their parsers accept: a seed that stopped
// parsing (a format changed, a writer broke) would leave its fuzzer mutating garbage.
#include <filesystem>
#include <functional>

#include <ATen/ATen.h>
#include <gtest/gtest.h>
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/npy.h"
#include "common/ply.h"
#include "common/safetensors.h"
#include "common/status_macros.h"
#include "common/torch_pickle.h"
#include "fuzz/proto_stream.h"
#include "gs_trainer/scene/colmap.h"
#include "gs_trainer/scene/scene.h"
#include "rpc/generation_codec.h"
#include "server/scene_upload.h"
#include "tests/test_util.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

const fs::path kCorpus = GAPS_FUZZ_CORPUS_DIR;

// Every seed of `target`, checked by `accepts`; at least one must exist.
void for_each_seed(const std::string& target, const std::function<absl::Status(const fs::path&)>& accepts) {
  int seen = 0;
  for (const auto& entry : fs::directory_iterator(kCorpus / target)) {
    ++seen;
    const absl::Status st = accepts(entry.path());
    EXPECT_TRUE(st.ok()) << entry.path() << ": " << st;
  }
  EXPECT_GT(seen, 0) << "no seeds for " << target;
}

// The colmap targets' first byte picks the file; the rest is the file.
absl::Status colmap_seed(const fs::path& seed, const fs::path& scratch, bool binary) {
  const std::string bytes = *read_file_bytes(seed);
  GAPS_RETURN_IF_ERROR(write_file_bytes(scratch, bytes.substr(1)));
  switch (bytes[0] % 3) {
    case 0:
      return (binary ? read_colmap_cameras_bin(scratch) : read_colmap_cameras_txt(scratch)).status();
    case 1:
      return (binary ? read_colmap_images_bin(scratch) : read_colmap_images_txt(scratch)).status();
    default:
      return (binary ? read_colmap_points_bin(scratch) : read_colmap_points_txt(scratch)).status();
  }
}

using FuzzSeeds = test::TempDirTest;

TEST_F(FuzzSeeds, FileFormatSeedsParse) {
  for_each_seed("npy", [](const fs::path& p) { return read_npy(p).status(); });
  for_each_seed("ply", [](const fs::path& p) { return read_point_cloud_ply(p).status(); });
  for_each_seed("safetensors", [](const fs::path& p) { return sdxl::read_safetensors(p.string()).status(); });
  for_each_seed("torch_pickle", [](const fs::path& p) { return load_torch_state_dict(p.string()).status(); });
  for_each_seed("image", [](const fs::path& p) { return read_image(p).status(); });
  for_each_seed("colmap_bin", [&](const fs::path& p) { return colmap_seed(p, dir_ / "model.bin", true); });
  for_each_seed("colmap_text", [&](const fs::path& p) { return colmap_seed(p, dir_ / "model.txt", false); });
}

TEST_F(FuzzSeeds, SceneSeedsLoadBesideThreeImages) {
  fs::create_directories(dir_ / "images");
  for (int i = 0; i < 3; ++i)
    ASSERT_TRUE(write_png(dir_ / "images" / ("00" + std::to_string(i) + ".png"), at::rand({6, 8, 3})).ok());
  for_each_seed("transforms_json", [&](const fs::path& p) {
    fs::copy_file(p, dir_ / "transforms.json", fs::copy_options::overwrite_existing);
    auto scene = load_transforms_scene(dir_);
    fs::remove(dir_ / "transforms.json");
    return scene.ok() && scene->cameras.size() == 3 ? absl::OkStatus() : scene.status();
  });
  for_each_seed("llff", [&](const fs::path& p) {
    fs::copy_file(p, dir_ / "poses_bounds.npy", fs::copy_options::overwrite_existing);
    auto scene = load_llff_scene(dir_);
    fs::remove(dir_ / "poses_bounds.npy");
    return scene.ok() && scene->cameras.size() == 3 ? absl::OkStatus() : scene.status();
  });
}

TEST_F(FuzzSeeds, MessageSeedsDecode) {
  for_each_seed("upload_stream", [&](const fs::path& p) {
    const std::string bytes = *read_file_bytes(p);
    const auto messages =
        fuzz::read_delimited<v1::SubmitJobRequest>(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size(), 256);
    size_t next = 0;
    GAPS_ASSIGN_OR_RETURN(SceneUpload upload, receive_upload(
                                                  [&](v1::SubmitJobRequest* m) {
                                                    if (next == messages.size()) return false;
                                                    *m = messages[next++];
                                                    return true;
                                                  },
                                                  uint64_t{1} << 20, dir_ / p.filename()));
    return write_uploaded_scene(upload);
  });
  for_each_seed("generation_request", [](const fs::path& p) {
    const std::string bytes = *read_file_bytes(p);
    if (bytes[0] % 2 == 0) {
      v1::GenerateBatch batch;
      if (!batch.ParseFromString(bytes.substr(1))) return absl::DataLossError("not a GenerateBatch");
      return rpc::decode_generation_batch(batch).status();
    }
    v1::AdaptSceneBatch batch;
    if (!batch.ParseFromString(bytes.substr(1))) return absl::DataLossError("not an AdaptSceneBatch");
    return rpc::decode_adapt_batch(batch).status();
  });
}

}  // namespace
}  // namespace gaps
