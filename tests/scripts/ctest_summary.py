#!/usr/bin/env python3
"""One line about a ctest run, from its JUnit file (ctest --output-junit) and the tests labelled gpu
(ctest --show-only=json-v1 -L gpu): how many passed, failed and were skipped, and of the skipped ones how
many are GPU tests, grouped by the reason their skip gave (on a machine without a GPU: no CUDA device), and
the other skips likewise (a test that needs the benchmark data skips without it: such a run has not trained
on a real scene, and the line says so).

    python3 ctest_summary.py results.xml gpu_tests.json
    ctest: 389 passed, 0 failed, 21 skipped (21 GPU tests, label gpu: no CUDA device)
    ctest: 380 passed, 0 failed, 30 skipped (21 GPU tests, label gpu: no CUDA device; 9 other: 9 benchmark data not found at /x)
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


def by_reason(reasons):
    if len(reasons) == 1:
        return next(iter(reasons))
    return ", ".join(f"{n} {reason}" for reason, n in reasons.most_common())


def summarise(junit_xml, gpu_names):
    counts = collections.Counter()
    gpu_reasons = collections.Counter()
    other_reasons = collections.Counter()
    for case in ET.fromstring(junit_xml).iter("testcase"):
        if case.find("skipped") is not None:
            counts["skipped"] += 1
            reasons = gpu_reasons if case.get("name") in gpu_names else other_reasons
            reasons[skip_reason(case.findtext("system-out"))] += 1
        elif case.get("status") == "run":
            counts["passed"] += 1
        elif case.get("status") != "disabled":
            counts["failed"] += 1  # failures, timeouts and tests that could not start, as ctest counts them
    line = f"ctest: {counts['passed']} passed, {counts['failed']} failed, {counts['skipped']} skipped"
    notes = []
    if gpu_reasons:
        total = sum(gpu_reasons.values())
        notes.append(f"{total} GPU test{'s' if total != 1 else ''}, label gpu: {by_reason(gpu_reasons)}")
    if other_reasons:
        total = sum(other_reasons.values())
        notes.append(f"{total} other: " + ", ".join(f"{n} {reason}" for reason, n in other_reasons.most_common()))
    if notes:
        line += f" ({'; '.join(notes)})"
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
