#!/usr/bin/env bash
# docs/options.md must be what `gaps options` prints, so the documented options are the ones the code has.
#   scripts/check_options_doc.sh [--fix] [GAPS_BINARY]   (default binary: build/client/gaps)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
fix=0
if [ "${1:-}" = "--fix" ]; then fix=1; shift; fi
gaps=${1:-$root/build/client/gaps}
doc=$root/docs/options.md
generated=$(mktemp)
trap 'rm -f "$generated"' EXIT
{
  echo "# Options"
  echo
  echo "Every training and GAPS option, as \`gaps options\` prints it from the option tables"
  echo "(\`gs_trainer/train/train_config.h\`, \`gs_trainer/gaps/config.h\`). Each is a key of the \`--config\`"
  echo "(training) or \`--gaps-config\` (gaps) JSON file, a flag of \`gaps train\`/\`demo\`/\`submit\`"
  echo "(\`--lambda-dssim 0.3\`; lists as \`--tier-alpha-max 1,1.25\`), and a field of the same name in"
  echo "\`gaps.v1.TrainHyperparameters\`/\`GapsHyperparameters\`. A flag given on the command line wins over the"
  echo "file, and the run says so. metrics.json records the values a run used, automatic ones resolved."
  echo "Regenerate with \`scripts/check_options_doc.sh --fix\`."
  echo
  "$gaps" options
} >"$generated"
if [ "$fix" = 1 ]; then cp "$generated" "$doc"; echo "wrote $doc"; exit 0; fi
if ! diff -u "$doc" "$generated"; then
  echo "docs/options.md differs from \`gaps options\`: run scripts/check_options_doc.sh --fix" >&2
  exit 1
fi
