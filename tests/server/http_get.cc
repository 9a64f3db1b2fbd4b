#include "tests/server/http_get.h"

#include <httplib.h>

namespace lsqsurf::testing {
namespace {

HttpReply Convert(const httplib::Result& result) {
  HttpReply reply;
  if (!result) return reply;
  reply.ok = true;
  reply.status = result->status;
  reply.body = result->body;
  for (const auto& [name, value] : result->headers) reply.headers.emplace(name, value);
  return reply;
}

httplib::Headers HeadersFor(const std::string& authorization) {
  if (authorization.empty()) return {};
  return {{"Authorization", authorization}};
}

}  // namespace

HttpReply HttpGet(const std::string& address, const std::string& path, const std::string& authorization,
                  const std::function<bool(const char*, size_t)>& receive) {
  httplib::Client client(address);
  if (receive) return Convert(client.Get(path, HeadersFor(authorization), receive));
  return Convert(client.Get(path, HeadersFor(authorization)));
}

HttpReply HttpPost(const std::string& address, const std::string& path, const std::string& authorization,
                   const std::string& body) {
  httplib::Client client(address);
  return Convert(client.Post(path, HeadersFor(authorization), body, "application/json"));
}

}  // namespace lsqsurf::testing
