#include "diffusion_worker/sdxl/clip_tokenizer.h"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <limits>
#include <utility>

#include <nlohmann/json.hpp>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

namespace gaps::sdxl {
namespace {

std::string utf8(uint32_t cp) {
  std::string s;
  if (cp < 0x80) {
    s += static_cast<char>(cp);
  } else if (cp < 0x800) {
    s += static_cast<char>(0xC0 | (cp >> 6));
    s += static_cast<char>(0x80 | (cp & 0x3F));
  } else {
    s += static_cast<char>(0xE0 | (cp >> 12));
    s += static_cast<char>(0x80 | ((cp >> 6) & 0x3F));
    s += static_cast<char>(0x80 | (cp & 0x3F));
  }
  return s;
}

// GPT-2/CLIP byte-level stand-ins: printable Latin-1 bytes map to themselves, the rest to 256 + n.
std::vector<std::string> byte_symbols() {
  std::vector<std::string> symbols(256);
  uint32_t next = 256;
  for (uint32_t b = 0; b < 256; ++b) {
    const bool printable = (b >= '!' && b <= '~') || (b >= 0xA1 && b <= 0xAC) || (b >= 0xAE && b <= 0xFF);
    symbols[b] = utf8(printable ? b : next++);
  }
  return symbols;
}

enum class CharClass { kSpace, kLetter, kDigit, kOther };

CharClass classify(unsigned char c) {
  if (c == ' ' || c == '\t' || c == '\n' || c == '\r' || c == '\f' || c == '\v') return CharClass::kSpace;
  if (c >= 0x80 || (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z')) return CharClass::kLetter;
  if (c >= '0' && c <= '9') return CharClass::kDigit;
  return CharClass::kOther;
}

// CLIP's split: 's 't 're 've 'm 'll 'd, letter runs, single digits,
// runs of other symbols; whitespace separates and is dropped.
std::vector<std::string> split_pieces(const std::string& text) {
  static const char* kContractions[] = {"'s", "'t", "'re", "'ve", "'m", "'ll", "'d"};
  std::vector<std::string> pieces;
  size_t i = 0;
  const auto starts_with = [&](const char* s) { return text.compare(i, std::char_traits<char>::length(s), s) == 0; };
  while (i < text.size()) {
    const CharClass cls = classify(static_cast<unsigned char>(text[i]));
    if (cls == CharClass::kSpace) {
      ++i;
      continue;
    }
    size_t len = 0;
    for (const char* s : kContractions) {
      if (len == 0 && starts_with(s)) len = std::char_traits<char>::length(s);
    }
    if (len == 0) {
      if (cls == CharClass::kDigit) {
        len = 1;
      } else {
        size_t j = i;
        while (j < text.size() && classify(static_cast<unsigned char>(text[j])) == cls) ++j;
        len = j - i;
      }
    }
    pieces.push_back(text.substr(i, len));
    i += len;
  }
  return pieces;
}

std::string normalise(const std::string& text) {
  std::string out;
  bool pending_space = false;
  for (unsigned char c : text) {
    if (classify(c) == CharClass::kSpace) {
      pending_space = !out.empty();
      continue;
    }
    if (pending_space) out += ' ';
    pending_space = false;
    out += static_cast<char>(c >= 'A' && c <= 'Z' ? c - 'A' + 'a' : c);
  }
  return out;
}

std::string token_string(const nlohmann::json& value) {
  if (value.is_string()) return value.get<std::string>();
  if (value.is_object() && value.contains("content")) return value["content"].get<std::string>();
  return "";
}

}  // namespace

absl::StatusOr<ClipTokenizer> ClipTokenizer::load(const std::string& folder) {
  const std::filesystem::path dir(folder);
  ClipTokenizer tok;
  tok.byte_symbols_ = byte_symbols();
  GAPS_ASSIGN_OR_RETURN(nlohmann::json vocab, read_json_file((dir / "vocab.json").string()));
  if (!vocab.is_object() || vocab.empty())
    return absl::InvalidArgumentError(absl::StrCat(folder, "/vocab.json is not a token -> id object"));
  for (const auto& [token, id] : vocab.items()) {
    if (!id.is_number_integer())
      return absl::InvalidArgumentError(absl::StrCat(folder, "/vocab.json: id of '", token, "' is not an integer"));
    tok.vocab_.emplace(token, id.get<int64_t>());
  }
  std::ifstream merges(dir / "merges.txt");
  if (!merges) return absl::NotFoundError(absl::StrCat("cannot read ", folder, "/merges.txt"));
  std::string line;
  int64_t rank = 0, line_number = 0;
  while (std::getline(merges, line)) {
    ++line_number;
    if (line.empty() || (line_number == 1 && line.rfind("#version", 0) == 0)) continue;
    const size_t space = line.find(' ');
    if (space == std::string::npos || line.find(' ', space + 1) != std::string::npos) {
      return absl::InvalidArgumentError(
          absl::StrCat(folder, "/merges.txt line ", line_number, " is not 'a b': ", line));
    }
    tok.merge_ranks_.emplace(std::make_pair(line.substr(0, space), line.substr(space + 1)), rank++);
  }
  std::string pad = "<|endoftext|>";
  if (std::filesystem::exists(dir / "tokenizer_config.json")) {
    GAPS_ASSIGN_OR_RETURN(nlohmann::json config, read_json_file((dir / "tokenizer_config.json").string()));
    if (config.contains("pad_token") && !token_string(config["pad_token"]).empty())
      pad = token_string(config["pad_token"]);
    if (config.contains("model_max_length") && config["model_max_length"].is_number_integer() &&
        config["model_max_length"].get<int64_t>() < 100000) {
      tok.model_max_length_ = config["model_max_length"].get<int64_t>();
    }
  }
  const auto id_of = [&](const std::string& token) -> absl::StatusOr<int64_t> {
    const auto it = tok.vocab_.find(token);
    if (it == tok.vocab_.end())
      return absl::InvalidArgumentError(absl::StrCat(folder, "/vocab.json lacks the token ", token));
    return it->second;
  };
  GAPS_ASSIGN_OR_RETURN(tok.bos_id_, id_of("<|startoftext|>"));
  GAPS_ASSIGN_OR_RETURN(tok.eos_id_, id_of("<|endoftext|>"));
  GAPS_ASSIGN_OR_RETURN(tok.pad_id_, id_of(pad));
  tok.special_tokens_ = {{"<|startoftext|>", tok.bos_id_}, {"<|endoftext|>", tok.eos_id_}, {pad, tok.pad_id_}};
  return tok;
}

std::vector<std::string> ClipTokenizer::bpe(const std::string& piece) const {
  std::vector<std::string> parts;
  for (unsigned char c : piece) parts.push_back(byte_symbols_[c]);
  if (parts.empty()) return parts;
  parts.back() += "</w>";
  while (parts.size() > 1) {
    int64_t best_rank = std::numeric_limits<int64_t>::max();
    size_t best = 0;
    for (size_t i = 0; i + 1 < parts.size(); ++i) {
      const auto it = merge_ranks_.find({parts[i], parts[i + 1]});
      if (it != merge_ranks_.end() && it->second < best_rank) {
        best_rank = it->second;
        best = i;
      }
    }
    if (best_rank == std::numeric_limits<int64_t>::max()) break;
    // Merge every occurrence of the best pair, left to right.
    const std::string a = parts[best], b = parts[best + 1];
    std::vector<std::string> merged;
    for (size_t i = 0; i < parts.size(); ++i) {
      if (i + 1 < parts.size() && parts[i] == a && parts[i + 1] == b) {
        merged.push_back(a + b);
        ++i;
      } else {
        merged.push_back(parts[i]);
      }
    }
    parts = std::move(merged);
  }
  return parts;
}

void ClipTokenizer::tokenize_plain(const std::string& text, std::vector<int64_t>* ids) const {
  for (const std::string& piece : split_pieces(normalise(text))) {
    for (const std::string& token : bpe(piece)) {
      const auto it = vocab_.find(token);
      ids->push_back(it == vocab_.end() ? eos_id_ : it->second);  // CLIP's unknown token is <|endoftext|>
    }
  }
}

std::vector<int64_t> ClipTokenizer::tokenize(const std::string& text) const {
  // Special tokens (start, end and pad, e.g. SDXL's second tokenizer pads with "!") are cut out of the
  // raw text first and never enter BPE, as in transformers.
  std::vector<int64_t> ids;
  size_t begin = 0, i = 0;
  while (i < text.size()) {
    const std::pair<std::string, int64_t>* match = nullptr;
    for (const auto& special : special_tokens_) {
      if (text.compare(i, special.first.size(), special.first) == 0 &&
          (match == nullptr || special.first.size() > match->first.size())) {
        match = &special;
      }
    }
    if (match == nullptr) {
      ++i;
      continue;
    }
    tokenize_plain(text.substr(begin, i - begin), &ids);
    ids.push_back(match->second);
    i += match->first.size();
    begin = i;
  }
  tokenize_plain(text.substr(begin), &ids);
  return ids;
}

std::vector<int64_t> ClipTokenizer::encode(const std::string& text, int64_t max_length) const {
  if (max_length < 0) max_length = model_max_length_;
  std::vector<int64_t> tokens = tokenize(text);
  if (static_cast<int64_t>(tokens.size()) > max_length - 2) tokens.resize(std::max<int64_t>(0, max_length - 2));
  std::vector<int64_t> ids{bos_id_};
  ids.insert(ids.end(), tokens.begin(), tokens.end());
  ids.push_back(eos_id_);
  ids.resize(std::max<int64_t>(max_length, ids.size()), pad_id_);
  return ids;
}

}  // namespace gaps::sdxl
