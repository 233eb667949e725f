#include "common/torch_pickle.h"

#include <set>

#include <ATen/ATen.h>
#include <c10/util/Exception.h>
#include <caffe2/serialize/inline_container.h>

#include <algorithm>
#include <cerrno>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <limits>
#include <memory>
#include <optional>
#include <string_view>
#include <unordered_map>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "common/status_macros.h"

namespace gaps {
namespace {

// ---------------------------------------------------------------------------------------------
// Byte sources. The unpickler reads from memory (zip: data.pkl) or straight from the file
// (legacy: pickles and storage bytes follow each other, so large storages are read directly into
// tensor memory instead of buffering the whole file).

class ByteSource {
 public:
  virtual ~ByteSource() = default;
  // Reads exactly n bytes; fails on truncated input.
  virtual absl::Status read(void* dst, uint64_t n) = 0;
  virtual uint64_t offset() const = 0;
  virtual uint64_t remaining() const = 0;
};

absl::Status truncated(uint64_t offset, uint64_t wanted, uint64_t left) {
  return absl::DataLossError(absl::StrFormat(
      "unexpected end of data at byte %d (needed %d more bytes, %d left): file truncated?", offset, wanted, left));
}

class MemorySource final : public ByteSource {
 public:
  explicit MemorySource(std::string_view data) : data_(data) {}
  absl::Status read(void* dst, uint64_t n) override {
    if (n > remaining()) return truncated(pos_, n, remaining());
    if (n > 0) std::memcpy(dst, data_.data() + pos_, n);
    pos_ += n;
    return absl::OkStatus();
  }
  uint64_t offset() const override { return pos_; }
  uint64_t remaining() const override { return data_.size() - pos_; }

 private:
  std::string_view data_;
  uint64_t pos_ = 0;
};

class FileSource final : public ByteSource {
 public:
  FileSource(std::ifstream& in, uint64_t size) : in_(in), size_(size) {}
  absl::Status read(void* dst, uint64_t n) override {
    // Checking against the known size first avoids huge allocations from corrupt length fields.
    if (n > remaining()) return truncated(pos_, n, remaining());
    in_.read(static_cast<char*>(dst), static_cast<std::streamsize>(n));
    if (static_cast<uint64_t>(in_.gcount()) != n) return truncated(pos_, n, in_.gcount());
    pos_ += n;
    return absl::OkStatus();
  }
  uint64_t offset() const override { return pos_; }
  uint64_t remaining() const override { return size_ - pos_; }

 private:
  std::ifstream& in_;
  uint64_t size_;
  uint64_t pos_ = 0;
};

// ---------------------------------------------------------------------------------------------
// The Python object model of the pickle VM: just enough for state dicts.

struct StorageRef {
  std::string key;
  at::ScalarType dtype;
  int64_t numel;    // elements of the whole storage
  at::Tensor data;  // 1-D CPU tensor of numel elements, filled once the storage bytes are read
};
using StorageTable = std::unordered_map<std::string, std::shared_ptr<StorageRef>>;

enum class Kind {
  kNone,
  kBool,
  kInt,
  kBigInt,
  kFloat,
  kString,
  kBytes,
  kTuple,
  kList,
  kDict,
  kGlobal,
  kStorage,
  kTensor
};

const char* kind_name(Kind kind) {
  switch (kind) {
    case Kind::kNone:
      return "None";
    case Kind::kBool:
      return "bool";
    case Kind::kInt:
      return "int";
    case Kind::kBigInt:
      return "int (wider than 64 bits)";
    case Kind::kFloat:
      return "float";
    case Kind::kString:
      return "str";
    case Kind::kBytes:
      return "bytes";
    case Kind::kTuple:
      return "tuple";
    case Kind::kList:
      return "list";
    case Kind::kDict:
      return "dict";
    case Kind::kGlobal:
      return "global";
    case Kind::kStorage:
      return "storage";
    case Kind::kTensor:
      return "tensor";
  }
  return "?";
}

struct PyObj;
using ObjPtr = std::shared_ptr<PyObj>;

struct PyObj {
  Kind kind = Kind::kNone;
  int64_t int_value = 0;  // kBool, kInt
  double float_value = 0;
  // kString/kBytes: the bytes; kBigInt: little-endian two's complement; kGlobal: "module.name".
  std::string text;
  std::vector<ObjPtr> items;                       // kTuple, kList
  std::vector<std::pair<ObjPtr, ObjPtr>> entries;  // kDict, insertion order (later keys win)
  std::shared_ptr<StorageRef> storage;             // kStorage, kTensor
  int64_t storage_offset = 0;                      // elements; kStorage: legacy view offset, kTensor: tensor offset
  std::vector<int64_t> sizes, strides;             // kTensor
};

ObjPtr make(Kind kind) {
  auto obj = std::make_shared<PyObj>();
  obj->kind = kind;
  return obj;
}
ObjPtr make_int(int64_t value, Kind kind = Kind::kInt) {
  ObjPtr obj = make(kind);
  obj->int_value = value;
  return obj;
}
ObjPtr make_text(std::string text, Kind kind) {
  ObjPtr obj = make(kind);
  obj->text = std::move(text);
  return obj;
}
ObjPtr make_sequence(Kind kind, std::vector<ObjPtr> items) {
  ObjPtr obj = make(kind);
  obj->items = std::move(items);
  return obj;
}

bool is_sequence(const PyObj& obj) { return obj.kind == Kind::kTuple || obj.kind == Kind::kList; }

// Whether `target` is `from` or lies inside it. Objects are shared_ptrs: a container put into itself
// (directly or through others) would never be freed (found by fuzz/torch_pickle_fuzz.cpp), so APPEND and
// SETITEM refuse to close such a cycle; checkpoints never hold one.
bool reaches(const ObjPtr& from, const PyObj* target) {
  std::vector<const PyObj*> pending{from.get()};
  std::set<const PyObj*> seen;
  while (!pending.empty()) {
    const PyObj* obj = pending.back();
    pending.pop_back();
    if (obj == nullptr || !seen.insert(obj).second) continue;
    if (obj == target) return true;
    for (const ObjPtr& item : obj->items) pending.push_back(item.get());
    for (const auto& [key, value] : obj->entries) {
      pending.push_back(key.get());
      pending.push_back(value.get());
    }
  }
  return false;
}

// torch.<Name>Storage (or the old torch.cuda.<Name>Storage) -> element type.
std::optional<at::ScalarType> storage_dtype(const std::string& global) {
  static const std::unordered_map<std::string, at::ScalarType> kTypes = {{"FloatStorage", at::kFloat},
                                                                         {"DoubleStorage", at::kDouble},
                                                                         {"HalfStorage", at::kHalf},
                                                                         {"BFloat16Storage", at::kBFloat16},
                                                                         {"LongStorage", at::kLong},
                                                                         {"IntStorage", at::kInt},
                                                                         {"ShortStorage", at::kShort},
                                                                         {"CharStorage", at::kChar},
                                                                         {"ByteStorage", at::kByte},
                                                                         {"BoolStorage", at::kBool},
                                                                         {"ComplexFloatStorage", at::kComplexFloat},
                                                                         {"ComplexDoubleStorage", at::kComplexDouble},
                                                                         {"UntypedStorage", at::kByte}};
  for (std::string_view module : {"torch.", "torch.cuda."}) {
    if (global.rfind(module, 0) != 0) continue;
    auto it = kTypes.find(global.substr(module.size()));
    if (it != kTypes.end()) return it->second;
  }
  return std::nullopt;
}

// ---------------------------------------------------------------------------------------------
// The pickle VM (protocols 0-5, the opcodes that state dicts use).

class Unpickler {
 public:
  // `storages` is shared by all pickles of one file so that every persistent id with the same key
  // resolves to the same storage.
  Unpickler(ByteSource& src, std::string context, StorageTable& storages)
      : src_(src), context_(std::move(context)), storages_(storages) {}

