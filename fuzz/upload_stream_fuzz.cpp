// SubmitJob's message stream as the trainer receives it: a JobSpec (cameras, config) and file chunks,
// streamed to files, then checked and made a scene. The input is the delimited stream of
// SubmitJobRequest messages (proto_stream.h).
#include "common/io_util.h"
#include "fuzz/fuzz_support.h"
#include "fuzz/proto_stream.h"
#include "server/scene_upload.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const auto messages = gaps::fuzz::read_delimited<gaps::v1::SubmitJobRequest>(data, size, 256);
  size_t next = 0;
  const auto source = [&](gaps::v1::SubmitJobRequest* m) {
    if (next == messages.size()) return false;
    *m = messages[next++];
    return true;
  };
  const auto dir = gaps::fuzz::scratch_dir() / "upload";
  const auto upload = gaps::receive_upload(source, uint64_t{1} << 20, dir);
  if (upload.ok()) (void)gaps::write_uploaded_scene(*upload);
  gaps::remove_tree(dir);
  return 0;
}
