#pragma once
// CLIP's byte-level BPE tokenizer, reading vocab.json and merges.txt (and the pad token from
// tokenizer_config.json) of a diffusers tokenizer folder.
//
// Text is whitespace-collapsed and lower-cased, split by CLIP's pattern (contractions, letter runs,
// single digits, other-symbol runs), each piece byte-encoded, given the "</w>" end-of-word mark and
// merged by rank; the special tokens (start, end, pad) are cut out of the raw text first. Exact for ASCII text; beyond
// ASCII, lower-casing and Unicode normalisation are not applied and every non-ASCII code point counts as a letter.
#include <map>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"

namespace gaps::sdxl {

class ClipTokenizer {
 public:
  // folder holds vocab.json, merges.txt and optionally tokenizer_config.json (pad_token,
  // model_max_length); the pad token defaults to <|endoftext|>.
  static absl::StatusOr<ClipTokenizer> load(const std::string& folder);

  // <|startoftext|>, the text's tokens (truncated to max_length - 2), <|endoftext|>, then the pad token
  // up to max_length (default: model_max_length).
  std::vector<int64_t> encode(const std::string& text, int64_t max_length = -1) const;
  // Tokens of the text alone, no special tokens.
  std::vector<int64_t> tokenize(const std::string& text) const;

  int64_t bos_id() const { return bos_id_; }
  int64_t eos_id() const { return eos_id_; }
  int64_t pad_id() const { return pad_id_; }
  int64_t model_max_length() const { return model_max_length_; }

 private:
  std::vector<std::string> bpe(const std::string& piece) const;
  void tokenize_plain(const std::string& text, std::vector<int64_t>* ids) const;

  std::unordered_map<std::string, int64_t> vocab_;
  std::map<std::pair<std::string, std::string>, int64_t> merge_ranks_;
  std::vector<std::pair<std::string, int64_t>> special_tokens_;
  std::vector<std::string> byte_symbols_;  // byte value -> its printable stand-in (UTF-8)
  int64_t bos_id_ = 0, eos_id_ = 0, pad_id_ = 0, model_max_length_ = 77;
};

}  // namespace gaps::sdxl
