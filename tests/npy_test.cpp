#include "common/npy.h"

#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "tests/test_util.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

// A .npy file built byte by byte, independent of write_npy: magic, version, header length, header, data.
std::string npy_bytes(const std::string& header_dict, const std::string& data, int major = 1) {
  std::string header = header_dict;
  const size_t prefix = major == 1 ? 10 : 12;
  header.append((64 - (prefix + header.size() + 1) % 64) % 64, ' ');
  header += '\n';
  std::string out = "\x93NUMPY";
  out += static_cast<char>(major);
  out += '\0';
  const size_t len = header.size();
  const int len_bytes = major == 1 ? 2 : 4;
  for (int i = 0; i < len_bytes; ++i) out += static_cast<char>((len >> (8 * i)) & 0xff);
  return out + header + data;
}

template <typename T>
std::string raw(std::initializer_list<T> values) {
  std::string out;
  for (T v : values) out.append(reinterpret_cast<const char*>(&v), sizeof(T));
  return out;
}

std::string dict(const std::string& descr, const std::string& shape, bool fortran = false) {
  return "{'descr': '" + descr + "', 'fortran_order': " + (fortran ? "True" : "False") + ", 'shape': " + shape + ", }";
}

class NpyTest : public test::TempDirTest {
 protected:
};

TEST_F(NpyTest, ReadsFloat64Version1) {
  const fs::path path = write("a.npy", npy_bytes(dict("<f8", "(2, 3)"), raw<double>({1, 2, 3, 4.5, -5, 6e10})));
  absl::StatusOr<NpyArray> array = read_npy(path);
  ASSERT_TRUE(array.ok()) << array.status();
  EXPECT_EQ(array->shape, (std::vector<int64_t>{2, 3}));
  EXPECT_EQ(array->descr, "<f8");
  ASSERT_EQ(array->data.scalar_type(), at::kDouble);
  EXPECT_EQ(array->data.sizes().vec(), (std::vector<int64_t>{2, 3}));
  EXPECT_EQ(array->data[1][0].item<double>(), 4.5);
  EXPECT_EQ(array->data[1][2].item<double>(), 6e10);
}

TEST_F(NpyTest, ReadsFloat32Versions2And3) {
  for (int major : {2, 3}) {
    const fs::path path = write("b.npy", npy_bytes(dict("<f4", "(4,)"), raw<float>({0.25f, -1, 3, 7}), major));
    absl::StatusOr<NpyArray> array = read_npy(path);
    ASSERT_TRUE(array.ok()) << array.status();
    EXPECT_EQ(array->shape, (std::vector<int64_t>{4}));
    EXPECT_EQ(array->data[0].item<double>(), 0.25);
    EXPECT_EQ(array->data[3].item<double>(), 7.0);
  }
}

TEST_F(NpyTest, ReadsIntegerAndBoolTypes) {
  struct Case {
    std::string descr, data;
    double last;
  };
  const std::vector<Case> cases = {
      {"<i4", raw<int32_t>({-3, 2, 2147483647}), 2147483647.0},
      {"<i8", raw<int64_t>({1, -2, -9000000000}), -9000000000.0},
      {"|u1", raw<uint8_t>({0, 1, 255}), 255.0},
      {"<u2", raw<uint16_t>({0, 1, 65535}), 65535.0},
      {"|i1", raw<int8_t>({0, 1, -128}), -128.0},
      {"|b1", raw<uint8_t>({1, 0, 1}), 1.0},
  };
  for (const Case& c : cases) {
    absl::StatusOr<NpyArray> array = parse_npy(npy_bytes(dict(c.descr, "(3,)"), c.data), c.descr);
    ASSERT_TRUE(array.ok()) << c.descr << ": " << array.status();
    EXPECT_EQ(array->data[2].item<double>(), c.last) << c.descr;
  }
}

TEST_F(NpyTest, ReadsScalarsAndEmptyArrays) {
  absl::StatusOr<NpyArray> scalar = parse_npy(npy_bytes(dict("<f8", "()"), raw<double>({42})), "scalar");
  ASSERT_TRUE(scalar.ok()) << scalar.status();
  EXPECT_TRUE(scalar->shape.empty());
  EXPECT_EQ(scalar->data.item<double>(), 42.0);
  absl::StatusOr<NpyArray> empty = parse_npy(npy_bytes(dict("<f8", "(0, 17)"), ""), "empty");
  ASSERT_TRUE(empty.ok()) << empty.status();
  EXPECT_EQ(empty->shape, (std::vector<int64_t>{0, 17}));
  EXPECT_EQ(empty->data.numel(), 0);
}

