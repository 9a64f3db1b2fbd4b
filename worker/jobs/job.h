// worker/jobs/job.h — what the service knows about a job: its spec, state and record.
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "worker/core/byte_view.h"
#include "worker/core/params.h"

namespace lsqsurf::jobs {

// The values are what the stores keep: they never change (rows::WithStates puts them in SQL).
enum class JobState { kQueued = 0, kRunning = 1, kSucceeded = 2, kFailed = 3, kCancelled = 4 };
inline constexpr JobState kLastJobState = JobState::kCancelled;

const char* JobStateName(JobState state);
bool IsTerminal(JobState state);

// Pictures a job draws into its results when it succeeds: preview.png of a surface job's mesh,
// or frame_NNNNN.png of every output frame of a track job (framed on the tracking domain).
struct PreviewSpec {
  bool enabled = false;
  core::ParamSet view;                 // render::RenderParams through ViewParams(); the framing box is the job's.
  double turntable_deg_per_frame = 0;  // Track jobs: azimuth step between frames, −360..360.
};

struct JobSpec {
  std::string method;     // A name from Methods() (method_registry.h).
  core::ParamSet params;  // The method's parameter struct; unset fields keep its defaults.
  // Draco quantization of result mesh positions, bits over the bounding box (8..30); 0 = chosen
  // per mesh, enough that no two distinct vertices merge.
  int mesh_position_bits = 0;
  PreviewSpec preview{};  // Off unless enabled.
};

// What a job's spec adds to its stored bytes: its encoded parameters past the first
// kFreeSpecBytes, which every job's small spec fits in. Text parameters (up to 64 KiB each) are
// the rest: a store filled with them counts against the quotas like uploads do.
inline constexpr int64_t kFreeSpecBytes = 4096;
int64_t SpecBytes(const JobSpec& spec);

// Uploaded bytes by slot: "input" (a Draco point cloud) and "velocity" (a legacy VTK grid). A
// server's uploads are its spool files mapped, a run's are its stored blobs mapped: no copy of
// an upload sits on the heap.
using Uploads = std::map<std::string, core::ByteView>;
inline constexpr char kInputUpload[] = "input";
inline constexpr char kVelocityUpload[] = "velocity";
inline constexpr char kCellsUpload[] = "cells";  // Volume meshes: the cell stream (io/volume_codec.h).

// A cloud may come in several Draco parts, each its own upload and blob, never concatenated:
// part 0 in kInputUpload, part n > 0 in "input.n".
inline constexpr int64_t kMaxInputParts = 4096;
std::string InputPartSlot(int64_t part);
// The part number of an input slot ("input" 0, "input.7" 7); -1 for any other slot.
int64_t InputPartOf(std::string_view slot);
// The input parts present, in order; a gap ends them.
std::vector<std::string_view> InputParts(const Uploads& uploads);
// The points an input part declares in its Draco header, read from its first bytes (64 KiB hold
// any header) before the rest is decoded; nullopt when they are no Draco header (decoding then
// says why).
inline constexpr size_t kDracoHeadBytes = size_t{64} << 10;
std::optional<uint64_t> DeclaredPoints(std::string_view head);

// The parts of a mesh delivered in parts (io/mesh_part.h), numbered from 0: "mesh-part-00000.lqm".
// They are the artifacts a job publishes while it runs: each is listed in the job's results as
// soon as it is stored, and can be fetched before the job ends.
std::string MeshPartArtifact(int64_t part);
// The part number of such a name; -1 for any other.
int64_t MeshPartOf(std::string_view name);

using Statistics = std::vector<std::pair<std::string, double>>;  // Name (units in it), value.

// Child jobs' spec formats start here, above any format a job's spec has: a server of a build
// older than child jobs never claims one.
inline constexpr int kChildFormatBase = 1 << 20;

struct JobRecord {
  std::string id;
  JobSpec spec;
  JobState state = JobState::kQueued;
  std::string stage;       // Current stage while running.
  double progress = 0;     // Overall fraction in [0, 1].
  int attempts = 0;        // Times a worker started the job.
  int interruptions = 0;   // Starts ended by a server shutdown (not the job's fault).
  std::string error;       // Why it failed or was cancelled.
  int64_t created_ms = 0;  // Unix epoch milliseconds.
  int64_t updated_ms = 0;
  int64_t input_points = 0;
  int64_t input_bytes = 0;
  Statistics statistics;             // Final statistics of a success.
  std::vector<std::string> results;  // Artifact names of a success.
  std::string runner;                // The server that runs the job, or ran it last.
  std::string owner;                 // Who submitted it (a token's name; empty without tokens).
  // The owner's stored-bytes quota when it was submitted (0: none): what its results are held to
  // as they are written, on whichever server runs it.
  int64_t quota_bytes = 0;
  int64_t stored_bytes = 0;       // Its uploads and results as stored, or reserved until it ends (quotas).
  bool cancel_requested = false;  // Running: its runner is asked to stop it.
  // The spec format of the server that stored it (SpecTables::format): only servers of that
  // format or a newer one claim it, so that a rolling update never runs a job on a server too
  // old to read its spec whole.
  int spec_format = 0;
  // A child job is a part of its parent's run that any server may make (a tile of a tiled PU
  // build): queued by the parent's run, claimed before new jobs while the parent runs, under the
  // same leases, attempt limits and recovery as any job; never listed, and removed with the
  // parent. Its spec_format is the format of its part (kChildFormatBase and up), which only
  // servers of that same format claim. Empty for a job a user submitted.
  std::string parent;
  int64_t child_index = 0;  // Which part of the parent's run (the tile).
  int64_t seq = 0;          // The store's change number of this state (job_store.h).
  uint64_t version = 0;     // Bumped on every change this server sees (watchers compare it).
};

// Whether `record` is a part of another job's run (JobRecord::parent), not a user's job.
inline bool IsChildJob(const JobRecord& record) { return !record.parent.empty(); }

}  // namespace lsqsurf::jobs
