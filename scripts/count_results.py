#!/usr/bin/env python3
"""Counts test cases in catkin's JUnit XML under the given folders and prints 'N passed, N failed'
(', N skipped').

Exit status 1 on any failure or error, or when no test case ran at all (a result file that exists
but is empty of cases, such as a rostest that crashed before running, counts as a failure).
"""
import pathlib
import sys
import xml.etree.ElementTree as ET


def reason(case, lines=8):
    """The first LINES lines of a failed CASE's message, indented: CI's log then says why, not only what."""
    element = case.find("failure")
    if element is None:
        element = case.find("error")
    text = (element.text or element.get("message") or "").strip().splitlines()
    shown = text[:lines] + ([f"... ({len(text) - lines} more lines)"] if len(text) > lines else [])
    return "\n".join("    " + line for line in shown)


def main(roots):
    passed = failed = skipped = 0
    files = sorted(f for root in roots for f in pathlib.Path(root).rglob("*.xml"))
    for path in files:
        try:
            tree = ET.parse(path)
        except ET.ParseError:
            print(f"unreadable result file: {path}", file=sys.stderr)
            failed += 1
            continue
        cases = list(tree.getroot().iter("testcase"))
        if not cases:
            print(f"no test cases in {path}", file=sys.stderr)
            failed += 1
            continue
        for case in cases:
            if case.find("failure") is not None or case.find("error") is not None:
                failed += 1
                print(f"FAILED: {path.name}: {case.get('classname')}.{case.get('name')}", file=sys.stderr)
                print(reason(case), file=sys.stderr)
            elif case.find("skipped") is not None:
                skipped += 1
            else:
                passed += 1
    line = f"{passed} passed, {failed} failed"
    if skipped:
        line += f", {skipped} skipped"
    print(line)
    return 1 if failed or passed == 0 else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:] or ["build/test_results"]))
