"""SIGTERM / SIGINT while a service is still starting: a clean exit 0, not death by the signal.

Start-up is slow (loading the config imports torch for the model registry: about a second), and
a launcher may stop a service at any time (``robion up`` failing or interrupted, ``docker stop``).
To hold the process in start-up deterministically, its config is a named pipe: the process blocks
reading it until the test writes the YAML, and the signal is sent while it waits.
"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.helpers import cluster_config

ROOT = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs named pipes")


def open_writer(fifo: Path, proc: subprocess.Popen, timeout_s: float = 20.0) -> int:
    """The write end of ``fifo``, once ``proc`` has opened it to read its config."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        try:
            return os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
        except OSError as exc:
            if exc.errno != errno.ENXIO:  # ENXIO: no reader yet
                raise
        assert proc.poll() is None, f"exited with {proc.returncode} before reading its config"
        time.sleep(0.005)
    raise AssertionError("the service never opened its config")


def signal_while_loading_config(tmp_path: Path, module: str, sig: signal.Signals, *extra: str) -> tuple[int, str]:
    path, _ = cluster_config(tmp_path)
    text = path.read_text()
    fifo = tmp_path / "cluster-fifo.yaml"
    os.mkfifo(fifo)
    proc = subprocess.Popen([sys.executable, "-m", module, "-c", str(fifo), "--log-level", "INFO", *extra],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True)
    try:
        fd = open_writer(fifo, proc)
        proc.send_signal(sig)  # while it reads its config: start-up has barely begun
        time.sleep(0.2)  # let the signal land before the config arrives
        try:
            os.write(fd, text.encode())
        except BrokenPipeError:
            pass  # it died of the signal: the return code says so
        finally:
            os.close(fd)
        _, err = proc.communicate(timeout=60)
        return proc.returncode, err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


SERVICES = {"router": ("services.router.main",), "control": ("services.controlplane.main",),
            # The executor goes on to load its models and start its engine, then sees the stop at once.
            "executor": ("services.executor.main", "--name", "ex1")}


@pytest.mark.parametrize("service", list(SERVICES))
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_service_stopped_during_start_up_exits_cleanly(tmp_path, service, sig):
    rc, err = signal_while_loading_config(tmp_path, *SERVICES[service][:1], sig, *SERVICES[service][1:])
    assert rc == 0, f"exit status {rc}\n{err[-3000:]}"
    assert f"signal {int(sig)}: shutting down" in err, err[-3000:]


def test_a_service_started_by_hand_under_a_running_launcher_stays_until_the_launcher_goes():
    """An executor restarted by hand under a running `robion up`, with the command line `ps` showed, is no child of
    the launcher: it took "not my parent" for "launcher gone" and shut down within a second."""
    import threading

    from shared.service import watch_parent

    launcher = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    gone, stop = threading.Event(), threading.Event()
    try:
        watch_parent(launcher.pid, gone.set, stop)
        assert not gone.wait(1.5)  # three checks: the launcher lives, though it is not our parent
        launcher.kill()
        launcher.wait()
        assert gone.wait(5)
    finally:
        stop.set()
        if launcher.poll() is None:
            launcher.kill()
