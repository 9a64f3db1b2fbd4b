#include "client/client.h"

#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <cctype>
#include <cstdlib>
#include <utility>

#include "grpc/health/v1/health.grpc.pb.h"
#include "lsqsurf/v1/enum_names.h"
#include "worker/core/number_list.h"
#include "worker/core/status.h"
#include "worker/core/strings.h"
#include "worker/io/files.h"
#include "worker/io/volume_codec.h"
#include "worker/io/volume_formats.h"

namespace lsqsurf::client {
namespace {

using core::StrCat;
using google::protobuf::FieldDescriptor;
using google::protobuf::Message;

const google::protobuf::OneofDescriptor& MethodOneof() { return *v1::JobSpec::descriptor()->FindOneofByName("method"); }

std::string KnownMethods() {
  std::string known;
  const auto& oneof = MethodOneof();
  for (int i = 0; i < oneof.field_count(); ++i) core::StrAppend(&known, i ? ", " : "", oneof.field(i)->name());
  return known;
}

// A choice by name ("gridlines"), as lsqsurf methods lists it, or by its full enum value name.
absl::Status SetEnum(Message* m, const FieldDescriptor& f, std::string_view value) {
  const auto& type = *f.enum_type();
  const auto* e = type.FindValueByName(v1::EnumValueName(type, value));
  if (e == nullptr) {
    std::string upper;
    for (char c : value) upper += static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
    e = type.FindValueByName(upper);
  }
  if (e == nullptr) {
    std::string names;
    for (int i = 0; i < type.value_count(); ++i) {
      if (const std::string n = v1::ChoiceName(*type.value(i)); !n.empty()) {
        core::StrAppend(&names, names.empty() ? "" : ", ", n);
      }
    }
    return absl::InvalidArgumentError(StrCat(f.name(), "='", value, "' is not one of: ", names));
  }
  m->GetReflection()->SetEnum(m, &f, e);
  return absl::OkStatus();
}

// A list parameter (`iso=0.5,0.7`), in the tables' text form; an empty text is no value.
absl::Status SetListField(Message* m, const FieldDescriptor& f, std::string_view value) {
  LSQSURF_ASSIGN_OR_RETURN(const std::vector<double> values, core::ParseNumberList(f.name(), value));
  const auto* r = m->GetReflection();
  r->ClearField(m, &f);
  for (double v : values) r->AddDouble(m, &f, v);
  return absl::OkStatus();
}

absl::Status SetField(Message* m, const FieldDescriptor& f, std::string_view value) {
  const auto* r = m->GetReflection();
  const std::string text(value);
  if (f.is_repeated()) {
    if (f.cpp_type() == FieldDescriptor::CPPTYPE_DOUBLE) return SetListField(m, f, value);
    return absl::InvalidArgumentError(StrCat(f.name(), " is not a parameter"));
  }
  if (f.cpp_type() == FieldDescriptor::CPPTYPE_ENUM) return SetEnum(m, f, value);
  if (f.cpp_type() == FieldDescriptor::CPPTYPE_STRING) {
    r->SetString(m, &f, text);
    return absl::OkStatus();
  }
  if (f.cpp_type() == FieldDescriptor::CPPTYPE_BOOL) {
    if (text != "true" && text != "false" && text != "1" && text != "0") {
      return absl::InvalidArgumentError(StrCat(f.name(), "='", value, "' is not true or false"));
    }
    r->SetBool(m, &f, text == "true" || text == "1");
    return absl::OkStatus();
  }
  char* end = nullptr;
  const double v = std::strtod(text.c_str(), &end);
  if (text.empty() || *end != '\0')
    return absl::InvalidArgumentError(StrCat(f.name(), "='", value, "' is not a number"));
  const bool whole = v == static_cast<double>(static_cast<int64_t>(v));
  switch (f.cpp_type()) {
    case FieldDescriptor::CPPTYPE_DOUBLE: r->SetDouble(m, &f, v); return absl::OkStatus();
    case FieldDescriptor::CPPTYPE_FLOAT: r->SetFloat(m, &f, static_cast<float>(v)); return absl::OkStatus();
    case FieldDescriptor::CPPTYPE_INT32:
      if (!whole || std::abs(v) > 2e9) break;
      r->SetInt32(m, &f, static_cast<int32_t>(v));
      return absl::OkStatus();
    case FieldDescriptor::CPPTYPE_INT64:
      if (!whole) break;
      r->SetInt64(m, &f, static_cast<int64_t>(v));
      return absl::OkStatus();
    default: break;
  }
  return absl::InvalidArgumentError(StrCat(f.name(), "='", value, "' must be a whole number"));
}

}  // namespace

template <class Request, class Response>
absl::StatusOr<Response> Client::Unary(grpc::Status (v1::Reconstruction::Stub::*call)(grpc::ClientContext*,
                                                                                      const Request&, Response*),
                                       const Request& request) {
  auto ctx = NewContext();
  if (unary_deadline_.count() > 0) ctx->set_deadline(std::chrono::system_clock::now() + unary_deadline_);
  Response response;
  if (grpc::Status s = ((*stub_).*call)(ctx.get(), request, &response); !s.ok()) return FromGrpc(s);
  return response;
}

std::unique_ptr<grpc::ClientContext> Client::NewContext() const {
  auto ctx = std::make_unique<grpc::ClientContext>();
  // gRPC aborts on a header value it cannot send; such a token is left out (the server then
  // answers UNAUTHENTICATED).
  if (!token_.empty() && CheckToken(token_).ok()) ctx->AddMetadata("authorization", "Bearer " + token_);
  return ctx;
}

absl::Status CheckToken(std::string_view token) {
  if (token.empty()) return absl::InvalidArgumentError("the token is empty");
  for (char c : token) {
    if (c <= ' ' || c > '~') {
      return absl::InvalidArgumentError(
          "the token holds a space, a line break or a character that is not printable ASCII: a token file holds "
          "one line, the token as `lsqsurfd tokens add` printed it");
    }
  }
  return absl::OkStatus();
}

absl::Status FromGrpc(const grpc::Status& status) {
  if (status.ok()) return absl::OkStatus();
  return absl::Status(static_cast<absl::StatusCode>(status.error_code()), status.error_message());
}

std::string MethodOf(const v1::JobSpec& spec) {
  const FieldDescriptor* f = spec.GetReflection()->GetOneofFieldDescriptor(spec, &MethodOneof());
  return f ? f->name() : "";
}

absl::Status SetMethod(v1::JobSpec* spec, const std::string& method) {
  const FieldDescriptor* f = v1::JobSpec::descriptor()->FindFieldByName(method);
  if (f == nullptr || f->containing_oneof() != &MethodOneof()) {
    return absl::InvalidArgumentError(StrCat("unknown method '", method, "'; available: ", KnownMethods()));
  }
  spec->GetReflection()->MutableMessage(spec, f);
  return absl::OkStatus();
}

absl::Status SetParam(v1::JobSpec* spec, std::string_view name, std::string_view value) {
  const FieldDescriptor* method = spec->GetReflection()->GetOneofFieldDescriptor(*spec, &MethodOneof());
  if (method == nullptr) return absl::InvalidArgumentError("set a method before its parameters");
  Message* params = spec->GetReflection()->MutableMessage(spec, method);
  if (params->GetDescriptor()->FindFieldByName(std::string(name)) == nullptr) {
    std::string valid;
    for (int i = 0; i < params->GetDescriptor()->field_count(); ++i) {
      core::StrAppend(&valid, i ? ", " : "", params->GetDescriptor()->field(i)->name());
    }
    return absl::InvalidArgumentError(
        StrCat("unknown parameter '", name, "' for method ", method->name(), "; valid parameters: ", valid));
  }
  return SetMessageField(params, name, value);
}

absl::Status SetMessageField(Message* message, std::string_view name, std::string_view value) {
  const FieldDescriptor* f = message->GetDescriptor()->FindFieldByName(std::string(name));
  if (f == nullptr) {
    return absl::InvalidArgumentError(StrCat(message->GetDescriptor()->name(), " has no field '", name, "'"));
  }
  return SetField(message, *f, value);
}

absl::Status SetParamAssignment(v1::JobSpec* spec, std::string_view assignment) {
  const size_t eq = assignment.find('=');
  if (eq == std::string_view::npos || eq == 0) {
    return absl::InvalidArgumentError(StrCat("--param expects name=value, got '", assignment, "'"));
  }
  return SetParam(spec, assignment.substr(0, eq), assignment.substr(eq + 1));
}

const char* StateName(v1::JobState s) {
  switch (s) {
    case v1::JOB_STATE_QUEUED: return "queued";
    case v1::JOB_STATE_RUNNING: return "running";
    case v1::JOB_STATE_SUCCEEDED: return "succeeded";
    case v1::JOB_STATE_FAILED: return "failed";
    case v1::JOB_STATE_CANCELLED: return "cancelled";
    default: return "unknown";
  }
}

bool IsTerminal(v1::JobState s) {
  return s == v1::JOB_STATE_SUCCEEDED || s == v1::JOB_STATE_FAILED || s == v1::JOB_STATE_CANCELLED;
}

Client::Client(const std::string& address, const ConnectOptions& options)
    : token_(options.token), unary_deadline_(options.unary_deadline) {
  grpc::ChannelArguments args;
  args.SetMaxReceiveMessageSize(16 << 20);
  args.SetMaxSendMessageSize(16 << 20);
  std::shared_ptr<grpc::ChannelCredentials> credentials = grpc::InsecureChannelCredentials();
  if (options.uses_tls()) {
    grpc::SslCredentialsOptions ssl;
    ssl.pem_root_certs = options.ca_pem;
    ssl.pem_cert_chain = options.cert_pem;
    ssl.pem_private_key = options.key_pem;
    credentials = grpc::SslCredentials(ssl);
    if (!options.server_name.empty()) args.SetSslTargetNameOverride(options.server_name);
  }
  channel_ = grpc::CreateCustomChannel(address, credentials, args);
  stub_ = v1::Reconstruction::NewStub(channel_);
}

absl::StatusOr<VolumeUpload> EncodeVolumeFile(const std::string& path, const std::string& raw_layout,
                                              const std::vector<std::string>& fields) {
  absl::StatusOr<core::VolumeMesh> mesh = absl::UnknownError("");
  if (raw_layout.empty()) {
    mesh = io::ReadVolumeFile(path);
  } else {
    auto bytes = io::ReadFileBytes(path);
    if (!bytes.ok()) return bytes.status();
    mesh = io::ParseRawVolume(*bytes, raw_layout, fields.empty() ? "value" : fields[0]);
  }
  if (!mesh.ok()) return mesh.status();
  return EncodeVolume(*std::move(mesh), fields, path);
}

absl::StatusOr<VolumeUpload> EncodeVolume(core::VolumeMesh mesh, const std::vector<std::string>& fields,
                                          std::string_view name) {
  VolumeUpload out;
  // Only the fields that go up may refuse the volume for their missing values.
  std::erase_if(mesh.fields, [&](const core::VertexField& f) {
    return std::find(fields.begin(), fields.end(), f.name) == fields.end();
  });
  auto missing = core::FillMissingValues(mesh);
  if (!missing.ok()) return absl::InvalidArgumentError(core::StrCat(name, ": ", missing.status().message()));
  out.missing_vertices = *missing;
  auto vertices = io::EncodeVolumeVertices(mesh, fields, {});
  if (!vertices.ok()) return absl::InvalidArgumentError(core::StrCat(name, ": ", vertices.status().message()));
  out.vertices = *std::move(vertices);
  if (mesh.has_cells()) out.cells = io::EncodeCellStream(mesh);
  return out;
}

PartSource CloudParts(std::shared_ptr<const core::PointCloud> cloud, const io::DracoOptions& options,
                      int64_t points_per_part) {
  auto next = std::make_shared<size_t>(0);
  const auto per_part = static_cast<size_t>(std::max<int64_t>(1, points_per_part));
  return [cloud = std::move(cloud), options, next, per_part]() -> absl::StatusOr<std::string> {
    if (*next >= cloud->size()) return std::string();
    const size_t begin = *next, end = std::min(cloud->size(), begin + per_part);
    *next = end;
    if (begin == 0 && end == cloud->size()) return io::EncodeDracoPointCloud(*cloud, options);
    core::PointCloud part;
    part.positions.assign(cloud->positions.begin() + static_cast<ptrdiff_t>(begin),
                          cloud->positions.begin() + static_cast<ptrdiff_t>(end));
    if (cloud->has_normals()) {
      part.normals.assign(cloud->normals.begin() + static_cast<ptrdiff_t>(begin),
                          cloud->normals.begin() + static_cast<ptrdiff_t>(end));
    }
    return io::EncodeDracoPointCloud(part, options);
  };
}

PartSource StreamParts(std::shared_ptr<io::PointStream> points, const io::DracoOptions& options,
                       int64_t points_per_part) {
  const auto per_part = static_cast<size_t>(std::max<int64_t>(1, points_per_part));
  return [points = std::move(points), options, per_part]() -> absl::StatusOr<std::string> {
    auto part = points->Next(per_part);
    if (!part.ok()) return part.status();
    if (part->empty()) return std::string();
    for (auto& n : part->normals) {
      if (n.norm() > 0) n.normalize();
    }
    return io::EncodeDracoPointCloud(*part, options);
  };
}

absl::StatusOr<v1::Job> Client::Submit(const v1::JobSpec& spec, std::string_view input, std::string_view velocity,
                                       std::string_view cells) {
  bool sent = false;
  return SubmitParts(
      spec,
      [&]() -> absl::StatusOr<std::string> {
        if (std::exchange(sent, true)) return std::string();
        return std::string(input);
      },
      velocity, cells);
}

absl::StatusOr<v1::Job> Client::SubmitParts(const v1::JobSpec& spec, const PartSource& input, std::string_view velocity,
                                            std::string_view cells) {
  auto ctx = NewContext();
  v1::Job job;
  auto writer = stub_->SubmitJob(ctx.get(), &job);
  v1::SubmitJobRequest request;
  *request.mutable_spec() = spec;
  bool open = writer->Write(request);
  constexpr size_t kChunk = size_t{1} << 20;
  // `chunk` picks the payload field a chunk goes in.
  auto send = [&](std::string_view bytes, std::string* (v1::SubmitJobRequest::*chunk)()) {
    for (size_t offset = 0; open && offset < bytes.size(); offset += kChunk) {
      (request.*chunk)()->assign(bytes.substr(offset, kChunk));
      open = writer->Write(request);
    }
  };
  for (int64_t part = 0; open; ++part) {
    auto bytes = input();
    if (!bytes.ok()) {
      ctx->TryCancel();
      (void)writer->Finish();
      return bytes.status();
    }
    if (bytes->empty()) break;
    if (part > 0) {
      request.set_input_part_end(true);
      open = writer->Write(request);
    }
    send(*bytes, &v1::SubmitJobRequest::mutable_input_chunk);
  }
  send(velocity, &v1::SubmitJobRequest::mutable_velocity_chunk);
  send(cells, &v1::SubmitJobRequest::mutable_cells_chunk);
  writer->WritesDone();
  if (grpc::Status s = writer->Finish(); !s.ok()) return FromGrpc(s);
  return job;
}

absl::StatusOr<v1::Job> Client::Watch(const std::string& id, const std::function<void(const v1::Job&)>& on_event) {
  auto ctx = NewContext();
  v1::WatchJobRequest request;
  request.set_job_id(id);
  auto reader = stub_->WatchJob(ctx.get(), request);
  v1::JobEvent event;
  v1::Job last;
  while (reader->Read(&event)) {
    last = event.job();
    if (on_event) on_event(last);
  }
  if (grpc::Status s = reader->Finish(); !s.ok()) return FromGrpc(s);
  if (!IsTerminal(last.state())) return absl::AbortedError("the watch ended before the job finished");
  return last;
}

absl::StatusOr<std::string> Client::Fetch(const std::string& id, const std::string& name) {
  auto ctx = NewContext();
  v1::FetchResultRequest request;
  request.set_job_id(id);
  request.set_name(name);
  auto reader = stub_->FetchResult(ctx.get(), request);
  v1::ResultChunk chunk;
  std::string bytes;
  while (reader->Read(&chunk)) {
    if (chunk.total_bytes() > 0) bytes.reserve(static_cast<size_t>(chunk.total_bytes()));
    bytes += chunk.data();
  }
  if (grpc::Status s = reader->Finish(); !s.ok()) return FromGrpc(s);
  return bytes;
}

absl::StatusOr<v1::RenderResponse> Client::Render(const std::string& id, const std::string& name,
                                                  const v1::RenderOptions& options) {
  v1::RenderRequest request;
  request.set_job_id(id);
  request.set_name(name);
  *request.mutable_options() = options;
  auto ctx = NewContext();
  ctx->set_deadline(std::chrono::system_clock::now() + std::chrono::minutes(5));
  v1::RenderResponse response;
  if (grpc::Status s = stub_->Render(ctx.get(), request, &response); !s.ok()) return FromGrpc(s);
  return response;
}

absl::StatusOr<v1::Job> Client::Get(const std::string& id) {
  v1::GetJobRequest request;
  request.set_job_id(id);
  return Unary(&v1::Reconstruction::Stub::GetJob, request);
}

absl::StatusOr<v1::ListJobsResponse> Client::ListPage(int limit, const std::string& page_token) {
  v1::ListJobsRequest request;
  request.set_limit(limit);
  request.set_page_token(page_token);
  return Unary(&v1::Reconstruction::Stub::ListJobs, request);
}

absl::StatusOr<v1::ListJobsResponse> Client::List(int limit) {
  v1::ListJobsResponse all;
  std::string token;
  do {
    const int wanted = limit > 0 ? limit - all.jobs_size() : 0;
    LSQSURF_ASSIGN_OR_RETURN(v1::ListJobsResponse page, ListPage(wanted > 0 ? std::min(wanted, 1000) : 1000, token));
    for (v1::Job& job : *page.mutable_jobs()) *all.add_jobs() = std::move(job);
    token = page.next_page_token();
  } while (!token.empty() && (limit <= 0 || all.jobs_size() < limit));
  return all;
}

absl::StatusOr<v1::Job> Client::Cancel(const std::string& id) {
  v1::CancelJobRequest request;
  request.set_job_id(id);
  return Unary(&v1::Reconstruction::Stub::CancelJob, request);
}

absl::Status Client::Delete(const std::string& id) {
  v1::DeleteJobRequest request;
  request.set_job_id(id);
  return Unary(&v1::Reconstruction::Stub::DeleteJob, request).status();
}

absl::StatusOr<v1::ListMethodsResponse> Client::ListMethods() {
  return Unary(&v1::Reconstruction::Stub::ListMethods, v1::ListMethodsRequest{});
}

absl::StatusOr<v1::ServerInfo> Client::GetServerInfo() {
  return Unary(&v1::Reconstruction::Stub::GetServerInfo, v1::GetServerInfoRequest{});
}

absl::StatusOr<bool> Client::Serving(const std::string& service, std::chrono::milliseconds timeout) {
  auto health = grpc::health::v1::Health::NewStub(channel_);
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + timeout);
  grpc::health::v1::HealthCheckRequest request;
  request.set_service(service);
  grpc::health::v1::HealthCheckResponse response;
  if (const grpc::Status status = health->Check(&ctx, request, &response); !status.ok()) return FromGrpc(status);
  return response.status() == grpc::health::v1::HealthCheckResponse::SERVING;
}

}  // namespace lsqsurf::client