  absl::StatusOr<ObjPtr> load() {
    while (!stopped_) {
      uint8_t op = 0;
      if (absl::Status s = src_.read(&op, 1); !s.ok()) return wrap(s);
      op_offset_ = src_.offset() - 1;
      if (absl::Status s = execute(op); !s.ok()) return wrap(s);
    }
    if (stack_.size() != 1 || !marks_.empty()) {
      return error(absl::StrFormat("malformed pickle: %d objects left on the stack at STOP", stack_.size()));
    }
    return stack_.back();
  }

 private:
  absl::Status wrap(const absl::Status& status) const {
    return absl::Status(status.code(), absl::StrCat(context_, ": ", status.message()));
  }
  absl::Status error(absl::string_view what) const {
    return absl::InvalidArgumentError(absl::StrFormat("%s: %s (pickle opcode at byte %d)", context_, what, op_offset_));
  }
  // Errors raised inside execute() get the context added by load().
  absl::Status fail(absl::string_view what) const {
    return absl::InvalidArgumentError(absl::StrFormat("%s (pickle opcode at byte %d)", what, op_offset_));
  }

  // ---- raw reads ----
  template <typename T>
  absl::StatusOr<T> read_le() {
    // Pickle integers are little-endian, as are the hosts LibTorch supports here (x86-64, arm64).
    T value{};
    GAPS_RETURN_IF_ERROR(src_.read(&value, sizeof(T)));
    return value;
  }
  absl::StatusOr<std::string> read_bytes(uint64_t n) {
    if (n > src_.remaining()) return truncated(src_.offset(), n, src_.remaining());
    std::string out(n, '\0');
    GAPS_RETURN_IF_ERROR(src_.read(out.data(), n));
    return out;
  }
  absl::StatusOr<std::string> read_line() {
    std::string line;
    for (;;) {
      char c = 0;
      GAPS_RETURN_IF_ERROR(src_.read(&c, 1));
      if (c == '\n') return line;
      if (line.size() > 4096) return fail("text opcode argument longer than 4096 bytes");
      line.push_back(c);
    }
  }
  absl::StatusOr<int64_t> read_decimal_line() {
    GAPS_ASSIGN_OR_RETURN(std::string line, read_line());
    if (!line.empty() && line.back() == 'L') line.pop_back();  // protocol-0 longs end with 'L'
    char* end = nullptr;
    errno = 0;
    int64_t value = std::strtoll(line.c_str(), &end, 10);
    if (line.empty() || *end != '\0' || errno != 0) {
      return fail(absl::StrCat("bad decimal integer '", line, "'"));
    }
    return value;
  }

