"""The files sear.py writes and the run directories it is given: storage errors in one line (`storing`,
`write_atomically`, `torch_save`: segment.py's writes too); a RUN_DIR given as an input (--run-root, --resume,
--evaluate, --init-from), who owns one, its snapshot and, for --init-from, the network sizes taken from it. cli.py
takes its names from here. Loads no numpy or torch at import.
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import socket
import time


def flag(name: str) -> str:
    """A setting's flag, as every message names it: recon_coef -> --recon-coef."""
    return "--" + name.replace("_", "-")


class ConfigError(ValueError):
    """Bad user input: reported as one line on stderr."""


class StorageError(Exception):
    """An OSError while writing a file the user keeps (a full disk, a read-only or foreign folder), as one line naming
    the file and the cause, never a traceback."""


def storage_message(path, err: OSError) -> str:
    """'cannot write PATH: No space left on device (ENOSPC)' (strerror: imageio's and torch's str(err) run on)."""
    if err.errno in (errno.EEXIST, errno.ENOTDIR):  # a file where a folder should be: say which
        for where in (path, *parents(path)):
            if os.path.lexists(where) and not os.path.isdir(where):
                return (f"cannot make the folder '{path}': a file of that name is in the way" if where == path
                        else f"cannot write '{path}': '{where}' is a file, not a folder")
    name = errno.errorcode.get(err.errno, "") if err.errno else ""
    reason = err.strerror or first_sentence(err) or type(err).__name__
    return f"cannot write '{path}': {reason}" + (f" ({name})" if name else "")


@contextlib.contextmanager
def storing(path):
    """Around every write of a run directory's or segment.py's files: an OSError is a StorageError naming `path`."""
    try:
        yield
    except OSError as e:
        raise StorageError(storage_message(path, e)) from None


class _WriteRecorder:
    """A file for torch.save that keeps the OSError of a failed write: torch turns it into 'inline_container.cc ...
    unexpected pos', which names neither the file nor the cause."""

    def __init__(self, f):
        self.f, self.error = f, None

    def write(self, data):
        try:
            return self.f.write(data)
        except OSError as e:
            self.error = e
            raise

    def flush(self):
        self.f.flush()


def torch_save(obj, f):
    import torch  # here: cli loads no torch at import
    recorder = _WriteRecorder(f)
    try:
        torch.save(obj, recorder)
    except RuntimeError:
        if recorder.error is not None:
            raise recorder.error from None
        raise


def write_atomically(path, write, mode="wb"):
    """write(f) into PATH.tmp, then rename it onto PATH: a kill or a storage error mid-write leaves the previous file
    whole and no .tmp behind; an OSError is a StorageError naming PATH."""
    tmp = path + ".tmp"
    try:
        with storing(path):
            with open(tmp, mode, **({} if "b" in mode else {"newline": ""})) as f:
                write(f)
            os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):  # after the rename there is nothing left to remove
            os.remove(tmp)


def first_sentence(text) -> str:
    """The first sentence of a message, on one line (torch's archive errors run on for 400 characters)."""
    text = " ".join(str(text).split())
    end = text.find(". ")
    sentence = text[: end + 1] if end >= 0 else text
    return sentence if not sentence or sentence.endswith((".", "!", "?")) else sentence + "."


# ------------------------------------------------------------------------------------------------ run directories
def parents(path):
    """The folders above path, nearest first, as given (relative stays relative)."""
    while os.path.dirname(path) not in ("", path):
        path = os.path.dirname(path)
        yield path


