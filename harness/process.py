"""The process sear.py runs in: SIGTERM (how SLURM, timeout, docker stop and systemd stop it), glibc's malloc,
torch's CPU threads, TF32, the C++ compiler inductor needs, and the start-up warnings. cli.py takes its names from
here. Loads no numpy or torch at import.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import signal
import sys
import threading


# ------------------------------------------------------------------------------------------------ SIGTERM
class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C raises KeyboardInterrupt: the same handlers stop the run."""


class TermSignal:
    """SIGTERM stops a run as Ctrl-C does (exit 143). While a run trains (`defer`, set by experiment.RunDir), the
    first SIGTERM only asks it to stop at the next episode end, where a snapshot holds the exact state (SLURM's
    --signal=TERM@SECONDS gives that grace); anywhere else, or a second time, it stops at once.

    Python runs a signal handler in the main thread only, between bytecodes: while that thread is inside one long
    native call (a torch operation, a render) the handler waits for the call to end, and a SIGTERM seems ignored. So a
    watcher thread hears every SIGTERM too (set_wakeup_fd: the interpreter's C-level handler writes the signal's number
    into a pipe at once), and when one that stops at once has not ended the process GRACE seconds later, it ends it:
    one line saying what stands (`stands`, set by experiment.RunDir), exit 143, no Python code of the main thread."""

    GRACE = 5.0

    def __init__(self):
        self.defer, self.pending = False, False
        self.received = 0  # SIGTERMs the watcher heard: the handler sees two that came during one call as one
        self.stands = None  # () -> what a forced stop leaves, e.g. "the last snapshot (frame N) stands; ..."
        self.waits_for = None  # () -> what a first SIGTERM waits for, e.g. "the next episode end (...)"

    @contextlib.contextmanager
    def installed(self):
        """The handler and its watcher for the time of a command (main), then the handler before it again."""
        if threading.current_thread() is not threading.main_thread():  # signals reach the main thread only
            yield
            return
        self.received = 0
        previous = signal.signal(signal.SIGTERM, self.handle)
        read, write = os.pipe()
        os.set_blocking(write, False)  # set_wakeup_fd's rule: a signal handler never blocks
        previous_fd = signal.set_wakeup_fd(write)
        done = threading.Event()
        threading.Thread(target=self.watch, args=(read, done), daemon=True, name="sigterm-watcher").start()
        try:
            yield
        finally:
            done.set()
            signal.set_wakeup_fd(previous_fd)
            signal.signal(signal.SIGTERM, previous)
            os.close(write)  # the watcher reads the end of the pipe and closes its side

    def watch(self, fd, done: threading.Event):
        try:
            while data := os.read(fd, 64):  # blocks without the GIL
                for signum in data:
                    if signum != signal.SIGTERM:
                        continue
                    self.received += 1
                    if (self.received > 1 or not self.defer) and not done.wait(self.GRACE):
                        self.force_stop()
        finally:
            os.close(fd)

    def force_stop(self):
        try:
            stands = self.stands() if self.stands else "nothing was saved"
        except Exception:  # the last words must not fail
            stands = "the last snapshot, if any, stands"
        os.write(2, f"\nsear.py: stopped by SIGTERM at once: the process did not answer it within {self.GRACE:g} s "
                    f"(inside a long native call); {stands}\n".encode())
        os._exit(128 + signal.SIGTERM)

    def handle(self, signum, frame):
        if self.defer and not self.pending and self.received <= 1:
            self.pending = True
            waits = "the next safe point (an episode end, with a snapshot)"
            with contextlib.suppress(Exception):  # the line must not fail
                waits = self.waits_for() if self.waits_for else waits
            # os.write: print() here could re-enter a write the signal interrupted
            os.write(2, f"\nsear.py: SIGTERM: stopping at {waits}; another SIGTERM stops at once\n".encode())
            return
        raise Terminated


TERM = TermSignal()


