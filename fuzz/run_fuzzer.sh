#!/usr/bin/env bash
# Runs one libFuzzer target for a bounded time: BINARY SECONDS WORK_DIR SEED_DIR...
# New inputs go to WORK_DIR (the repository's seeds are only read); a crash leaves its input as
# WORK_DIR-crash-* (or -oom-, -timeout-, -leak-) and fails. The last line gives executions and corpus size.
set -euo pipefail
binary=$1 seconds=$2 work=$3
shift 3
mkdir -p "$work"
log="$work.log"
status=0
LSAN_OPTIONS=${LSAN_OPTIONS:-suppressions=$(dirname "$0")/lsan.supp:print_suppressions=0} \
ASAN_OPTIONS=${ASAN_OPTIONS:-detect_leaks=1:allocator_may_return_null=1} \
  "$binary" -max_total_time="$seconds" -timeout=30 -rss_limit_mb=4096 -print_final_stats=1 \
  -artifact_prefix="$work-" "$work" "$@" >"$log" 2>&1 || status=$?
name=$(basename "$binary")
if [ "$status" -ne 0 ]; then
  tail -n 60 "$log"
  echo "$name: FAILED (exit $status); the input is $(ls "$work"-* 2>/dev/null | tr '\n' ' '); log $log"
  exit "$status"
fi
execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$log" | tail -n 1)
done_line=$(grep -E '^#[0-9]+ +DONE' "$log" | tail -n 1 || true)
echo "$name: ${execs:-?} executions in ${seconds} s, corpus $(find "$work" -type f | wc -l) new + seeds; ${done_line}"
