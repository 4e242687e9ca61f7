"""The suite's own xdist scheduler (tests/xdist_scheduling.py): a worker that dies mid-test, by
SIGKILL (what the OOM killer sends) or by a segfault, is reported once with how it died, the
rest of its work unit runs on a live worker, and the run ends with pytest's summary line.
(xdist 3.8's LoadScopeScheduling ran the dead worker's test again and then raised KeyError or
hung, so the run ended without its summary.) A small session of two workers in a subprocess,
without JAX: a few seconds."""
from __future__ import annotations

import os
import pathlib
import re
import subprocess
import sys
import textwrap

HERE = pathlib.Path(__file__).resolve().parent

DYING = """
import os, signal

def test_before():
    pass

def test_dies():
    os.kill(os.getpid(), signal.{sig})

def test_after():
    pass
"""


def test_dead_workers_are_reported_and_the_run_ends_with_its_summary(tmp_path):
    (tmp_path / "conftest.py").write_text(textwrap.dedent("""
        import sys
        sys.path.insert(0, %r)
        from xdist_scheduling import crash_diagnosis, make_scheduler

        def pytest_xdist_make_scheduler(config, log):
            return make_scheduler(config, log)

        def pytest_handlecrashitem(crashitem, report, sched):
            report.longrepr = f"{report.longrepr}: {crash_diagnosis(report)}"
        """ % str(HERE)))
    # One death in the MJX group (a test_kuka_* module, grouped with test_kuka_b), one in a
    # module of its own; the other modules keep the second worker busy meanwhile.
    (tmp_path / "test_kuka_a.py").write_text(DYING.format(sig="SIGKILL"))
    (tmp_path / "test_kuka_b.py").write_text("def test_b1():\n    pass\n")
    (tmp_path / "test_segv.py").write_text(DYING.format(sig="SIGSEGV"))
    for name in "cdef":
        (tmp_path / f"test_{name}.py").write_text(f"def test_{name}():\n    pass\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-n", "2", "--dist", "loadscope", "-rf",
         "-p", "no:cacheprovider", "-o", "addopts=", "-o", "faulthandler_timeout=0", "."],
        cwd=tmp_path, capture_output=True, text=True, timeout=240, env=env)
    out = proc.stdout
    lines = out.strip().splitlines()
    assert lines and re.fullmatch(r"(=+ )?2 failed, 9 passed in [0-9.]+s( =+)?", lines[-1]), out
    assert proc.returncode == 1, out
    assert "INTERNALERROR" not in out + proc.stderr
    # The crash reports in the FAILURES section; the short summary ('FAILED ...' lines) repeats
    # them in full or cut to the terminal's width, so it is counted separately below.
    body = [ln for ln in lines if not ln.startswith("FAILED ")]
    kill = [ln for ln in body if "crashed while running 'test_kuka_a.py::test_dies'" in ln]
    segv = [ln for ln in body if "crashed while running 'test_segv.py::test_dies'" in ln]
    assert len(kill) == 1 and "killed by SIGKILL" in kill[0] and "OOM killer" in kill[0], out
    assert len(segv) == 1 and "killed by SIGSEGV" in segv[0], out
    # Each dying test ran once (not again on the next worker); the rest of its unit ran.
    assert out.count("FAILED test_kuka_a.py::test_dies") == 1
    assert out.count("FAILED test_segv.py::test_dies") == 1