def stop_cause(stop: KeyboardInterrupt) -> tuple[str, int]:
    """What stopped the process, as the messages say it, and its exit code."""
    return ("stopped by SIGTERM", 128 + signal.SIGTERM) if isinstance(stop, Terminated) else ("interrupted", 130)


# ------------------------------------------------------------------------------------------------ the process
# glibc's malloc at run time (mallopt): never mmap a block of its own (M_MMAP_MAX 0) and never give
# freed heap back to the OS (M_TRIM_THRESHOLD -1): the update's large activation buffers are then
# reused from one update to the next instead of being mapped, faulted in and unmapped each time.
M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4  # <malloc.h>


def configure_allocator() -> bool:
    """Set glibc's malloc as above for the rest of this process (blocks allocated before keep their mmap); False
    without glibc. Why: on CPU the decoder's activations (tens of MB at batch 256) would otherwise cost 0.9M minor
    page faults per SEAR update (`benchmarks/bench_agent.py --compare-allocators`, docs/speed.md, "Allocator")."""
    if not sys.platform.startswith("linux"):
        return False
    import ctypes
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    return mallopt(M_MMAP_MAX, 0) == 1 and mallopt(M_TRIM_THRESHOLD, -1) == 1


def usable_cores():
    """The cores this process may run on (taskset / cgroup affinity)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def default_threads():
    """OMP_NUM_THREADS when set (sweep.py sets it per job), else every core this process may run on."""
    omp = os.environ.get("OMP_NUM_THREADS", "")
    return int(omp) if omp.isdigit() and int(omp) > 0 else usable_cores()


def torch_threads(run) -> int:
    """--threads, else $OMP_NUM_THREADS, else every usable core; never more than the usable cores. Clamped, not
    refused (start_warnings says so): more threads cannot be faster (torch's OpenMP threads spin waiting for each
    other), and an OMP_NUM_THREADS a cluster set for other jobs should not stop a run."""
    return min(run.threads or default_threads(), usable_cores())


def start_warnings(cfg, run, training=True) -> list[str]:
    """Settings that run, but not as meant: more threads than cores (clamped), Distracting Control without the paper's
    DAVIS backgrounds, a replay smaller than a batch."""
    warnings, threads, cores = [], run.threads or default_threads(), usable_cores()
    if threads > cores:
        given = f"--threads {run.threads}" if run.threads else f"OMP_NUM_THREADS={threads}"
        warnings.append(f"{given} is more threads than the {cores} cores this process may use; using {cores} "
                        f"(more would only wait on each other: torch's threads spin, and on 2 cores 64 of them "
                        f"took minutes for one operation)")
    if training and cfg.replay_size < cfg.batch_size:
        warnings.append(f"--replay-size {cfg.replay_size} is smaller than --batch-size {cfg.batch_size}: every "
                        f"batch holds the same transitions several times")
    if cfg.env.endswith("-distracting") and not cfg.backgrounds:  # a default that is not the paper's: said every run
        warnings.append(f"{cfg.env} runs on the built-in procedural backgrounds, not the paper's DAVIS-2017 videos; "
                        "for the paper's setting: python envs.py --fetch-davis, then --backgrounds davis")
    return warnings


def set_tf32(on: bool) -> None:
    """TF32 in CUDA's float32 convolutions and matmuls, on or off (torch's default is on for cuDNN's)."""
    import torch
    # Not torch 2.9's fp32_precision API: "ieee" for convolutions makes torch.func.vmap's convolutions (the seeds'
    # batched update) raise on torch 2.13's check of cuDNN's TF32 flag, on the CPU too.
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = on


def cxx_compiler() -> str | None:
    """The C++ compiler inductor's CPU kernels would be built with ($CXX, else the first one found)."""
    return next(filter(None, map(shutil.which, (os.environ.get("CXX", ""), "g++", "c++", "clang++"))), None)
