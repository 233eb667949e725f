#include "server/artifacts.h"

#include <algorithm>
#include <fstream>
#include <string>

#include "absl/strings/str_cat.h"
#include "rpc/codec.h"

namespace gaps {
namespace fs = std::filesystem;

std::vector<JobStore::Artifact> list_artifacts(const fs::path& out_dir) {
  std::vector<JobStore::Artifact> out;
  std::error_code ec;
  for (auto it = fs::recursive_directory_iterator(out_dir, ec); !ec && it != fs::recursive_directory_iterator();
       it.increment(ec)) {
    if (!it->is_regular_file()) continue;
    out.push_back({fs::relative(it->path(), out_dir).generic_string(), static_cast<int64_t>(it->file_size())});
  }
  std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) { return a.path < b.path; });
  return out;
}

grpc::Status stream_artifacts(const fs::path& out_dir, const std::vector<JobStore::Artifact>& artifacts,
                              grpc::ServerWriter<v1::ArtifactChunk>* writer) {
  for (const auto& a : artifacts) {
    std::ifstream file(out_dir / a.path, std::ios::binary);
    if (!file)
      return grpc::Status(grpc::StatusCode::DATA_LOSS, absl::StrCat("artifact ", a.path, " is missing on disk"));
    std::string buffer(rpc::kChunkBytes, '\0');
    do {
      file.read(buffer.data(), buffer.size());
      v1::ArtifactChunk chunk;
      chunk.set_path(a.path);
      chunk.set_data(buffer.data(), file.gcount());
      chunk.set_last(file.eof());
      if (!writer->Write(chunk)) return grpc::Status(grpc::StatusCode::CANCELLED, "reader went away");
    } while (!file.eof());
  }
  return grpc::Status::OK;
}

}  // namespace gaps
