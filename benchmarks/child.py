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


def measured(args: list[str], cwd: str | None = None, max_bytes: int | None = None
             ) -> tuple[float, float, int, int, str]:
    """See ``measured_all``; without the bytes written."""
    out, err = measured_all(args, cwd, max_bytes)
    return out["wall"], out["cpu"], int(out["maxrss_kb"]), int(out["code"]), err


def measured_all(args: list[str], cwd: str | None = None, max_bytes: int | None = None,
                 env: dict[str, str] | None = None) -> tuple[dict[str, float], str]:
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
    t = time.perf_counter()
    limit = spec.get("max_bytes")

    def limited() -> None:
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    proc = subprocess.Popen(spec["args"], cwd=spec["cwd"], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            preexec_fn=limited if limit else None)
    tree = [0, 0]  # the largest sums of the resident memory (RSS, PSS) of the command and its own processes
    done = threading.Event()
    threading.Thread(target=_watch_tree, args=(proc.pid, tree, done), daemon=True).start()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    done.set()
    # ru_* of wait4 count the command and the processes it waited for (its workers): CPU is theirs together;
    # ru_maxrss is the largest of them, so the sum of the tree is sampled (tree_rss_kb, Linux)
    print(json.dumps({"wall": wall, "cpu": usage.ru_utime + usage.ru_stime, "sys": usage.ru_stime,
                      "maxrss_kb": usage.ru_maxrss, "tree_rss_kb": max(tree[0], usage.ru_maxrss),
                      "tree_pss_kb": tree[1],
                      "code": os.waitstatus_to_exitcode(status),
                      "written_bytes": usage.ru_oublock * 512}))  # Linux: the command's block output


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
