#include "server/convert.h"

#include <google/protobuf/unknown_field_set.h>

#include "lsqsurf/v1/enum_names.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/jobs/method_registry.h"

namespace lsqsurf::server {
namespace {

using google::protobuf::EnumValueDescriptor;
using google::protobuf::FieldDescriptor;
using google::protobuf::Message;
using google::protobuf::Reflection;

absl::Status FillField(const Message& message, const FieldDescriptor& f, core::ParamSet* params) {
  const Reflection& r = *message.GetReflection();
  const std::string& name = f.name();
  if (f.is_repeated()) {
    if (f.cpp_type() != FieldDescriptor::CPPTYPE_DOUBLE) {
      return absl::InvalidArgumentError(core::StrCat(name, " is not a parameter value"));
    }
    std::vector<double> values(static_cast<size_t>(r.FieldSize(message, &f)));
    for (size_t i = 0; i < values.size(); ++i) values[i] = r.GetRepeatedDouble(message, &f, static_cast<int>(i));
    return params->SetList(name, std::move(values));
  }
  switch (f.cpp_type()) {
    case FieldDescriptor::CPPTYPE_DOUBLE: return params->Set(name, r.GetDouble(message, &f));
    case FieldDescriptor::CPPTYPE_FLOAT: return params->Set(name, r.GetFloat(message, &f));
    case FieldDescriptor::CPPTYPE_INT32: return params->Set(name, r.GetInt32(message, &f));
    case FieldDescriptor::CPPTYPE_INT64: return params->Set(name, static_cast<double>(r.GetInt64(message, &f)));
    case FieldDescriptor::CPPTYPE_UINT32: return params->Set(name, r.GetUInt32(message, &f));
    case FieldDescriptor::CPPTYPE_UINT64: return params->Set(name, static_cast<double>(r.GetUInt64(message, &f)));
    case FieldDescriptor::CPPTYPE_BOOL: return params->Set(name, r.GetBool(message, &f) ? 1 : 0);
    case FieldDescriptor::CPPTYPE_STRING: return params->SetText(name, r.GetString(message, &f));
    case FieldDescriptor::CPPTYPE_ENUM: {
      const std::string choice = v1::ChoiceName(*r.GetEnum(message, &f));
      return choice.empty() ? absl::OkStatus() : params->Parse(name, choice);
    }
    case FieldDescriptor::CPPTYPE_MESSAGE: break;
  }
  return absl::InvalidArgumentError(core::StrCat(name, " is not a parameter value"));
}

// Fields this server's proto does not know (a client built from another version) are refused,
// naming their numbers, rather than ignored: the job would otherwise run with the defaults.
absl::Status RefuseUnknownFields(const Message& message) {
  const google::protobuf::UnknownFieldSet& unknown = message.GetReflection()->GetUnknownFields(message);
  if (unknown.empty()) return absl::OkStatus();
  std::string numbers;
  for (int i = 0; i < unknown.field_count(); ++i) {
    core::StrAppend(&numbers, i == 0 ? "" : ", ", unknown.field(i).number());
  }
  return absl::InvalidArgumentError(core::StrCat(message.GetDescriptor()->name(), " has field number",
                                                 unknown.field_count() > 1 ? "s " : " ", numbers,
                                                 ", which this server does not know; check ListMethods"));
}

}  // namespace

grpc::Status ToGrpcStatus(const absl::Status& status) {
  if (status.ok()) return grpc::Status::OK;
  return grpc::Status(static_cast<grpc::StatusCode>(status.code()), std::string(status.message()));
}

absl::Status FillParams(const Message& message, core::ParamSet* params) {
  LSQSURF_RETURN_IF_ERROR(RefuseUnknownFields(message));
  std::vector<const FieldDescriptor*> fields;
  message.GetReflection()->ListFields(message, &fields);  // The fields that are set.
  for (const FieldDescriptor* f : fields) {
    if (absl::Status s = FillField(message, *f, params); !s.ok()) return s;
  }
  return absl::OkStatus();
}

void ParamsToProto(const core::ParamSet& params, Message* message) {
  const Reflection& r = *message->GetReflection();
  for (const core::ParamInfo& info : params.Describe()) {
    const FieldDescriptor* f = message->GetDescriptor()->FindFieldByName(info.name);
    if (f == nullptr) continue;  // The server's tests keep tables and messages in step.
    if (info.type == core::ParamType::kText) {
      if (f->cpp_type() == FieldDescriptor::CPPTYPE_STRING)
        r.SetString(message, f, params.GetText(info.name).value_or(""));
      continue;
    }
    if (info.type == core::ParamType::kRealList) {
      if (!f->is_repeated() || f->cpp_type() != FieldDescriptor::CPPTYPE_DOUBLE) continue;
      r.ClearField(message, f);
      for (double v : params.GetList(info.name).value_or(std::vector<double>{})) r.AddDouble(message, f, v);
      continue;
    }
    const double v = params.Get(info.name).value_or(0);
    switch (f->cpp_type()) {
      case FieldDescriptor::CPPTYPE_DOUBLE: r.SetDouble(message, f, v); break;
      case FieldDescriptor::CPPTYPE_FLOAT: r.SetFloat(message, f, static_cast<float>(v)); break;
      case FieldDescriptor::CPPTYPE_INT32: r.SetInt32(message, f, static_cast<int32_t>(v)); break;
      case FieldDescriptor::CPPTYPE_INT64: r.SetInt64(message, f, static_cast<int64_t>(v)); break;
      case FieldDescriptor::CPPTYPE_UINT32: r.SetUInt32(message, f, static_cast<uint32_t>(v)); break;
      case FieldDescriptor::CPPTYPE_UINT64: r.SetUInt64(message, f, static_cast<uint64_t>(v)); break;
      case FieldDescriptor::CPPTYPE_BOOL: r.SetBool(message, f, v != 0); break;
      case FieldDescriptor::CPPTYPE_ENUM: {
        const core::ParamChoice* c = info.FindChoice(static_cast<int>(v));
        const EnumValueDescriptor* e =
            c ? f->enum_type()->FindValueByName(v1::EnumValueName(*f->enum_type(), c->name)) : nullptr;
        if (e != nullptr) r.SetEnum(message, f, e);
        break;
      }
      default: break;
    }
  }
}

absl::StatusOr<jobs::JobSpec> FromProto(const v1::JobSpec& spec) {
  const FieldDescriptor* method =
      spec.GetReflection()->GetOneofFieldDescriptor(spec, v1::JobSpec::descriptor()->FindOneofByName("method"));
  if (method == nullptr) {
    std::string known;
    for (const auto& m : jobs::Methods()) core::StrAppend(&known, known.empty() ? "" : ", ", m.info.name);
    return absl::InvalidArgumentError(core::StrCat("the spec names no method; set one of: ", known));
  }
  LSQSURF_RETURN_IF_ERROR(RefuseUnknownFields(spec));
  jobs::JobSpec out;
  out.method = method->name();
  auto params = jobs::DefaultParams(out.method);
  if (!params.ok()) return params.status();
  out.params = *std::move(params);
  if (absl::Status s = FillParams(spec.GetReflection()->GetMessage(spec, method), &out.params); !s.ok()) {
    return absl::InvalidArgumentError(core::StrCat(out.method, ": ", s.message()));
  }
  out.mesh_position_bits = spec.mesh_position_bits();
  if (spec.has_preview()) {
    auto view = FromProto(spec.preview().options());
    if (!view.ok()) return absl::InvalidArgumentError(core::StrCat("preview: ", view.status().message()));
    out.preview.enabled = true;
    out.preview.view = *std::move(view);
    out.preview.turntable_deg_per_frame = spec.preview().turntable_deg_per_frame();
  }
  // The cross-field rules and the preview's attribute, so that a bad spec fails before its upload.
  LSQSURF_RETURN_IF_ERROR(jobs::ValidateSpec(out));
  return out;
}

absl::StatusOr<core::ParamSet> FromProto(const v1::RenderOptions& options) {
  core::ParamSet view = jobs::DefaultView();
  if (absl::Status s = FillParams(options, &view); !s.ok()) return s;
  return view;
}

v1::JobState ToProto(jobs::JobState state) {
  switch (state) {
    case jobs::JobState::kQueued: return v1::JOB_STATE_QUEUED;
    case jobs::JobState::kRunning: return v1::JOB_STATE_RUNNING;
    case jobs::JobState::kSucceeded: return v1::JOB_STATE_SUCCEEDED;
    case jobs::JobState::kFailed: return v1::JOB_STATE_FAILED;
    case jobs::JobState::kCancelled: return v1::JOB_STATE_CANCELLED;
  }
  return v1::JOB_STATE_UNSPECIFIED;
}

void ToProto(const jobs::JobRecord& r, v1::Job* out) {
  out->set_id(r.id);
  v1::JobSpec* spec = out->mutable_spec();
  if (const FieldDescriptor* f = v1::JobSpec::descriptor()->FindFieldByName(r.spec.method);
      f != nullptr && !r.spec.params.empty()) {
    ParamsToProto(r.spec.params, spec->GetReflection()->MutableMessage(spec, f));
  }
  spec->set_mesh_position_bits(r.spec.mesh_position_bits);
  if (r.spec.preview.enabled) {
    v1::PreviewSpec* preview = spec->mutable_preview();
    ParamsToProto(r.spec.preview.view, preview->mutable_options());
    preview->set_turntable_deg_per_frame(r.spec.preview.turntable_deg_per_frame);
  }
  out->set_state(ToProto(r.state));
  out->set_stage(r.stage);
  out->set_progress(r.progress);
  out->set_error(r.error);
  out->set_attempts(r.attempts);
  out->set_created_ms(r.created_ms);
  out->set_updated_ms(r.updated_ms);
  out->set_input_points(r.input_points);
  out->set_input_bytes(r.input_bytes);
  for (const auto& [name, value] : r.statistics) {
    v1::Statistic* s = out->add_statistics();
    s->set_name(name);
    s->set_value(value);
  }
  for (const auto& name : r.results) out->add_results(name);
  out->set_runner(r.runner);
  out->set_owner(r.owner);
  out->set_stored_bytes(r.stored_bytes);
}

void ToProto(const core::ParamInfo& p, v1::Parameter* out) {
  out->set_name(p.name);
  switch (p.type) {
    case core::ParamType::kReal: out->set_type(v1::Parameter::TYPE_REAL); break;
    case core::ParamType::kInteger: out->set_type(v1::Parameter::TYPE_INTEGER); break;
    case core::ParamType::kFlag: out->set_type(v1::Parameter::TYPE_FLAG); break;
    case core::ParamType::kChoice: out->set_type(v1::Parameter::TYPE_CHOICE); break;
    case core::ParamType::kText: out->set_type(v1::Parameter::TYPE_TEXT); break;
    case core::ParamType::kRealList: out->set_type(v1::Parameter::TYPE_REAL_LIST); break;
  }
  out->set_max_count(p.max_count);
  out->set_default_value(p.default_value);
  out->set_min_value(p.type == core::ParamType::kFlag ? 0 : p.min_value);
  out->set_max_value(p.type == core::ParamType::kFlag ? 1 : p.max_value);
  out->set_integer(p.type == core::ParamType::kInteger);
  out->set_help(p.help);
  out->set_unit(p.unit);
  for (const core::ParamSpecial& s : p.special) {
    v1::Parameter::Special* special = out->add_special_values();
    special->set_value(s.value);
    special->set_meaning(s.meaning);
  }
  for (const auto& c : p.choices) {
    v1::Parameter::Choice* choice = out->add_choices();
    choice->set_name(c.name);
    choice->set_help(c.help);
  }
  if (p.type == core::ParamType::kChoice) {
    if (const core::ParamChoice* c = p.FindChoice(static_cast<int>(p.default_value))) out->set_default_choice(c->name);
  }
}

}  // namespace lsqsurf::server
