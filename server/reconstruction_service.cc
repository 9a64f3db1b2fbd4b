#include "server/reconstruction_service.h"

#include <spdlog/spdlog.h>

#include <filesystem>
#include <fstream>
#include <optional>

#include "server/convert.h"
#include "server/limits.h"
#include "worker/core/byte_view.h"
#include "worker/core/strings.h"
#include "worker/jobs/job_admission.h"
#include "worker/jobs/job_ids.h"
#include "worker/jobs/job_retention.h"
#include "worker/jobs/method_registry.h"

namespace lsqsurf::server {
namespace {

// Threads that decode and submit finished uploads: a few, as each uses a core while it decodes.
// One of them takes only small uploads, so that a small submission never waits behind large
// ones' decoding and repair (two 400k-vertex volumes once held a 19 KB submission for 60 s).
constexpr int kSubmitThreads = 3;
constexpr size_t kSmallUploadBytes = 1 << 20;

// ListJobs pages: jobs by default and at most, and the bytes after which a page ends early
// (a job's text parameters may take 64 KiB each; gRPC's messages end at 16 MiB).
constexpr int kDefaultPageJobs = 100;
constexpr int kMaxPageJobs = 1000;
constexpr size_t kMaxPageBytes = 4 << 20;

// A page token names the last job of its page by its place in the newest-first order:
// "CREATED_MS.ID". Opaque to clients; checked as any other input.
std::string PageToken(const jobs::JobRecord& r) { return core::StrCat(r.created_ms, ".", r.id); }

std::optional<std::pair<int64_t, std::string>> ParsePageToken(const std::string& token) {
  const size_t dot = token.find('.');
  if (dot == std::string::npos || dot == 0 || dot > 19) return std::nullopt;
  int64_t created = 0;
  for (char c : std::string_view(token).substr(0, dot)) {
    if (c < '0' || c > '9') return std::nullopt;
    created = created * 10 + (c - '0');
  }
  std::string id = token.substr(dot + 1);
  if (!jobs::IsJobIdForm(id)) return std::nullopt;
  return std::pair{created, std::move(id)};
}

// Runs a handler body; an exception becomes a status instead of leaving the gRPC thread.
template <class Body>
grpc::Status Run(const char* rpc, Body&& body) {
  try {
    return body();
  } catch (const std::bad_alloc&) {
    spdlog::error("{}: out of memory", rpc);
    return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED, "the server ran out of memory for this call");
  } catch (const std::exception& e) {
    spdlog::error("{}: {}", rpc, e.what());
    return grpc::Status(grpc::StatusCode::INTERNAL, core::StrCat(rpc, " failed: ", e.what()));
  }
}

// What a job-service call sees of its gRPC call: cancelled once the client has gone, so that
// work done for it (a picture) stops and frees its slot.
class CallContext final : public core::JobContext {
 public:
  explicit CallContext(const grpc::ServerContext& call) : call_(call) {}
  void ReportProgress(std::string_view, double) override {}
  bool IsCancelled() const override { return call_.IsCancelled(); }

 private:
  const grpc::ServerContext& call_;
};

}  // namespace

grpc::Status ReconstructionService::Conclude(const CallRecord& call, grpc::Status status) const {
  // Messages may quote what a client sent: bounded, and with no control bytes, before they are
  // logged or sent back (a long one wedges some clients; a newline would forge a log line).
  if (!status.ok())
    status = grpc::Status(status.error_code(), core::Printable(status.error_message(), kMaxMessageBytes));
  if (!status.ok() && status.error_code() != grpc::StatusCode::CANCELLED) {
    spdlog::info("{} by {} refused ({}): {}", call.rpc, call.who,
                 absl::StatusCodeToString(static_cast<absl::StatusCode>(status.error_code())), status.error_message());
  }
  if (calls_ != nullptr) {
    calls_->CallEnded(call.rpc, status.error_code(),
                      std::chrono::duration<double>(std::chrono::steady_clock::now() - call.start).count());
  }
  return status;
}

