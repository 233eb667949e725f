// PNG/JPEG bytes through the image loader: from memory (uploads, generated images) and from a file header.
#include "common/image_io.h"
#include "fuzz/fuzz_support.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string bytes(gaps::fuzz::as_bytes(data, size));
  const auto header = gaps::decode_image_size(bytes, "input");
  const auto image = gaps::decode_image(bytes, "input");
  // The header alone must predict what decoding gives.
  if (image.ok() && (!header.ok() || image->size(0) != header->second || image->size(1) != header->first))
    __builtin_trap();
  const auto path = gaps::fuzz::write_scratch("input.img", bytes);
  const auto file_header = gaps::read_image_size(path);
  if (header.ok() != file_header.ok() || (header.ok() && *header != *file_header)) __builtin_trap();
  return 0;
}
