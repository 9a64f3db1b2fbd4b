// worker/jobs/store/job_rows.h — a job record as the columns both job stores keep, in text.
//
// Both stores bind and read every column as text (SQLite converts by column affinity,
// PostgreSQL by column type), so one conversion serves both and their rows stay alike.
#pragma once

#include <string>
#include <string_view>
#include <vector>

#include "worker/jobs/job.h"
#include "worker/jobs/store/spec_tables.h"

namespace lsqsurf::jobs::rows {

// The job columns in the order JobColumns and FromColumns use; `seq` is last.
inline constexpr const char* kColumnNames[] = {"id",
                                               "method",
                                               "parameters",
                                               "mesh_bits",
                                               "state",
                                               "stage",
                                               "attempts",
                                               "error",
                                               "created_ms",
                                               "updated_ms",
                                               "input_points",
                                               "input_bytes",
                                               "statistics",
                                               "results",
                                               "preview",
                                               "preview_color",
                                               "interruptions",
                                               "progress",
                                               "runner",
                                               "cancel_requested",
                                               "owner",
                                               "stored_bytes",
                                               "quota_bytes",
                                               "spec_format",
                                               "parent",
                                               "child_index",
                                               "seq"};
inline constexpr int kColumnCount = sizeof(kColumnNames) / sizeof(kColumnNames[0]);

// "id, method, ..., seq".
const std::string& ColumnList();

// The record's values for every column but seq (a new row). A store writes its own format into
// the spec_format of a job a user submitted (WithFormat); a child job keeps its part's.
std::vector<std::string> JobColumns(const JobRecord& record);
// `record` as a store of spec format `format` stores it.
JobRecord WithFormat(JobRecord record, int format);

// A runner's write of a job it holds sets every column but id, seq and cancel_requested (which
// another server may raise meanwhile). "method = ?2, parameters = ?3, ...": the assignments,
// numbered from 2 (the id is parameter 1), with `placeholder` before each number ('?' for
// SQLite, '$' for PostgreSQL); HeldColumns gives the values, id first.
std::string HeldAssignments(char placeholder);
std::vector<std::string> HeldColumns(const JobRecord& record);
// The record a row of kColumnCount texts holds. A stored spec that no longer decodes (its
// method is gone, or a value left its range) comes back failed with the reason, unless it is of
// a newer format than `tables` (a newer server's job, which this one never claims).
JobRecord FromColumns(const std::vector<std::string>& row, const SpecTables& tables);

// `sql` with the states named instead of numbered: {queued}, {running}, {succeeded}, {failed},
// {cancelled}, and {finished} for the list of the last three ("(2, 3, 4)").
std::string WithStates(std::string_view sql);

std::string Number(double value);  // Shortest text that reads back to the same double.
int64_t ToInt(const std::string& text);

}  // namespace lsqsurf::jobs::rows
