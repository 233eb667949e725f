#pragma once
// The events of a job's history as the Trainer service writes them, shared by its RPC handlers
// (server/trainer_service.h) and its job runner (server/job_runner.h), so that both close a job the same way.
#include <string>

#include <nlohmann/json.hpp>
#include "gaps/v1/trainer.pb.h"

namespace gaps {

// Seconds since the epoch: the time base of every event and status the store holds.
double now_seconds();
// SUCCEEDED, FAILED or CANCELLED: nothing changes a job in these states any more.
bool terminal(v1::JobState state);
// An empty event of the job, stamped now.
v1::JobEvent event_for(const std::string& job_id);
// The event that ends a job's history; watchers stop at it.
v1::JobEvent closing_event(const v1::JobStatus& status);
// The event's kind, for messages about it.
std::string event_name(const v1::JobEvent& event);
// A phase entry of the run's report (gs_trainer/pipeline.h's on_phase) as a phase event.
v1::PhaseEvent phase_event(const nlohmann::json& entry);

}  // namespace gaps
