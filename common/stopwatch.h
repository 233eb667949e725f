#pragma once
// Stage timings: consecutive laps of one clock time consecutive stages without gaps or overlaps.
#include <chrono>

namespace gaps {

// Seconds from *since to now; *since moves to now, so the next call times the next stage.
inline double lap_seconds(std::chrono::steady_clock::time_point* since) {
  const auto now = std::chrono::steady_clock::now();
  const double seconds = std::chrono::duration<double>(now - *since).count();
  *since = now;
  return seconds;
}

}  // namespace gaps
