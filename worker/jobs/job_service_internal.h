// worker/jobs/job_service_internal.h — helpers the job service's parts (job_service.cc,
// job_table, job_admission, job_retention, job_runner, job_replication, job_pictures) share.
// Only those files include it.
#pragma once

#include <cstdint>
#include <map>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "worker/jobs/job.h"
#include "worker/jobs/job_kind.h"
#include "worker/jobs/store/blob_store.h"

namespace lsqsurf::jobs {

class JobTable;  // job_table.h

inline int64_t MiB(int64_t bytes) { return (bytes + (int64_t{1} << 20) - 1) >> 20; }

// Milliseconds since the epoch, what records keep.
int64_t NowMs();

// Where each upload slot is kept in a job's folder (names kept from earlier versions).
const std::map<std::string, std::string>& UploadFiles();
// The blob of an upload slot: UploadFiles(), and "input.n.drc" for input part n > 0.
std::string UploadBlob(const std::string& slot);

// The kind that runs `method`'s jobs: a test's override, else the registry's; null if none.
const JobKind* KindFor(const std::map<std::string, const JobKind*>& overrides, const std::string& method);

// A result artifact of job `id` for reading, as JobService::OpenResult answers.
absl::StatusOr<std::unique_ptr<BlobReader>> OpenJobResult(const JobTable& table, BlobStore& blobs,
                                                          const std::string& id, const std::string& name);

}  // namespace lsqsurf::jobs
