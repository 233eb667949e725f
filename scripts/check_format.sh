#!/usr/bin/env bash
# Checks that every C++/CUDA source follows .clang-format (clang-format 14, Debian bookworm's); prints the
# files that do not and how to fix them. Exit 0: formatted; 1: not; 77: no clang-format 14 (ctest: skipped).
#   bash scripts/check_format.sh          # check
#   bash scripts/check_format.sh --fix    # format in place
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"
tool=${CLANG_FORMAT:-clang-format}
if ! command -v "$tool" >/dev/null || ! "$tool" --version | grep -q "version 14\."; then
  echo "check_format: skipped: needs clang-format 14 (scripts/setup.sh installs it); found: $("$tool" --version 2>/dev/null || echo none)"
  exit 77
fi
mapfile -t files < <(git ls-files '*.h' '*.hpp' '*.cpp' '*.cc' '*.cu' '*.cuh' | grep -v '^tests/fixtures/')
if [ "${1:-}" = "--fix" ]; then
  "$tool" -i "${files[@]}"
  exit 0
fi
bad=()
for f in "${files[@]}"; do
  "$tool" --dry-run -Werror "$f" >/dev/null 2>&1 || bad+=("$f")
done
if [ ${#bad[@]} -gt 0 ]; then
  printf 'not formatted: %s\n' "${bad[@]}"
  echo "check_format: ${#bad[@]} of ${#files[@]} files differ from .clang-format; run: bash scripts/check_format.sh --fix"
  exit 1
fi
echo "check_format: ${#files[@]} files formatted"
