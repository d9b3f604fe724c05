"""nerfstudio's parallel data manager, whose data-loading worker neither outlives the trainer nor
dies unnoticed.

nerfstudio's ``ParallelDataManager`` reads the training images and samples rays in a separate
process (``DataProcessor``, started with ``spawn``) and hands batches over a queue. Two things
go wrong with it:

* **A worker that dies hangs the run.** The trainer waits on the queue forever (at 0% CPU) when
  the worker raised (an image of another size: "stack expects each tensor to be equal size"),
  was killed by the OOM killer, or crashed. Here the worker sends what ended it over the same
  queue (:class:`WorkerFailure`), and the trainer, while it waits, looks every
  :data:`WATCHDOG_PERIOD_S` seconds whether the worker is still alive: either way the run ends
  with the worker's error (:class:`DataWorkerError`, or the :class:`~seathru_nerfstudio.
  input_errors.InputError` the worker met, one line naming the file).
* **A worker outlives a killed trainer.** It is a daemon process, which Python ends only when the
  trainer exits normally: after SIGKILL (the kill-and-resume workflow) or a SIGTERM it survives,
  holding its copy of the images in memory. Here it follows its parent (:func:`follow_parent`):
  on Linux the kernel sends it SIGKILL when the thread that started it ends
  (``prctl(PR_SET_PDEATHSIG)``; only used when the main thread starts it, the thread nerfstudio's
  commands build the pipeline in), and everywhere a thread in it exits when its parent process has
  changed (polled every :data:`WATCHDOG_PERIOD_S` seconds).

And one thing it costs for nothing: **commands that only evaluate start a worker too.** Every
data manager starts its training workers when it is built, also the one ``eval_setup`` builds for
``ns-eval``, ``ns-render``, ``ns-export``, ``ns-viewer`` and ``seathru-medium``, which never ask
for a training batch. Such a worker imports nerfstudio again (under a console script, the whole of
``ns-*``'s start-up, as ``__mp_main__``) and holds a copy of every training image. Here the
workers start when a trainer builds the data manager (``test_mode="val"``), or otherwise at the
first training batch asked for.
"""

from __future__ import annotations

import ctypes
import os
import queue
import signal
import sys
import threading
import time
import traceback
from dataclasses import dataclass
from typing import Dict, Tuple

from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.datamanagers.parallel_datamanager import DataProcessor, ParallelDataManager
from pathos.helpers import mp

from seathru_nerfstudio.data.linear_images import LinearImageDataset
from seathru_nerfstudio.input_errors import InputError

WATCHDOG_PERIOD_S = 1.0
"""How often (seconds) the trainer checks a worker it waits for, and a worker checks its parent."""
REPORT_TIMEOUT_S = 10.0
"""How long a failing worker tries to hand its error to the trainer before it exits anyway."""
_PR_SET_PDEATHSIG = 1  # from <linux/prctl.h>


class DataWorkerError(RuntimeError):
    """The data-loading worker ended with an error of ours; the message holds its traceback."""


class DataWorkerKilled(DataWorkerError):
    """The data-loading worker was killed (a signal, no report): one line says so (``ns-train``: exit status 1)."""


@dataclass
class WorkerFailure:
    """What ended a worker, sent to the trainer in place of a batch (plain strings: always picklable)."""

    pid: int
    kind: str
    message: str
    trace: str
    input_error: bool

    def error(self) -> Exception:
        if self.input_error:
            return InputError(self.message)
        return DataWorkerError(
            f"the data-loading worker (pid {self.pid}) stopped with {self.kind}: {self.message}\n{self.trace}"
        )


def follow_parent(parent_pid: int, kernel_signal: bool) -> None:
    """End this process when its parent ``parent_pid`` ends (see the module docstring); exits at
    once if that has already happened. ``kernel_signal``: also ask Linux for SIGKILL at the
    parent's death (only right when the parent's thread that started us lives as long as it)."""
    if kernel_signal and sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):  # no prctl: the thread below still follows the parent
            pass
    if os.getppid() != parent_pid:  # the parent died before we could follow it
        os._exit(1)
    threading.Thread(target=_exit_when_orphaned, args=(parent_pid,), name="follow-parent", daemon=True).start()


