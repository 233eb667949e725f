#include "server/job_events.h"

#include <chrono>

namespace gaps {

double now_seconds() {
  return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

bool terminal(v1::JobState s) { return s == v1::SUCCEEDED || s == v1::FAILED || s == v1::CANCELLED; }

v1::JobEvent event_for(const std::string& job_id) {
  v1::JobEvent e;
  e.set_job_id(job_id);
  e.set_time(now_seconds());
  return e;
}

v1::JobEvent closing_event(const v1::JobStatus& status) {
  v1::JobEvent e = event_for(status.job_id());
  if (status.state() == v1::SUCCEEDED)
    *e.mutable_finished() = status;
  else if (status.state() == v1::CANCELLED)
    *e.mutable_cancelled() = status;
  else
    *e.mutable_failed() = status;
  return e;
}

std::string event_name(const v1::JobEvent& event) {
  const auto* field = v1::JobEvent::descriptor()->FindFieldByNumber(event.event_case());
  return field ? field->name() : "empty";
}

v1::PhaseEvent phase_event(const nlohmann::json& entry) {
  v1::PhaseEvent p;
  p.set_phase(entry.value("phase", -1));
  p.set_iteration(entry.value("iteration", 0));
  if (entry.contains("selection")) p.set_selected(static_cast<int>(entry["selection"].size()));
  p.set_admitted(entry.value("admitted", 0));
  p.set_skipped(entry.value("skipped", false));
  p.set_skip_reason(entry.value("skip_reason", std::string()));
  p.set_details_json(entry.dump());
  return p;
}

}  // namespace gaps
