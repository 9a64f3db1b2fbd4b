#include "server/http_gateway.h"

#include <google/protobuf/util/json_util.h>
#include <httplib.h>

#include <algorithm>
#include <charconv>
#include <chrono>
#include <map>
#include <utility>

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

void SetCommonHeaders(httplib::Response& res) {
  res.set_header("Content-Security-Policy", kContentSecurityPolicy);
  res.set_header("X-Content-Type-Options", "nosniff");
  res.set_header("Referrer-Policy", "no-referrer");
  res.set_header("Cache-Control", "no-store");
}

std::string JsonString(std::string_view text) {
  std::string out = "\"";
  for (char c : text) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else if (static_cast<unsigned char>(c) < 0x20) {
      char escaped[8];
      std::snprintf(escaped, sizeof escaped, "\\u%04x", c);
      out += escaped;
    } else {
      out += c;
    }
  }
  return out + "\"";
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

void Fail(httplib::Response& res, grpc::StatusCode code, std::string_view message) {
  res.status = HttpStatus(code);
  if (code == grpc::StatusCode::UNAUTHENTICATED) res.set_header("WWW-Authenticate", "Bearer");
  res.set_content(StrCat("{\"code\": ", JsonString(absl::StatusCodeToString(static_cast<absl::StatusCode>(code))),
                         ", \"message\": ", JsonString(message), "}"),
                  "application/json");
}

void Reply(httplib::Response& res, const google::protobuf::Message& message) {
  google::protobuf::util::JsonPrintOptions options;
  options.preserve_proto_field_names = true;
  options.always_print_primitive_fields = true;
  std::string json;
  if (!google::protobuf::util::MessageToJsonString(message, &json, options).ok()) {
    Fail(res, grpc::StatusCode::INTERNAL, "the answer could not be written as JSON");
    return;
  }
  res.set_content(json, "application/json");
}

