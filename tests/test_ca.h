// tests/test_ca.h — a certificate authority made by the test that needs it: a CA, and server
// and client certificates it signs (P-256 keys, PEM), valid now or already expired.
#pragma once

#include <openssl/bio.h>
#include <openssl/ec.h>
#include <openssl/evp.h>
#include <openssl/pem.h>
#include <openssl/x509.h>
#include <openssl/x509v3.h>

#include <memory>
#include <stdexcept>
#include <string>

namespace lsqsurf::testing {

struct PemPair {
  std::string cert;  // PEM certificate.
  std::string key;   // PEM private key.
};

class TestCa {
 public:
  explicit TestCa(const std::string& name) : key_(NewKey()) {
    cert_ = Sign(name, "", /*ca=*/true, 0, 30, key_.get(), nullptr);
    pem_ = {ToPem(cert_.get()), KeyPem(key_.get())};
  }
  const std::string& cert_pem() const { return pem_.cert; }

  // A leaf certificate for `name` (also its DNS name; "127.0.0.1" becomes an IP name), valid
  // from `from_days` to `to_days` around now: (-10, -1) is one that expired yesterday.
  PemPair Issue(const std::string& name, long from_days = -1, long to_days = 30) const {
    Key key = NewKey();
    const bool ip = name.find_first_not_of("0123456789.") == std::string::npos;
    const std::string alt = (ip ? "IP:" : "DNS:") + name;
    auto cert = Sign(name, alt, /*ca=*/false, from_days, to_days, key.get(), this);
    return {ToPem(cert.get()), KeyPem(key.get())};
  }

 private:
  struct KeyFree {
    void operator()(EVP_PKEY* k) const { EVP_PKEY_free(k); }
  };
  struct CertFree {
    void operator()(X509* x) const { X509_free(x); }
  };
  using Key = std::unique_ptr<EVP_PKEY, KeyFree>;
  using Cert = std::unique_ptr<X509, CertFree>;

  static Key NewKey() {
    Key key(EVP_EC_gen("P-256"));
    if (key == nullptr) throw std::runtime_error("no EC key");
    return key;
  }

  static void AddExtension(X509* cert, X509* issuer, int nid, const std::string& value) {
    X509V3_CTX ctx;
    X509V3_set_ctx_nodb(&ctx);
    X509V3_set_ctx(&ctx, issuer, cert, nullptr, nullptr, 0);
    X509_EXTENSION* ext = X509V3_EXT_conf_nid(nullptr, &ctx, nid, value.c_str());
    if (ext == nullptr) throw std::runtime_error("bad extension " + value);
    X509_add_ext(cert, ext, -1);
    X509_EXTENSION_free(ext);
  }

  // Signed by `issuer` (this CA), or by `key` itself when null.
  Cert Sign(const std::string& name, const std::string& alt, bool ca, long from_days, long to_days, EVP_PKEY* key,
            const TestCa* issuer) const {
    static long serial = 1;
    Cert cert(X509_new());
    X509_set_version(cert.get(), 2);
    ASN1_INTEGER_set(X509_get_serialNumber(cert.get()), serial++);
    X509_gmtime_adj(X509_getm_notBefore(cert.get()), from_days * 86400);
    X509_gmtime_adj(X509_getm_notAfter(cert.get()), to_days * 86400);
    X509_set_pubkey(cert.get(), key);
    X509_NAME* subject = X509_get_subject_name(cert.get());
    X509_NAME_add_entry_by_txt(subject, "CN", MBSTRING_ASC, reinterpret_cast<const unsigned char*>(name.c_str()), -1,
                               -1, 0);
    X509* issuer_cert = issuer ? issuer->cert_.get() : cert.get();
    X509_set_issuer_name(cert.get(), X509_get_subject_name(issuer_cert));
    AddExtension(cert.get(), issuer_cert, NID_basic_constraints, ca ? "critical,CA:TRUE" : "CA:FALSE");
    AddExtension(cert.get(), issuer_cert, NID_key_usage,
                 ca ? "critical,keyCertSign,cRLSign" : "critical,digitalSignature,keyEncipherment");
    if (!alt.empty()) AddExtension(cert.get(), issuer_cert, NID_subject_alt_name, alt);
    if (!ca) AddExtension(cert.get(), issuer_cert, NID_ext_key_usage, "serverAuth,clientAuth");
    if (X509_sign(cert.get(), issuer ? issuer->key_.get() : key, EVP_sha256()) == 0) {
      throw std::runtime_error("cannot sign");
    }
    return cert;
  }

  static std::string Drain(BIO* bio) {
    char* data = nullptr;
    const long size = BIO_get_mem_data(bio, &data);
    std::string out(data, static_cast<size_t>(size));
    BIO_free(bio);
    return out;
  }
  static std::string ToPem(X509* cert) {
    BIO* bio = BIO_new(BIO_s_mem());
    PEM_write_bio_X509(bio, cert);
    return Drain(bio);
  }
  static std::string KeyPem(EVP_PKEY* key) {
    BIO* bio = BIO_new(BIO_s_mem());
    PEM_write_bio_PrivateKey(bio, key, nullptr, nullptr, 0, nullptr, nullptr);
    return Drain(bio);
  }

  Key key_;
  Cert cert_;
  PemPair pem_;
};

}  // namespace lsqsurf::testing
