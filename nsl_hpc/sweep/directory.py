"""The sweep directory as a unit that cannot be hijacked, run twice or moved out from under its jobs.

- One command that changes a sweep (launch, resubmit, clean) at a time: ``sweep_lock`` holds an exclusive
  lock on ``<sweep_dir>/.lock``, which names its holder, for as long as the command runs (a local sweep: until
  its tasks end). The lock is the kernel's (flock): it goes with the process, however it ends; on a file system
  without flock it is a file created exclusively (``exclusive_lock``).
- Nobody but the owner can change what a sweep's jobs run: its control files (the submitit folder with the
  pickled job runners, ``launch.yaml``, ``run.yaml``, ``configs/``, the manifest) and its compile cache must not
  be writable by group or others, nor owned by another user (``check_control_files``, as ssh's StrictModes checks
  ~/.ssh; a job checks the compile cache again before it compiles). Commands create them so
  (``private_umask``).
- Paths inside the sweep directory are stored relative to it (``portable_paths``): a sweep can be moved or
  copied, and a command run from any directory, and its jobs still write into it.
"""

import contextlib
import copy
import errno
import fcntl
import getpass
import os
import re
import socket
import stat
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from nsl_hpc.core.errors import ConfigError
from nsl_hpc.sweep import layout

# the path keys of a launch config (portable_paths)
PATH_KEYS = (("out_dir",), ("cache_dir",), ("compile_cache_dir",), ("data_dir",), ("system", "source", "data_dir"))
SWEEP_DIR_REFERENCE = "${sweep_dir}"


def usable_sweep_dir(sweep_dir: str | os.PathLike) -> Path:
    """``sweep_dir`` created if needed, refused with one line when it cannot hold a sweep (a file, not
    writable, a read-only or pseudo file system)."""
    path = Path(sweep_dir)
    probe = path / f".write-test-{socket.gethostname()}-{os.getpid()}"
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe.touch()
        probe.unlink()
    except OSError as error:
        reason = "it is a file" if path.is_file() else error.strerror
        raise ConfigError(f"sweep_dir={str(path)!r} cannot hold a sweep ({reason}); choose a directory you can "
                          "write to") from None
    return path


NO_FLOCK = (errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOLCK, errno.EINVAL)  # a file system without flock (Lustre, NFS)


@contextlib.contextmanager
def sweep_lock(sweep_dir: Path, command: str) -> Iterator[None]:
    """Hold the sweep's lock while ``command`` changes it; refuse with one line naming the holder when another
    command holds it. Where the file system takes no flock, the lock is a file created exclusively
    (``exclusive_lock``)."""
    path = Path(sweep_dir) / layout.LOCK
    descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    holder = (f"{command} (pid {os.getpid()} on {socket.gethostname()}, since "
              f"{time.strftime('%Y-%m-%d %H:%M:%S')})\n").encode()
    try:
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
            exclusive: contextlib.AbstractContextManager[None] = contextlib.nullcontext()
        except BlockingIOError:
            raise refusal(sweep_dir, os.pread(descriptor, 1000, 0).decode(errors="replace")) from None
        except OSError as error:
            if error.errno not in NO_FLOCK:
                raise
            exclusive = exclusive_lock(Path(sweep_dir), holder)
        with exclusive:
            os.ftruncate(descriptor, 0)
            os.pwrite(descriptor, holder, 0)
            try:
                yield
            finally:
                os.ftruncate(descriptor, 0)
    finally:
        os.close(descriptor)  # releases the flock


@contextlib.contextmanager
def exclusive_lock(sweep_dir: Path, holder: bytes) -> Iterator[None]:
    """The sweep's lock without flock: ``<sweep_dir>/.lock.held``, created exclusively (atomic on NFS and Lustre)
    and removed at the end. A file left by a command of this host whose process is gone is taken over; one of
    another host's command is refused: only its user can tell it is gone (a lost node) and remove it."""
    path = Path(sweep_dir) / layout.LOCK_HELD
    for _ in range(2):
        try:
            descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            break
        except FileExistsError:
            text = path.read_text(errors="replace") if path.exists() else ""
            match = HOLDER.match(text)
            if match is None or match["host"] != socket.gethostname() or process_alive(int(match["pid"])):
                raise refusal(sweep_dir, text, f"; if it ended without removing {path} (a lost node), remove it") \
                    from None
            path.unlink(missing_ok=True)  # its holder, of this host, is gone
    else:
        raise refusal(sweep_dir, path.read_text(errors="replace"))
    try:
        os.write(descriptor, holder)
        os.close(descriptor)
        yield
    finally:
        path.unlink(missing_ok=True)


def refusal(sweep_dir: Path, holder: str, advice: str = "") -> ConfigError:
    """The one line that refuses a command while ``holder`` (its lock line) holds the sweep."""
    return ConfigError(f"sweep_dir={str(sweep_dir)!r} is in use by {holder.strip() or 'another command'}; wait for "
                       f"it to end (or stop it) and run again{advice}")


HOLDER = re.compile(r"^(?P<command>\S+) \(pid (?P<pid>\d+) on (?P<host>\S+), since")