template <class Body>
grpc::Status ReconstructionService::Serve(const char* rpc, grpc::ServerContext* context, Body&& body) {
  CallRecord call{rpc};
  grpc::Status status = Run(rpc, [&] {
    auto caller = Identify(*context);
    if (!caller.ok()) {
      call.who = core::StrCat("peer ", context->peer());
      return ToGrpcStatus(caller.status());
    }
    call.who = caller->name.empty() ? core::StrCat("peer ", context->peer()) : core::StrCat("'", caller->name, "'");
    return body(*caller);
  });
  return Conclude(call, status);
}

absl::StatusOr<Caller> ReconstructionService::Identify(const grpc::ServerContextBase& context) const {
  if (tokens_ == nullptr) return Caller{};
  const auto& metadata = context.client_metadata();
  const auto header = metadata.find("authorization");
  if (header == metadata.end()) return tokens_->Authenticate("");
  return tokens_->Authenticate(std::string_view(header->second.data(), header->second.size()));
}

absl::StatusOr<jobs::JobRecord> ReconstructionService::Visible(const Caller& caller, const std::string& id) const {
  if (!jobs::IsJobIdForm(id)) return absl::InvalidArgumentError(jobs::kNotAJobId);
  return jobs_.GetFor(caller.submitter, id);
}

absl::StatusOr<ReconstructionService::Admitted> ReconstructionService::Admit(grpc::CallbackServerContext* context,
                                                                             CallRecord& call, StreamKind kind,
                                                                             const std::string* job_id) {
  auto caller = Identify(*context);
  call.who = caller.ok() && !caller->name.empty() ? core::StrCat("'", caller->name, "'")
                                                  : core::StrCat("peer ", context->peer());
  if (!caller.ok()) return caller.status();
  Admitted admitted{*std::move(caller), {}, nullptr};
  if (job_id != nullptr) {
    auto record = Visible(admitted.caller, *job_id);
    if (!record.ok()) return record.status();
    admitted.job = *std::move(record);
  }
  auto ticket = streams_.Admit(kind, admitted.caller.submitter.owner, context);
  if (!ticket.ok()) return ticket.status();
  admitted.ticket = *std::move(ticket);
  return admitted;
}

absl::Status ReconstructionService::ReserveSpool(const Caller& caller, int64_t bytes) {
  SpoolLedger::Room room;
  std::error_code error;
  const std::filesystem::space_info space = std::filesystem::space(spool_dir_, error);
  if (!error) room.disk_free = static_cast<int64_t>(space.available);
  room.min_free = jobs_.options().min_free_bytes;
  room.quota = caller.submitter.max_stored_bytes;
  if (room.quota > 0) room.stored = jobs_.admission().UsageOf(caller.submitter.owner).stored_bytes;
  return spool_.Reserve(caller.submitter.owner, bytes, room);
}

ReconstructionService::ReconstructionService(jobs::JobService& jobs, CallObserver* calls, const TokenTable* tokens,
                                             StreamLimits limits)
    : jobs_(jobs),
      calls_(calls),
      tokens_(tokens),
      streams_(limits),
      spool_dir_((std::filesystem::path(jobs.options().data_dir) / "uploads").string()) {
  // What a previous run was receiving when it stopped is gone with its client.
  std::error_code error;
  std::filesystem::remove_all(spool_dir_, error);
  std::filesystem::create_directories(spool_dir_, error);
  if (error) spdlog::error("cannot make the upload folder {}: {}", spool_dir_, error.message());
  for (int i = 0; i < kSubmitThreads; ++i)
    submit_threads_.emplace_back([this, i] { SubmitLoop(/*small_only=*/i == 0); });
  watch_thread_ = std::thread([this] { WatchLoop(); });
}

