#pragma once
// Names inside a run folder that several parts write or read: the method saves its pseudo-views there, the report
// and the viewer show them.
#include <filesystem>

namespace gaps {

// The run folder's sub-folder of pseudo-views saved for inspection.
inline constexpr char kPseudoViewsFolder[] = "pseudo_views";

// A saved pseudo-view's path inside kPseudoViewsFolder: phase_PP/cand_III_admitted.png (or _rejected.png).
std::filesystem::path pseudo_view_file(int phase, int candidate_id, bool admitted);

}  // namespace gaps
