#!/usr/bin/env python3
"""CI's summary line and its failure reasons come from scripts/junit.py (the checks the scripts run
themselves) and scripts/count_results.py (everything): what they write must read back, and what
they count must be what the files say."""
import contextlib
import io
import pathlib
import sys
import tempfile
import unittest

SCRIPTS = pathlib.Path(__file__).resolve().parents[2] / "scripts"
sys.path.insert(0, str(SCRIPTS))
import count_results  # noqa: E402
import junit  # noqa: E402


def count(folder):
    """count_results.main on FOLDER: (exit status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = count_results.main([str(folder)])
    return status, out.getvalue().strip(), err.getvalue()


class Results(unittest.TestCase):
    def setUp(self):
        self.folder = pathlib.Path(tempfile.mkdtemp(prefix="arucotag_junit_"))

    def test_roslaunch_colour_codes_are_written_readably_and_the_reason_is_shown(self):
        log = "\x1b[31m[ERROR] rviz died\x1b[0m\nsecond line\x07"
        junit.write_suite(self.folder / "w.xml", "arucotag.workspace_test",
                          [("catkin_make", None, None, "", "12"), ("run_tests", "failure", None, log, "3")], time=15)
        status, line, reasons = count(self.folder)
        self.assertEqual((status, line), (1, "1 passed, 1 failed"))
        self.assertIn("FAILED: w.xml: arucotag.workspace_test.run_tests", reasons)
        self.assertIn("    ?[31m[ERROR] rviz died?[0m", reasons)
        self.assertIn("    second line?", reasons)

    def test_skipped_cases_and_messages_apart_from_the_text(self):
        junit.write_suite(self.folder / "s.xml", "sanitizers",
                          [("asan.1", "skipped", "leak check did not run", "Tracer caught signal 11", None),
                           ("asan.2", "failure", "SUMMARY: AddressSanitizer: heap-use-after-free", "==1==ERROR: ...",
                            None)])
        status, line, reasons = count(self.folder)
        self.assertEqual((status, line), (1, "0 passed, 1 failed, 1 skipped"))
        self.assertIn("==1==ERROR: ...", reasons)
        self.assertNotIn("Tracer", reasons)

    def test_long_reasons_are_cut_and_say_so(self):
        junit.write_suite(self.folder / "l.xml", "long",
                          [("many", "failure", None, "\n".join(f"line {i}" for i in range(20)), None)])
        _, _, reasons = count(self.folder)
        self.assertIn("    line 7\n", reasons)
        self.assertNotIn("line 8\n", reasons)
        self.assertIn("(12 more lines)", reasons)

    def test_files_without_cases_or_unreadable_count_as_failures(self):
        (self.folder / "empty.xml").write_text('<testsuite name="crashed" tests="0"/>')
        (self.folder / "broken.xml").write_text("<testsuite><testcase")
        status, line, reasons = count(self.folder)
        self.assertEqual((status, line), (1, "0 passed, 2 failed"))
        self.assertIn("no test cases in", reasons)
        self.assertIn("unreadable result file", reasons)

    def test_nothing_ran_is_a_failure_and_all_passed_is_not(self):
        self.assertEqual(count(self.folder)[:2], (1, "0 passed, 0 failed"))
        junit.write_suite(self.folder / "p.xml", "ok", [("a", None, None, "", "1")])
        self.assertEqual(count(self.folder)[:2], (0, "1 passed, 0 failed"))


if __name__ == "__main__":
    import rosunit
    rosunit.unitrun("arucotag", "test_junit", Results)