ReconstructionService::~ReconstructionService() {
  {
    std::lock_guard lock(submit_mutex_);
    stopping_ = true;
  }
  submit_wake_.notify_all();
  for (std::thread& t : submit_threads_) t.join();
  stop_watching_ = true;
  watch_thread_.join();
}

void ReconstructionService::Post(std::function<void()> task, size_t upload_bytes) {
  {
    std::lock_guard lock(submit_mutex_);
    (upload_bytes < kSmallUploadBytes ? small_submissions_ : submissions_).push_back(std::move(task));
  }
  submit_wake_.notify_all();
}

void ReconstructionService::SubmitLoop(bool small_only) {
  for (;;) {
    std::function<void()> task;
    {
      std::unique_lock lock(submit_mutex_);
      submit_wake_.wait(
          lock, [&] { return stopping_ || !small_submissions_.empty() || (!small_only && !submissions_.empty()); });
      // The others take large uploads first: the small ones have a thread of their own.
      std::deque<std::function<void()>>& from = small_only || submissions_.empty() ? small_submissions_ : submissions_;
      if (from.empty()) return;
      task = std::move(from.front());
      from.pop_front();
    }
    task();
  }
}

// SubmitJob: the spec first, then chunks, each appended to its slot's spool file as it comes; at
// the end the token is asked again and the job submitted on a submission thread.
class ReconstructionService::Upload final : public grpc::ServerReadReactor<v1::SubmitJobRequest> {
 public:
  Upload(ReconstructionService& service, grpc::CallbackServerContext* context, v1::Job* response, Caller caller,
         CallRecord call, std::unique_ptr<StreamGuard::Ticket> ticket)
      : service_(service),
        context_(context),
        response_(response),
        caller_(std::move(caller)),
        call_(std::move(call)),
        ticket_(std::move(ticket)),
        limit_(static_cast<size_t>(service.jobs_.admission().MaxUploadBytes(caller_.submitter))),
        prefix_((std::filesystem::path(service.spool_dir_) / jobs::NewJobId()).string()) {
    StartRead(&message_);
  }

  void OnReadDone(bool ok) override {
    if (!ok) {
      if (!spec_.has_value()) return End(InvalidArgument("the first SubmitJob message must carry the job spec"));
      if (context_->IsCancelled()) return End(grpc::Status(grpc::StatusCode::CANCELLED, "upload cancelled"));
      // From here the call waits on the server (a submission thread, the checks), not on its
      // client: the idle sweeper must not cancel a job it is about to store.
      ticket_->SetBusy(true);
      service_.Post([this] { Submit(); }, received_);
      return;
    }
    ticket_->Touch();
    grpc::Status status = Take();
    if (!status.ok()) return End(status);
    StartRead(&message_);
  }

  void OnDone() override {
    files_.clear();
    std::error_code error;
    for (const auto& [slot, path] : paths_) std::filesystem::remove(path, error);
    service_.spool_.Release(caller_.submitter.owner, spooled_);
    delete this;
  }

