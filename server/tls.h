// server/tls.h — lsqsurfd's TLS: the certificate it serves, and the client CA of mutual TLS.
//
// The files are checked (the certificate and key parse and match, the CA parses) and copied
// into a folder of the server's own; gRPC serves that copy and looks at it every second. A
// reload (SIGHUP) checks the files again and swaps in a new copy in one step (a symlink), so a
// certificate renewed on disk is served only once asked for, and never half-written or with the
// wrong key: a bad file is refused and the one in use stays.
#pragma once

#include <memory>
#include <string>

#include "absl/status/statusor.h"

namespace grpc {
class ServerCredentials;
}

namespace lsqsurf::server {

struct TlsFiles {
  std::string cert;       // PEM certificate chain, the server's first.
  std::string key;        // PEM private key of that certificate.
  std::string client_ca;  // PEM CA bundle; when set, clients must present a certificate it signed.
};

class ServerTls {
 public:
  // Checks and stages the files under `staging_dir` (made, owner-only). Errors:
  // kInvalidArgument naming the file and the problem, kUnavailable (I/O).
  static absl::StatusOr<std::unique_ptr<ServerTls>> Open(const TlsFiles& files, const std::string& staging_dir);
  ~ServerTls();
  std::shared_ptr<grpc::ServerCredentials> credentials() const { return credentials_; }
  // Checks and stages the files again; new connections get them within about a second. Returns
  // a line for the log (the certificate's subject and expiry). Errors: those of Open; the files
  // in use stay.
  absl::StatusOr<std::string> Reload();
  // The certificate in use, e.g. "CN=lsqsurf.example, expires 2027-11-23 10:00:00 GMT".
  const std::string& description() const { return description_; }

 private:
  ServerTls(TlsFiles files, std::string staging_dir) : files_(std::move(files)), staging_dir_(std::move(staging_dir)) {}
  absl::Status Stage();
  TlsFiles files_;
  std::string staging_dir_;
  int generation_ = 0;
  std::string description_;
  std::shared_ptr<grpc::ServerCredentials> credentials_;
};

}  // namespace lsqsurf::server
