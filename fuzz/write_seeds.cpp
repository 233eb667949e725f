// Writes the seed corpora of the fuzz targets (fuzz/corpus/<target>/): small valid inputs of every format,
// made by the project's own writers where it has them, so the fuzzers start from what the parsers accept.
// Usage: gaps_fuzz_write_seeds OUT_DIR  (fuzz/README.md; the torch_pickle seeds come from PyTorch itself).
#include <cstring>
#include <fstream>
#include <iostream>

#include <ATen/ATen.h>
#include <Eigen/Geometry>
#include <nlohmann/json.hpp>
#include "absl/strings/str_format.h"
#include "common/image_io.h"
#include "common/io_util.h"
#include "common/npy.h"
#include "common/ply.h"
#include "common/safetensors.h"
#include "fuzz/proto_stream.h"
#include "gs_trainer/scene/cameras_json.h"
#include "gs_trainer/scene/colmap.h"
#include "rpc/codec.h"
#include "rpc/generation_codec.h"

// JPEG seeds come from stb's writer (the project reads JPEG but never writes it), compiled here privately.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmissing-field-initializers"
#define STB_IMAGE_WRITE_STATIC
#define STB_IMAGE_WRITE_IMPLEMENTATION
#include <stb/stb_image_write.h>
#pragma GCC diagnostic pop