 private:
  static grpc::Status InvalidArgument(const std::string& why) {
    return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, why);
  }

  // The message just read: the spec, or a chunk for the spool.
  grpc::Status Take() {
    return Run("SubmitJob", [&] {
      if (!spec_.has_value()) {
        if (!message_.has_spec()) return InvalidArgument("the first SubmitJob message must carry the job spec");
        auto spec = FromProto(message_.spec());  // Fully checked: a bad spec fails before its upload.
        if (!spec.ok()) return ToGrpcStatus(spec.status());
        spec_ = *std::move(spec);
        return grpc::Status::OK;
      }
      if (message_.has_spec()) return InvalidArgument("only the first message may carry a spec");
      if (message_.has_input_part_end()) return EndInputPart();
      const std::string slot = message_.has_velocity_chunk() ? jobs::kVelocityUpload
                               : message_.has_cells_chunk()  ? jobs::kCellsUpload
                                                             : jobs::InputPartSlot(input_part_);
      const std::string& chunk = message_.has_velocity_chunk() ? message_.velocity_chunk()
                                 : message_.has_cells_chunk()  ? message_.cells_chunk()
                                                               : message_.input_chunk();
      if (chunk.size() > kMaxChunkBytes) return InvalidArgument("upload chunks must be at most 1 MiB");
      if (received_ + chunk.size() > limit_) {
        const bool quota = static_cast<int64_t>(limit_) < service_.jobs_.options().max_input_bytes;
        return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                            core::StrCat("the upload exceeds ", quota ? "your quota's" : "this server's", " limit of ",
                                         limit_, " bytes"));
      }
      if (absl::Status room = service_.ReserveSpool(caller_, static_cast<int64_t>(chunk.size())); !room.ok()) {
        return ToGrpcStatus(room);
      }
      spooled_ += static_cast<int64_t>(chunk.size());
      received_ += chunk.size();
      if (message_.has_input_chunk()) input_part_bytes_ += chunk.size();
      std::ofstream& file = FileOf(slot);
      file.write(chunk.data(), static_cast<std::streamsize>(chunk.size()));
      file.flush();
      if (!file) {
        return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                            "the server cannot keep the upload (its disk may be full); try again later");
      }
      if (service_.calls_ != nullptr) service_.calls_->Received(static_cast<int64_t>(chunk.size()));
      return grpc::Status::OK;
    });
  }

  grpc::Status EndInputPart() {
    if (input_part_bytes_ == 0) {
      return InvalidArgument(core::StrCat("input part ", input_part_,
                                          " ended before any of its chunks came; end a part only after its data"));
    }
    if (input_part_ + 1 >= jobs::kMaxInputParts) {
      return InvalidArgument(core::StrCat("an input has at most ", jobs::kMaxInputParts, " parts"));
    }
    files_.erase(jobs::InputPartSlot(input_part_));  // Closed: no more chunks come for it.
    // The points the parts so far declare, from their Draco headers: a cloud over the server's
    // limit is refused now, not after the rest of its parts have come.
    if (auto points = jobs::DeclaredPoints(HeadOf(paths_[jobs::InputPartSlot(input_part_)])); points.has_value()) {
      declared_points_ += *points;
      if (const int64_t limit = service_.jobs_.options().max_points;
          declared_points_ > static_cast<uint64_t>(std::max<int64_t>(limit, 0))) {
        return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                            core::StrCat("input parts 0 to ", input_part_, " declare ", declared_points_,
                                         " points; this server accepts at most ", limit));
      }
    }
    ++input_part_;
    input_part_bytes_ = 0;
    return grpc::Status::OK;
  }

  // The first bytes of a spool file, where a Draco header lies.
  static std::string HeadOf(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    std::string head(jobs::kDracoHeadBytes, '\0');
    in.read(head.data(), static_cast<std::streamsize>(head.size()));
    head.resize(static_cast<size_t>(in.gcount()));
    return head;
  }

  std::ofstream& FileOf(const std::string& slot) {
    auto& file = files_[slot];
    if (file == nullptr) {
      paths_[slot] = core::StrCat(prefix_, ".", slot);
      file = std::make_unique<std::ofstream>(paths_[slot], std::ios::binary | std::ios::trunc);
    }
    return *file;
  }

  // On a submission thread: the token asked again (one revoked meanwhile may not have the job
  // accepted, and the quotas are those in force now), the spool files mapped (never read onto
  // the heap) and the job submitted; its store takes them by rename.
  void Submit() {
    End(Run("SubmitJob", [this] { return Accept(); }));
  }

  grpc::Status Accept() {
    auto now = service_.Identify(*context_);
    if (!now.ok()) return ToGrpcStatus(now.status());
    if (now->name != caller_.name) {
      return grpc::Status(grpc::StatusCode::UNAUTHENTICATED, "the token changed during the upload");
    }
    if (context_->IsCancelled()) {  // The client gave up while the submission waited its turn.
      return grpc::Status(grpc::StatusCode::CANCELLED, "the submission was cancelled before its job was stored");
    }
    jobs::Uploads uploads;
    files_.clear();  // Flushed and closed.
    for (const auto& [slot, path] : paths_) {
      auto bytes = core::ByteView::MapFile(path, /*movable=*/true);
      if (!bytes.ok()) return ToGrpcStatus(bytes.status());
      uploads[slot] = *std::move(bytes);
    }
    // OnDone removes what the store did not take.
    auto record = service_.jobs_.Submit(*spec_, std::move(uploads), now->submitter);
    if (!record.ok()) return ToGrpcStatus(record.status());
    ToProto(*record, response_);
    return grpc::Status::OK;
  }

  void End(const grpc::Status& status) { Finish(service_.Conclude(call_, status)); }

  ReconstructionService& service_;
  grpc::CallbackServerContext* context_;
  v1::Job* response_;
  const Caller caller_;
  const CallRecord call_;
  std::unique_ptr<StreamGuard::Ticket> ticket_;
  const size_t limit_;
  const std::string prefix_;  // Of the spool files.
  v1::SubmitJobRequest message_;
  std::optional<jobs::JobSpec> spec_;
  size_t received_ = 0;
  int64_t spooled_ = 0;           // Reserved in the service's SpoolLedger.
  uint64_t declared_points_ = 0;  // By the Draco headers of the input parts ended so far.
  int64_t input_part_ = 0;        // The input part chunks go to now...
  size_t input_part_bytes_ = 0;   // ...and its bytes so far.
  std::map<std::string, std::string> paths_;
  std::map<std::string, std::unique_ptr<std::ofstream>> files_;
};

