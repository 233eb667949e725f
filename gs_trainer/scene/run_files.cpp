#include "gs_trainer/scene/run_files.h"

#include "absl/strings/str_format.h"

namespace gaps {

std::filesystem::path pseudo_view_file(int phase, int candidate_id, bool admitted) {
  return std::filesystem::path(absl::StrFormat("phase_%02d", phase)) /
         absl::StrFormat("cand_%03d_%s.png", candidate_id, admitted ? "admitted" : "rejected");
}

}  // namespace gaps