def sweep_lock_holder(sweep_dir: Path) -> str | None:
    """The command that holds the sweep's lock now (``launch``, ``resubmit``, ``clean``; not this process), or
    None. Read from the line its holder writes (and empties when it ends), without taking the lock: a peek never
    refuses a launch."""
    try:
        match = HOLDER.match((Path(sweep_dir) / layout.LOCK).read_text())
    except OSError:
        return None
    here = match is not None and match["host"] == socket.gethostname()
    if match is None or (here and (int(match["pid"]) == os.getpid() or not process_alive(int(match["pid"])))):
        return None  # free, held by this process, or its holder was killed before it could empty the line
    return match["command"]


def launch_running(sweep_dir: Path) -> bool:
    """Whether another process's launch or resubmit runs the sweep now (its tasks without a row run later)."""
    return sweep_lock_holder(sweep_dir) in ("launch", "resubmit")


def process_alive(pid: int) -> bool:
    """Whether a process of this id exists (on this machine)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def check_control_files(sweep_dir: Path, compile_cache_dir: str | None, allow_shared: bool) -> None:
    """Refuse (one line) a sweep directory whose control files another user could change: anyone who can
    write a job runner pickle, ``launch.yaml`` (its ``launcher.setup`` lines run in every job), a task config or
    the compile cache ``compile_cache_dir`` (Inductor unpickles what it finds there) can run code as you when a
    job starts; ``allow_shared`` (``allow_shared_sweep_dir=true``) skips the check."""
    if (refusal := unsafe_refusal([*control_paths(Path(sweep_dir)), *tree(compile_cache(compile_cache_dir))],
                                  allow_shared)):
        raise ConfigError(refusal)


def unsafe_refusal(paths: Sequence[Path], allow_shared: bool) -> str | None:
    """The one line that refuses the first of ``paths`` another user could change, None when none is (or
    ``allow_shared``: ``allow_shared_sweep_dir=true``)."""
    if allow_shared:
        return None
    for path in paths:
        if (reason := unsafe(path)) is not None:
            fix = (f"ask its owner or root to `chown -R {getpass.getuser()} {path}`"
                   if reason.startswith("another user") else f"run `chmod -R go-w {path}`")
            return (f"{path} is not safe: {reason}, and whoever can change a sweep's control files or compile cache "
                    f"can run code as you in its jobs; {fix}, or pass allow_shared_sweep_dir=true if you trust "
                    "everyone who can write there")
    return None


def unsafe(path: Path) -> str | None:
    """Why another user could change ``path`` (owned by another user, writable by group or others), None when
    no one but its owner, this user, can (or it does not exist)."""
    try:
        info = path.lstat()
    except FileNotFoundError:
        return None
    writable = not stat.S_ISLNK(info.st_mode) and info.st_mode & (stat.S_IWGRP | stat.S_IWOTH)  # links: owner
    if info.st_uid == os.getuid() and not writable:
        return None
    who = "another user owns" if info.st_uid != os.getuid() else (
        "group and others can write" if info.st_mode & stat.S_IWOTH and info.st_mode & stat.S_IWGRP
        else "others can write" if info.st_mode & stat.S_IWOTH else "the group can write")
    return f"{who} it (mode {stat.filemode(info.st_mode)})"


def compile_cache(folder: str | None) -> Path | None:
    """The compile cache a sweep's jobs compile into (``compile_cache_dir``), None for torch's default."""
    return None if folder is None else Path(folder).resolve()


def tree(path: Path | None) -> Iterator[Path]:
    """``path`` and, a folder, everything in it (nothing when None)."""
    if path is None:
        return
    yield path
    if path.is_dir() and not path.is_symlink():
        yield from path.rglob("*")


def control_paths(sweep_dir: Path) -> Iterator[Path]:
    """The sweep directory, its control files and folders, and everything in those folders."""
    yield sweep_dir
    for name in layout.CONTROL:
        yield from tree(sweep_dir / name)


@contextlib.contextmanager
def private_umask() -> Iterator[None]:
    """Files and folders created meanwhile (by this process and the processes it starts, SLURM jobs included:
    sbatch passes the umask on) are not writable by group or others."""
    previous = os.umask(0)
    os.umask(previous | 0o022)
    try:
        yield
    finally:
        os.umask(previous)


def portable_paths(values: Mapping[str, Any], sweep_dir: Path) -> dict[str, Any]:
    """A resolved plain launch or task config with its paths made portable: inside ``sweep_dir`` as
    ``${sweep_dir}/...``, elsewhere absolute; ``sweep_dir`` itself is left to the reader (``???``)."""
    root = Path(sweep_dir).resolve()
    portable = copy.deepcopy(dict(values))
    portable["sweep_dir"] = "???"
    for keys in PATH_KEYS:
        parent: Any = portable
        for key in keys[:-1]:
            parent = parent.get(key) if isinstance(parent, Mapping) else None
        if not isinstance(parent, dict) or parent.get(keys[-1]) is None:
            continue
        path = Path(parent[keys[-1]]).resolve()
        if path == root or path.is_relative_to(root):
            relative = path.relative_to(root).as_posix()
            parent[keys[-1]] = SWEEP_DIR_REFERENCE + ("" if relative == "." else f"/{relative}")
        else:
            parent[keys[-1]] = str(path)
    return portable