grpc::ServerReadReactor<v1::SubmitJobRequest>* ReconstructionService::SubmitJob(grpc::CallbackServerContext* context,
                                                                                v1::Job* response) {
  CallRecord call{"SubmitJob"};
  auto admitted = Admit(context, call, StreamKind::kUpload, nullptr);
  if (!admitted.ok()) {
    return new Refusal<grpc::ServerReadReactor<v1::SubmitJobRequest>>(Conclude(call, ToGrpcStatus(admitted.status())));
  }
  return new Upload(*this, context, response, std::move(admitted->caller), std::move(call),
                    std::move(admitted->ticket));
}

// WatchJob: the job's record now, then every change until it ends. The watcher thread pokes
// every watch when any job changes; a poke writes when the record is newer than the last sent
// and no write is in flight. Start* and Finish are never called with the lock held (their
// reactions may run at once on the calling thread).
class ReconstructionService::Watch final : public grpc::ServerWriteReactor<v1::JobEvent> {
 public:
  Watch(ReconstructionService& service, std::string id, CallRecord call, std::unique_ptr<StreamGuard::Ticket> ticket)
      : service_(service), id_(std::move(id)), call_(std::move(call)), ticket_(std::move(ticket)) {}

  void Poke() {
    std::optional<grpc::Status> end;
    {
      std::lock_guard lock(mutex_);
      if (finished_ || writing_) return;
      auto record = service_.jobs_.Get(id_);
      if (cancelled_) {
        end = grpc::Status(grpc::StatusCode::CANCELLED, "watch cancelled");
      } else if (!record.ok()) {
        end = ToGrpcStatus(record.status());
      } else if (service_.jobs_.shutting_down()) {
        end = grpc::Status(grpc::StatusCode::UNAVAILABLE, "the server is shutting down; watch again later");
      } else if (!sent_any_ || record->version != sent_version_) {
        sent_any_ = true;
        sent_version_ = record->version;
        last_ = jobs::IsTerminal(record->state);
        event_.Clear();
        ToProto(*record, event_.mutable_job());
        writing_ = true;
      } else {
        return;
      }
      if (end.has_value()) finished_ = true;
    }
    if (end.has_value()) return Finish(service_.Conclude(call_, *end));
    StartWrite(&event_);
  }

