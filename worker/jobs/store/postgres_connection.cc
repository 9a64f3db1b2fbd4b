#include "worker/jobs/store/postgres_connection.h"

#include <libpq-fe.h>

#include "worker/core/strings.h"

namespace lsqsurf::jobs::pg {
namespace {

std::string Trimmed(const char* message) {
  std::string out = message ? message : "";
  while (!out.empty() && (out.back() == '\n' || out.back() == ' ')) out.pop_back();
  return out;
}

}  // namespace

std::string Redacted(const std::string& url) {
  std::string out = url;
  // postgresql://user:secret@host/... — the password sits between the user's ':' and the '@'.
  if (const size_t scheme = out.find("://"); scheme != std::string::npos) {
    const size_t at = out.find('@', scheme), colon = out.find(':', scheme + 3);
    if (at != std::string::npos && colon < at) out.replace(colon + 1, at - colon - 1, "***");
  }
  // "host=... password=secret ..." — the value up to the next space (or closing quote).
  for (size_t key = out.find("password"); key != std::string::npos; key = out.find("password", key + 1)) {
    size_t value = out.find_first_not_of(' ', key + 8);
    if (value == std::string::npos || out[value] != '=') continue;
    value = out.find_first_not_of(' ', value + 1);
    if (value == std::string::npos) break;
    const bool quoted = out[value] == '\'';
    const size_t end = quoted ? out.find('\'', value + 1) + 1 : out.find(' ', value);
    out.replace(value, (end == std::string::npos || end == 0 ? out.size() : end) - value, "***");
  }
  return out;
}

absl::StatusOr<pg_conn*> Connect(const std::string& url) {
  PGconn* conn = PQconnectdb(url.c_str());
  if (conn == nullptr) return absl::UnavailableError("PostgreSQL: out of memory");
  if (PQstatus(conn) != CONNECTION_OK) {
    std::string why = Trimmed(PQerrorMessage(conn));
    PQfinish(conn);
    return absl::UnavailableError(core::StrCat("cannot connect to PostgreSQL at ", Redacted(url), ": ", why));
  }
  // Notices (e.g. "relation already exists, skipping") are not the service's business.
  PQsetNoticeProcessor(
      conn, [](void*, const char*) {}, nullptr);
  return conn;
}

void Close(pg_conn* conn) {
  if (conn != nullptr) PQfinish(conn);
}

absl::StatusOr<Rows> Exec(pg_conn* conn, std::string_view sql, const std::vector<Param>& params, bool binary_results) {
  // libpq reads text parameters up to a NUL, so they are copied; binary ones go as they are.
  std::vector<std::string> texts(params.size());
  std::vector<const char*> values;
  std::vector<int> lengths, formats;
  for (size_t i = 0; i < params.size(); ++i) {
    const Param& p = params[i];
    if (!p.binary) texts[i].assign(p.value);
    values.push_back(p.binary ? p.value.data() : texts[i].c_str());
    lengths.push_back(static_cast<int>(p.value.size()));
    formats.push_back(p.binary ? 1 : 0);
  }
  const std::string statement(sql);
  // Without parameters the simple protocol runs it, which takes scripts of several statements.
  std::unique_ptr<PGresult, decltype(&PQclear)> result(
      params.empty() && !binary_results
          ? PQexec(conn, statement.c_str())
          : PQexecParams(conn, statement.c_str(), static_cast<int>(params.size()), nullptr, values.data(),
                         lengths.data(), formats.data(), binary_results ? 1 : 0),
      &PQclear);
  const ExecStatusType status = result ? PQresultStatus(result.get()) : PGRES_FATAL_ERROR;
  if (status != PGRES_COMMAND_OK && status != PGRES_TUPLES_OK) {
    const char* state = result ? PQresultErrorField(result.get(), PG_DIAG_SQLSTATE) : nullptr;
    const std::string message = core::StrCat("PostgreSQL: ", Trimmed(PQerrorMessage(conn)));
    const std::string code = state ? state : "";
    if (code == "23505") return absl::AlreadyExistsError(message);
    if (code == "40001" || code == "40P01") return absl::AbortedError(message);
    return absl::UnavailableError(message);
  }
  Rows out;
  const int n = PQntuples(result.get()), columns = PQnfields(result.get());
  out.rows.resize(static_cast<size_t>(n));
  for (int i = 0; i < n; ++i) {
    auto& row = out.rows[static_cast<size_t>(i)];
    row.reserve(static_cast<size_t>(columns));
    for (int j = 0; j < columns; ++j) {
      row.emplace_back(PQgetvalue(result.get(), i, j), static_cast<size_t>(PQgetlength(result.get(), i, j)));
    }
  }
  const char* affected = PQcmdTuples(result.get());
  out.affected = affected && *affected ? std::strtoll(affected, nullptr, 10) : 0;
  return out;
}

absl::StatusOr<std::shared_ptr<Pool>> Pool::Open(std::string url, int size) {
  auto first = Connect(url);
  if (!first.ok()) return first.status();
  std::shared_ptr<Pool> pool(new Pool(std::move(url), std::max(size, 1)));
  pool->idle_.push_back(*first);
  pool->open_ = 1;
  return pool;
}

Pool::~Pool() {
  for (pg_conn* conn : idle_) Close(conn);
}

Pool::Handle::~Handle() {
  if (conn_ != nullptr) pool_->Release(conn_);
}

absl::StatusOr<Pool::Handle> Pool::Acquire() {
  std::unique_lock lock(mutex_);
  released_.wait(lock, [&] { return !idle_.empty() || open_ < size_; });
  if (!idle_.empty()) {
    pg_conn* conn = idle_.back();
    idle_.pop_back();
    lock.unlock();
    if (PQstatus(conn) != CONNECTION_OK) PQreset(conn);  // The server restarted, or the link broke.
    if (PQstatus(conn) != CONNECTION_OK) {
      const std::string why = Trimmed(PQerrorMessage(conn));
      Close(conn);
      std::lock_guard relock(mutex_);
      --open_;
      released_.notify_one();
      return absl::UnavailableError(core::StrCat("lost the connection to PostgreSQL: ", why));
    }
    return Handle(this, conn);
  }
  ++open_;
  lock.unlock();
  auto conn = Connect(url_);
  if (!conn.ok()) {
    std::lock_guard relock(mutex_);
    --open_;
    released_.notify_one();
    return conn.status();
  }
  return Handle(this, *conn);
}

void Pool::Release(pg_conn* conn) {
  // A connection left inside a transaction (a failed body) is not reused as it is.
  if (PQtransactionStatus(conn) != PQTRANS_IDLE) (void)pg::Exec(conn, "ROLLBACK");
  std::lock_guard lock(mutex_);
  idle_.push_back(conn);
  released_.notify_one();
}

absl::StatusOr<Rows> Pool::Exec(std::string_view sql, const std::vector<Param>& params, bool binary_results) {
  auto conn = Acquire();
  if (!conn.ok()) return conn.status();
  return pg::Exec(conn->get(), sql, params, binary_results);
}

absl::Status Pool::Transaction(const std::function<absl::Status(pg_conn*)>& body) {
  auto conn = Acquire();
  if (!conn.ok()) return conn.status();
  if (auto begun = pg::Exec(conn->get(), "BEGIN"); !begun.ok()) return begun.status();
  if (absl::Status s = body(conn->get()); !s.ok()) {
    (void)pg::Exec(conn->get(), "ROLLBACK");
    return s;
  }
  return pg::Exec(conn->get(), "COMMIT").status();
}

}  // namespace lsqsurf::jobs::pg
