#include "server/http_gateway.h"

#include <google/protobuf/util/json_util.h>

#include <algorithm>
#include <cctype>
#include <charconv>
#include <chrono>
#include <map>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "lsqsurf/v1/reconstruction.grpc.pb.h"
#include "server/web_assets.h"
#include "worker/core/strings.h"

namespace lsqsurf::server {
namespace {

using core::StrCat;
using Stub = v1::Reconstruction::Stub;

constexpr auto kUnaryDeadline = std::chrono::seconds(30);
constexpr size_t kMaxAuthorization = 4096;

// Only what the page needs: its own scripts, three's, Draco's decoder (WebAssembly, in a worker
// made from a blob), pictures fetched as blobs. No inline script, nothing from elsewhere.
constexpr const char* kContentSecurityPolicy =
    "default-src 'self'; script-src 'self' 'wasm-unsafe-eval'; worker-src 'self' blob:; img-src 'self' blob: data:; "
    "style-src 'self'; connect-src 'self' blob:; frame-ancestors 'none'; base-uri 'none'; form-action 'self'";

void SetCommonHeaders(HttpAnswer& res) {
  res.headers.emplace_back("Content-Security-Policy", kContentSecurityPolicy);
  res.headers.emplace_back("X-Content-Type-Options", "nosniff");
  res.headers.emplace_back("Referrer-Policy", "no-referrer");
  res.headers.emplace_back("Cache-Control", "no-store");
}

void SetContent(HttpAnswer& res, std::string body, std::string type) {
  res.body = std::move(body);
  res.headers.emplace_back("Content-Type", std::move(type));
}

int HttpStatus(grpc::StatusCode code) {
  switch (code) {
    case grpc::StatusCode::INVALID_ARGUMENT:
    case grpc::StatusCode::OUT_OF_RANGE:
    case grpc::StatusCode::FAILED_PRECONDITION: return 400;
    case grpc::StatusCode::UNAUTHENTICATED: return 401;
    case grpc::StatusCode::PERMISSION_DENIED: return 403;
    case grpc::StatusCode::NOT_FOUND: return 404;
    case grpc::StatusCode::RESOURCE_EXHAUSTED: return 429;
    case grpc::StatusCode::UNAVAILABLE: return 503;
    case grpc::StatusCode::DEADLINE_EXCEEDED: return 504;
    default: return 500;
  }
}

void Fail(HttpAnswer& res, grpc::StatusCode code, std::string_view message) {
  res.status = HttpStatus(code);
  if (code == grpc::StatusCode::UNAUTHENTICATED) res.headers.emplace_back("WWW-Authenticate", "Bearer");
  SetContent(res,
             StrCat("{\"code\": ", JsonQuoted(absl::StatusCodeToString(static_cast<absl::StatusCode>(code))),
                    ", \"message\": ", JsonQuoted(message), "}"),
             "application/json");
}

void Reply(HttpAnswer& res, const google::protobuf::Message& message) {
  google::protobuf::util::JsonPrintOptions options;
  options.preserve_proto_field_names = true;
  options.always_print_primitive_fields = true;
  std::string json;
  if (!google::protobuf::util::MessageToJsonString(message, &json, options).ok()) {
    Fail(res, grpc::StatusCode::INTERNAL, "the answer could not be written as JSON");
    return;
  }
  SetContent(res, std::move(json), "application/json");
}

// A context carrying the caller's token, as a gRPC client would send it. A header gRPC could not
// send (a line break, a space in the token) is refused here: gRPC would abort on it.
std::unique_ptr<grpc::ClientContext> CallerContext(const HttpRequest& req, HttpAnswer& res) {
  auto context = std::make_unique<grpc::ClientContext>();
  const std::string authorization = req.header("authorization");
  if (authorization.empty()) return context;
  const std::string_view scheme = "Bearer ";
  const bool well_formed = authorization.size() <= kMaxAuthorization &&
                           authorization.compare(0, scheme.size(), scheme) == 0 &&
                           authorization.size() > scheme.size() &&
                           std::all_of(authorization.begin() + static_cast<ptrdiff_t>(scheme.size()),
                                       authorization.end(), [](char c) { return c > ' ' && c <= '~'; });
  if (!well_formed) {
    Fail(res, grpc::StatusCode::UNAUTHENTICATED, "the Authorization header must be 'Bearer TOKEN'");
    return nullptr;
  }
  context->AddMetadata("authorization", authorization);
  return context;
}

template <class Request, class Response>
void Unary(const HttpRequest& req, HttpAnswer& res, Stub& stub,
           grpc::Status (Stub::*call)(grpc::ClientContext*, const Request&, Response*), const Request& request) {
  auto context = CallerContext(req, res);
  if (context == nullptr) return;
  context->set_deadline(std::chrono::system_clock::now() + kUnaryDeadline);
  Response response;
  if (grpc::Status s = (stub.*call)(context.get(), request, &response); !s.ok()) {
    Fail(res, s.error_code(), s.error_message());
    return;
  }
  Reply(res, response);
}

const char* ResultType(std::string_view name) {
  if (name.ends_with(".png")) return "image/png";
  if (name.ends_with(".csv")) return "text/csv; charset=utf-8";
  if (name.ends_with(".txt")) return "text/plain; charset=utf-8";
  return "application/octet-stream";
}

// A result streamed from FetchResult as the browser takes it: one gRPC chunk held at a time.
// The first chunk is read before answering, so that a refusal gets its own status.
void Download(const HttpRequest& req, HttpAnswer& res, Stub& stub, std::string job_id, std::string name) {
  struct Transfer {
    std::unique_ptr<grpc::ClientContext> context;
    std::unique_ptr<grpc::ClientReader<v1::ResultChunk>> reader;
    std::string pending;
    size_t offset = 0;
    ~Transfer() {
      if (context != nullptr) context->TryCancel();  // The browser went, or the last byte went.
    }
  };
  auto transfer = std::make_shared<Transfer>();
  transfer->context = CallerContext(req, res);
  if (transfer->context == nullptr) return;
  v1::FetchResultRequest request;
  request.set_job_id(std::move(job_id));
  request.set_name(std::move(name));
  transfer->reader = stub.FetchResult(transfer->context.get(), request);
  v1::ResultChunk first;
  if (!transfer->reader->Read(&first)) {
    if (grpc::Status s = transfer->reader->Finish(); !s.ok()) return Fail(res, s.error_code(), s.error_message());
    SetContent(res, "", ResultType(request.name()));
    return;
  }
  transfer->pending = std::move(*first.mutable_data());
  if (!std::string_view(request.name()).ends_with(".png")) {
    res.headers.emplace_back("Content-Disposition", StrCat("attachment; filename=\"", request.name(), "\""));
  }
  res.headers.emplace_back("Content-Type", ResultType(request.name()));
  const int64_t announced = std::max<int64_t>(first.total_bytes(), 0);
  res.stream_size = announced;
  res.stream = [transfer, announced, sent = int64_t{0}](char* buffer, size_t room) mutable -> int64_t {
    if (transfer->offset == transfer->pending.size()) {
      if (sent == announced) return 0;
      v1::ResultChunk chunk;
      if (!transfer->reader->Read(&chunk) || chunk.data().empty()) return -1;  // Fewer bytes than announced: cut.
      transfer->pending = std::move(*chunk.mutable_data());
      transfer->offset = 0;
    }
    const size_t n = std::min(room, transfer->pending.size() - transfer->offset);
    std::copy_n(transfer->pending.data() + transfer->offset, n, buffer);
    transfer->offset += n;
    sent += static_cast<int64_t>(n);
    return static_cast<int64_t>(n);
  };
}

void ServeAsset(const WebAsset& asset, HttpAnswer& res) {
  std::string type(asset.content_type);
  if (type.starts_with("text/")) type += "; charset=utf-8";
  SetContent(res, std::string(asset.bytes), std::move(type));
}

int LimitOf(const HttpRequest& req) {
  int limit = 200;
  if (auto found = req.query.find("limit"); found != req.query.end()) {
    std::from_chars(found->second.data(), found->second.data() + found->second.size(), limit);
  }
  return std::clamp(limit, 1, 1000);
}

// The path's parts between slashes ("/api/jobs/ID" -> api, jobs, ID); a trailing slash adds none.
std::vector<std::string_view> PathParts(std::string_view path) {
  std::vector<std::string_view> parts;
  while (!path.empty()) {
    if (path.front() == '/') {
      path.remove_prefix(1);
      continue;
    }
    const size_t slash = std::min(path.find('/'), path.size());
    parts.push_back(path.substr(0, slash));
    path.remove_prefix(slash);
  }
  return parts;
}

bool IsHexId(std::string_view text) {
  return !text.empty() && text.size() <= 64 &&
         std::all_of(text.begin(), text.end(), [](char c) { return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'); });
}

bool IsAssetPath(std::string_view path) {
  return std::all_of(path.begin(), path.end(), [](char c) {
    return std::isalnum(static_cast<unsigned char>(c)) != 0 || c == '_' || c == '.' || c == '/' || c == '-';
  });
}

// Every route of the page and its API; `stub` reaches the gRPC service in this process.
class Routes {
 public:
  explicit Routes(std::shared_ptr<grpc::Channel> channel) : stub_(v1::Reconstruction::NewStub(channel)) {
    for (const WebAsset& asset : WebAssets()) assets_.emplace(std::string(asset.path), &asset);
    if (auto found = assets_.find("/"); found != assets_.end()) page_ = found->second;
  }

  HttpAnswer operator()(const HttpRequest& req) const {
    HttpAnswer res;
    SetCommonHeaders(res);
    if (req.method != "GET" && req.method != "HEAD") {
      res.headers.emplace_back("Allow", "GET, HEAD");
      Fail(res, grpc::StatusCode::UNIMPLEMENTED, "only GET and HEAD are served here; jobs are submitted over gRPC");
      res.status = 405;
      return res;
    }
    const std::vector<std::string_view> parts = PathParts(req.path);
    if (req.path.starts_with("/static/")) {
      Static(req.path, res);
    } else if (!Api(req, parts, res) && !Page(parts, res)) {
      Fail(res, grpc::StatusCode::NOT_FOUND, "no such page");
    }
    return res;
  }

 private:
  void Static(const std::string& path, HttpAnswer& res) const {
    const auto found = IsAssetPath(path) ? assets_.find(path) : assets_.end();
    if (found == assets_.end()) return Fail(res, grpc::StatusCode::NOT_FOUND, "no such file");
    ServeAsset(*found->second, res);
  }

  bool Page(const std::vector<std::string_view>& parts, HttpAnswer& res) const {
    if (parts.size() == 1 && parts[0] == "favicon.ico") {
      res.status = 204;
      return true;
    }
    if (!parts.empty() && !(parts.size() == 2 && parts[0] == "jobs" && IsHexId(parts[1]))) return false;
    if (page_ == nullptr) {
      SetContent(res, "lsqsurfd was built without its job page (LSQSURF_WITH_WEB=OFF); the JSON API is at /api/jobs\n",
                 "text/plain; charset=utf-8");
    } else {
      ServeAsset(*page_, res);
    }
    return true;
  }

  bool Api(const HttpRequest& req, const std::vector<std::string_view>& parts, HttpAnswer& res) const {
    if (parts.empty() || parts[0] != "api") return false;
    if (parts.size() == 2 && parts[1] == "methods") {
      Unary(req, res, *stub_, &Stub::ListMethods, v1::ListMethodsRequest{});
    } else if (parts.size() == 2 && parts[1] == "jobs") {
      v1::ListJobsRequest request;
      request.set_limit(LimitOf(req));
      if (auto token = req.query.find("page_token"); token != req.query.end()) request.set_page_token(token->second);
      Unary(req, res, *stub_, &Stub::ListJobs, request);
    } else if (parts.size() == 3 && parts[1] == "jobs") {
      v1::GetJobRequest request;
      request.set_job_id(std::string(parts[2]));
      Unary(req, res, *stub_, &Stub::GetJob, request);
    } else if (parts.size() == 5 && parts[1] == "jobs" && parts[3] == "results") {
      Download(req, res, *stub_, std::string(parts[2]), std::string(parts[4]));
    } else {
      return false;
    }
    return true;
  }

  std::shared_ptr<Stub> stub_;
  std::map<std::string, const WebAsset*, std::less<>> assets_;
  const WebAsset* page_ = nullptr;
};

}  // namespace

absl::StatusOr<std::unique_ptr<HttpGateway>> HttpGateway::Start(std::shared_ptr<grpc::Channel> channel,
                                                                const HttpFrontOptions& options) {
  std::unique_ptr<HttpGateway> gateway(new HttpGateway);
  auto routes = std::make_shared<const Routes>(std::move(channel));
  auto front = HttpFront::Start(options, [routes](const HttpRequest& req) { return (*routes)(req); });
  if (!front.ok()) return front.status();
  gateway->front_ = *std::move(front);
  gateway->host_ = options.listen.substr(0, options.listen.rfind(':'));
  gateway->scheme_ = gateway->front_->scheme();
  gateway->port_ = gateway->front_->port();
  return gateway;
}

HttpGateway::~HttpGateway() { Stop(); }

void HttpGateway::Stop() { front_.reset(); }

std::string HttpGateway::address() const { return StrCat(scheme_, "://", host_, ":", port_); }

}  // namespace lsqsurf::server