  // ---- stack ----
  void push(ObjPtr obj) { stack_.push_back(std::move(obj)); }
  size_t floor() const { return marks_.empty() ? 0 : marks_.back(); }
  absl::StatusOr<ObjPtr> pop() {
    if (stack_.size() <= floor()) return fail("pickle stack underflow");
    ObjPtr obj = std::move(stack_.back());
    stack_.pop_back();
    return obj;
  }
  absl::StatusOr<ObjPtr> top() {
    if (stack_.size() <= floor()) return fail("pickle stack underflow");
    return stack_.back();
  }
  absl::StatusOr<std::vector<ObjPtr>> pop_to_mark() {
    if (marks_.empty()) return fail("pickle MARK expected but none is set");
    size_t mark = marks_.back();
    marks_.pop_back();
    std::vector<ObjPtr> items(stack_.begin() + static_cast<std::ptrdiff_t>(mark), stack_.end());
    stack_.resize(mark);
    return items;
  }
  absl::StatusOr<ObjPtr> top_of_kind(Kind kind, absl::string_view opcode) {
    GAPS_ASSIGN_OR_RETURN(ObjPtr obj, top());
    if (obj->kind != kind) {
      return fail(absl::StrCat(opcode, " applied to a ", kind_name(obj->kind), ", expected a ", kind_name(kind)));
    }
    return obj;
  }

  // ---- memo ----
  absl::Status memo_put(uint64_t index) {
    GAPS_ASSIGN_OR_RETURN(ObjPtr obj, top());
    memo_[index] = std::move(obj);
    return absl::OkStatus();
  }
  absl::Status memo_get(uint64_t index) {
    auto it = memo_.find(index);
    if (it == memo_.end()) return fail(absl::StrFormat("memo key %d is not defined", index));
    push(it->second);
    return absl::OkStatus();
  }

  // ---- compound opcodes ----
  absl::Status push_long(const std::string& bytes) {
    if (bytes.size() > 8) {
      push(make_text(bytes, Kind::kBigInt));
      return absl::OkStatus();
    }
    uint64_t value = 0;
    for (size_t i = 0; i < bytes.size(); ++i) value |= uint64_t{uint8_t(bytes[i])} << (8 * i);
    // Sign-extend from the top byte (two's complement of the given width).
    if (!bytes.empty() && bytes.size() < 8 && (uint8_t(bytes.back()) & 0x80)) {
      value |= ~uint64_t{0} << (8 * bytes.size());
    }
    push(make_int(static_cast<int64_t>(value)));
    return absl::OkStatus();
  }
  absl::Status push_text(uint64_t n, Kind kind) {
    GAPS_ASSIGN_OR_RETURN(std::string text, read_bytes(n));
    push(make_text(std::move(text), kind));
    return absl::OkStatus();
  }
  absl::Status push_tuple_of(size_t n) {
    std::vector<ObjPtr> items(n);
    for (size_t i = n; i-- > 0;) {
      GAPS_ASSIGN_OR_RETURN(items[i], pop());
    }
    push(make_sequence(Kind::kTuple, std::move(items)));
    return absl::OkStatus();
  }
  absl::Status append_items(std::vector<ObjPtr> values) {
    GAPS_ASSIGN_OR_RETURN(ObjPtr list, top_of_kind(Kind::kList, "APPEND"));
    for (const ObjPtr& value : values)
      if (reaches(value, list.get())) return fail("APPEND would put a list inside itself (a cycle)");
    for (ObjPtr& value : values) list->items.push_back(std::move(value));
    return absl::OkStatus();
  }
  absl::Status set_items(std::vector<ObjPtr> kv) {
    if (kv.size() % 2 != 0) return fail("SETITEMS with an odd number of keys and values");
    GAPS_ASSIGN_OR_RETURN(ObjPtr dict, top_of_kind(Kind::kDict, "SETITEM"));
    for (const ObjPtr& item : kv)
      if (reaches(item, dict.get())) return fail("SETITEM would put a dict inside itself (a cycle)");
    for (size_t i = 0; i < kv.size(); i += 2) dict->entries.emplace_back(kv[i], kv[i + 1]);
    return absl::OkStatus();
  }
  absl::Status global(std::string module, std::string name) {
    push(make_text(absl::StrCat(module, ".", name), Kind::kGlobal));
    return absl::OkStatus();
  }
  absl::Status stack_global() {
    GAPS_ASSIGN_OR_RETURN(ObjPtr name, pop());
    GAPS_ASSIGN_OR_RETURN(ObjPtr module, pop());
    if (name->kind != Kind::kString || module->kind != Kind::kString) {
      return fail("STACK_GLOBAL needs two strings");
    }
    return global(module->text, name->text);
  }
  absl::Status reduce() {
    GAPS_ASSIGN_OR_RETURN(ObjPtr args, pop());
    GAPS_ASSIGN_OR_RETURN(ObjPtr callable, pop());
    if (callable->kind != Kind::kGlobal) {
      return fail(absl::StrCat("cannot call a ", kind_name(callable->kind)));
    }
    if (args->kind != Kind::kTuple) return fail("REDUCE arguments are not a tuple");
    GAPS_ASSIGN_OR_RETURN(ObjPtr result, call(callable->text, args->items));
    push(std::move(result));
    return absl::OkStatus();
  }
  absl::Status build() {
    GAPS_ASSIGN_OR_RETURN(ObjPtr state, pop());
    GAPS_ASSIGN_OR_RETURN(ObjPtr obj, top());
    // An OrderedDict's instance attributes (a state dict's `_metadata`: module versions) arrive
    // through BUILD; they hold no tensors, so they are dropped.
    if (obj->kind == Kind::kDict) return absl::OkStatus();
    return fail(absl::StrCat("BUILD (setting object state) on a ", kind_name(obj->kind), " is not supported"));
  }

