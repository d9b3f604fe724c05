"""Run an installed console command (``ns-train``, ``seathru-process-data``, ...) in a process of
its own without paying its imports each time.

A command's entry point (the function its console script calls, read from the installed
package's ``console_scripts``) runs in a child of multiprocessing's fork server, which has
imported nerfstudio and our package once (:data:`PRELOAD`): the same code as the command typed in
a shell, with its own process, working folder, arguments, output and exit status. Each run also
carries an environment marker (:data:`MARKER`) that every process it starts inherits, so a test
can find any process a run left behind, whoever its parent is now.
"""

from __future__ import annotations

import multiprocessing
import os
import re
import sys
import tempfile
import time
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from typing import List, Sequence

import psutil

MARKER = "SEATHRU_FAULT_TEST_RUN"
PRELOAD = [
    "nerfstudio.scripts.train",
    "nerfstudio.scripts.eval",
    "nerfstudio.scripts.render",
    "seathru_nerfstudio.config",
    "seathru_nerfstudio.data.process",
]
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


@dataclass
class Result:
    returncode: int
    output: str
    stray: List[str]
    """Processes of this run still alive after it ended (``pid cmdline``)."""
    stdout: str = ""
    """Its standard output alone, where :func:`run` was asked to keep the streams apart (else "")."""

    def error_lines(self) -> List[str]:
        return [line for line in self.output.splitlines() if line.startswith("Error:")]


def _entry(command: str):
    (found,) = [ep for ep in entry_points(group="console_scripts") if ep.name == command]
    return found.load()


def _main(command: str, args: Sequence[str], cwd: str, log: str, tag: str, error_log: str = "") -> None:
    """The forked child: the command's entry point, its output in ``log`` (its standard error in
    ``error_log`` where one is given)."""
    os.chdir(cwd)
    handle = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    sys.stdout.flush()
    sys.stderr.flush()
    os.dup2(handle, 1)
    os.dup2(os.open(error_log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644) if error_log else handle, 2)
    os.environ[MARKER] = tag
    os.environ["PYTHONWARNINGS"] = "ignore"
    sys.argv = [command, *args]
    _entry(command)()


def processes_tagged(tag: str) -> List[psutil.Process]:
    """The live processes whose environment carries this run's marker."""
    found = []
    for process in psutil.process_iter():
        try:
            if process.environ().get(MARKER) == tag and process.status() != psutil.STATUS_ZOMBIE:
                found.append(process)
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            pass
    return found


def describe(processes: Sequence[psutil.Process]) -> List[str]:
    out = []
    for process in processes:
        try:
            out.append(f"{process.pid} {' '.join(process.cmdline())[:120]}")
        except psutil.Error:
            pass
    return out


def stray_after(tag: str, grace_s: float = 10.0) -> List[str]:
    """Processes of run ``tag`` still alive ``grace_s`` seconds after it ended (killed, then reported)."""
    deadline = time.monotonic() + grace_s
    left = processes_tagged(tag)
    while left and time.monotonic() < deadline:
        time.sleep(0.2)
        left = processes_tagged(tag)
    names = describe(left)
    for process in left:
        try:
            process.kill()
        except psutil.Error:
            pass
    return names


_context = None


def run(command: str, *args, cwd: Path, timeout_s: float = 120.0, streams_apart: bool = False) -> Result:
    """``command *args`` in ``cwd`` (see the module docstring); a run past ``timeout_s`` is killed
    and reported with return code -9. ``streams_apart``: standard output and error go to two files,
    ``Result.stdout`` holds the first and ``output`` the first followed by the second."""
    global _context
    if _context is None:
        _context = multiprocessing.get_context("forkserver")
        _context.set_forkserver_preload(PRELOAD)
    tag = f"{os.getpid()}-{time.monotonic_ns()}"
    log = Path(cwd) / f".{command}-{tag}.log"
    error_log = log.with_suffix(".err") if streams_apart else None
    arguments = (command, [str(a) for a in args], str(cwd), str(log), tag, str(error_log or ""))
    process = _context.Process(target=_main, args=arguments)
    process.start()
    process.join(timeout_s)
    if process.is_alive():
        process.kill()
        process.join()
        returncode = -9
    else:
        returncode = process.exitcode
    texts = []
    for path in (log, error_log) if error_log else (log,):
        texts.append(ANSI.sub("", path.read_text(errors="replace")) if path.exists() else "")
        path.unlink(missing_ok=True)
    stdout = texts[0] if error_log else ""
    return Result(returncode=returncode, output="".join(texts), stray=stray_after(tag), stdout=stdout)


def run_in_a_folder_of_its_own(command: str, *args, timeout_s: float = 120.0, streams_apart: bool = False) -> Result:
    """:func:`run` from a temporary working folder, removed after it: nothing of the run (its log,
    a file written to a relative path) lands beside the caller's folders."""
    with tempfile.TemporaryDirectory(prefix=f"{command}-cwd-") as cwd:
        return run(command, *args, cwd=Path(cwd), timeout_s=timeout_s, streams_apart=streams_apart)

