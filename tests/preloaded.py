"""``python -m nsl_hpc.<verb>`` for the tests, forked from a process that has imported the libraries every command
imports (torch, numpy, pyarrow, Hydra, submitit, matplotlib, MLflow), on which a fresh interpreter spends 1-4 s of
CPU (torch alone 2.2-2.8 s on this VM: a tiny local launch takes 1.3 s of CPU so, not 5).

Each command still runs as a process of its own, with its own arguments, working directory, environment, umask,
standard streams and exit status: a fork of the preloaded process runs the module as ``python -m`` would
(``runpy``), and Python's own exit ends it (atexit handlers, threads joined, streams flushed). nsl_hpc itself is
imported afresh by each command, after its environment is set. One preloaded process per test process (an xdist
worker), started on its first command, ended with it.

    python -m tests.preloaded FD    # the preloaded process: takes commands on the socket FD
"""

import io
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO

PRELOAD = ("torch", "numpy", "scipy.optimize", "scipy.stats", "pyarrow.parquet", "pyarrow.compute", "omegaconf",
           "hydra", "submitit", "matplotlib.pyplot", "mlflow.tracking", "tqdm")
MAX_REQUEST = 1 << 20  # bytes of one command's JSON (its environment, mostly)


# ----------------------------------------------------------------------------------------------- the test's side
_server: tuple[subprocess.Popen, socket.socket] | None = None


def _connection() -> socket.socket:
    """The control socket of this process's preloaded process, started on first use."""
    global _server
    if _server is None or _server[0].poll() is not None:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)  # a command per message
        process = subprocess.Popen([sys.executable, "-m", "tests.preloaded", str(theirs.fileno())],
                                   pass_fds=[theirs.fileno()], cwd=Path(__file__).parent.parent,
                                   stdin=subprocess.DEVNULL)
        theirs.close()
        _server = (process, ours)
    return _server[1]


def run(module: str, args: Sequence[str], timeout: float, cwd: Path | None = None, umask: int | None = None,
        env: Mapping[str, str] | None = None) -> subprocess.CompletedProcess:
    """``subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, ...)``, forked from
    the preloaded process, in ``cwd`` with ``umask`` and ``env`` (default: this process's); on ``timeout`` (s) the
    command is killed and ``subprocess.TimeoutExpired`` raised."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err, open(os.devnull, "rb") as null:
        ours, theirs = socket.socketpair()
        with ours, theirs:
            request = json.dumps(dict(module=module, argv=list(args), cwd=str(cwd or os.getcwd()),
                                      env=dict(os.environ if env is None else env),
                                      umask=_umask() if umask is None else umask)).encode()
            socket.send_fds(_connection(), [request], [null.fileno(), out.fileno(), err.fileno(), theirs.fileno()])
            theirs.close()
            pid = int(_line(ours))
            try:
                status = int(_line(ours, timeout))
            except TimeoutError:
                os.kill(pid, signal.SIGKILL)
                _line(ours)
                raise subprocess.TimeoutExpired([module, *args], timeout) from None
        return subprocess.CompletedProcess([sys.executable, "-m", module, *args], os.waitstatus_to_exitcode(status),
                                           _text(out), _text(err))


def _text(output: IO[bytes]) -> str:
    """What a command wrote, read as ``subprocess.run(..., text=True)`` reads it (locale encoding, newlines
    translated: a progress bar's carriage returns too)."""
    output.seek(0)
    return io.TextIOWrapper(output, newline=None).read()


def _umask() -> int:
    """This process's umask (reading it means setting it)."""
    current = os.umask(0o077)
    os.umask(current)
    return current


def _line(reply: socket.socket, timeout: float | None = None) -> str:
    """The next line the waiter replies (it replies the command's pid, then its wait status)."""
    reply.settimeout(timeout)
    line = b""
    while not line.endswith(b"\n"):
        chunk = reply.recv(1)  # a byte at a time: the status may follow the pid at once
        if not chunk:
            raise RuntimeError("the preloaded process ended before the command did: see the test's stderr")
        line += chunk
    return line.decode()


# ------------------------------------------------------------------------------------ the preloaded process's side
def _receive(control: socket.socket) -> tuple[dict, list[int]] | None:
    """The next command and its descriptors (stdin, stdout, stderr, its reply socket); None once the test ended."""
    request, fds, _, _ = socket.recv_fds(control, MAX_REQUEST, 4)
    if not request:
        return None
    return json.loads(request), fds


def _become(command: dict, stdin: int, stdout: int, stderr: int) -> None:
    """Turn this fork into ``python -m <module> <argv>``, run as the command asked; returns when the module has."""
    import runpy

    for target, fd in ((0, stdin), (1, stdout), (2, stderr)):
        os.dup2(fd, target)
        os.close(fd)
    # sys.stdin, stdout and stderr, which the preloaded process has not used, now read and write these
    os.chdir(command["cwd"])
    os.environ.clear()
    os.environ.update(command["env"])
    os.umask(command["umask"])
    sys.path[0] = command["cwd"]  # where `python -m` looks first
    sys.argv = [command["module"], *command["argv"]]
    runpy.run_module(command["module"], run_name="__main__", alter_sys=True)


def serve(control: socket.socket) -> None:
    """Fork a waiter per command, which forks the command, replies its pid, waits and replies its wait status."""
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # waiters are reaped by the kernel
    while (received := _receive(control)) is not None:
        command, (stdin, stdout, stderr, reply_fd) = received
        if os.fork() == 0:  # the waiter
            signal.signal(signal.SIGCHLD, signal.SIG_DFL)
            control.close()
            reply = socket.socket(fileno=reply_fd)
            pid = os.fork()
            if pid == 0:  # the command: from here on, an interpreter running a module, ended by Python's own exit
                reply.close()
                _become(command, stdin, stdout, stderr)
                sys.exit(0)
            for fd in (stdin, stdout, stderr):
                os.close(fd)
            reply.sendall(f"{pid}\n".encode())
            _, status = os.waitpid(pid, 0)
            reply.sendall(f"{status}\n".encode())
            os._exit(0)
        for fd in (stdin, stdout, stderr, reply_fd):
            os.close(fd)


if __name__ == "__main__":
    import gc
    import importlib
    import threading

    for name in PRELOAD:
        importlib.import_module(name)
    assert threading.active_count() == 1, "a preloaded library started a thread: forking it is not safe"
    gc.freeze()  # the collector of each command leaves the preloaded objects alone, as a fresh process has none
    serve(socket.socket(fileno=int(sys.argv[1])))