  void OnWriteDone(bool ok) override {
    std::optional<grpc::Status> end;
    {
      std::lock_guard lock(mutex_);
      writing_ = false;
      if (!ok) end = grpc::Status(grpc::StatusCode::CANCELLED, "watcher went away");
      if (ok && last_) end = grpc::Status::OK;
      if (end.has_value()) finished_ = true;
    }
    if (end.has_value()) return Finish(service_.Conclude(call_, *end));
    Poke();  // It may have changed while the event was on its way.
  }

  void OnCancel() override {
    {
      std::lock_guard lock(mutex_);
      cancelled_ = true;
      if (writing_ || finished_) return;  // The write's end finishes it.
      finished_ = true;
    }
    Finish(service_.Conclude(call_, grpc::Status(grpc::StatusCode::CANCELLED, "watch cancelled")));
  }

  void OnDone() override {
    service_.RemoveWatch(this);
    delete this;
  }

 private:
  ReconstructionService& service_;
  const std::string id_;
  const CallRecord call_;
  std::unique_ptr<StreamGuard::Ticket> ticket_;
  std::mutex mutex_;
  bool writing_ = false, finished_ = false, cancelled_ = false, sent_any_ = false, last_ = false;
  uint64_t sent_version_ = 0;
  v1::JobEvent event_;  // The event in flight.
};

grpc::ServerWriteReactor<v1::JobEvent>* ReconstructionService::WatchJob(grpc::CallbackServerContext* context,
                                                                        const v1::WatchJobRequest* request) {
  CallRecord call{"WatchJob"};
  auto admitted = Admit(context, call, StreamKind::kWatch, &request->job_id());
  if (!admitted.ok()) {
    return new Refusal<grpc::ServerWriteReactor<v1::JobEvent>>(Conclude(call, ToGrpcStatus(admitted.status())));
  }
  auto* watch = new Watch(*this, admitted->job->id, std::move(call), std::move(admitted->ticket));
  {
    std::lock_guard lock(watch_mutex_);
    watches_.insert(watch);
  }
  watch->Poke();
  return watch;
}

void ReconstructionService::RemoveWatch(Watch* watch) {
  std::lock_guard lock(watch_mutex_);
  watches_.erase(watch);
}

void ReconstructionService::WatchLoop() {
  uint64_t seen = 0;
  while (!stop_watching_) {
    // The timeout bounds how late a shutdown or a change no one announced is noticed.
    seen = jobs_.WaitForAnyChange(seen, std::chrono::milliseconds(500));
    std::lock_guard lock(watch_mutex_);
    const std::vector<Watch*> all(watches_.begin(), watches_.end());
    for (Watch* watch : all) {
      if (watches_.contains(watch)) watch->Poke();  // One poked earlier may have ended meanwhile.
    }
  }
}

// FetchResult: the artifact in chunks of at most 1 MiB, each read when the last has gone out.
class ReconstructionService::Download final : public grpc::ServerWriteReactor<v1::ResultChunk> {
 public:
  Download(ReconstructionService& service, std::unique_ptr<jobs::BlobReader> reader, CallRecord call,
           std::unique_ptr<StreamGuard::Ticket> ticket)
      : service_(service), reader_(std::move(reader)), call_(std::move(call)), ticket_(std::move(ticket)) {
    chunk_.set_total_bytes(reader_->size());
    Next();
  }

  void OnWriteDone(bool ok) override {
    if (!ok) return End(grpc::Status(grpc::StatusCode::CANCELLED, "client went away"));
    ticket_->Touch();
    if (service_.calls_ != nullptr) service_.calls_->Sent(static_cast<int64_t>(chunk_.data().size()));
    if (chunk_.data().empty()) return End(grpc::Status::OK);  // An empty artifact: one empty chunk.
    chunk_.clear_total_bytes();
    Next();
  }

