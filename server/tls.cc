#include "server/tls.h"

#include <grpcpp/security/server_credentials.h>
#include <grpcpp/security/tls_certificate_provider.h>
#include <grpcpp/security/tls_credentials_options.h>
#include <openssl/bio.h>
#include <openssl/pem.h>
#include <openssl/x509.h>

#include <filesystem>

#include "server/owner_files.h"
#include "worker/core/strings.h"

namespace lsqsurf::server {
namespace {

namespace fs = std::filesystem;
using core::StrCat;

// OpenSSL objects freed on scope exit.
struct BioDeleter {
  void operator()(BIO* b) const { BIO_free(b); }
};
struct X509Deleter {
  void operator()(X509* x) const { X509_free(x); }
};
struct KeyDeleter {
  void operator()(EVP_PKEY* k) const { EVP_PKEY_free(k); }
};
using Bio = std::unique_ptr<BIO, BioDeleter>;

Bio MemoryBio(const std::string& text) { return Bio(BIO_new_mem_buf(text.data(), static_cast<int>(text.size()))); }

std::unique_ptr<X509, X509Deleter> FirstCertificate(const std::string& pem) {
  Bio bio = MemoryBio(pem);
  return std::unique_ptr<X509, X509Deleter>(PEM_read_bio_X509(bio.get(), nullptr, nullptr, nullptr));
}

// "CN=..., expires ..." of a certificate.
std::string Describe(X509* cert) {
  char subject[256];
  X509_NAME_oneline(X509_get_subject_name(cert), subject, sizeof(subject));
  Bio out(BIO_new(BIO_s_mem()));
  ASN1_TIME_print(out.get(), X509_get0_notAfter(cert));
  char* data = nullptr;
  const long size = BIO_get_mem_data(out.get(), &data);
  return StrCat(subject, ", expires ", std::string(data, static_cast<size_t>(size)));
}

}  // namespace

ServerTls::~ServerTls() = default;

absl::StatusOr<std::unique_ptr<ServerTls>> ServerTls::Open(const TlsFiles& files, const std::string& staging_dir) {
  std::unique_ptr<ServerTls> tls(new ServerTls(files, staging_dir));
  std::error_code error;
  fs::remove_all(staging_dir, error);
  fs::create_directories(staging_dir, error);
  if (error) return absl::UnavailableError(StrCat("cannot make ", staging_dir, ": ", error.message()));
  fs::permissions(staging_dir, fs::perms::owner_all, fs::perm_options::replace, error);
  if (absl::Status s = tls->Stage(); !s.ok()) return s;
  const fs::path current = fs::path(staging_dir) / "current";
  const bool mutual = !files.client_ca.empty();
  auto provider = std::make_shared<grpc::experimental::FileWatcherCertificateProvider>(
      (current / "key.pem").string(), (current / "cert.pem").string(), mutual ? (current / "ca.pem").string() : "",
      /*refresh_interval_sec=*/1);
  grpc::experimental::TlsServerCredentialsOptions options(provider);
  options.watch_identity_key_cert_pairs();
  if (mutual) {
    options.watch_root_certs();
    options.set_cert_request_type(GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY);
  } else {
    options.set_cert_request_type(GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE);
  }
  tls->credentials_ = grpc::experimental::TlsServerCredentials(options);
  return tls;
}

absl::StatusOr<std::string> ServerTls::Reload() {
  if (absl::Status s = Stage(); !s.ok()) return s;
  return description_;
}

absl::Status ServerTls::Stage() {
  auto cert_pem = ReadOwnerFile(files_.cert, "certificate");
  if (!cert_pem.ok()) return cert_pem.status();
  auto key_pem = ReadOwnerFile(files_.key, "private key");
  if (!key_pem.ok()) return key_pem.status();
  std::string ca_pem;
  if (!files_.client_ca.empty()) {
    auto ca = ReadOwnerFile(files_.client_ca, "client CA");
    if (!ca.ok()) return ca.status();
    if (FirstCertificate(*ca) == nullptr) {
      return absl::InvalidArgumentError(StrCat(files_.client_ca, " holds no PEM certificate"));
    }
    ca_pem = *std::move(ca);
  }
  auto cert = FirstCertificate(*cert_pem);
  if (cert == nullptr) return absl::InvalidArgumentError(StrCat(files_.cert, " holds no PEM certificate"));
  Bio key_bio = MemoryBio(*key_pem);
  std::unique_ptr<EVP_PKEY, KeyDeleter> key(PEM_read_bio_PrivateKey(key_bio.get(), nullptr, nullptr, nullptr));
  if (key == nullptr) {
    return absl::InvalidArgumentError(StrCat(files_.key, " holds no PEM private key (an encrypted key is not read)"));
  }
  if (X509_check_private_key(cert.get(), key.get()) != 1) {
    return absl::InvalidArgumentError(StrCat(files_.key, " is not the key of the certificate in ", files_.cert));
  }
  const std::string description = Describe(cert.get());
  if (X509_cmp_current_time(X509_get0_notAfter(cert.get())) < 0) {
    return absl::InvalidArgumentError(StrCat("the certificate in ", files_.cert, " has expired: ", description));
  }
  if (X509_cmp_current_time(X509_get0_notBefore(cert.get())) > 0) {
    return absl::InvalidArgumentError(StrCat("the certificate in ", files_.cert,
                                             " is not valid yet (check the clock, or its issuer's): ", description));
  }
  // A new folder, then the `current` link swapped onto it: gRPC reads one folder or the other.
  const fs::path root(staging_dir_);
  const fs::path folder = root / StrCat("gen-", ++generation_);
  std::error_code error;
  fs::create_directories(folder, error);
  if (error) return absl::UnavailableError(StrCat("cannot make ", folder.string(), ": ", error.message()));
  for (const auto& [name, text] : {std::pair<const char*, const std::string*>{"cert.pem", &*cert_pem},
                                   {"key.pem", &*key_pem},
                                   {"ca.pem", &ca_pem}}) {
    if (absl::Status s = WriteOwnerFile((folder / name).string(), *text, name); !s.ok()) return s;
  }
  const fs::path link = root / "current.new";
  fs::remove(link, error);
  fs::create_directory_symlink(folder.filename(), link, error);
  if (!error) fs::rename(link, root / "current", error);
  if (error)
    return absl::UnavailableError(StrCat("cannot swap the certificate in ", staging_dir_, ": ", error.message()));
  // The folder before last may still be read by a refresh under way; older ones are not.
  if (generation_ > 2) fs::remove_all(root / StrCat("gen-", generation_ - 2), error);
  description_ = description;
  return absl::OkStatus();
}

}  // namespace lsqsurf::server