  absl::StatusOr<ObjPtr> call(const std::string& name, const std::vector<ObjPtr>& args);
  absl::StatusOr<ObjPtr> make_ordered_dict(const std::vector<ObjPtr>& args);
  absl::StatusOr<ObjPtr> rebuild_tensor(const std::vector<ObjPtr>& args);
  absl::StatusOr<ObjPtr> persistent_load(const ObjPtr& pid);
  absl::Status execute(uint8_t op);

  ByteSource& src_;
  std::string context_;
  StorageTable& storages_;
  std::vector<ObjPtr> stack_;
  std::vector<size_t> marks_;  // stack heights at each MARK
  std::unordered_map<uint64_t, ObjPtr> memo_;
  uint64_t op_offset_ = 0;
  bool stopped_ = false;
};

absl::StatusOr<ObjPtr> Unpickler::call(const std::string& name, const std::vector<ObjPtr>& args) {
  if (name == "collections.OrderedDict" || name == "builtins.dict") return make_ordered_dict(args);
  if (name == "torch._utils._rebuild_tensor_v2" || name == "torch._utils._rebuild_tensor") {
    return rebuild_tensor(args);
  }
  // Parameters saved directly (keep_vars=True) wrap a tensor; the wrapper is irrelevant here.
  if (name == "torch._utils._rebuild_parameter" || name == "torch._utils._rebuild_parameter_with_state") {
    if (args.empty() || args[0]->kind != Kind::kTensor) return fail(name + " without a tensor");
    return args[0];
  }
  return fail(absl::StrCat("unsupported callable ", name, " (only state dicts of plain tensors can be read)"));
}

absl::StatusOr<ObjPtr> Unpickler::make_ordered_dict(const std::vector<ObjPtr>& args) {
  ObjPtr dict = make(Kind::kDict);
  if (args.empty()) return dict;
  // Python 2 era pickles (e.g. the LPIPS weights) pass the items: OrderedDict([[k, v], ...]).
  if (args.size() != 1 || !is_sequence(*args[0])) return fail("unexpected OrderedDict arguments");
  for (const ObjPtr& pair : args[0]->items) {
    if (!is_sequence(*pair) || pair->items.size() != 2) {
      return fail("OrderedDict item is not a (key, value) pair");
    }
    dict->entries.emplace_back(pair->items[0], pair->items[1]);
  }
  return dict;
}

absl::StatusOr<std::vector<int64_t>> int_tuple(const PyObj& obj, absl::string_view what) {
  if (!is_sequence(obj)) return absl::InvalidArgumentError(absl::StrCat(what, " is not a tuple"));
  std::vector<int64_t> values;
  for (const ObjPtr& item : obj.items) {
    if (item->kind != Kind::kInt) {
      return absl::InvalidArgumentError(absl::StrCat(what, " holds a ", kind_name(item->kind)));
    }
    values.push_back(item->int_value);
  }
  return values;
}

// _rebuild_tensor_v2(storage, storage_offset, size, stride, requires_grad, backward_hooks[, meta])
absl::StatusOr<ObjPtr> Unpickler::rebuild_tensor(const std::vector<ObjPtr>& args) {
  if (args.size() < 4 || args[0]->kind != Kind::kStorage || args[1]->kind != Kind::kInt) {
    return fail("malformed _rebuild_tensor arguments (expected storage, offset, size, stride)");
  }
  ObjPtr tensor = make(Kind::kTensor);
  tensor->storage = args[0]->storage;
  tensor->storage_offset = args[0]->storage_offset + args[1]->int_value;
  auto sizes = int_tuple(*args[2], "tensor size");
  auto strides = int_tuple(*args[3], "tensor stride");
  if (!sizes.ok()) return fail(sizes.status().message());
  if (!strides.ok()) return fail(strides.status().message());
  if (sizes->size() != strides->size()) return fail("tensor size and stride differ in length");
  tensor->sizes = std::move(*sizes);
  tensor->strides = std::move(*strides);
  return tensor;
}

// ('storage', <storage type>, key, location, numel[, view_metadata]) -> storage object.
absl::StatusOr<ObjPtr> Unpickler::persistent_load(const ObjPtr& pid) {
  const auto& f = pid->items;
  if (pid->kind != Kind::kTuple || f.size() < 5 || f[0]->kind != Kind::kString || f[0]->text != "storage") {
    return fail("unsupported persistent id (expected a ('storage', ...) tuple)");
  }
  if (f[1]->kind != Kind::kGlobal || f[2]->kind != Kind::kString || f[4]->kind != Kind::kInt) {
    return fail("malformed storage persistent id");
  }
  std::optional<at::ScalarType> dtype = storage_dtype(f[1]->text);
  if (!dtype) return fail(absl::StrCat("unsupported storage type ", f[1]->text));
  const std::string& key = f[2]->text;
  // Bounding the element count keeps byte counts (up to 16 bytes per element) free of overflow.
  if (f[4]->int_value < 0 || f[4]->int_value > std::numeric_limits<int64_t>::max() / 16) {
    return fail(absl::StrCat("storage '", key, "' has an impossible size ", f[4]->int_value));
  }
  std::shared_ptr<StorageRef>& ref = storages_[key];
  if (!ref) {
    ref = std::make_shared<StorageRef>(StorageRef{key, *dtype, f[4]->int_value, {}});
  } else if (ref->dtype != *dtype) {
    return fail(absl::StrCat("storage '", key, "' is referenced with two element types"));
  }
  ObjPtr storage = make(Kind::kStorage);
  storage->storage = ref;
  // Legacy files from torch < 0.4 may reference a view (view_key, offset, size) of a storage.
  if (f.size() >= 6 && f[5]->kind == Kind::kTuple) {
    if (f[5]->items.size() != 3 || f[5]->items[1]->kind != Kind::kInt) {
      return fail("malformed storage view metadata");
    }
    storage->storage_offset = f[5]->items[1]->int_value;
  }
  return storage;
}

absl::Status Unpickler::execute(uint8_t op) {
  switch (op) {
    case 0x80: {  // PROTO
      GAPS_ASSIGN_OR_RETURN(uint8_t proto, read_le<uint8_t>());
      if (proto > 5) return fail(absl::StrFormat("unsupported pickle protocol %d", proto));
      return absl::OkStatus();
    }
    case 0x95:  // FRAME: a length prefix for buffering only
      return read_le<uint64_t>().status();
    case '.':  // STOP
      stopped_ = true;
      return absl::OkStatus();
    case '(':  // MARK
      marks_.push_back(stack_.size());
      return absl::OkStatus();
    case '0':  // POP
      return pop().status();
    case '1':  // POP_MARK
      return pop_to_mark().status();
    case '2': {  // DUP
      GAPS_ASSIGN_OR_RETURN(ObjPtr obj, top());
      push(obj);
      return absl::OkStatus();
    }
    case 'N':
      push(make(Kind::kNone));
      return absl::OkStatus();
    case 0x88:  // NEWTRUE
    case 0x89:  // NEWFALSE
      push(make_int(op == 0x88, Kind::kBool));
      return absl::OkStatus();
    case 'I': {  // INT (text; protocol 0 spells booleans 01/00)
      GAPS_ASSIGN_OR_RETURN(int64_t value, read_decimal_line());
      push(make_int(value));
      return absl::OkStatus();
    }
    case 'L': {  // LONG (text)
      GAPS_ASSIGN_OR_RETURN(int64_t value, read_decimal_line());
      push(make_int(value));
      return absl::OkStatus();
    }
    case 'J': {  // BININT
      GAPS_ASSIGN_OR_RETURN(int32_t value, read_le<int32_t>());
      push(make_int(value));
      return absl::OkStatus();
    }
    case 'K': {  // BININT1
      GAPS_ASSIGN_OR_RETURN(uint8_t value, read_le<uint8_t>());
      push(make_int(value));
      return absl::OkStatus();
    }
    case 'M': {  // BININT2
      GAPS_ASSIGN_OR_RETURN(uint16_t value, read_le<uint16_t>());
      push(make_int(value));
      return absl::OkStatus();
    }
    case 0x8a: {  // LONG1
      GAPS_ASSIGN_OR_RETURN(uint8_t n, read_le<uint8_t>());
      GAPS_ASSIGN_OR_RETURN(std::string bytes, read_bytes(n));
      return push_long(bytes);
    }
    case 0x8b: {  // LONG4
      GAPS_ASSIGN_OR_RETURN(int32_t n, read_le<int32_t>());
      if (n < 0) return fail("LONG4 with a negative length");
      GAPS_ASSIGN_OR_RETURN(std::string bytes, read_bytes(n));
      return push_long(bytes);
    }
    case 'G': {  // BINFLOAT: big-endian IEEE double
      GAPS_ASSIGN_OR_RETURN(uint64_t bits, read_le<uint64_t>());
      bits = __builtin_bswap64(bits);
      ObjPtr obj = make(Kind::kFloat);
      std::memcpy(&obj->float_value, &bits, sizeof(double));
      push(std::move(obj));
      return absl::OkStatus();
    }
    case 'F': {  // FLOAT (text)
      GAPS_ASSIGN_OR_RETURN(std::string line, read_line());
      ObjPtr obj = make(Kind::kFloat);
      obj->float_value = std::strtod(line.c_str(), nullptr);
      push(std::move(obj));
      return absl::OkStatus();
    }
    // Python 2 `str` (SHORT_BINSTRING/BINSTRING) is decoded as text, as torch.load does.
    case 'U': {
      GAPS_ASSIGN_OR_RETURN(uint8_t n, read_le<uint8_t>());
      return push_text(n, Kind::kString);
    }
    case 'T': {
      GAPS_ASSIGN_OR_RETURN(int32_t n, read_le<int32_t>());
      if (n < 0) return fail("BINSTRING with a negative length");
      return push_text(static_cast<uint64_t>(n), Kind::kString);
    }
    case 0x8c: {  // SHORT_BINUNICODE
      GAPS_ASSIGN_OR_RETURN(uint8_t n, read_le<uint8_t>());
      return push_text(n, Kind::kString);
    }
    case 'X': {  // BINUNICODE
      GAPS_ASSIGN_OR_RETURN(uint32_t n, read_le<uint32_t>());
      return push_text(n, Kind::kString);
    }
    case 0x8d: {  // BINUNICODE8
      GAPS_ASSIGN_OR_RETURN(uint64_t n, read_le<uint64_t>());
      return push_text(n, Kind::kString);
    }
    case 'C': {  // SHORT_BINBYTES
      GAPS_ASSIGN_OR_RETURN(uint8_t n, read_le<uint8_t>());
      return push_text(n, Kind::kBytes);
    }
    case 'B': {  // BINBYTES
      GAPS_ASSIGN_OR_RETURN(uint32_t n, read_le<uint32_t>());
      return push_text(n, Kind::kBytes);
    }
    case 0x8e:    // BINBYTES8
    case 0x96: {  // BYTEARRAY8
      GAPS_ASSIGN_OR_RETURN(uint64_t n, read_le<uint64_t>());
      return push_text(n, Kind::kBytes);
    }
    case ')':
      push(make_sequence(Kind::kTuple, {}));
      return absl::OkStatus();
    case 't': {  // TUPLE
      GAPS_ASSIGN_OR_RETURN(std::vector<ObjPtr> items, pop_to_mark());
      push(make_sequence(Kind::kTuple, std::move(items)));
      return absl::OkStatus();
    }
    case 0x85:
      return push_tuple_of(1);
    case 0x86:
      return push_tuple_of(2);
    case 0x87:
      return push_tuple_of(3);
    case ']':
      push(make_sequence(Kind::kList, {}));
      return absl::OkStatus();
    case 'l': {  // LIST
      GAPS_ASSIGN_OR_RETURN(std::vector<ObjPtr> items, pop_to_mark());
      push(make_sequence(Kind::kList, std::move(items)));
      return absl::OkStatus();
    }
    case 'a': {  // APPEND
      GAPS_ASSIGN_OR_RETURN(ObjPtr value, pop());
      return append_items({std::move(value)});
    }
    case 'e': {  // APPENDS
      GAPS_ASSIGN_OR_RETURN(std::vector<ObjPtr> values, pop_to_mark());
      return append_items(std::move(values));
    }
    case '}':
      push(make(Kind::kDict));
      return absl::OkStatus();
    case 'd': {  // DICT
      GAPS_ASSIGN_OR_RETURN(std::vector<ObjPtr> kv, pop_to_mark());
      push(make(Kind::kDict));
      return set_items(std::move(kv));
    }
    case 's': {  // SETITEM
      GAPS_ASSIGN_OR_RETURN(ObjPtr value, pop());
      GAPS_ASSIGN_OR_RETURN(ObjPtr key, pop());
      return set_items({std::move(key), std::move(value)});
    }
    case 'u': {  // SETITEMS
      GAPS_ASSIGN_OR_RETURN(std::vector<ObjPtr> kv, pop_to_mark());
      return set_items(std::move(kv));
    }
    case 'c': {  // GLOBAL
      GAPS_ASSIGN_OR_RETURN(std::string module, read_line());
      GAPS_ASSIGN_OR_RETURN(std::string name, read_line());
      return global(std::move(module), std::move(name));
    }
    case 0x93:
      return stack_global();
    case 'R':   // REDUCE
    case 0x81:  // NEWOBJ: cls.__new__(cls, *args); only OrderedDict gets here in state dicts
      return reduce();
    case 'b':
      return build();
    case 'Q': {  // BINPERSID
      GAPS_ASSIGN_OR_RETURN(ObjPtr pid, pop());
      GAPS_ASSIGN_OR_RETURN(ObjPtr storage, persistent_load(pid));
      push(std::move(storage));
      return absl::OkStatus();
    }
    case 'p': {  // PUT (text)
      GAPS_ASSIGN_OR_RETURN(int64_t index, read_decimal_line());
      return memo_put(static_cast<uint64_t>(index));
    }
    case 'q': {  // BINPUT
      GAPS_ASSIGN_OR_RETURN(uint8_t index, read_le<uint8_t>());
      return memo_put(index);
    }
    case 'r': {  // LONG_BINPUT
      GAPS_ASSIGN_OR_RETURN(uint32_t index, read_le<uint32_t>());
      return memo_put(index);
    }
    case 0x94:  // MEMOIZE
      return memo_put(memo_.size());
    case 'g': {  // GET (text)
      GAPS_ASSIGN_OR_RETURN(int64_t index, read_decimal_line());
      return memo_get(static_cast<uint64_t>(index));
    }
    case 'h': {  // BINGET
      GAPS_ASSIGN_OR_RETURN(uint8_t index, read_le<uint8_t>());
      return memo_get(index);
    }
    case 'j': {  // LONG_BINGET
      GAPS_ASSIGN_OR_RETURN(uint32_t index, read_le<uint32_t>());
      return memo_get(index);
    }
    default:
      return fail(absl::StrFormat("unsupported pickle opcode 0x%02x", op));
  }
}

// ---------------------------------------------------------------------------------------------
// From the unpickled objects to tensors.

absl::StatusOr<at::Tensor> materialise(const PyObj& t, const std::string& name) {
  const StorageRef& s = *t.storage;
  auto problem = [&](absl::string_view what) {
    return absl::InvalidArgumentError(absl::StrCat("tensor '", name, "': ", what));
  };
  if (!s.data.defined()) return problem(absl::StrCat("storage '", s.key, "' has no data"));
  // The furthest element the view touches must lie inside the storage (corrupt files otherwise
  // make as_strided read out of bounds).
  int64_t last = t.storage_offset;
  bool empty = false;
  for (size_t d = 0; d < t.sizes.size(); ++d) {
    if (t.sizes[d] < 0 || t.strides[d] < 0) return problem("negative size or stride");
    if (t.sizes[d] == 0) empty = true;
    int64_t reach = 0;
    if (__builtin_mul_overflow(t.sizes[d] > 0 ? t.sizes[d] - 1 : 0, t.strides[d], &reach) ||
        __builtin_add_overflow(last, reach, &last)) {
      return problem("size/stride overflow");
    }
  }
  if (empty) return at::empty(t.sizes, at::TensorOptions().dtype(s.dtype));
  if (t.storage_offset < 0 || last >= s.numel) {
    return problem(absl::StrFormat("view (offset %d, sizes [%s], strides [%s]) exceeds its storage of %d elements",
                                   t.storage_offset, absl::StrJoin(t.sizes, ","), absl::StrJoin(t.strides, ","),
                                   s.numel));
  }
  // Independent contiguous copies: callers get plain tensors whatever views were saved.
  return s.data.as_strided(t.sizes, t.strides, t.storage_offset).clone(at::MemoryFormat::Contiguous);
}

absl::StatusOr<std::map<std::string, at::Tensor>> to_state_dict(const PyObj& root, const std::string& path) {
  auto problem = [&](absl::string_view what) {
    return absl::InvalidArgumentError(absl::StrCat("torch checkpoint '", path, "': ", what));
  };
  if (root.kind != Kind::kDict) {
    return problem(absl::StrCat("is not a state dict (found ", kind_name(root.kind), ")"));
  }
  std::map<std::string, at::Tensor> out;
  for (const auto& [key, value] : root.entries) {
    if (key->kind != Kind::kString) {
      return problem(absl::StrCat("a key is not a string (found ", kind_name(key->kind), ")"));
    }
    if (value->kind != Kind::kTensor) {
      return problem(absl::StrCat("entry '", key->text, "' is not a tensor (found ", kind_name(value->kind), ")"));
    }
    auto tensor = materialise(*value, key->text);
    if (!tensor.ok()) return problem(tensor.status().message());
    out[key->text] = std::move(*tensor);
  }
  return out;
}

at::Tensor allocate_storage(const StorageRef& ref) {
  return at::empty({ref.numel}, at::TensorOptions().dtype(ref.dtype));
}

int64_t storage_nbytes(const StorageRef& ref) { return ref.numel * static_cast<int64_t>(c10::elementSize(ref.dtype)); }

// ---- zip container ----

absl::StatusOr<std::map<std::string, at::Tensor>> load_zip(const std::string& path) {
  const std::string context = absl::StrCat("torch checkpoint '", path, "' (zip)");
  try {
    caffe2::serialize::PyTorchStreamReader reader(path);
    if (reader.hasRecord("byteorder")) {
      auto [ptr, size] = reader.getRecord("byteorder");
      std::string order(static_cast<const char*>(ptr.get()), size);
      if (order != "little") {
        return absl::UnimplementedError(absl::StrCat(context, ": byte order '", order, "' is not supported"));
      }
    }
    if (!reader.hasRecord("data.pkl")) {
      return absl::InvalidArgumentError(absl::StrCat(context, ": no data.pkl record"));
    }
    auto [pkl, pkl_size] = reader.getRecord("data.pkl");
    MemorySource src(std::string_view(static_cast<const char*>(pkl.get()), pkl_size));
    StorageTable storages;
    Unpickler unpickler(src, absl::StrCat(context, " data.pkl"), storages);
    GAPS_ASSIGN_OR_RETURN(ObjPtr root, unpickler.load());
    for (auto& [key, ref] : storages) {
      const std::string record = "data/" + key;
      if (!reader.hasRecord(record)) {
        return absl::InvalidArgumentError(absl::StrCat(context, ": storage record ", record, " is missing"));
      }
      const size_t nbytes = reader.getRecordSize(record);
      if (static_cast<int64_t>(nbytes) != storage_nbytes(*ref)) {
        return absl::DataLossError(absl::StrFormat("%s: storage record %s has %d bytes, expected %d", context, record,
                                                   nbytes, storage_nbytes(*ref)));
      }
      ref->data = allocate_storage(*ref);
      reader.getRecord(record, ref->data.data_ptr(), nbytes);
    }
    return to_state_dict(*root, path);
  } catch (const c10::Error& e) {
    return absl::DataLossError(absl::StrCat(context, ": unreadable archive: ", e.what_without_backtrace()));
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat(context, ": unreadable archive: ", e.what()));
  }
}

// ---- legacy container ----

// pickle of the magic number 0x1950a86a20f9469cfc6c (LONG1 payload, little-endian).
constexpr std::string_view kLegacyMagic("\x6c\xfc\x9c\x46\xf9\x20\x6a\xa8\x50\x19", 10);
constexpr int64_t kLegacyProtocolVersion = 1001;

absl::Status check_legacy_header(ByteSource& src, StorageTable& storages, const std::string& context) {
  auto magic = Unpickler(src, absl::StrCat(context, " magic number"), storages).load();
  if (!magic.ok() || (*magic)->kind != Kind::kBigInt || (*magic)->text != kLegacyMagic) {
    return absl::InvalidArgumentError(
        absl::StrCat(context,
                     ": not a PyTorch checkpoint (neither a zip archive nor a legacy torch pickle"
                     " starting with the torch magic number)",
                     magic.ok() ? "" : absl::StrCat("; ", magic.status().message())));
  }
  GAPS_ASSIGN_OR_RETURN(ObjPtr version, Unpickler(src, absl::StrCat(context, " protocol"), storages).load());
  if (version->kind != Kind::kInt || version->int_value != kLegacyProtocolVersion) {
    return absl::UnimplementedError(absl::StrCat(context, ": unsupported legacy protocol version"));
  }
  GAPS_ASSIGN_OR_RETURN(ObjPtr sys_info, Unpickler(src, absl::StrCat(context, " sys_info"), storages).load());
  if (sys_info->kind != Kind::kDict) {
    return absl::InvalidArgumentError(absl::StrCat(context, ": sys_info is not a dict"));
  }
  for (const auto& [key, value] : sys_info->entries) {
    if (key->kind == Kind::kString && key->text == "little_endian" && value->kind == Kind::kBool && !value->int_value) {
      return absl::UnimplementedError(absl::StrCat(context, ": big-endian files are not supported"));
    }
  }
  return absl::OkStatus();
}

// After the main pickle: a pickled list of storage keys, then per key an int64 element count and
// the raw bytes, in that order.
absl::Status read_legacy_storages(ByteSource& src, StorageTable& storages, const std::string& context) {
  GAPS_ASSIGN_OR_RETURN(ObjPtr keys, Unpickler(src, absl::StrCat(context, " storage keys"), storages).load());
  if (keys->kind != Kind::kList) {
    return absl::InvalidArgumentError(absl::StrCat(context, ": storage key list is not a list"));
  }
  for (const ObjPtr& key : keys->items) {
    auto it = key->kind == Kind::kString ? storages.find(key->text) : storages.end();
    if (it == storages.end()) {
      return absl::InvalidArgumentError(absl::StrCat(context, ": storage key list names an unreferenced storage"));
    }
    StorageRef& ref = *it->second;
    auto fail = [&](const absl::Status& s) {
      return absl::Status(s.code(), absl::StrCat(context, ": storage '", ref.key, "': ", s.message()));
    };
    int64_t numel = 0;
    if (absl::Status s = src.read(&numel, sizeof numel); !s.ok()) return fail(s);
    if (numel != ref.numel) {
      return fail(
          absl::DataLossError(absl::StrFormat("%d elements in the data section, %d in the pickle", numel, ref.numel)));
    }
    if (static_cast<uint64_t>(storage_nbytes(ref)) > src.remaining()) {
      return fail(truncated(src.offset(), storage_nbytes(ref), src.remaining()));
    }
    ref.data = allocate_storage(ref);
    if (absl::Status s = src.read(ref.data.data_ptr(), storage_nbytes(ref)); !s.ok()) return fail(s);
  }
  return absl::OkStatus();
}

absl::StatusOr<std::map<std::string, at::Tensor>> load_legacy(const std::string& path, std::ifstream& in,
                                                              uint64_t size) {
  const std::string context = absl::StrCat("torch checkpoint '", path, "' (legacy format)");
  FileSource src(in, size);
  StorageTable storages;
  GAPS_RETURN_IF_ERROR(check_legacy_header(src, storages, context));
  GAPS_ASSIGN_OR_RETURN(ObjPtr root, Unpickler(src, absl::StrCat(context, " main pickle"), storages).load());
  GAPS_RETURN_IF_ERROR(read_legacy_storages(src, storages, context));
  return to_state_dict(*root, path);
}

absl::StatusOr<std::map<std::string, at::Tensor>> load_checkpoint(const std::string& path) {
  std::ifstream in(path, std::ios::binary | std::ios::ate);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot open torch checkpoint '", path, "'"));
  const std::streamoff end = in.tellg();  // -1 for directories and other unreadable things
  if (end <= 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("torch checkpoint '", path, "' is ", end == 0 ? "empty" : "not a readable file"));
  }
  const auto size = static_cast<uint64_t>(end);
  in.seekg(0);
  char head[4] = {};
  in.read(head, std::min<uint64_t>(size, 4));
  in.seekg(0);
  if (size >= 4 && std::string_view(head, 4) == std::string_view("PK\x03\x04", 4)) {
    in.close();
    return load_zip(path);
  }
  return load_legacy(path, in, size);
}

}  // namespace

absl::StatusOr<std::map<std::string, at::Tensor>> load_torch_state_dict(const std::string& path) {
  // Allocation failures (a corrupt size that still fits in the file is unlikely but possible) and
  // any ATen error surface as a status rather than an exception through the caller.
  try {
    return load_checkpoint(path);
  } catch (const c10::Error& e) {
    return absl::InternalError(absl::StrCat("torch checkpoint '", path, "': ", e.what_without_backtrace()));
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError(absl::StrCat("torch checkpoint '", path, "': out of memory while loading"));
  }
}

}  // namespace gaps