  void OnDone() override { delete this; }

 private:
  void Next() {
    absl::StatusOr<std::string> data;
    try {
      data = reader_->Next(kMaxChunkBytes);
    } catch (const std::bad_alloc&) {
      data = absl::ResourceExhaustedError("the server ran out of memory for this call");
    }
    if (!data.ok()) return End(ToGrpcStatus(data.status()));
    if (data->empty() && !first_) return End(grpc::Status::OK);
    first_ = false;
    chunk_.set_data(*std::move(data));
    StartWrite(&chunk_);
  }
  void End(const grpc::Status& status) { Finish(service_.Conclude(call_, status)); }

  ReconstructionService& service_;
  std::unique_ptr<jobs::BlobReader> reader_;
  const CallRecord call_;
  std::unique_ptr<StreamGuard::Ticket> ticket_;
  v1::ResultChunk chunk_;
  bool first_ = true;
};

grpc::ServerWriteReactor<v1::ResultChunk>* ReconstructionService::FetchResult(grpc::CallbackServerContext* context,
                                                                              const v1::FetchResultRequest* request) {
  using Refused = Refusal<grpc::ServerWriteReactor<v1::ResultChunk>>;
  CallRecord call{"FetchResult"};
  auto admitted = Admit(context, call, StreamKind::kDownload, &request->job_id());
  if (!admitted.ok()) return new Refused(Conclude(call, ToGrpcStatus(admitted.status())));
  auto reader = jobs_.OpenResult(request->job_id(), request->name());
  if (!reader.ok()) return new Refused(Conclude(call, ToGrpcStatus(reader.status())));
  return new Download(*this, *std::move(reader), std::move(call), std::move(admitted->ticket));
}

grpc::Status ReconstructionService::GetJob(grpc::ServerContext* context, const v1::GetJobRequest* request,
                                           v1::Job* response) {
  return Serve("GetJob", context, [&](const Caller& caller) {
    auto record = Visible(caller, request->job_id());
    if (!record.ok()) return ToGrpcStatus(record.status());
    ToProto(*record, response);
    return grpc::Status::OK;
  });
}

grpc::Status ReconstructionService::ListJobs(grpc::ServerContext* context, const v1::ListJobsRequest* request,
                                             v1::ListJobsResponse* response) {
  return Serve("ListJobs", context, [&](const Caller& caller) {
    if (request->limit() < 0) return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "limit must not be negative");
    const int page_jobs = request->limit() == 0 ? kDefaultPageJobs : std::min(request->limit(), kMaxPageJobs);
    std::optional<std::pair<int64_t, std::string>> after;
    if (!request->page_token().empty()) {
      after = ParsePageToken(request->page_token());
      if (!after) {
        return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT,
                            "page_token is not one this server gave; pass a response's next_page_token as it came");
      }
    }
    size_t bytes = 0;
    const jobs::JobRecord* last = nullptr;
    for (const auto& r : jobs_.List()) {  // Newest first: by created_ms, then id, both descending.
      if (after && (r.created_ms > after->first || (r.created_ms == after->first && r.id >= after->second))) continue;
      if (!jobs::MayView(caller.submitter, r)) continue;
      v1::Job job;
      ToProto(r, &job);
      const size_t size = job.ByteSizeLong();
      if (response->jobs_size() >= page_jobs || (response->jobs_size() > 0 && bytes + size > kMaxPageBytes)) {
        response->set_next_page_token(PageToken(*last));
        break;
      }
      bytes += size;
      *response->add_jobs() = std::move(job);
      last = &r;
    }
    return grpc::Status::OK;
  });
}

