"""Run one command and report its own wall time, CPU time and peak memory, measured from a small launcher.

Linux counts a child's peak memory (``ru_maxrss``) from the moment it is forked, and a fork is a copy
of its parent: a command that a 150 MB benchmark process starts reports at least 150 MB, whatever it
used itself. So the benchmarks start this small launcher (a bare Python, about 10 MB, below any
command measured), which starts the command and reads the command's own rusage from ``wait4``.
Run as a script (``python benchmarks/child.py SPEC``): it imports nothing from the project.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

HERE = os.path.abspath(__file__)


def measured(
    args: list[str], cwd: str | None = None, max_bytes: int | None = None, env: dict[str, str] | None = None
) -> tuple[float, float, int, int, str]:
    """See ``measured_all``; without the bytes written."""
    out, err = measured_all(args, cwd, max_bytes, env)
    return out["wall"], out["cpu"], int(out["maxrss_kb"]), int(out["code"]), err


def measured_all(
    args: list[str], cwd: str | None = None, max_bytes: int | None = None, env: dict[str, str] | None = None
) -> tuple[dict[str, float], str]:
    """One command's ``wall`` seconds, ``cpu`` seconds (user + system), peak RSS (``maxrss_kb``), exit
    ``code`` and ``written_bytes`` (block output: what reached the disk's queue, not the page cache), and
    its stderr.

    The command's stdin and stdout are /dev/null; wall time is taken by the launcher around the command
    alone (not the launcher's own start-up). ``max_bytes``: the command's address space is limited to it
    (a command that tries to take gigabytes fails instead of taking the machine).
    """
    spec = json.dumps({"args": args, "cwd": cwd, "max_bytes": max_bytes})
    proc = subprocess.run([sys.executable, HERE, spec], capture_output=True, stdin=subprocess.DEVNULL, env=env)
    if proc.returncode != 0 or not proc.stdout.strip():
        raise RuntimeError(f"the launcher failed for {' '.join(args[:4])}: {proc.stderr.decode(errors='replace')}")
    return json.loads(proc.stdout.decode().strip().splitlines()[-1]), proc.stderr.decode(errors="replace")


def _main() -> None:
    spec = json.loads(sys.argv[1])
    if sys.platform == "win32":
        _main_windows(spec)
        return
    t = time.perf_counter()
    limit = spec.get("max_bytes")

    def limited() -> None:
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    proc = subprocess.Popen(
        spec["args"],
        cwd=spec["cwd"],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        preexec_fn=limited if limit else None,
    )
    tree = [0, 0]  # the largest sums of the resident memory (RSS, PSS) of the command and its own processes
    done = threading.Event()
    threading.Thread(target=_watch_tree, args=(proc.pid, tree, done), daemon=True).start()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    done.set()
    # ru_* of wait4 count the command and the processes it waited for (its workers): CPU is theirs together;
    # ru_maxrss is the largest of them, so the sum of the tree is sampled (tree_rss_kb, Linux)
    print(
        json.dumps(
            {
                "wall": wall,
                "cpu": usage.ru_utime + usage.ru_stime,
                "sys": usage.ru_stime,
                "maxrss_kb": usage.ru_maxrss,
                "tree_rss_kb": max(tree[0], usage.ru_maxrss),
                "tree_pss_kb": tree[1],
                "code": os.waitstatus_to_exitcode(status),
                "written_bytes": usage.ru_oublock * 512,
            }
        )
    )  # Linux: the command's block output


def _main_windows(spec: dict[str, object]) -> None:
    """Windows has no rlimits and no wait4: the command runs in a job object, which bounds its memory
    (``max_bytes``: the job's per-process commit limit) and counts the CPU time of the command and its own processes;
    the peak memory is the command's largest commit charge (Windows' measure of what a process took), sampled every
    20 ms while it runs and taken once more at its end (Wine: its job objects neither limit nor count, and an ended
    process's counters read 0, so the samples and the process's own times are what it has)."""
    if sys.platform != "win32":
        raise AssertionError("Windows only")
    import ctypes

    class _JobLimits(ctypes.Structure):
        """JOBOBJECT_EXTENDED_LIMIT_INFORMATION, as far as the limits set here."""

        _fields_ = [
            ("user_time_limits", ctypes.c_int64 * 2),
            ("flags", ctypes.c_uint32),
            ("working_set", ctypes.c_size_t * 2),
            ("active_processes", ctypes.c_uint32),
            ("affinity", ctypes.c_size_t),
            ("priority", ctypes.c_uint32),
            ("scheduling", ctypes.c_uint32),
            ("io", ctypes.c_uint64 * 6),
            ("process_memory_limit", ctypes.c_size_t),
            ("job_memory_limit", ctypes.c_size_t),
            ("peaks", ctypes.c_size_t * 2),
        ]

    k32 = ctypes.WinDLL("kernel32", use_last_error=True)
    k32.CreateJobObjectW.restype = ctypes.c_void_p
    job = k32.CreateJobObjectW(None, None)
    info = _JobLimits()
    info.flags = 0x2000  # JOB_OBJECT_LIMIT_KILL_ON_JOB_CLOSE: the command ends with its launcher
    limit = spec.get("max_bytes")
    if isinstance(limit, int):
        info.flags |= 0x100  # JOB_OBJECT_LIMIT_PROCESS_MEMORY
        info.process_memory_limit = limit
    k32.SetInformationJobObject(ctypes.c_void_p(job), 9, ctypes.byref(info), ctypes.sizeof(info))
    t = time.perf_counter()
    args, cwd = spec["args"], spec["cwd"]
    assert isinstance(args, list) and (cwd is None or isinstance(cwd, str))
    proc = subprocess.Popen(args, cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    handle = ctypes.c_void_p(int(proc._handle))  # type: ignore[attr-defined,unused-ignore]
    k32.AssignProcessToJobObject(ctypes.c_void_p(job), handle)  # its start-up (a few MB) may precede the limit
    peak = 0
    while proc.poll() is None:
        peak = max(peak, _peak_commit(k32, handle))
        time.sleep(0.02)
    peak = max(peak, _peak_commit(k32, handle))
    wall = time.perf_counter() - t
    times = [ctypes.c_int64() for _ in range(4)]  # creation, exit, kernel, user (100 ns)
    k32.GetProcessTimes(handle, *[ctypes.byref(x) for x in times])
    acct = (ctypes.c_int64 * 6)()  # JOBOBJECT_BASIC_ACCOUNTING_INFORMATION: user, kernel first
    k32.QueryInformationJobObject(ctypes.c_void_p(job), 1, ctypes.byref(acct), ctypes.sizeof(acct), None)
    user, kernel = max(acct[0], times[3].value), max(acct[1], times[2].value)
    print(
        json.dumps(
            {
                "wall": wall,
                "cpu": (user + kernel) / 1e7,
                "sys": kernel / 1e7,
                "maxrss_kb": peak // 1024,
                "tree_rss_kb": peak // 1024,
                "tree_pss_kb": 0,
                "code": proc.returncode,
                "written_bytes": 0,
            }
        )
    )


def _peak_commit(k32: object, handle: object) -> int:
    import ctypes

    counters = (ctypes.c_size_t * 10)()  # PROCESS_MEMORY_COUNTERS; its first word is cb (with PageFaultCount)
    counters[0] = ctypes.sizeof(counters)
    if not k32.K32GetProcessMemoryInfo(handle, ctypes.byref(counters), ctypes.sizeof(counters)):  # type: ignore
        return 0
    return int(max(counters[2], counters[9]))  # PeakWorkingSetSize, PeakPagefileUsage


def _watch_tree(pid: int, peak: list[int], done: threading.Event) -> None:
    """Every 20 ms: the resident memory of ``pid`` and its child processes, summed; the largest sum in peak[0].

    peak[1]: the same for the proportional set size (``Pss`` of /proc/PID/smaps_rollup), which counts a page
    shared by N processes (a forked worker's pages still its parent's) as 1/N in each: the memory the tree
    really takes, where the RSS sum counts shared pages once per process. Read every 0.25 s only (a peak shorter
    than that may be missed): smaps_rollup walks a process's page tables (1.8 ms for 150 MB), and every 20 ms for
    three processes took a fifth of a core from the command measured, on a machine of two."""
    pss_due = 0.0
    while not done.wait(0.02):
        kids: dict[int, list[int]] = {}
        rss: dict[int, int] = {}
        try:
            entries = [e for e in os.listdir("/proc") if e.isdigit()]
        except OSError:
            return  # not Linux: ru_maxrss only
        for e in entries:
            try:
                with open(f"/proc/{e}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except (OSError, IndexError):
                continue
            kids.setdefault(int(fields[1]), []).append(int(e))
            rss[int(e)] = int(fields[21]) * (os.sysconf("SC_PAGE_SIZE") // 1024)
        tree, todo = [], [pid]
        while todo:
            p = todo.pop()
            tree.append(p)
            todo.extend(kids.get(p, []))
        peak[0] = max(peak[0], sum(rss.get(p, 0) for p in tree))
        if time.monotonic() >= pss_due:
            pss_due = time.monotonic() + 0.25
            peak[1] = max(peak[1], sum(_pss_kb(p) for p in tree))


def _pss_kb(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                if line.startswith("Pss:"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return 0


if __name__ == "__main__":
    _main()
