#!/usr/bin/env python3
"""One line about a ctest run, from its JUnit file (ctest --output-junit) and the tests labelled gpu
(ctest --show-only=json-v1 -L gpu): how many passed, failed and were skipped, and of the skipped ones how
many are GPU tests, grouped by the reason their skip gave (on a machine without a GPU: no CUDA device).

    python3 ctest_summary.py results.xml gpu_tests.json
    ctest: 389 passed, 0 failed, 21 skipped (21 GPU tests, label gpu: no CUDA device)
"""
import collections
import json
import re
import sys
import xml.etree.ElementTree as ET

# GoogleTest prints "<file>:<line>: Skipped", then the test's message, then "[  SKIPPED ] <test>".
SKIP_REASON = re.compile(r": Skipped\n(.*?)\n\[  SKIPPED \]", re.S)


def skip_reason(output):
    found = SKIP_REASON.search(output or "")
    return found.group(1).strip().splitlines()[0] if found and found.group(1).strip() else "no reason given"


def gpu_test_names(show_only_json):
    return {test["name"] for test in json.loads(show_only_json).get("tests", [])}


def summarise(junit_xml, gpu_names):
    counts = collections.Counter()
    gpu_reasons = collections.Counter()
    for case in ET.fromstring(junit_xml).iter("testcase"):
        if case.find("skipped") is not None:
            counts["skipped"] += 1
            if case.get("name") in gpu_names:
                gpu_reasons[skip_reason(case.findtext("system-out"))] += 1
        elif case.get("status") == "run":
            counts["passed"] += 1
        elif case.get("status") != "disabled":
            counts["failed"] += 1  # failures, timeouts and tests that could not start, as ctest counts them
    line = f"ctest: {counts['passed']} passed, {counts['failed']} failed, {counts['skipped']} skipped"
    if gpu_reasons:
        total = sum(gpu_reasons.values())
        if len(gpu_reasons) == 1:
            why = next(iter(gpu_reasons))
        else:
            why = ", ".join(f"{n} {reason}" for reason, n in gpu_reasons.most_common())
        line += f" ({total} GPU test{'s' if total != 1 else ''}, label gpu: {why})"
    return line


def main(argv):
    if len(argv) != 3:
        sys.exit(__doc__)
    with open(argv[2], encoding="utf-8") as f:
        gpu_names = gpu_test_names(f.read())
    try:
        with open(argv[1], encoding="utf-8") as f:
            junit_xml = f.read()
    except FileNotFoundError:
        print("ctest: no test results (nothing ran)")
        return
    print(summarise(junit_xml, gpu_names))


if __name__ == "__main__":
    main(sys.argv)