def _exit_when_orphaned(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(WATCHDOG_PERIOD_S)
    os._exit(1)  # no clean-up: the images in memory go with the process


class FollowingDataProcessor(DataProcessor):
    """nerfstudio's data-loading worker that follows its parent and reports what ends it."""

    def __init__(self, *args, parent_pid: int, kernel_signal: bool, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.parent_pid = parent_pid
        self.kernel_signal = kernel_signal

    def run(self) -> None:
        follow_parent(self.parent_pid, self.kernel_signal)
        try:
            super().run()
        except KeyboardInterrupt:  # Ctrl-C reaches the whole process group: the trainer reports it
            sys.exit(1)
        except BaseException as error:  # noqa: BLE001 - whatever it is, the trainer must hear of it
            failure = WorkerFailure(
                pid=os.getpid(),
                kind=type(error).__name__,
                message=str(error),
                trace="" if isinstance(error, InputError) else traceback.format_exc(),
                input_error=isinstance(error, InputError),
            )
            try:
                self.out_queue.put(failure, timeout=REPORT_TIMEOUT_S)
            except Exception:  # noqa: BLE001 - the trainer's watchdog still sees the exit
                pass
            sys.exit(1)


class SeathruDataManager(ParallelDataManager[LinearImageDataset]):
    """``ParallelDataManager`` of :class:`LinearImageDataset` whose workers follow the trainer and
    whose death ends the run with its error (see the module docstring)."""

    def setup_train(self) -> None:
        """As nerfstudio's, with :class:`FollowingDataProcessor` workers, started now only for a
        trainer (``test_mode="val"``); a data manager built to evaluate starts them at the first
        training batch asked for (see the module docstring)."""
        assert self.train_dataset is not None
        if self.config.num_processes < 1:
            raise InputError(
                f"--pipeline.datamanager.num-processes {self.config.num_processes}: at least one data-loading "
                "worker is needed (the training rays are sampled in it)"
            )
        self.train_pixel_sampler = self._get_pixel_sampler(self.train_dataset, self.config.train_num_rays_per_batch)
        self.data_procs = []
        if self.test_mode == "val":
            self._start_workers()

    def _start_workers(self) -> None:
        """Start ``num_processes`` :class:`FollowingDataProcessor` workers on a fresh queue."""
        self.data_queue = mp.Queue(maxsize=self.config.queue_size)  # type: ignore[attr-defined]
        in_main_thread = threading.current_thread() is threading.main_thread()
        self.data_procs = [
            FollowingDataProcessor(
                out_queue=self.data_queue,
                config=self.config,
                dataparser_outputs=self.train_dataparser_outputs,
                dataset=self.train_dataset,
                pixel_sampler=self.train_pixel_sampler,
                parent_pid=os.getpid(),
                kernel_signal=in_main_thread,
            )
            for _ in range(self.config.num_processes)
        ]
        for proc in self.data_procs:
            proc.start()

    def next_train(self, step: int) -> Tuple[RayBundle, Dict]:
        """The next batch from the workers; raises the error of a worker that has ended."""
        self.train_count += 1
        if not self.data_procs:
            self._start_workers()
        bundle, batch = self._next_from_workers()
        return bundle.to(self.device), batch

    def _next_from_workers(self) -> Tuple[RayBundle, Dict]:
        """Wait for the next batch, looking at the workers every :data:`WATCHDOG_PERIOD_S` seconds.

        The queue is read by a thread of its own (:meth:`_pump`): a worker killed halfway through
        sending a batch leaves half a message in the pipe, and a read of it never returns (the
        trainer holds the pipe's other end too, so no end-of-file comes). That thread is left
        waiting; this one raises."""
        if getattr(self, "_received", None) is None:
            self._received: queue.Queue = queue.Queue(maxsize=1)
            threading.Thread(target=self._pump, name="data-queue-reader", daemon=True).start()
        while True:
            try:
                item = self._received.get(timeout=WATCHDOG_PERIOD_S)
            except queue.Empty:
                self._check_workers()
                continue
            if isinstance(item, WorkerFailure):
                raise item.error()
            return item

    def _pump(self) -> None:
        """Move what the workers send into ``self._received``, until a failure."""
        while True:
            try:
                item = self.data_queue.get()
            except BaseException as error:  # noqa: BLE001 - e.g. a batch that cannot be unpickled
                item = WorkerFailure(os.getpid(), type(error).__name__, str(error), traceback.format_exc(), False)
            self._received.put(item)
            if isinstance(item, WorkerFailure):
                return

    def _check_workers(self) -> None:
        """Raise when a worker has ended: with its report if one is still on its way."""
        dead = [proc for proc in self.data_procs if not proc.is_alive()]
        if not dead:
            return
        try:  # a report sent just before the exit may still be in the pipe
            item = self._received.get(timeout=WATCHDOG_PERIOD_S)
        except queue.Empty:
            item = None
        if isinstance(item, WorkerFailure):
            raise item.error()
        proc = dead[0]
        how = f"exit status {proc.exitcode}"
        if proc.exitcode is not None and proc.exitcode < 0:
            how = f"signal {-proc.exitcode}" + (f" ({signal.Signals(-proc.exitcode).name})" if -proc.exitcode in signal.valid_signals() else "")
        raise DataWorkerKilled(
            f"the data-loading worker (pid {proc.pid}) ended with {how} and no report: killed by the system "
            "(out of memory? see dmesg) or crashed"
        )