def check_run_root(run_root):
    """--run-root must be a folder this process can write, or one it can create (its nearest existing parent)."""
    existing = next(p for p in (run_root, *parents(run_root), ".") if os.path.lexists(p))
    if not os.path.isdir(existing):
        raise ConfigError(f"--run-root: '{run_root}' is a file, not a folder" if existing == run_root else
                          f"--run-root: cannot make '{run_root}': '{existing}' is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        read_only = os.statvfs(existing).f_flag & getattr(os, "ST_RDONLY", 0)
        raise ConfigError(f"--run-root: cannot write in '{existing}': "
                          + ("read-only file system" if read_only else "permission denied"))


def check_run_dir(run_dir, flag="--resume"):
    """A folder sear.py made (config.json or snapshot.pt in it), not a file, a typo or the folder of runs."""
    flag = f"{flag}: " if flag else ""
    if not os.path.exists(run_dir):
        raise ConfigError(f"{flag}no such run directory '{run_dir}'")
    if not os.path.isdir(run_dir):
        raise ConfigError(f"{flag}'{run_dir}' is a file, not a run directory")
    if not any(os.path.exists(os.path.join(run_dir, name)) for name in ("config.json", "snapshot.pt")):
        runs = []
        with contextlib.suppress(OSError):
            runs = sorted(d for d in os.listdir(run_dir) if os.path.isfile(os.path.join(run_dir, d, "config.json")))
        hint = (f"; it holds {len(runs)} run director{'y' if len(runs) == 1 else 'ies'}, e.g. "
                f"{os.path.join(run_dir, runs[0])}") if runs else ""
        raise ConfigError(f"{flag}'{run_dir}' is not a run directory (no config.json or snapshot.pt in it){hint}")


def check_run_config(run_dir):
    """--resume: config.json must be the JSON object the run wrote (plot.py and sweep.py read it); a broken one is not
    replaced silently: moved aside, the resumed run writes it again from the snapshot's copy."""
    path = os.path.join(run_dir, "config.json")
    if not os.path.lexists(path):
        return
    try:
        with open(path) as f:
            ok = isinstance(json.load(f), dict)
        reason = "not a JSON object"
    except (OSError, ValueError) as e:  # ValueError: JSONDecodeError, UnicodeDecodeError
        ok, reason = False, f"{type(e).__name__}: {first_sentence(getattr(e, 'strerror', None) or e).rstrip('.')}"
    if not ok:
        raise ConfigError(f"--resume: cannot read '{path}' ({reason}); snapshot.pt holds the run's config: move "
                          f"config.json aside and resume again to have it written from there")


# The owner's lock (experiment.take_lock takes it): an flock on this file, which holds "pid host".
LOCK_FILE = "run.lock"


def lock_holder(fd) -> str:
    """'sear.py process PID [on HOST]', as the owner wrote it right after taking the lock: a file still empty, or
    naming a dead process of this host (the previous owner's), is read again for up to 2 s."""
    for _ in range(40):
        pid, _, host = os.pread(fd, 256, 0).decode(errors="replace").strip().partition(" ")
        if pid.isdigit() and (host != socket.gethostname() or pid_alive(int(pid))):
            return f"sear.py process {pid}" + (f" on {host}" if host != socket.gethostname() else "")
        time.sleep(0.05)
    return "another sear.py process (pid unknown)"


def lock_owner(run_dir) -> str | None:
    """Who holds RUN_DIR's lock now (see lock_holder), or None; takes nothing and creates nothing."""
    try:
        import fcntl
        fd = os.open(os.path.join(run_dir, LOCK_FILE), os.O_RDONLY)
    except (ImportError, OSError):
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return None
    except OSError:
        return lock_holder(fd)
    finally:
        os.close(fd)  # also drops the shared lock, if it was taken


def pid_alive(pid) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def load_snapshot(run_dir, flag="--resume", mmap=False):
    """A run's snapshot.pt; every problem is a ConfigError naming `flag` (if any). mmap=True maps the tensors instead
    of reading them (--init-from reads a snapshot twice: its config, then its weights)."""
    import torch
    path = os.path.join(run_dir, "snapshot.pt")
    check_run_dir(run_dir, flag)
    flag = f"{flag}: " if flag else ""
    if not os.path.exists(path):
        owner = lock_owner(run_dir)
        if owner:
            raise ConfigError(f"{flag}'{run_dir}' is in use by {owner}, which has not written its first snapshot yet")
        raise ConfigError(f"{flag}'{run_dir}' has no snapshot.pt (the run stopped before its first snapshot; see "
                          f"--snapshot-minutes)")
    try:
        return torch.load(path, map_location="cpu", weights_only=False, mmap=mmap)
    except Exception as e:  # corrupt or foreign file: say so in one line
        reason = first_sentence(e)
        what = f"{type(e).__name__}" + (f": {reason}" if reason else "")
        if isinstance(e, EOFError) or "failed finding central directory" in str(e):  # a zip without its end
            raise ConfigError(f"{flag}'{path}' is cut short ({what.rstrip('.')}): sear.py writes a snapshot whole or "
                              f"not at all, so this is a copy or move that did not finish; copy snapshot.pt again "
                              f"from the run's original folder, where its last snapshot stands (this folder keeps "
                              f"no other)") from None
        raise ConfigError(f"{flag}cannot read '{path}': {what}")


def init_fields(cfg, init_parts: str) -> tuple[str, ...]:
    """The config fields that fix the shapes of the parts --init-parts copies: they must be the source run's."""
    fields = ("method", "latent_dim", "frame_stack")
    if init_parts != "encoder" and cfg.method == "curl":
        fields += ("feature_dim",)  # CURL's W and key read the critic's feature
    if init_parts == "all":
        fields += ("feature_dim", "hidden_dim")
    return fields


def inherit_from_source(cfg, run, explicit: set, Config) -> set:
    """--init-from: the fields that fix the shapes of the copied networks (init_fields) come from the source run's
    config; given explicitly, they must equal it. Returns the fields taken."""
    state = load_snapshot(run.init_from, "--init-from", mmap=True)
    source, defaults = state["config"], Config()
    run.init_from = os.path.abspath(run.init_from)  # config.json names the source from anywhere
    taken = set()
    if "method" not in explicit:  # first: which fields matter depends on the method
        cfg.method = source["method"]
        taken.add("method")
    for name in init_fields(cfg, run.init_parts):
        value = source.get(name, getattr(defaults, name))
        if name in explicit and getattr(cfg, name) != value:
            raise ConfigError(f"--init-from: the source run has {flag(name)} {value} but this run "
                              f"{getattr(cfg, name)}; --init-parts {run.init_parts} copies networks of that size "
                              f"(leave {flag(name)} out to take the source's)")
        if name not in explicit:
            setattr(cfg, name, value)
            taken.add(name)
    frame = state["counters"]["step"] * source.get("action_repeat", 1)
    print(f"init-from {run.init_from} ({source['env']}, frame {frame}): copies {run.init_parts}; "
          + ", ".join(f"{k}={getattr(cfg, k)}" for k in init_fields(cfg, run.init_parts)) + " as the source run")
    return taken
