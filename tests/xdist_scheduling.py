"""The test suite's xdist scheduler and crash report (tests/conftest.py uses them; no JAX here, so
tests/test_suite_scheduling.py runs them in a small pytest session of its own).

Tests go to the workers by module (a module's fixtures are built once), except that every test
that compiles MuJoCo MJX programs runs on one worker, one after the other (mjx_scope).

A worker that dies (the kernel's OOM killer, a segfault) must not end the run without its summary
line. xdist 3.8's LoadScopeScheduling handles a dead worker badly: it puts the test that was
running back in the queue with the rest of its work unit, so the next worker runs it again (and
dies again when the test itself is the cause), and it assigns work to the replacement worker
before that worker has collected, which raised KeyError inside xdist (INTERNALERROR) or hung the
run. CrashSafeScheduling reports the test once (xdist's failure "worker 'gwN' crashed while
running ...", to which crash_diagnosis adds how the worker died) and runs the rest of its unit on
a live worker.
"""
from __future__ import annotations

import os
import signal

MJX_GROUP = "mjx"
"""The xdist work unit of every test that compiles MuJoCo MJX programs."""


def mjx_scope(nodeid: str) -> str | None:
    """MJX_GROUP for a test that compiles MJX programs (a tests/test_kuka_* module, or a test
    whose id names kuka), else None."""
    module = nodeid.split("::", 1)[0]
    if os.path.basename(module).startswith("test_kuka_") or "kuka" in nodeid.lower():
        return MJX_GROUP
    return None


def make_scheduler(config, log):
    """The MJX-grouping, crash-safe LoadScopeScheduling (see the module docstring)."""
    from xdist.scheduler import LoadScopeScheduling

    class CrashSafeScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return mjx_scope(nodeid) or nodeid.split("::", 1)[0]

        def remove_node(self, node):
            """As LoadScopeScheduling.remove_node, except that the test that was running when
            the worker died is marked done (xdist reports it failed) instead of queued again."""
            workload = self.assigned_work.pop(node)
            crashitem = next((nodeid for unit in workload.values()
                              for nodeid, done in unit.items() if not done), None)
            if crashitem is None:
                return None
            scope = self._split_scope(crashitem)
            workload[scope][crashitem] = True
            rest = {s: unit for s, unit in workload.items() if not all(unit.values())}
            for s, unit in rest.items():  # the interrupted units first
                self.workqueue[s] = unit
                self.workqueue.move_to_end(s, last=False)
            for other in list(self.assigned_work):
                self._reschedule(other)
            return crashitem

        def _reschedule(self, node):
            """No work for a worker (a replacement) before its collection has arrived."""
            if node not in self.registered_collections:
                return
            super()._reschedule(node)

    return CrashSafeScheduling(config, log)


def exit_description(returncode: int | None) -> str:
    """How a worker process ended, in words, with the likely cause of a signal."""
    if returncode is None:
        return "its exit status is unknown (the process had not ended)"
    if returncode >= 0:
        return f"it exited with status {returncode}"
    sig = -returncode
    name = signal.Signals(sig).name if sig in signal.Signals._value2member_map_ else str(sig)
    hint = {
        signal.SIGKILL: "the kernel's OOM killer sends SIGKILL when memory runs out (dmesg "
                        "says so); so does a user's kill -9",
        signal.SIGSEGV: "a segmentation fault: LLVM segfaults when compiling past "
                        "vm.max_map_count memory mappings (tests/conftest.py, MAX_MAPPINGS)",
        signal.SIGTERM: "terminated by another process",
        signal.SIGABRT: "aborted (a failed check in native code)",
    }.get(sig, "")
    return f"it was killed by {name}" + (f" ({hint})" if hint else "")


def worker_returncode(worker, timeout: float = 5.0) -> int | None:
    """The exit status of an xdist worker's process (negative: the signal), or None."""
    popen = getattr(getattr(getattr(worker, "gateway", None), "_io", None), "popen", None)
    if popen is None:
        return None
    try:
        return popen.wait(timeout=timeout)
    except Exception:  # still running, or not a subprocess.Popen
        return popen.poll() if hasattr(popen, "poll") else None


def available_memory_gb() -> float | None:
    """MemAvailable of /proc/meminfo in GB (None where there is none)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 2 ** 20
    except OSError:
        pass
    return None


def crash_diagnosis(report) -> str:
    """The line added to xdist's crash report: how the worker died, and the memory left."""
    text = exit_description(worker_returncode(getattr(report, "node", None)))
    available = available_memory_gb()
    if available is not None:
        text += f"; {available:.1f} GB of memory available now"
    return text