TEST_F(NpyTest, AcceptsKeysInAnyOrder) {
  const std::string header = "{'shape': (2,), 'fortran_order': False, 'descr': '<f8'}";
  absl::StatusOr<NpyArray> array = parse_npy(npy_bytes(header, raw<double>({1, 2})), "reordered");
  ASSERT_TRUE(array.ok()) << array.status();
  EXPECT_EQ(array->data[1].item<double>(), 2.0);
}

// Each corrupt file must fail with an error naming the file and the problem.
TEST_F(NpyTest, RejectsCorruptFiles) {
  const std::string good_data = raw<double>({1, 2});
  const std::string good = npy_bytes(dict("<f8", "(2,)"), good_data);
  std::string bad_version = good;
  bad_version[6] = 4;
  struct Case {
    std::string name, bytes, problem;
  };
  const std::vector<Case> cases = {
      {"magic.npy", "PK\x03\x04 not numpy at all", "bad magic"},
      {"version.npy", bad_version, "version 4"},
      {"fortran.npy", npy_bytes(dict("<f8", "(2,)", true), good_data), "fortran_order"},
      {"bigendian.npy", npy_bytes(dict(">f8", "(2,)"), good_data), "big-endian"},
      {"structured.npy", npy_bytes("{'descr': [('a', '<f8')], 'fortran_order': False, 'shape': (2,), }", good_data),
       "structured"},
      {"complex.npy", npy_bytes(dict("<c16", "(1,)"), good_data), "unsupported dtype"},
      {"short.npy", npy_bytes(dict("<f8", "(3,)"), good_data), "16 bytes"},
      {"long.npy", npy_bytes(dict("<f8", "(1,)"), good_data), "16 bytes"},
      {"noshape.npy", npy_bytes("{'descr': '<f8', 'fortran_order': False}", good_data), "'shape'"},
      {"badshape.npy", npy_bytes(dict("<f8", "(2, x)"), good_data), "shape"},
      {"header.npy", good.substr(0, 30), "truncated header"},
      // No data, but strides that overflow (found by fuzz/npy_fuzz.cpp: LibTorch threw, the reader aborted).
      {"zero_extent.npy", npy_bytes(dict("<f8", "(0, 9999, 99999999999999)"), ""), "shape is too large"},
  };
  for (const Case& c : cases) {
    const fs::path path = write(c.name, c.bytes);
    absl::StatusOr<NpyArray> array = read_npy(path);
    ASSERT_FALSE(array.ok()) << c.name;
    EXPECT_NE(array.status().message().find(path.string()), absl::string_view::npos) << array.status();
    EXPECT_NE(array.status().message().find(c.problem), absl::string_view::npos) << array.status();
  }
}

TEST_F(NpyTest, MissingFileIsNotFound) {
  const fs::path path = dir_ / "nope.npy";
  absl::StatusOr<NpyArray> array = read_npy(path);
  ASSERT_FALSE(array.ok());
  EXPECT_TRUE(absl::IsNotFound(array.status()));
  EXPECT_NE(array.status().message().find(path.string()), absl::string_view::npos);
}

TEST_F(NpyTest, WriteThenReadRoundTrips) {
  const at::Tensor f64 = at::arange(12, at::kDouble).reshape({3, 4}).div(7.0);
  ASSERT_TRUE(write_npy(dir_ / "d.npy", f64).ok());
  absl::StatusOr<NpyArray> back = read_npy(dir_ / "d.npy");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->descr, "<f8");
  EXPECT_TRUE(at::equal(back->data, f64));

  const at::Tensor f32 = at::rand({5}, at::kFloat);
  ASSERT_TRUE(write_npy(dir_ / "f.npy", f32).ok());
  back = read_npy(dir_ / "f.npy");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->descr, "<f4");
  EXPECT_EQ(back->shape, (std::vector<int64_t>{5}));
  EXPECT_TRUE(at::equal(back->data.to(at::kFloat), f32));
  // numpy aligns the payload to 64 bytes.
  EXPECT_EQ((fs::file_size(dir_ / "f.npy") - 5 * sizeof(float)) % 64, 0u);
}

TEST_F(NpyTest, ReadsRealPosesBounds) {
  const fs::path file = fs::path(GAPS_DATA_DIR) / "llff" / "fern" / "poses_bounds.npy";
  if (!fs::exists(file)) GTEST_SKIP() << "no benchmark data at " << GAPS_DATA_DIR;
  absl::StatusOr<NpyArray> array = read_npy(file);
  ASSERT_TRUE(array.ok()) << array.status();
  EXPECT_EQ(array->shape, (std::vector<int64_t>{20, 17}));
  // Row 0 ends its 3x5 matrix with H, W, focal of the full-size photos.
  EXPECT_EQ(array->data[0][4].item<double>(), 3024.0);
  EXPECT_EQ(array->data[0][9].item<double>(), 4032.0);
  EXPECT_NEAR(array->data[0][14].item<double>(), 3260.526, 1e-3);
}

}  // namespace
}  // namespace gaps
