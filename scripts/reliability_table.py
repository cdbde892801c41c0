"""The fault-injection table of docs/reliability.md: runs tests/reliability and counts its cases.

    .venv/bin/python scripts/reliability_table.py            # print the table
    .venv/bin/python scripts/reliability_table.py --write    # also replace it in docs/reliability.md
    .venv/bin/python scripts/reliability_table.py --from-xml REPORT.xml --write   # from a pytest --junitxml
                                                             # report of a run that included tests/reliability

Every test of tests/reliability is one fault (a parametrised test: one per parameter set) tried against
one stage; it asserts what happens after the fault — nothing lost (files present before byte-identical
or replaced by a complete newer version), nothing silently wrong, one clear line and no traceback
without --debug. A passing case is counted under its outcome, a failing one as a failure: the table's
"data lost", "silent wrong output" and "traceback" columns are the failures of cases that assert them
(every case asserts them), so they read 0 exactly when the suite passes.
"""
from __future__ import annotations

import re
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "reliability.md"
BEGIN, END = "<!-- reliability-table:begin -->", "<!-- reliability-table:end -->"

#: (module regex, test-name regex) -> (stage, fault class, outcome); first match wins
RULES = [
    (r"test_bad_options", r"every_command", ("every command", "bad option value (coverage)", "clear error")),
    (r"test_bad_options", r"\[(\S+) ", None),          # stage = the command in the parameter id
    (r"test_steps", r"sigkill", ("demo", "kill (SIGKILL)", "recovered")),
    (r"test_steps", r"two_demos", ("demo", "two processes", "clear error")),
    (r"test_model_transactions", r"verify_passes", ("model", "sound input (control)", "correct, nothing to report")),
    (r"test_steps", r"", ("demo", "second run, nothing changed", "correct, nothing to report")),
    (r"test_model_transactions", r"template_inconsistent", ("build", "inconsistent input (template)", "clear error")),
    (r"manifests", r"checked_when_read", ("capture/performance", "corrupt/truncate/delete a file", "clear error")),
    (r"test_render_warnings", r"fails_writing", ("render", "full disk (ENOSPC)", "recovered")),
    (r"test_cli_errors", r"locked", ("every command", "two processes (lock refused, exit 3)", "clear error")),
    (r"test_capture_cli_faults", r"zero_and_negative", ("capture", "bad option value", "clear error")),
    (r"test_capture_cli_faults", r"write_failure", ("capture", "full disk (ENOSPC)", "recovered")),
    (r"test_capture_cli_faults", r"bad_port", ("capture", "missing device", "recovered")),
    (r"test_radiance", r"build", ("build", "corrupt input (negative radiance)", "clear error")),
    (r"test_radiance", r"", ("registration/build", "corrupt input (NaN/Inf/negative radiance)", "clear error")),
    (r"test_render_warnings", r"without_warnings", ("render", "sound input (control)", "correct, nothing to report")),
    (r"test_render_warnings", r"", ("render", "view/target outside the model", "documented fall-back")),
    (r"test_corruption", r"model", ("model", "corrupt/truncate/delete a file", "clear error")),
    (r"test_corruption", r"registration", ("registration", "corrupt/truncate/delete a file", "clear error")),
    (r"test_corruption", r"capture", ("capture", "corrupt/truncate/delete a file", "clear error")),
    (r"test_cli_errors", r"", ("every command", "error reporting", "clear error")),
    (r"test_output_transactions", r"refused_with_exit_3", (None, "two processes", "clear error")),
    (r"manifests", r"second_is_refused", (None, "two processes", "clear error")),
    (r"test_output_transactions", r"dropped_unfinished", (None, "failed step / refused input", "recovered")),
    (r"test_output_transactions", r"next_render_finishes", ("render", "kill (SIGKILL)", "recovered")),
    (r"test_output_transactions", r"cannot_exist", ("render", "bad option value", "clear error")),
    (r"test_output_transactions", r"ephemeral_lock", ("formats (files, locks)", "two processes", "recovered")),
    (r"transactions|atomic|manifests", r"sigkill|interrupted", (None, "kill (SIGKILL)", "recovered")),
    (r"transactions|atomic|manifests", r"full_disk", (None, "full disk (ENOSPC)", "recovered")),
    (r"transactions|atomic|manifests", r"two_|lock|thread", (None, "two processes", "recovered")),
    (r"transactions|atomic|manifests", r"flipped|bit_rot|missing|key|checksum|truncat",
     (None, "corrupt/truncate/delete a file", "clear error")),
    (r"transactions|atomic|manifests", r"failed|failure|refuse|never|needs|cover|not_mixed",
     (None, "failed step / refused input", "clear error")),
    (r"transactions|atomic|manifests", r"", (None, "other", "recovered")),
]
STAGE_OF_MODULE = {"test_model_transactions": "build", "test_registration_transactions": "register",
                   "test_atomic_files": "formats (files, locks)", "test_capture_performance_manifests":
                   "capture/performance"}