namespace gaps::fuzz {
namespace {

namespace fs = std::filesystem;

void must(const absl::Status& status) {
  if (status.ok()) return;
  std::cerr << "gaps_fuzz_write_seeds: " << status << "\n";
  std::exit(1);
}

void put(const fs::path& file, const std::string& bytes) {
  fs::create_directories(file.parent_path());
  must(write_file_bytes(file, bytes));
}

Camera seed_camera(int i, int width = 8, int height = 6) {
  Camera c;
  c.name = absl::StrFormat("%03d.png", i);
  c.width = width;
  c.height = height;
  c.fx = c.fy = 7;
  c.cx = width / 2.0;
  c.cy = height / 2.0;
  c.R = Eigen::AngleAxisd(0.1 * i, Eigen::Vector3d::UnitY()).toRotationMatrix();
  c.t = Eigen::Vector3d(-0.2 * i, 0, 0);
  c.near = 0.5;
  c.far = 5;
  return c;
}

PointCloud seed_points() {
  at::manual_seed(0);
  return {at::rand({6, 3}), at::rand({6, 3})};
}

void npy_seeds(const fs::path& out) {
  must(write_npy(out / "float64_2x3.npy", at::arange(6, at::kDouble).reshape({2, 3})));
  must(write_npy(out / "float32_0d.npy", at::scalar_tensor(1.5, at::kFloat)));
  // A header of version 2.0 with a little-endian int16 array, written by hand (write_npy does floats only).
  std::string v2("\x93NUMPY\x02\x00", 8);
  std::string header = "{'descr': '<i2', 'fortran_order': False, 'shape': (3,), }";
  header.append(64 - (12 + header.size() + 1) % 64, ' ');
  header += '\n';
  const uint32_t length = static_cast<uint32_t>(header.size());
  v2.append(reinterpret_cast<const char*>(&length), 4);
  v2 += header;
  const int16_t values[3] = {1, -2, 3};
  v2.append(reinterpret_cast<const char*>(values), sizeof(values));
  put(out / "int16_v2.npy", v2);
}

void ply_seeds(const fs::path& out) {
  fs::create_directories(out);
  must(write_point_cloud_ply(seed_points(), out / "binary_rgb.ply"));
  must(write_ply_vertices(out / "binary_f_dc.ply", {"x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"}, at::rand({4, 6})));
  put(out / "ascii.ply",
      "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
      "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n0 0 1 255 0 0\n1 0.5 2 0 255 0\n");
}

ColmapModel seed_colmap_model() {
  std::vector<Camera> cameras;
  for (int i = 0; i < 3; ++i) cameras.push_back(seed_camera(i));
  ColmapModel model = colmap_from_cameras(cameras, seed_points());
  model.images.begin()->second.xys = {Eigen::Vector2d(1, 2), Eigen::Vector2d(3, 4)};
  model.images.begin()->second.point3d_ids = {0, -1};
  model.points[0].track = {{model.images.begin()->first, 0}};
  return model;
}

template <typename T>
void raw(std::string* out, T value) {
  out->append(reinterpret_cast<const char*>(&value), sizeof(T));
}

// COLMAP's binary layout (src/colmap/scene/reconstruction_io.cc): little-endian counts, ids and doubles.
std::string cameras_bin(const ColmapModel& m) {
  std::string b;
  raw<uint64_t>(&b, m.cameras.size());
  for (const auto& [id, c] : m.cameras) {
    raw<int32_t>(&b, id);
    raw<int32_t>(&b, 1);  // PINHOLE
    raw<uint64_t>(&b, c.width);
    raw<uint64_t>(&b, c.height);
    for (double p : c.params) raw<double>(&b, p);
  }
  return b;
}

std::string images_bin(const ColmapModel& m) {
  std::string b;
  raw<uint64_t>(&b, m.images.size());
  for (const auto& [id, image] : m.images) {
    raw<int32_t>(&b, id);
    for (int k = 0; k < 4; ++k) raw<double>(&b, image.qvec(k));
    for (int k = 0; k < 3; ++k) raw<double>(&b, image.tvec(k));
    raw<int32_t>(&b, image.camera_id);
    b += image.name;
    b.push_back('\0');
    raw<uint64_t>(&b, image.xys.size());
    for (size_t k = 0; k < image.xys.size(); ++k) {
      raw<double>(&b, image.xys[k].x());
      raw<double>(&b, image.xys[k].y());
      raw<int64_t>(&b, image.point3d_ids[k]);
    }
  }
  return b;
}

std::string points_bin(const ColmapModel& m) {
  std::string b;
  raw<uint64_t>(&b, m.points.size());
  for (const auto& p : m.points) {
    raw<uint64_t>(&b, p.id);
    for (int k = 0; k < 3; ++k) raw<double>(&b, p.xyz(k));
    for (uint8_t v : p.rgb) raw<uint8_t>(&b, v);
    raw<double>(&b, p.error);
    raw<uint64_t>(&b, p.track.size());
    for (const auto& t : p.track) {
      raw<int32_t>(&b, t.image_id);
      raw<int32_t>(&b, t.point2d_idx);
    }
  }
  return b;
}

// The colmap targets read one file whose kind the first byte picks: 0 cameras, 1 images, 2 points3D.
void colmap_seeds(const fs::path& bin_out, const fs::path& text_out) {
  const ColmapModel model = seed_colmap_model();
  put(bin_out / "cameras", std::string(1, '\0') + cameras_bin(model));
  put(bin_out / "images", std::string(1, '\1') + images_bin(model));
  put(bin_out / "points3D", std::string(1, '\2') + points_bin(model));
  const fs::path text = bin_out.parent_path() / ".colmap_text";
  must(write_colmap_text(text, model));
  const char* files[3] = {"cameras.txt", "images.txt", "points3D.txt"};
  for (int k = 0; k < 3; ++k)
    put(text_out / fs::path(files[k]).stem(), std::string(1, static_cast<char>(k)) + *read_file_bytes(text / files[k]));
  remove_tree(text);
}

// Three frames naming images/000.png ... (the fuzz target provides them), in both intrinsics styles.
void transforms_seeds(const fs::path& out) {
  nlohmann::json blender{{"camera_angle_x", 1.2}, {"frames", nlohmann::json::array()}};
  nlohmann::json per_frame{{"camera_model", "PINHOLE"}, {"frames", nlohmann::json::array()}};
  for (int i = 0; i < 3; ++i) {
    const Camera c = seed_camera(i);
    blender["frames"].push_back({{"file_path", "images/" + c.name}, {"transform_matrix", transform_matrix_json(c)}});
    per_frame["frames"].push_back({{"file_path", "images/" + c.name},
                                   {"transform_matrix", transform_matrix_json(c)},
                                   {"fl_x", c.fx},
                                   {"fl_y", c.fy},
                                   {"cx", c.cx},
                                   {"cy", c.cy},
                                   {"w", c.width},
                                   {"h", c.height}});
  }
  put(out / "camera_angle_x.json", blender.dump(1));
  put(out / "per_frame_intrinsics.json", per_frame.dump(1));
}

// poses_bounds.npy for three images: per image a 3x5 [R | t | (h, w, f)] in LLFF's axes, then near, far.
void llff_seeds(const fs::path& out) {
  at::Tensor poses = at::zeros({3, 17}, at::kDouble);
  for (int i = 0; i < 3; ++i) {
    const double row[17] = {0, 1, 0, 0.2 * i, 6, 1, 0, 0, 0, 8, 0, 0, -1, 0, 7, 0.5, 5};
    for (int k = 0; k < 17; ++k) poses[i][k] = row[k];
  }
  fs::create_directories(out);
  must(write_npy(out / "three_views.npy", poses));
}

void safetensors_seeds(const fs::path& out) {
  fs::create_directories(out);
  must(sdxl::write_safetensors((out / "two_tensors.safetensors").string(),
                               {{"weight", at::rand({2, 3})}, {"bias", at::arange(3, at::kHalf)}}, {{"format", "pt"}}));
}

void append_bytes(void* context, void* data, int size) {
  static_cast<std::string*>(context)->append(static_cast<const char*>(data), size);
}

void image_seeds(const fs::path& out) {
  const at::Tensor rgb = at::rand({6, 8, 3});
  put(out / "rgb.png", *encode_png(rgb, "seed"));
  put(out / "grey.png", *encode_png(rgb.mean(2, true), "seed"));
  const at::Tensor bytes = rgb.mul(255).to(at::kByte).contiguous();
  std::string jpeg;
  if (!stbi_write_jpg_to_func(append_bytes, &jpeg, 8, 6, 3, bytes.data_ptr<uint8_t>(), 90)) {
    std::cerr << "gaps_fuzz_write_seeds: JPEG encoding failed\n";
    std::exit(1);
  }
  put(out / "rgb.jpg", jpeg);
}

// A SubmitJob stream: a spec of three cameras (views 2) and their PNGs in chunks, optionally a point cloud.
std::string upload_stream(const fs::path& scratch, bool with_points, size_t chunk_bytes) {
  v1::SubmitJobRequest first;
  v1::JobSpec& spec = *first.mutable_spec();
  spec.set_name("seed");
  spec.mutable_config()->set_views(2);
  spec.mutable_config()->mutable_training()->set_iterations(10);
  if (with_points) {
    spec.set_has_points(true);
    spec.mutable_config()->set_init("points");
  }
  for (int i = 0; i < 3; ++i) rpc::encode_camera(seed_camera(i), spec.add_cameras());
  std::string stream;
  append_delimited(first, &stream);
  const auto keep = [&stream](const v1::SubmitJobRequest& m) {
    append_delimited(m, &stream);
    return true;
  };
  for (int i = 0; i < 3; ++i)
    rpc::write_file_chunks(v1::FileChunk::IMAGE, i, *encode_png(at::full({6, 8, 3}, 0.2 * (i + 1)), "seed"), keep,
                           chunk_bytes);
  if (with_points) {
    must(write_point_cloud_ply(seed_points(), scratch));
    rpc::write_file_chunks(v1::FileChunk::POINTS, 0, *read_file_bytes(scratch), keep, chunk_bytes);
    fs::remove(scratch);
  }
  return stream;
}

void upload_seeds(const fs::path& out) {
  fs::create_directories(out);
  put(out / "three_views", upload_stream(out / ".points.ply", false, rpc::kChunkBytes));
  put(out / "three_views_chunked", upload_stream(out / ".points.ply", false, 40));
  put(out / "three_views_points", upload_stream(out / ".points.ply", true, rpc::kChunkBytes));
}

ReferenceView seed_reference(int i) {
  const Camera c = seed_camera(i);
  return {c, at::rand({c.height, c.width, 3}), at::full({c.height, c.width}, 2.0), at::ones({c.height, c.width})};
}

// The generation target reads a selector byte (0: GenerateBatch, 1: AdaptSceneBatch) and the message.
void generation_seeds(const fs::path& out) {
  GenerationRequest q;
  q.camera = seed_camera(1);
  q.render_rgb = at::rand({6, 8, 3});
  q.render_depth = at::full({6, 8}, 2.0);
  q.render_alpha = at::ones({6, 8});
  q.coverage = 0.9;
  q.strength = 0.4;
  q.control_scale = 0.8;
  q.references = {seed_reference(0), seed_reference(2)};
  q.prompt = "a photo";
  q.seed = 3;
  q.ip_adapter_scale = 0.5;
  v1::GenerateBatch batch;
  if (!rpc::encode_generation_batch({q}, &batch).ok()) std::abort();
  put(out / "generate", std::string(1, '\0') + batch.SerializeAsString());
  v1::GenerateBatch compact;
  const rpc::TensorTransfer compact_transfer{rpc::TensorEncoding::kUint8, nullptr,
                                             rpc::depth_encoding_for(rpc::TensorEncoding::kUint8, false)};
  if (!rpc::encode_generation_batch({q}, &compact, compact_transfer).ok()) std::abort();
  put(out / "generate_compact", std::string(1, '\0') + compact.SerializeAsString());
  v1::AdaptSceneBatch adapt;
  rpc::encode_adapt_batch("scene", {seed_reference(0), seed_reference(1)}, SceneAdaptation{4, 50}, &adapt);
  put(out / "adapt", std::string(1, '\1') + adapt.SerializeAsString());
}

void render_request_seeds(const fs::path& out) {
  v1::RenderViewRequest request;
  request.set_job_id("job-0123456789ab");
  rpc::encode_camera(seed_camera(1, 64, 48), request.mutable_camera());
  put(out / "render_view", std::string(1, '\0') + request.SerializeAsString());
  rpc::encode_camera(seed_camera(2, 8192, 8192), request.mutable_camera());  // over the render bound
  put(out / "render_view_huge", std::string(1, '\0') + request.SerializeAsString());
  v1::JobCameras cameras;
  for (int i = 0; i < 3; ++i) rpc::encode_camera(seed_camera(i), cameras.add_train());
  rpc::encode_camera(seed_camera(3), cameras.add_test());
  cameras.set_near(0.5);
  cameras.set_far(40);
  put(out / "job_cameras", std::string(1, '\1') + cameras.SerializeAsString());
}

void options_json_seeds(const fs::path& out) {
  put(out / "training", R"({"iterations": 300, "lambda_dssim": 0.3, "max_gaussians": 50000, "device": "cpu"})");
  put(out / "gaps", R"({"warmup_iterations": 20, "phase_interval": 20, "n_active": 2, "tier_alpha_max": [1, 1.25]})");
  put(out / "points", R"({"random_points": 100000000000, "gaussians_per_variation": 2.5})");
}

}  // namespace
}  // namespace gaps::fuzz

int main(int argc, char** argv) {
  namespace fs = std::filesystem;
  if (argc != 2) {
    std::cerr << "usage: gaps_fuzz_write_seeds OUT_DIR  (writes OUT_DIR/<target>/...)\n";
    return 2;
  }
  const fs::path out(argv[1]);
  using namespace gaps::fuzz;
  for (const char* target : {"npy", "ply", "colmap_bin", "colmap_text", "transforms_json", "llff", "safetensors",
                             "image", "upload_stream", "generation_request", "render_request", "options_json"})
    fs::create_directories(out / target);
  npy_seeds(out / "npy");
  ply_seeds(out / "ply");
  colmap_seeds(out / "colmap_bin", out / "colmap_text");
  transforms_seeds(out / "transforms_json");
  llff_seeds(out / "llff");
  safetensors_seeds(out / "safetensors");
  image_seeds(out / "image");
  upload_seeds(out / "upload_stream");
  generation_seeds(out / "generation_request");
  render_request_seeds(out / "render_request");
  options_json_seeds(out / "options_json");
  std::cout << "seeds written under " << out << "\n";
  return 0;
}
