"""Where the test suite's CPU time goes: every process it starts, sampled once a second.

Runs a command (by default the README's test command, fixed order, with ``--durations=30``)
and samples the whole process tree under it with psutil every second, keeping each process's
last CPU time (user + system, seconds). Printed at the end:

* the wall time, the tree's total CPU time and their ratio (the cores kept busy on average);
* the CPU time by kind of process (``ns-train``, ``ns-eval``, ``seathru-bench``'s worker,
  multiprocessing's spawned data workers, chromium, ...), with the count;
* the ``--top`` most expensive processes with when they started and ended (seconds from the start).

The sampled figures miss a process that lives under a second and what a process spends after
its last sample; the total also comes from the kernel (``RUSAGE_CHILDREN``: every process of the
tree that was waited for), which misses only orphans. Run it alone (``heavy``): the figures are the
machine's as much as the suite's.

    /work/shared/tools/heavy .venv/bin/python scripts/suite_census.py
    .venv/bin/python scripts/suite_census.py --top 10 -- .venv/bin/python -m pytest -q tests/test_faults.py
"""

from __future__ import annotations

import re
import resource
import subprocess
import sys
import time
from collections import defaultdict
from typing import Dict, List

import psutil

DEFAULT_COMMAND = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:randomly", "--durations=30", "tests"]
KINDS = [  # (kind, pattern in the command line), the first that matches
    ("spawned data worker (pathos)", r"multiprocess\.spawn"),
    ("spawned worker (multiprocessing)", r"multiprocessing\.spawn"),
    ("fork server", r"forkserver"),
    ("chromium", r"chromium"),
    ("pytest (the tests' own process)", r"-m pytest"),
    ("seathru-bench worker", r"seathru_nerfstudio\.bench\.worker"),
    ("seathru-bench", r"seathru_nerfstudio\.bench\.cli|bin/seathru-bench"),
]


def kind_of(command: str) -> str:
    for kind, pattern in KINDS:
        if re.search(pattern, command):
            return kind
    programs = [name for name in re.findall(r"bin/([\w.-]+)", command) if not name.startswith("python")]
    if programs:
        return programs[0]
    module = re.search(r"-m ([\w.]+)", command)
    return module.group(1) if module else command[:40]


def sample(root: psutil.Process, seen: Dict[tuple, dict], start: float) -> None:
    """Add or update every live process of ``root``'s tree in ``seen``, by pid and start time (a
    reused pid is another process)."""
    try:
        processes = [root, *root.children(recursive=True)]
    except psutil.Error:
        return
    for process in processes:
        try:
            with process.oneshot():
                times = process.cpu_times()
                created = process.create_time()
                record = seen.setdefault((process.pid, created), {"command": " ".join(process.cmdline()), "start": created - start})
                record["cpu_s"] = times.user + times.system
                record["end"] = time.time() - start
        except psutil.Error:
            pass


def main(argv: List[str]) -> int:
    top = 15
    if argv[:1] == ["--top"]:
        top, argv = int(argv[1]), argv[2:]
    command = argv[argv.index("--") + 1 :] if "--" in argv else DEFAULT_COMMAND
    start = time.time()
    child = subprocess.Popen(command)
    root = psutil.Process(child.pid)
    seen: Dict[tuple, dict] = {}
    while child.poll() is None:
        sample(root, seen, start)
        time.sleep(1.0)
    wall = time.time() - start
    total = sum(record["cpu_s"] for record in seen.values())
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    reaped = usage.ru_utime + usage.ru_stime  # the kernel's count: every process of the tree that was waited for
    print(f"\nexit status {child.returncode}; wall {wall:.0f} s; CPU {total:.0f} s sampled over {len(seen)} processes, "
          f"{reaped:.0f} s by the kernel's count of the reaped ones ({reaped / wall:.2f} cores busy on average); "
          f"load average now {', '.join(f'{x:.1f}' for x in psutil.getloadavg())}")
    by_kind: Dict[str, List[float]] = defaultdict(lambda: [0, 0.0])
    for record in seen.values():
        entry = by_kind[kind_of(record["command"])]
        entry[0] += 1
        entry[1] += record["cpu_s"]
    print("CPU s  count  kind")
    for kind, (count, cpu) in sorted(by_kind.items(), key=lambda item: -item[1][1]):
        print(f"{cpu:6.0f} {count:6d}  {kind}")
    print(f"the {top} most expensive processes: CPU s, start-end s, command")
    for record in sorted(seen.values(), key=lambda r: -r["cpu_s"])[:top]:
        print(f"{record['cpu_s']:6.1f} {record['start']:5.0f}-{record['end']:4.0f}  {record['command'][:110]}")
    return child.returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