#: module -> [(test-name regex, stage)]: the stage of a module's tests by name (before STAGE_OF_MODULE)
STAGE_BY_NAME = {"test_model_transactions": [(r"compress", "compress")],
                 "test_output_transactions": [(r"track", "track"), (r"drive", "drive"),
                                              (r"output_folder", "formats (files, locks)"),
                                              (r"render", "render")],
                 "test_capture_performance_manifests": [(r"recordings", "capture/performance")]}


def stage_of(module: str, name: str) -> str:
    for rx, stage in STAGE_BY_NAME.get(module, []):
        if re.search(rx, name):
            return stage
    return STAGE_OF_MODULE.get(module, module)


def classify(module: str, name: str) -> tuple[str, str, str]:
    for mod_rx, name_rx, what in RULES:
        if re.search(mod_rx, module) and re.search(name_rx, name):
            if what is None:    # bad options: the command from the id
                cmd = re.search(r"\[(.+?) (-|[A-Z_]+=)", name)
                return (cmd.group(1) if cmd else "?", "bad option value", "clear error")
            stage, cls, outcome = what
            return stage or stage_of(module, name), cls, outcome
    return module, "other", "clear error"


def read_junit(xml: Path) -> list[tuple[str, str, bool]]:
    """(module, test name, failed) of every tests/reliability case a JUnit XML report holds (not skipped)."""
    cases = []
    for tc in ET.parse(xml).getroot().iter("testcase"):
        classname = tc.get("classname", "")
        if "reliability" not in classname.split("."):
            continue
        failed = any(c.tag in ("failure", "error") for c in tc)
        skipped = any(c.tag == "skipped" for c in tc)
        if not skipped:
            cases.append((classname.split(".")[-1], tc.get("name", ""), failed))
    return cases


def run(extra=()) -> list[tuple[str, str, bool]]:
    with tempfile.TemporaryDirectory() as tmp:
        xml = Path(tmp) / "junit.xml"
        subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/reliability",
                        f"--junitxml={xml}", *extra], cwd=ROOT)
        return read_junit(xml)


def table(cases) -> str:
    rows = defaultdict(lambda: defaultdict(int))
    for module, name, failed in cases:
        stage, cls, outcome = classify(module, name)
        key = (stage, cls)
        rows[key]["tried"] += 1
        rows[key]["failed" if failed else outcome] += 1
    outcomes = ["clear error", "documented fall-back", "recovered", "correct, nothing to report"]
    head = ("| stage | fault class | tried | " + " | ".join(outcomes) +
            " | data lost | silent wrong output | traceback |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    tot = defaultdict(int)
    for (stage, cls), r in sorted(rows.items()):
        f = r["failed"]
        lines.append(f"| {stage} | {cls} | {r['tried']} | " + " | ".join(str(r[o]) for o in outcomes) +
                     f" | {f} | {f} | {f} |")
        for k in ["tried", *outcomes, "failed"]:
            tot[k] += r[k]
    f = tot["failed"]
    lines.append(f"| **all** | | **{tot['tried']}** | " + " | ".join(f"**{tot[o]}**" for o in outcomes) +
                 f" | **{f}** | **{f}** | **{f}** |")
    return "\n".join(lines)


def main(argv) -> int:
    if "--from-xml" in argv:      # the report of a run that included tests/reliability (e.g. the whole suite)
        cases = read_junit(Path(argv[argv.index("--from-xml") + 1]))
    else:
        cases = run([a for a in argv if a != "--write"])
    text = table(cases)
    print(text)
    if "--write" in argv:
        doc = DOC.read_text()
        a, b = doc.index(BEGIN) + len(BEGIN), doc.index(END)
        DOC.write_text(doc[:a] + "\n" + text + "\n" + doc[b:])
        print(f"written to {DOC.relative_to(ROOT)}")
    return 1 if any(f for *_, f in cases) else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
