#include "server/reflection.h"

#include <google/protobuf/descriptor.h>
#include <google/protobuf/descriptor.pb.h>

#include <set>

namespace lsqsurf::server {
namespace {

namespace reflection = grpc::reflection::v1alpha;
using google::protobuf::DescriptorPool;
using google::protobuf::FileDescriptor;

// The file and every file it imports, each once, dependencies first.
void AddFileAndDependencies(const FileDescriptor* file, std::set<std::string>& sent,
                            reflection::FileDescriptorResponse* out) {
  if (!sent.insert(file->name()).second) return;
  for (int i = 0; i < file->dependency_count(); ++i) AddFileAndDependencies(file->dependency(i), sent, out);
  google::protobuf::FileDescriptorProto proto;
  file->CopyTo(&proto);
  proto.SerializeToString(out->add_file_descriptor_proto());
}

void NotFound(const std::string& what, reflection::ServerReflectionResponse* response) {
  reflection::ErrorResponse* error = response->mutable_error_response();
  error->set_error_code(static_cast<int>(grpc::StatusCode::NOT_FOUND));
  error->set_error_message(what + " not found");
}

}  // namespace

void ReflectionService::Answer(const reflection::ServerReflectionRequest& request,
                               reflection::ServerReflectionResponse* response) const {
  const DescriptorPool* pool = DescriptorPool::generated_pool();
  response->Clear();
  response->set_valid_host(request.host());
  *response->mutable_original_request() = request;
  std::set<std::string> sent;
  const FileDescriptor* file = nullptr;
  switch (request.message_request_case()) {
    case reflection::ServerReflectionRequest::kListServices:
      for (const std::string& name : services_)
        response->mutable_list_services_response()->add_service()->set_name(name);
      return;
    case reflection::ServerReflectionRequest::kFileByFilename:
      file = pool->FindFileByName(request.file_by_filename());
      if (file == nullptr) return NotFound("file", response);
      break;
    case reflection::ServerReflectionRequest::kFileContainingSymbol:
      file = pool->FindFileContainingSymbol(request.file_containing_symbol());
      if (file == nullptr) return NotFound("symbol", response);
      break;
    case reflection::ServerReflectionRequest::kFileContainingExtension: {
      const auto* type = pool->FindMessageTypeByName(request.file_containing_extension().containing_type());
      const auto* extension =
          type == nullptr ? nullptr
                          : pool->FindExtensionByNumber(type, request.file_containing_extension().extension_number());
      if (extension == nullptr) return NotFound("extension", response);
      file = extension->file();
      break;
    }
    case reflection::ServerReflectionRequest::kAllExtensionNumbersOfType: {
      const auto* type = pool->FindMessageTypeByName(request.all_extension_numbers_of_type());
      if (type == nullptr) return NotFound("type", response);
      std::vector<const google::protobuf::FieldDescriptor*> extensions;
      pool->FindAllExtensions(type, &extensions);
      reflection::ExtensionNumberResponse* numbers = response->mutable_all_extension_numbers_response();
      numbers->set_base_type_name(type->full_name());
      for (const auto* e : extensions) numbers->add_extension_number(e->number());
      return;
    }
    default: {
      reflection::ErrorResponse* error = response->mutable_error_response();
      error->set_error_code(static_cast<int>(grpc::StatusCode::UNIMPLEMENTED));
      error->set_error_message("unknown reflection request");
      return;
    }
  }
  AddFileAndDependencies(file, sent, response->mutable_file_descriptor_response());
}

// One reflection stream: a request read, its answer written, and so on until the client is done.
class ReflectionService::Stream final
    : public grpc::ServerBidiReactor<reflection::ServerReflectionRequest, reflection::ServerReflectionResponse> {
 public:
  Stream(const ReflectionService& service, std::unique_ptr<StreamGuard::Ticket> ticket)
      : service_(service), ticket_(std::move(ticket)) {
    StartRead(&request_);
  }
  void OnReadDone(bool ok) override {
    if (!ok) return Finish(grpc::Status::OK);  // The client is done (or gone).
    ticket_->Touch();
    service_.Answer(request_, &response_);
    StartWrite(&response_);
  }
  void OnWriteDone(bool ok) override {
    if (!ok) return Finish(grpc::Status(grpc::StatusCode::CANCELLED, "the client went away"));
    ticket_->Touch();
    StartRead(&request_);
  }
  void OnDone() override { delete this; }

 private:
  const ReflectionService& service_;
  std::unique_ptr<StreamGuard::Ticket> ticket_;
  reflection::ServerReflectionRequest request_;
  reflection::ServerReflectionResponse response_;
};

grpc::ServerBidiReactor<reflection::ServerReflectionRequest, reflection::ServerReflectionResponse>*
ReflectionService::ServerReflectionInfo(grpc::CallbackServerContext* context) {
  auto ticket = streams_.Admit(StreamKind::kReflection, "", context);
  if (!ticket.ok()) {
    return new Refusal<
        grpc::ServerBidiReactor<reflection::ServerReflectionRequest, reflection::ServerReflectionResponse>>(
        grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED, std::string(ticket.status().message())));
  }
  return new Stream(*this, *std::move(ticket));
}

}  // namespace lsqsurf::server
