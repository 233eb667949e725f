#pragma once
// Text that came from elsewhere (a job's or a camera's name, a job's log line, an artifact's path) made safe to
// print or to name a file with: a control character (C0 or DEL) could otherwise move the cursor, recolour or
// rewrite another user's terminal, or make a file name that no shell lists plainly.
#include <string>

#include "absl/strings/str_format.h"
#include "absl/strings/string_view.h"

namespace gaps {

inline bool is_control_character(char c) {
  const auto u = static_cast<unsigned char>(c);
  return u < 0x20 || u == 0x7f;
}

inline bool has_control_characters(absl::string_view text) {
  for (char c : text)
    if (is_control_character(c)) return true;
  return false;
}

// Control characters become \xNN escapes; everything else stays as it is. Text of several lines (a job's log)
// keeps its line breaks and tabs with `keep_lines`; a name never does.
inline std::string printable(absl::string_view text, bool keep_lines = false) {
  std::string out;
  out.reserve(text.size());
  for (char c : text) {
    if (is_control_character(c) && !(keep_lines && (c == '\n' || c == '\t')))
      out += absl::StrFormat("\\x%02x", static_cast<unsigned char>(c));
    else
      out += c;
  }
  return out;
}

// Control characters become '_' (a file name keeps its length and stays one path component).
inline std::string safe_file_name(absl::string_view name) {
  std::string out(name);
  for (char& c : out)
    if (is_control_character(c)) c = '_';
  return out;
}

}  // namespace gaps
