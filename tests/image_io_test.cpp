#include "common/image_io.h"

#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include <gtest/gtest.h>

#include "tests/test_util.h"

namespace gaps {
namespace {

namespace fs = std::filesystem;

// --- A minimal PNG encoder (stored, uncompressed deflate blocks), independent of stb, so the reader is
// tested on bit depths and colour types that write_png does not produce.
uint32_t crc32(const std::string& bytes) {
  uint32_t crc = 0xffffffffu;
  for (unsigned char b : bytes) {
    crc ^= b;
    for (int k = 0; k < 8; ++k) crc = (crc >> 1) ^ (0xedb88320u & (0u - (crc & 1u)));
  }
  return crc ^ 0xffffffffu;
}

std::string be32(uint32_t v) {
  return {static_cast<char>(v >> 24), static_cast<char>(v >> 16), static_cast<char>(v >> 8), static_cast<char>(v)};
}

std::string chunk(const std::string& type, const std::string& data) {
  return be32(static_cast<uint32_t>(data.size())) + type + data + be32(crc32(type + data));
}

std::string zlib_stored(const std::string& data) {
  std::string out = "\x78\x01";
  uint32_t a = 1, b = 0;
  for (unsigned char c : data) {
    a = (a + c) % 65521;
    b = (b + a) % 65521;
  }
  for (size_t pos = 0; pos == 0 || pos < data.size(); pos += 65535) {
    const size_t n = std::min<size_t>(65535, data.size() - pos);
    out += static_cast<char>(pos + n >= data.size() ? 1 : 0);
    out += {static_cast<char>(n & 0xff), static_cast<char>(n >> 8), static_cast<char>(~n & 0xff),
            static_cast<char>((~n >> 8) & 0xff)};
    out += data.substr(pos, n);
  }
  return out + be32((b << 16) | a);
}

// `samples` holds every row's samples in order, big-endian when 16-bit.
std::string png_bytes(int width, int height, int bit_depth, int color_type, const std::string& samples) {
  const size_t row_bytes = samples.size() / height;
  std::string raw;
  for (int y = 0; y < height; ++y) raw += '\0' + samples.substr(y * row_bytes, row_bytes);  // filter type 0
  const std::string ihdr = be32(width) + be32(height) + static_cast<char>(bit_depth) + static_cast<char>(color_type) +
                           std::string("\0\0\0", 3);
  return std::string("\x89PNG\r\n\x1a\n", 8) + chunk("IHDR", ihdr) + chunk("IDAT", zlib_stored(raw)) +
         chunk("IEND", "");
}

class ImageIoTest : public test::TempDirTest {
 protected:
  static void expect_names(const absl::Status& status, const fs::path& path) {
    EXPECT_FALSE(status.ok());
    EXPECT_NE(status.message().find(path.string()), absl::string_view::npos) << status;
  }
};

TEST_F(ImageIoTest, WritePngThenReadRoundTrips) {
  const at::Tensor image = at::rand({7, 5, 3}, at::kFloat);
  ASSERT_TRUE(write_png(dir_ / "a.png", image).ok());
  absl::StatusOr<at::Tensor> back = read_image(dir_ / "a.png");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->sizes().vec(), (std::vector<int64_t>{7, 5, 3}));
  EXPECT_EQ(back->scalar_type(), at::kFloat);
  EXPECT_LE((*back - image).abs().max().item<float>(), 0.5f / 255 + 1e-6f);
  absl::StatusOr<std::pair<int, int>> size = read_image_size(dir_ / "a.png");
  ASSERT_TRUE(size.ok()) << size.status();
  EXPECT_EQ(*size, std::make_pair(5, 7));
}

TEST_F(ImageIoTest, WritePngClampsAndAcceptsGrey) {
  at::Tensor grey = at::tensor({-1.0f, 0.5f, 2.0f, NAN}, at::kFloat).reshape({2, 2, 1});
  ASSERT_TRUE(write_png(dir_ / "g.png", grey).ok());
  absl::StatusOr<at::Tensor> back = read_image(dir_ / "g.png");
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->sizes().vec(), (std::vector<int64_t>{2, 2, 3}));
  const at::Tensor expected = at::tensor({0.0f, 128 / 255.0f, 1.0f, 0.0f}).reshape({2, 2, 1}).expand({2, 2, 3});
  EXPECT_TRUE(at::allclose(*back, expected, 0, 1e-6));
}

TEST_F(ImageIoTest, WritePngRejectsOtherShapes) {
  const fs::path path = dir_ / "bad.png";
  expect_names(write_png(path, at::zeros({4, 4, 2})), path);
  expect_names(write_png(path, at::zeros({4, 4})), path);
  expect_names(write_png(dir_ / "no_such_dir" / "x.png", at::zeros({4, 4, 3})), dir_ / "no_such_dir" / "x.png");
}

