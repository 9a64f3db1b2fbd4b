// worker/jobs/job_ids.h — job ids, and the form an id must have before it is looked up.
//
// An id is the one secret that separates one user's jobs from another's guess, so it is drawn
// from the operating system's CSPRNG (getrandom), never from a seeded generator whose state a
// user could reconstruct from ids of his own.
#pragma once

#include <string>
#include <string_view>

namespace lsqsurf::jobs {

// 128 random bits as 32 lowercase hexadecimal digits. Throws std::runtime_error only if the
// kernel's generator cannot be read (no getrandom, a seccomp filter), as no safe id exists then.
std::string NewJobId();

// Whether `text` has the form of a job id: 32 lowercase hexadecimal digits, or 16 (the 64-bit
// ids of earlier versions, which keep working). Anything else is refused before it is logged,
// looked up or echoed.
bool IsJobIdForm(std::string_view text);

// Whether `text` has the form of an artifact name (what a job writes: mesh.drc, frame_00010.drc,
// preview.png): 1 to 128 letters, digits, '.', '_' or '-', not starting with '.'.
bool IsArtifactNameForm(std::string_view text);

// The message for a text that is not an id (it does not repeat the text).
inline constexpr char kNotAJobId[] =
    "a job id is 32 hexadecimal digits (16 for jobs made by earlier versions), as SubmitJob returned it";
inline constexpr char kNotAnArtifactName[] =
    "an artifact name is 1 to 128 letters, digits, '.', '_' or '-' (GetJob lists a job's results)";

}  // namespace lsqsurf::jobs