grpc::Status ReconstructionService::CancelJob(grpc::ServerContext* context, const v1::CancelJobRequest* request,
                                              v1::Job* response) {
  return Serve("CancelJob", context, [&](const Caller& caller) {
    if (auto visible = Visible(caller, request->job_id()); !visible.ok()) return ToGrpcStatus(visible.status());
    auto record = jobs_.Cancel(request->job_id());
    if (!record.ok()) return ToGrpcStatus(record.status());
    ToProto(*record, response);
    return grpc::Status::OK;
  });
}

grpc::Status ReconstructionService::DeleteJob(grpc::ServerContext* context, const v1::DeleteJobRequest* request,
                                              v1::DeleteJobResponse*) {
  return Serve("DeleteJob", context, [&](const Caller& caller) {
    if (auto visible = Visible(caller, request->job_id()); !visible.ok()) return ToGrpcStatus(visible.status());
    return ToGrpcStatus(jobs_.retention().Delete(request->job_id()));
  });
}

grpc::Status ReconstructionService::Render(grpc::ServerContext* context, const v1::RenderRequest* request,
                                           v1::RenderResponse* response) {
  return Serve("Render", context, [&](const Caller& caller) {
    if (auto visible = Visible(caller, request->job_id()); !visible.ok()) return ToGrpcStatus(visible.status());
    auto view = FromProto(request->options());
    if (!view.ok()) return ToGrpcStatus(view.status());
    const CallContext call(*context);
    auto picture = jobs_.Render(caller.submitter, request->job_id(), request->name(), *view, &call);
    if (!picture.ok()) return ToGrpcStatus(picture.status());
    if (calls_ != nullptr) {
      calls_->Sent(static_cast<int64_t>(picture->png.size()));
      calls_->FrameRendered();
    }
    response->set_png(std::move(picture->png));
    response->set_color_min(picture->color_min);
    response->set_color_max(picture->color_max);
    response->set_renderer(picture->renderer);
    response->set_grid_rms_error(picture->grid_rms_error);
    response->set_grid_max_error(picture->grid_max_error);
    response->set_samples(picture->samples);
    return grpc::Status::OK;
  });
}

grpc::Status ReconstructionService::ListMethods(grpc::ServerContext* context, const v1::ListMethodsRequest*,
                                                v1::ListMethodsResponse* response) {
  return Serve("ListMethods", context, [&](const Caller&) {
    for (const auto& m : jobs::Methods()) {
      v1::Method* out = response->add_methods();
      out->set_name(m.info.name);
      out->set_description(m.info.description);
      for (const auto& a : m.info.attributes) out->add_attributes(a);
      for (const auto& p : m.info.defaults.Describe()) ToProto(p, out->add_parameters());
    }
    return grpc::Status::OK;
  });
}

grpc::Status ReconstructionService::GetServerInfo(grpc::ServerContext* context, const v1::GetServerInfoRequest*,
                                                  v1::ServerInfo* response) {
  return Serve("GetServerInfo", context, [&](const Caller& caller) {
    const jobs::JobServiceOptions& o = jobs_.options();
    response->set_version(LSQSURF_VERSION);
    ReportLimits(o, *response);
    response->set_max_chunk_bytes(static_cast<int64_t>(kMaxChunkBytes));
    response->set_can_render(jobs_.CanRender());
    response->set_requires_token(tokens_ != nullptr);
    if (caller.admin()) response->set_stored_bytes(jobs_.admission().StoredBytes());
    v1::Account* account = response->mutable_account();
    account->set_name(caller.name);
    account->set_admin(caller.admin());
    account->set_max_jobs(caller.submitter.max_active_jobs);
    account->set_max_stored_bytes(caller.submitter.max_stored_bytes);
    account->set_max_upload_bytes(caller.submitter.max_upload_bytes);
    const jobs::JobService::Usage usage = jobs_.admission().UsageOf(caller.submitter.owner);
    account->set_active_jobs(usage.active_jobs);
    account->set_stored_bytes(usage.stored_bytes);
    return grpc::Status::OK;
  });
}

}  // namespace lsqsurf::server