// Every image is written (in parallel) and each reads back as its own; one that cannot be written is the error,
// named, and does not stop the others.
TEST_F(ImageIoTest, WritePngsWritesEveryImageAndNamesTheOneThatFails) {
  std::vector<std::pair<fs::path, at::Tensor>> images;
  for (int i = 0; i < 9; ++i) images.push_back({dir_ / ("v" + std::to_string(i) + ".png"), at::rand({6, 4 + i, 3})});
  ASSERT_TRUE(write_pngs(images).ok());
  for (const auto& [path, image] : images) {
    absl::StatusOr<at::Tensor> back = read_image(path);
    ASSERT_TRUE(back.ok()) << back.status();
    EXPECT_LE((*back - image).abs().max().item<float>(), 0.5f / 255 + 1e-6f) << path;
  }
  const fs::path unwritable = dir_ / "no_such_dir" / "x.png";
  images.insert(images.begin() + 4, {unwritable, at::zeros({4, 4, 3})});
  fs::remove(images.back().first);
  expect_names(write_pngs(images), unwritable);
  EXPECT_TRUE(fs::exists(images.back().first));
}

TEST_F(ImageIoTest, Reads16BitRgb) {
  std::string samples;
  for (uint16_t v : {0, 65535, 32768, 1, 2, 3}) samples += {static_cast<char>(v >> 8), static_cast<char>(v & 0xff)};
  const fs::path path = write("deep.png", png_bytes(2, 1, 16, 2, samples));
  absl::StatusOr<at::Tensor> image = read_image(path);
  ASSERT_TRUE(image.ok()) << image.status();
  ASSERT_EQ(image->sizes().vec(), (std::vector<int64_t>{1, 2, 3}));
  EXPECT_EQ((*image)[0][0][1].item<float>(), 1.0f);
  EXPECT_NEAR((*image)[0][0][2].item<float>(), 32768 / 65535.0f, 1e-7);
  EXPECT_NEAR((*image)[0][1][0].item<float>(), 1 / 65535.0f, 1e-9);
}

TEST_F(ImageIoTest, DropsAlphaAndExpandsGrey) {
  // RGBA: alpha must not leak into the colours.
  const fs::path rgba = write("rgba.png", png_bytes(1, 1, 8, 6, std::string("\x0a\x14\x1e\x00", 4)));
  absl::StatusOr<at::Tensor> image = read_image(rgba);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_TRUE(at::allclose(*image, at::tensor({10.0f, 20.0f, 30.0f}).div(255).reshape({1, 1, 3})));
  // Grey + alpha.
  const fs::path ga = write("ga.png", png_bytes(2, 1, 8, 4, std::string("\x33\xff\xcc\x00", 4)));
  image = read_image(ga);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_TRUE(at::allclose((*image)[0][1], at::full({3}, 0xcc / 255.0f)));
}

TEST_F(ImageIoTest, ErrorsNameTheFile) {
  const fs::path missing = dir_ / "missing.png";
  absl::StatusOr<at::Tensor> image = read_image(missing);
  expect_names(image.status(), missing);
  EXPECT_TRUE(absl::IsNotFound(image.status()));
  expect_names(read_image_size(missing).status(), missing);

  const fs::path garbage = write("garbage.jpg", "this is not an image at all");
  expect_names(read_image(garbage).status(), garbage);
  expect_names(read_image_size(garbage).status(), garbage);

  // A PNG cut short keeps a valid header (its size reads fine) but its pixels cannot be decoded.
  const std::string full = png_bytes(8, 8, 8, 2, std::string(8 * 8 * 3, '\x40'));
  const fs::path truncated = write("truncated.png", full.substr(0, full.size() / 2));
  EXPECT_TRUE(read_image_size(truncated).ok());
  image = read_image(truncated);
  expect_names(image.status(), truncated);
  EXPECT_NE(image.status().message().find("not a readable"), absl::string_view::npos) << image.status();

  const fs::path bmp = write("picture.bmp", std::string("BM") + std::string(60, '\0'));
  expect_names(read_image(bmp).status(), bmp);
}

TEST_F(ImageIoTest, ResizeAveragesBoxesForIntegerFactors) {
  const at::Tensor image = at::arange(16, at::kFloat).reshape({4, 4, 1}).expand({4, 4, 3}).contiguous();
  const at::Tensor half = resize_image(image, 2, 2);
  ASSERT_EQ(half.sizes().vec(), (std::vector<int64_t>{2, 2, 3}));
  // Top-left 2x2 block is {0, 1, 4, 5}.
  EXPECT_FLOAT_EQ(half[0][0][0].item<float>(), 2.5f);
  EXPECT_FLOAT_EQ(half[1][1][2].item<float>(), (10 + 11 + 14 + 15) / 4.0f);
  const at::Tensor wide = resize_image(image, 6, 3);
  EXPECT_EQ(wide.sizes().vec(), (std::vector<int64_t>{3, 6, 3}));
  EXPECT_TRUE(at::equal(resize_image(image, 4, 4), image));
}

