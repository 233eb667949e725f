#include "rpc/config_codec.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/reflection.h>
#include "absl/strings/str_cat.h"

namespace gaps::rpc {

using google::protobuf::FieldDescriptor;

nlohmann::json present_fields(const google::protobuf::Message& message) {
  const auto* reflection = message.GetReflection();
  std::vector<const FieldDescriptor*> fields;
  reflection->ListFields(message, &fields);
  nlohmann::json j = nlohmann::json::object();
  for (const FieldDescriptor* f : fields) {
    if (f->is_repeated()) {
      nlohmann::json values = nlohmann::json::array();
      for (int i = 0; i < reflection->FieldSize(message, f); ++i)
        if (f->cpp_type() == FieldDescriptor::CPPTYPE_DOUBLE)
          values.push_back(reflection->GetRepeatedDouble(message, f, i));
      j[f->name()] = values;
      continue;
    }
    switch (f->cpp_type()) {
      case FieldDescriptor::CPPTYPE_INT32:
        j[f->name()] = reflection->GetInt32(message, f);
        break;
      case FieldDescriptor::CPPTYPE_INT64:
        j[f->name()] = reflection->GetInt64(message, f);
        break;
      case FieldDescriptor::CPPTYPE_UINT64:
        j[f->name()] = reflection->GetUInt64(message, f);
        break;
      case FieldDescriptor::CPPTYPE_DOUBLE:
        j[f->name()] = reflection->GetDouble(message, f);
        break;
      case FieldDescriptor::CPPTYPE_BOOL:
        j[f->name()] = reflection->GetBool(message, f);
        break;
      case FieldDescriptor::CPPTYPE_STRING:
        j[f->name()] = reflection->GetString(message, f);
        break;
      default:
        break;  // the hyperparameter messages use none of the other types
    }
  }
  return j;
}

absl::Status set_fields(const nlohmann::json& object, google::protobuf::Message* message) {
  if (!object.is_object()) return absl::InvalidArgumentError("options must be a JSON object");
  const auto* descriptor = message->GetDescriptor();
  const auto* reflection = message->GetReflection();
  for (auto it = object.begin(); it != object.end(); ++it) {
    const FieldDescriptor* f = descriptor->FindFieldByName(it.key());
    if (f == nullptr) return absl::InvalidArgumentError(absl::StrCat("unknown option '", it.key(), "'"));
    const nlohmann::json& v = it.value();
    const auto wrong = [&] {
      return absl::InvalidArgumentError(absl::StrCat("option '", it.key(), "' has the wrong type"));
    };
    if (f->is_repeated()) {
      if (!v.is_array() || f->cpp_type() != FieldDescriptor::CPPTYPE_DOUBLE) return wrong();
      reflection->ClearField(message, f);
      for (const auto& x : v) {
        if (!x.is_number()) return wrong();
        reflection->AddDouble(message, f, x.get<double>());
      }
      continue;
    }
    switch (f->cpp_type()) {
      case FieldDescriptor::CPPTYPE_INT32:
        if (!v.is_number_integer()) return wrong();
        reflection->SetInt32(message, f, v.get<int32_t>());
        break;
      case FieldDescriptor::CPPTYPE_INT64:
        if (!v.is_number_integer()) return wrong();
        reflection->SetInt64(message, f, v.get<int64_t>());
        break;
      case FieldDescriptor::CPPTYPE_UINT64:
        if (!v.is_number_unsigned() && !(v.is_number_integer() && v.get<int64_t>() >= 0)) return wrong();
        reflection->SetUInt64(message, f, v.get<uint64_t>());
        break;
      case FieldDescriptor::CPPTYPE_DOUBLE:
        if (!v.is_number()) return wrong();
        reflection->SetDouble(message, f, v.get<double>());
        break;
      case FieldDescriptor::CPPTYPE_BOOL:
        if (!v.is_boolean()) return wrong();
        reflection->SetBool(message, f, v.get<bool>());
        break;
      case FieldDescriptor::CPPTYPE_STRING:
        if (!v.is_string()) return wrong();
        reflection->SetString(message, f, v.get<std::string>());
        break;
      default:
        return wrong();
    }
  }
  return absl::OkStatus();
}

}  // namespace gaps::rpc
