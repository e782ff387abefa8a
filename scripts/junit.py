"""JUnit XML in catkin's form for the checks the scripts run themselves (workspace_test.sh,
sanitize.sh), so scripts/count_results.py counts them with the tests."""
import re
import xml.etree.ElementTree as ET


def xml_text(text):
    """TEXT without what XML 1.0 cannot hold (roslaunch's colour codes, ...): ElementTree would write
    those raw and the file could not be read back."""
    return re.sub(r"[^\t\n\r\x20-\ud7ff\ue000-\ufffd\U00010000-\U0010ffff]", "?", text)


def write_suite(path, name, cases, time=None):
    """Writes one testsuite NAME to PATH. CASES: (case name, outcome, message, text, seconds) with
    outcome None (passed), "failure" or "skipped"; message None is the first line of text."""
    outcomes = [case[1] for case in cases]
    suite = ET.Element("testsuite", name=name, tests=str(len(cases)), errors="0",
                       failures=str(outcomes.count("failure")), skipped=str(outcomes.count("skipped")))
    if time is not None:
        suite.set("time", str(time))
    for case_name, outcome, message, text, seconds in cases:
        case = ET.SubElement(suite, "testcase", classname=name, name=case_name)
        if seconds is not None:
            case.set("time", str(seconds))
        if outcome:
            message = (text.splitlines() or [""])[0] if message is None else message
            ET.SubElement(case, outcome, message=xml_text(message)).text = xml_text(text)
    ET.ElementTree(suite).write(path, encoding="utf-8", xml_declaration=True)