TEST_F(ImageIoTest, ReadsRealPngAndJpeg) {
  const fs::path data(GAPS_DATA_DIR);
  const fs::path png = data / "llff" / "fern" / "images_8" / "image000.png";
  const fs::path jpg = data / "mipnerf360" / "bonsai" / "images_800x533" / "DSCF5565.JPG";
  if (!fs::exists(png) || !fs::exists(jpg)) GTEST_SKIP() << "no benchmark data at " << GAPS_DATA_DIR;
  for (const auto& [path, w, h] : {std::tuple{png, 504, 378}, std::tuple{jpg, 800, 533}}) {
    absl::StatusOr<at::Tensor> image = read_image(path);
    ASSERT_TRUE(image.ok()) << image.status();
    EXPECT_EQ(image->sizes().vec(), (std::vector<int64_t>{h, w, 3})) << path;
    EXPECT_GE(image->min().item<float>(), 0.0f);
    EXPECT_LE(image->max().item<float>(), 1.0f);
    EXPECT_GT(image->std().item<float>(), 0.05f) << "a real photo is not flat";
    absl::StatusOr<std::pair<int, int>> size = read_image_size(path);
    ASSERT_TRUE(size.ok()) << size.status();
    EXPECT_EQ(*size, std::make_pair(w, h));
  }
}

// A PNG header announcing 16000 x 16000 pixels (a decompression bomb: the pixels would follow as a few
// hundred kilobytes of zlib) is refused from the header, before anything is allocated for the pixels.
std::string png_header(uint32_t width, uint32_t height) {
  const auto be32 = [](uint32_t v) {
    return std::string{static_cast<char>(v >> 24), static_cast<char>(v >> 16), static_cast<char>(v >> 8),
                       static_cast<char>(v)};
  };
  return std::string("\x89PNG\r\n\x1a\n", 8) + be32(13) + "IHDR" + be32(width) + be32(height) +
         std::string("\x08\x02\x00\x00\x00", 5) + be32(0);
}

TEST(ImageIo, AHugeImageIsRefusedFromItsHeader) {
  const auto decoded = decode_image(png_header(16000, 16000), "upload.png");
  ASSERT_FALSE(decoded.ok());
  EXPECT_EQ(decoded.status().code(), absl::StatusCode::kInvalidArgument) << decoded.status();
  EXPECT_NE(decoded.status().message().find("16000x16000 pixels (256 megapixels) is over the limit of 100"),
            std::string_view::npos)
      << decoded.status();
}

// 400 megapixels of RGB pass stb's own 1 GiB header limit, which answered "unknown image type": the size
// is the reason, and the message says so.
TEST(ImageIo, AnImageOverStbsOwnLimitIsRefusedForItsSize) {
  const auto decoded = decode_image(png_header(20000, 20000), "big.png");
  ASSERT_FALSE(decoded.ok());
  EXPECT_EQ(decoded.status().code(), absl::StatusCode::kInvalidArgument) << decoded.status();
  EXPECT_NE(decoded.status().message().find("20000x20000 pixels (400 megapixels) is over the limit of 100"),
            std::string_view::npos)
      << decoded.status();
}

// A DHT segment whose 16 code counts sum past 256 made stb_image write beyond its Huffman table (found by
// fuzz/image_fuzz.cpp; the inputs are in fuzz/regressions/image/). JPEG goes through libjpeg-turbo, which
// refuses them, from memory and from a file, naming the file.
TEST(ImageIo, AJpegHuffmanTableWithMoreThan256CodesIsRefused) {
  // SOI, then a DHT of one table: class/id byte, 16 counts (16 x 17 = 272 codes), the code values.
  std::string jpeg("\xFF\xD8\xFF\xC4", 4);
  const size_t length = 2 + 1 + 16 + 272;
  jpeg += static_cast<char>(length >> 8);
  jpeg += static_cast<char>(length & 0xFF);
  jpeg += '\x00';
  jpeg += std::string(16, '\x11');
  jpeg += std::string(272, '\x01');
  jpeg += std::string("\xFF\xD9", 2);
  for (const absl::Status& st :
       {decode_image(jpeg, "upload.jpg").status(), decode_image_size(jpeg, "upload.jpg").status()}) {
    EXPECT_EQ(st.code(), absl::StatusCode::kDataLoss) << st;
    EXPECT_NE(st.message().find("upload.jpg: not a readable JPEG image (Bogus Huffman table definition)"),
              std::string_view::npos)
        << st;
  }
  for (const auto& entry :
       std::filesystem::directory_iterator(std::filesystem::path(GAPS_SOURCE_DIR) / "fuzz/regressions/image")) {
    const auto found = read_file_bytes(entry.path());
    ASSERT_TRUE(found.ok()) << found.status();
    EXPECT_NE(decode_image(*found, "found.jpg").status().message().find("found.jpg: not a readable JPEG image"),
              std::string_view::npos)
        << entry.path();
  }
  // A valid JPEG still decodes, to the size its header gives.
  const auto seed = read_file_bytes(std::filesystem::path(GAPS_SOURCE_DIR) / "fuzz/corpus/image/rgb.jpg");
  ASSERT_TRUE(seed.ok());
  const auto decoded = decode_image(*seed, "rgb.jpg");
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_EQ(decoded->sizes().vec(), (std::vector<int64_t>{6, 8, 3}));
}

}  // namespace
}  // namespace gaps
