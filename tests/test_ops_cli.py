"""`robion` and the service entry points on bad input: a message and an exit code, never a traceback."""

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.helpers import cluster_config, sigterm_after_line

ROOT = Path(__file__).resolve().parent.parent


def run(*argv: str, timeout: float = 120, **env) -> subprocess.CompletedProcess:
    import os

    return subprocess.run([sys.executable, "-m", *argv], capture_output=True, text=True, cwd=ROOT, timeout=timeout,
                          env={**os.environ, **env})


@pytest.mark.parametrize("argv", [
    ("shared.cli", "--log-level", "verbose", "models"),
    ("services.router.main", "-c", "configs/demo.yaml", "--log-level", "verbose"),
    ("services.controlplane.main", "-c", "configs/demo.yaml", "--log-level", "verbose"),
    ("services.fleet.main", "-c", "configs/demo.yaml", "--log-level", "verbose"),
])
def test_an_unknown_log_level_is_a_usage_error(argv):
    res = run(*argv)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "--log-level" in res.stderr and "verbose" in res.stderr, res.stderr


def test_a_bad_ROBION_LOG_LEVEL_is_a_usage_error():
    res = run("services.router.main", "-c", "configs/demo.yaml", ROBION_LOG_LEVEL="chatty")
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "chatty" in res.stderr, res.stderr


def test_log_levels_are_case_insensitive():
    from shared.service import log_level

    assert log_level("debug") == "DEBUG" and log_level("Warning") == "WARNING" and log_level("warn") == "WARN"


def test_ctl_apply_of_a_file_that_is_not_text(tmp_path):
    path, _ = cluster_config(tmp_path)
    binary = tmp_path / "weights.bin"
    binary.write_bytes(b"\x80\xd0\xff" * 100)
    res = run("shared.cli", "ctl", "apply", str(binary), "-c", str(path))
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert "robion ctl apply: cannot read" in res.stderr and str(binary) in res.stderr, res.stderr


@pytest.mark.parametrize("cmd", ["up", "demo"])
def test_a_service_that_fails_at_start_up_is_reported_without_traceback(tmp_path, cmd):
    path, data = cluster_config(tmp_path)
    data["models"][0]["weights"] = str(tmp_path / "missing.safetensors")  # both executors exit 2 while loading
    path.write_text(yaml.safe_dump(data))
    res = run("shared.cli", cmd, "-c", str(path), "--timeout", "90")
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert f"robion {cmd}: executor[" in res.stderr and "exited with code 2 during start-up" in res.stderr, res.stderr
    assert "weights file not found" in res.stderr  # the executor's own log line says why


def test_a_cluster_not_ready_in_time_is_reported_without_traceback(tmp_path):
    path, _ = cluster_config(tmp_path)
    res = run("shared.cli", "up", "-c", str(path), "--timeout", "0.2")
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert "robion up: cluster not ready within" in res.stderr, res.stderr


@pytest.mark.parametrize("argv, rc, expected", [
    (("plan", "--help"), 0, "usage: robion plan"),
    (("plan", "-h"), 0, "usage: robion plan"),
    (("bench", "--help"), 0, "bench/capacity.py"),
    (("bench",), 2, "bench/capacity.py"),
    (("bench", "solver", "--help"), 0, "usage:"),
])
def test_the_subcommands_that_take_their_own_options_show_their_help(argv, rc, expected):
    """`robion plan --help` was refused as an unrecognized argument, and `robion bench --help` asked for a name
    without saying which ones there are."""
    res = run("shared.cli", *argv)
    assert res.returncode == rc and expected in res.stdout + res.stderr, (res.returncode, res.stdout, res.stderr)
    assert "Traceback" not in res.stderr


def test_a_config_that_is_not_utf8_is_a_config_error(tmp_path):
    path, _ = cluster_config(tmp_path)
    path.write_bytes(b"# r\xe9glage usine\n" + path.read_bytes())  # a Latin-1 comment
    for argv in (("shared.cli", "up", "-c", str(path)), ("shared.cli", "plan", str(path)),
                 ("services.router.main", "-c", str(path))):
        res = run(*argv)
        assert res.returncode == 2 and "not a UTF-8 text file" in res.stderr, (argv, res.stderr[-2000:])
        assert "Traceback" not in res.stderr, res.stderr[-2000:]


def test_a_port_another_process_holds_is_named_and_exits_2(tmp_path):
    """A router or control plane whose port was taken died with zmq's traceback."""
    import zmq

    path, data = cluster_config(tmp_path)
    ctx = zmq.Context()
    held = [ctx.socket(zmq.ROUTER) for _ in range(2)]
    try:
        held[0].bind(data["router"]["bind"])
        held[1].bind(data["control"]["bind"])
        for module, key in (("services.router.main", "router.bind"), ("services.controlplane.main", "control.bind")):
            res = run(module, "-c", str(path))
            assert res.returncode == 2 and key in res.stderr and "cannot bind" in res.stderr, res.stderr[-2000:]
            assert "Traceback" not in res.stderr, res.stderr[-2000:]
    finally:
        ctx.destroy(0)


