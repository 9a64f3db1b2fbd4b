// tests/server/http_get.h — HTTP requests for the gateway's tests, through cpp-httplib's client,
// kept in a file of its own: httplib.h brings <resolv.h>, whose `_res` macro breaks Eigen's
// headers when they come after it.
#pragma once

#include <cstddef>
#include <functional>
#include <map>
#include <string>

namespace lsqsurf::testing {

struct HttpReply {
  bool ok = false;  // An answer came (whatever its status); false: the transfer failed or was cut.
  int status = 0;
  std::map<std::string, std::string> headers;
  std::string body;
  std::string header(const std::string& name) const {
    auto found = headers.find(name);
    return found == headers.end() ? "" : found->second;
  }
};

// `address`: "http://HOST:PORT". `authorization`: the header's value, or none when empty.
// `receive`, when given, takes the body as it comes; returning false cuts the transfer.
HttpReply HttpGet(const std::string& address, const std::string& path, const std::string& authorization = "",
                  const std::function<bool(const char*, size_t)>& receive = {});
HttpReply HttpPost(const std::string& address, const std::string& path, const std::string& authorization,
                   const std::string& body);

}  // namespace lsqsurf::testing