// A context carrying the caller's token, as a gRPC client would send it. A header gRPC could not
// send (a line break, a space in the token) is refused here: gRPC would abort on it.
std::unique_ptr<grpc::ClientContext> CallerContext(const httplib::Request& req, httplib::Response& res) {
  auto context = std::make_unique<grpc::ClientContext>();
  const std::string authorization = req.get_header_value("Authorization");
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
void Unary(const httplib::Request& req, httplib::Response& res, Stub& stub,
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
void Download(const httplib::Request& req, httplib::Response& res, Stub& stub) {
  struct Transfer {
    std::unique_ptr<grpc::ClientContext> context;
    std::unique_ptr<grpc::ClientReader<v1::ResultChunk>> reader;
    std::string pending;
  };
  auto transfer = std::make_shared<Transfer>();
  transfer->context = CallerContext(req, res);
  if (transfer->context == nullptr) return;
  v1::FetchResultRequest request;
  request.set_job_id(req.matches[1].str());
  request.set_name(req.matches[2].str());
  transfer->reader = stub.FetchResult(transfer->context.get(), request);
  v1::ResultChunk first;
  if (!transfer->reader->Read(&first)) {
    if (grpc::Status s = transfer->reader->Finish(); !s.ok()) return Fail(res, s.error_code(), s.error_message());
    res.set_content("", ResultType(request.name()));
    return;
  }
  transfer->pending = std::move(*first.mutable_data());
  if (!std::string_view(request.name()).ends_with(".png")) {
    res.set_header("Content-Disposition", StrCat("attachment; filename=\"", request.name(), "\""));
  }
  res.set_content_provider(
      static_cast<size_t>(std::max<int64_t>(first.total_bytes(), 0)), ResultType(request.name()),
      [transfer](size_t, size_t, httplib::DataSink& sink) {
        if (transfer->pending.empty()) {
          v1::ResultChunk chunk;
          if (!transfer->reader->Read(&chunk)) return false;  // Fewer bytes than announced: cut off.
          transfer->pending = std::move(*chunk.mutable_data());
        }
        const bool written = sink.write(transfer->pending.data(), transfer->pending.size());
        transfer->pending.clear();
        return written;
      },
      [transfer](bool) { transfer->context->TryCancel(); });
}

void ServeAsset(const WebAsset& asset, httplib::Response& res) {
  std::string type(asset.content_type);
  if (type.starts_with("text/")) type += "; charset=utf-8";
  res.set_content(asset.bytes.data(), asset.bytes.size(), type);
}

int LimitOf(const httplib::Request& req) {
  int limit = 200;
  if (req.has_param("limit")) {
    const std::string text = req.get_param_value("limit");
    std::from_chars(text.data(), text.data() + text.size(), limit);
  }
  return std::clamp(limit, 1, 1000);
}

}  // namespace

void HttpGateway::Route(std::shared_ptr<grpc::Channel> channel) {
  auto stub = std::shared_ptr<Stub>(v1::Reconstruction::NewStub(channel));
  std::map<std::string, const WebAsset*, std::less<>> assets;
  for (const WebAsset& asset : WebAssets()) assets.emplace(std::string(asset.path), &asset);
  const WebAsset* page = assets.contains("/") ? assets.at("/") : nullptr;

  auto serve_page = [page](const httplib::Request&, httplib::Response& res) {
    if (page == nullptr) {
      res.set_content("lsqsurfd was built without its job page (LSQSURF_WITH_WEB=OFF); the JSON API is at /api/jobs\n",
                      "text/plain; charset=utf-8");
      return;
    }
    ServeAsset(*page, res);
  };
  // Before any route (the unknown ones included): the headers every answer carries.
  http_->set_pre_routing_handler([](const httplib::Request&, httplib::Response& res) {
    SetCommonHeaders(res);
    return httplib::Server::HandlerResponse::Unhandled;
  });
  http_->Get("/", serve_page);
  http_->Get("/favicon.ico", [](const httplib::Request&, httplib::Response& res) { res.status = 204; });
  http_->Get(R"(/jobs/[0-9a-f]{1,64}/?)", serve_page);
  http_->Get(R"(/static/([A-Za-z0-9_./-]+))", [assets](const httplib::Request& req, httplib::Response& res) {
    const auto found = assets.find(StrCat("/static/", req.matches[1].str()));
    if (found == assets.end()) return Fail(res, grpc::StatusCode::NOT_FOUND, "no such file");
    ServeAsset(*found->second, res);
  });
  http_->Get("/api/jobs", [stub](const httplib::Request& req, httplib::Response& res) {
    v1::ListJobsRequest request;
    request.set_limit(LimitOf(req));
    Unary(req, res, *stub, &Stub::ListJobs, request);
  });
  http_->Get(R"(/api/jobs/([^/]+))", [stub](const httplib::Request& req, httplib::Response& res) {
    v1::GetJobRequest request;
    request.set_job_id(req.matches[1].str());
    Unary(req, res, *stub, &Stub::GetJob, request);
  });
  http_->Get(R"(/api/jobs/([^/]+)/results/([^/]+))",
             [stub](const httplib::Request& req, httplib::Response& res) { Download(req, res, *stub); });
  http_->Get("/api/methods", [stub](const httplib::Request& req, httplib::Response& res) {
    Unary(req, res, *stub, &Stub::ListMethods, v1::ListMethodsRequest{});
  });
}

absl::StatusOr<std::unique_ptr<HttpGateway>> HttpGateway::Start(std::shared_ptr<grpc::Channel> channel,
                                                                const HttpOptions& options) {
  const size_t colon = options.listen.rfind(':');
  int port = -1;
  if (colon != std::string::npos) {
    const char* end = options.listen.data() + options.listen.size();
    if (std::from_chars(options.listen.data() + colon + 1, end, port).ptr != end) port = -1;
  }
  if (colon == std::string::npos || colon == 0 || port < 0 || port > 65535) {
    return absl::InvalidArgumentError(StrCat("--http-listen '", options.listen, "': expected HOST:PORT"));
  }
  std::unique_ptr<HttpGateway> gateway(new HttpGateway);
  gateway->host_ = options.listen.substr(0, colon);
  std::string bind_host = gateway->host_;
  if (bind_host.size() > 2 && bind_host.front() == '[' && bind_host.back() == ']') {
    bind_host = bind_host.substr(1, bind_host.size() - 2);
  }
  if (options.tls_cert_path.empty()) {
    gateway->http_ = std::make_unique<httplib::Server>();
    gateway->scheme_ = "http";
  } else {
    auto tls = std::make_unique<httplib::SSLServer>(options.tls_cert_path.c_str(), options.tls_key_path.c_str());
    if (!tls->is_valid()) {
      return absl::UnavailableError(StrCat("HTTPS cannot load ", options.tls_cert_path, " and ", options.tls_key_path));
    }
    gateway->http_ = std::move(tls);
    gateway->scheme_ = "https";
  }
  httplib::Server& http = *gateway->http_;
  const auto threads = static_cast<size_t>(std::max(1, options.threads));
  http.new_task_queue = [threads] { return new httplib::ThreadPool(threads); };
  http.set_read_timeout(10, 0);
  http.set_write_timeout(60, 0);
  http.set_keep_alive_timeout(5);
  http.set_payload_max_length(64 << 10);  // GET requests carry no body worth more.
  gateway->Route(std::move(channel));
  gateway->port_ = port == 0 ? http.bind_to_any_port(bind_host) : (http.bind_to_port(bind_host, port) ? port : -1);
  if (gateway->port_ <= 0) return absl::UnavailableError(StrCat("cannot listen on ", options.listen, " for HTTP"));
  gateway->listener_ = std::thread([&http] { http.listen_after_bind(); });
  return gateway;
}

HttpGateway::~HttpGateway() { Stop(); }

void HttpGateway::Stop() {
  if (http_ != nullptr) http_->stop();
  if (listener_.joinable()) listener_.join();
}

std::string HttpGateway::address() const { return StrCat(scheme_, "://", host_, ":", port_); }

}  // namespace lsqsurf::server