def test_a_stopped_demo_stops_its_fleet_and_cluster(tmp_path):
    """SIGTERM to `robion demo` left its fleet running against the stopped cluster, which then printed a report
    of requests nobody answered."""
    import os
    import signal

    from tests.helpers import wait_for
    from tests.test_up import children_of_config

    path, data = cluster_config(tmp_path)
    data["fleet"]["duration_s"] = 60
    path.write_text(yaml.safe_dump(data))
    proc = subprocess.Popen([sys.executable, "-m", "shared.cli", "demo", "-c", str(path)], cwd=ROOT, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        sigterm_after_line(proc, proc.stdout, "driving", 2.0)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode != 0 and "SLO-AT" not in out, (out, err[-2000:])
        assert "Traceback" not in err, err[-2000:]
        # The fleet and every service carry the config path on their command lines. (`pgrep -f "--parent-pid N"`
        # read the pattern as an option: it matched nothing whatever was left running.)
        assert wait_for(lambda: not children_of_config(path), 5), \
            f"processes of the demo still running: {children_of_config(path)}"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for pid in children_of_config(path):
            os.kill(pid, signal.SIGKILL)


def test_ctrl_c_at_a_terminal_stops_the_services_in_order(tmp_path):
    """A terminal's Ctrl-C reaches the whole foreground process group: every service stopped at once, and the
    executors could not withdraw through a router that was already gone. The services now run in sessions of
    their own, and `robion up` stops them in order, executors first."""
    import os
    import signal

    path, _ = cluster_config(tmp_path)
    proc = subprocess.Popen([sys.executable, "-m", "shared.cli", "--log-level", "INFO", "up", "-c", str(path)],
                            cwd=ROOT, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        for line in proc.stdout:
            if "robion is up" in line:
                break
        os.killpg(proc.pid, signal.SIGINT)  # what the terminal does on Ctrl-C
        out, err = proc.communicate(timeout=60)
        assert "withdrawn from routing" in err and "did not pick up" not in err, err[-3000:]
        assert "'router': 0" in out and "'control': 0" in out, out
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


class StandInPlane:
    """A ROUTER on the config's control address answering each message it reads with the next of ``answers``
    (kind, fields, delay before answering); what it was asked is in ``asked``."""

    def __init__(self, address: str, answers: list[tuple[str, dict, float]]):
        import threading

        import zmq

        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.ROUTER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.bind(address)
        self.asked: list[dict] = []
        self.thread = threading.Thread(target=self._serve, args=(answers,), daemon=True)
        self.thread.start()

    def _serve(self, answers) -> None:
        import time

        from shared import control

        for kind, fields, delay_s in answers:
            if not self.sock.poll(60_000):
                return
            peer, frame = self.sock.recv_multipart()
            self.asked.append(control.unpack(frame))
            time.sleep(delay_s)
            self.sock.send_multipart([peer, control.error(fields["code"], fields["message"]) if kind == "error"
                                      else control.pack(kind, **fields)])

    def close(self) -> None:
        self.thread.join(20)
        self.sock.close()
        self.ctx.term()


def test_ctl_waits_out_the_traffic_solve_the_plane_runs_before_its_answer(tmp_path):
    """The control plane re-solves the traffic plan before it answers a drain, for up to its
    control.solve_time_limit_s. `robion ctl` waited by the limit of its own file, so after an apply had raised the
    plane's limit it reported "does not answer" and exit 1 for a drain that had taken effect. The stand-in plane
    runs a limit of 8 s (the file says 1) and answers the drain after 12 s."""
    path, data = cluster_config(tmp_path)
    data["control"]["solve_time_limit_s"] = 1
    path.write_text(yaml.safe_dump(data))
    plane = StandInPlane(data["control"]["bind"], [("status", {"status": {"control": {"solve_time_limit_s": 8}}}, 0.0),
                                                    ("ok", {"version": 3}, 12.0)])
    try:
        res = run("shared.cli", "ctl", "drain", "ex0", "-c", str(path))
    finally:
        plane.close()
    assert [a["kind"] for a in plane.asked] == ["status", "drain"] and plane.asked[1]["executor"] == "ex0", plane.asked
    assert res.returncode == 0, res.stderr
    assert "drain ex0: routing table v3" in res.stdout, res.stdout


def test_ctl_drain_warns_of_the_models_it_leaves_without_a_host(tmp_path):
    path, data = cluster_config(tmp_path)
    plane = StandInPlane(data["control"]["bind"], [("status", {"status": {"control": {"solve_time_limit_s": 1}}}, 0.0),
                                                    ("ok", {"version": 4, "unrouted": ["toy-b"]}, 0.0)])
    try:
        res = run("shared.cli", "ctl", "drain", "ex0", "-c", str(path))
    finally:
        plane.close()
    assert res.returncode == 0 and "drain ex0: routing table v4" in res.stdout, res.stdout + res.stderr
    assert ("warning: no other executor serves toy-b: their requests are answered UNAVAILABLE until "
            "`robion ctl resume ex0`") in res.stderr, res.stderr


def test_ctl_reports_a_plane_that_does_not_answer_at_once(tmp_path):
    """Nothing at the control address: a drain waited out its whole answer time (10 s plus the solve limit)."""
    import time

    path, data = cluster_config(tmp_path)
    data["control"]["solve_time_limit_s"] = 30
    path.write_text(yaml.safe_dump(data))
    t0 = time.monotonic()
    res = run("shared.cli", "ctl", "drain", "ex0", "-c", str(path))
    assert res.returncode == 1 and "does not answer" in res.stderr, res.stderr
    assert time.monotonic() - t0 < 15


def test_ctl_status_prints_the_planes_error(tmp_path):
    """A plane that answers status with an error was reported as one that "does not answer"."""
    from shared.control import ControlError

    path, data = cluster_config(tmp_path)
    plane = StandInPlane(data["control"]["bind"],
                         [("error", {"code": ControlError.INTERNAL, "message": "status failed on the control plane"}, 0)])
    try:
        res = run("shared.cli", "ctl", "status", "-c", str(path))
    finally:
        plane.close()
    assert res.returncode == 1 and "status failed on the control plane" in res.stderr, res.stderr
    assert "does not answer" not in res.stderr


def test_the_solve_limit_of_an_applied_file_is_read_without_a_full_check():
    from shared.cli import applied_solve_limit

    assert applied_solve_limit("control: {solve_time_limit_s: 20}\nmodels: []\n") == 20.0
    assert applied_solve_limit("models: []\n") == 0.0
    assert applied_solve_limit("control: {solve_time_limit_s: true}") == 0.0
    # a limit the plane refuses (over an hour) is not waited for: the apply's answer is a quick error
    assert applied_solve_limit("control: {solve_time_limit_s: 3600}") == 3600.0
    assert applied_solve_limit("control: {solve_time_limit_s: 1.0e+9}") == 0.0
    assert applied_solve_limit("[1, 2") == 0.0 and applied_solve_limit("- a\n- b\n") == 0.0


def test_ctl_takes_its_options_between_the_action_and_its_target(tmp_path):
    """`robion ctl apply --no-wait new.yaml` exited 2 with "unrecognized arguments: new.yaml"."""
    path, _ = cluster_config(tmp_path)
    binary = tmp_path / "new.yaml"
    binary.write_bytes(b"\x80\xd0\xff")
    res = run("shared.cli", "ctl", "apply", "--no-wait", "--timeout", "5", str(binary), "-c", str(path))
    assert res.returncode == 2 and "robion ctl apply: cannot read" in res.stderr, res.stderr  # the file was taken
    res = run("shared.cli", "ctl", "drain", "-c", str(path), "ex0", "ex1")
    assert res.returncode == 2 and "unrecognized arguments: ex0 ex1" in res.stderr, res.stderr


def test_a_percent_sign_in_a_service_name_keeps_its_log_readable():
    """The service name goes into a %-style log format: an executor named `gpu%1` logged nothing but
    "--- Logging error ---" tracebacks."""
    code = ("import logging; from shared.service import setup_logging; setup_logging('executor[gpu%1]', 'INFO'); "
            "logging.getLogger('robion.executor').info('serving %s', 'pi0')")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert "Logging error" not in res.stderr, res.stderr
    assert "executor[gpu%1] INFO robion.executor: serving pi0" in res.stderr, res.stderr


def test_a_benchmarks_own_refusal_is_shown_by_robion_bench():
    """`robion bench capacity` without --models exited 1 silently: the script's SystemExit message was dropped."""
    res = run("shared.cli", "bench", "capacity", "--device", "cpu")
    assert res.returncode == 1 and "--models is required" in res.stderr, res.stderr


def test_an_installed_package_finds_the_demo_config_and_benchmarks_in_the_working_directory(tmp_path, monkeypatch):
    """`pip install .` (the image) puts the package in site-packages, without configs/ or bench/: `robion demo`
    without -c failed to read site-packages/configs/demo.yaml although the image has /app/configs."""
    import shutil

    from shared import cli

    site = tmp_path / "site" / "shared"
    site.mkdir(parents=True)
    work = tmp_path / "app"
    (work / "configs").mkdir(parents=True)
    shutil.copy(Path(cli.__file__).parent.parent / "configs" / "demo.yaml", work / "configs" / "demo.yaml")
    monkeypatch.setattr(cli, "__file__", str(site / "cli.py"))
    monkeypatch.chdir(work)
    assert cli.checkout_path("configs/demo.yaml") == work / "configs" / "demo.yaml"
    assert cli.checkout_path("bench/capacity.py") == tmp_path / "site" / "bench" / "capacity.py"  # named as missing


@pytest.mark.parametrize("argv", [("shared.cli", "demo"), ("services.fleet.main", "-c", "configs/demo.yaml")])
def test_a_report_file_that_cannot_be_written_is_refused_before_the_run(tmp_path, argv):
    """`robion demo --json` into a missing folder ran the whole demo, then the fleet ended in a traceback."""
    res = run(*argv, "--json", str(tmp_path / "missing" / "report.json"), timeout=60)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert "--json: cannot write" in res.stderr and "No such file or directory" in res.stderr, res.stderr
    assert "starting the cluster" not in res.stdout and not (tmp_path / "missing").exists()
