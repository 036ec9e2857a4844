"""Rollouts (`robion ctl apply`) on a real cluster: what happens to an executor whose reload fails,
and which changes need no reload at all."""


import yaml

from shared.cluster import LocalCluster, control_request, control_status
from shared.config import load_config
from tests.helpers import cluster_config, wait_for


def apply_and_wait(address: str, new: dict, steps: list[str]) -> dict:
    """`apply` ``new`` (a config dict), check it reloads ``steps``, and return the status once its rollout ended."""
    reply = control_request(address, "apply", timeout_s=30, config=yaml.safe_dump(new))
    assert reply is not None and reply["kind"] == "applied" and reply["steps"] == steps, reply

    def finished():
        status = control_status(address, 5)
        rollout = status and status["rollout"]
        return status if rollout and not rollout["pending"] else None

    status = wait_for(finished, 60, poll_s=0.2)
    assert status is not None, control_status(address, 5)
    return status


def test_an_executor_that_cannot_load_its_new_models_is_put_back_at_once(tmp_path):
    """ex1 is told to add a model whose weights file is missing: it keeps serving its previous models and
    registers them again. The control plane left it drained (serving nothing) until the step's 600 s
    timeout, with every further `apply` refused BUSY; now the step fails as soon as it registers."""
    path, data = cluster_config(tmp_path)  # ex0: toy-a, toy-b; ex1: toy-a
    cfg = load_config(path)
    new = yaml.safe_load(path.read_text())
    new["models"].append({"name": "toy-c", "arch": "toy", "size": "tiny", "seed": 2, "slo_ms": 500,
                          "weights": str(tmp_path / "missing.safetensors")})
    new["executors"][1]["models"] = ["toy-a", "toy-c"]
    with LocalCluster(cfg, path, log_level="WARNING"):
        status = apply_and_wait(cfg.control.bind, new, ["ex1"])
        assert status["rollout"]["failed"] == ["ex1"] and status["rollout"]["done"] == []
        assert status["executors"]["ex1"]["models"] == ["toy-a"]
        assert not status["executors"]["ex1"]["draining"]
        assert status["table"]["routes"]["toy-a"] == ["ex0", "ex1"]


def test_new_weights_that_cannot_be_loaded_fail_their_steps(tmp_path):
    """A step ended when its executor registered the step's model names. New weights keep the names, and a
    reload that could not load them falls back to the old ones under the same names: the rollout reported
    both steps done while the old weights kept serving. The registration after a reload says how it went."""
    path, data = cluster_config(tmp_path)  # ex0: toy-a, toy-b; ex1: toy-a
    cfg = load_config(path)
    new = yaml.safe_load(path.read_text())
    new["models"][0]["weights"] = str(tmp_path / "missing.safetensors")
    with LocalCluster(cfg, path, log_level="WARNING"):
        # ex1 first: while it reloads ex0 serves toy-a; ex0 is toy-b's only host whenever it goes.
        status = apply_and_wait(cfg.control.bind, new, ["ex1", "ex0"])
        assert status["rollout"]["failed"] == ["ex1", "ex0"] and status["rollout"]["done"] == [], status["rollout"]
        assert not status["executors"]["ex0"]["draining"] and not status["executors"]["ex1"]["draining"]
        assert status["table"]["routes"]["toy-a"] == ["ex0", "ex1"]


def test_a_population_change_reloads_no_executor(tmp_path):
    """`robots` and `limit` are read by the traffic controller only; a change of them re-solves the quotas. It
    used to drain and reload every executor hosting the model in turn (engines rebuilt, minutes on a GPU)."""
    path, data = cluster_config(tmp_path)
    for m, robots in zip(data["models"], (4, 2)):
        m.update(robots=robots, limit=4)
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    new = yaml.safe_load(path.read_text())
    new["models"][0]["robots"] = 6
    with LocalCluster(cfg, path, log_level="WARNING"):
        before = control_status(cfg.control.bind, 5)
        assert {m: sum(q.values()) for m, q in before["table"]["quotas"].items()} == {"toy-a": 4, "toy-b": 2}
        reply = control_request(cfg.control.bind, "apply", timeout_s=30, config=yaml.safe_dump(new))
        assert reply is not None and reply["kind"] == "applied", reply
        assert reply["steps"] == []
        status = control_status(cfg.control.bind, 5)
        assert status["rollout"]["pending"] == [] and not any(e["draining"] for e in status["executors"].values())
        assert {m: sum(q.values()) for m, q in status["table"]["quotas"].items()} == {"toy-a": 6, "toy-b": 2}
        # A robot limit is read by the traffic controller only too (an executor measures none where one is given).
        new["models"][0]["limit"] = 6
        reply = control_request(cfg.control.bind, "apply", timeout_s=30, config=yaml.safe_dump(new))
        assert reply is not None and reply["kind"] == "applied" and reply["steps"] == [], reply
        assert control_status(cfg.control.bind, 5)["table"]["limits"]["toy-a"] == 6
        # A change the executors do need (the deadline they schedule by) still reloads the hosts.
        new["models"][1]["slo_ms"] = 400
        reply = control_request(cfg.control.bind, "apply", timeout_s=30, config=yaml.safe_dump(new))
        assert reply is not None and reply["kind"] == "applied" and reply["steps"] == ["ex0"], reply
        # ex0 is toy-b's only host: the answer names it as the model without a host during that reload.
        assert reply["unhosted"] == {"ex0": ["toy-b"]}, reply


def test_an_executor_restarted_after_an_apply_is_brought_to_the_applied_state(tmp_path):
    """A process loads the models of its own config file as it starts. After an apply, an executor that crashed
    and was restarted came back with the placement from before it, and nothing told it otherwise: the applied
    placement reverted for good while `ctl status` showed the rollout done."""
    import signal

    path, data = cluster_config(tmp_path)  # ex0: toy-a, toy-b; ex1: toy-a
    cfg = load_config(path)
    new = yaml.safe_load(path.read_text())
    new["executors"][1]["models"] = ["toy-a", "toy-b"]
    with LocalCluster(cfg, path, log_level="WARNING") as cluster:
        status = apply_and_wait(cfg.control.bind, new, ["ex1"])
        assert status["rollout"]["done"] == ["ex1"] and status["table"]["routes"]["toy-b"] == ["ex0", "ex1"]
        killed = status["executors"]["ex1"]["instance"]
        proc = cluster.procs["executor[ex1]"]
        proc.send_signal(signal.SIGKILL)  # a crash; its supervisor starts it again, from the same file
        proc.wait(10)
        cluster._spawn("executor[ex1]", "services.executor.main", "--name", "ex1")

        def applied_again():
            s = control_status(cfg.control.bind, 5)
            ex1 = s and s["executors"].get("ex1")
            return s if (ex1 and ex1["instance"] != killed and ex1["models"] == ["toy-a", "toy-b"]
                         and not ex1["draining"]) else None

        status = wait_for(applied_again, 60, poll_s=0.2)
        assert status is not None, control_status(cfg.control.bind, 5)
        assert status["table"]["routes"]["toy-b"] == ["ex0", "ex1"], status["table"]["routes"]
        assert status["rollout"]["done"] == ["ex1"] and status["rollout"]["failed"] == [], status["rollout"]


def test_a_model_whose_new_host_failed_to_load_it_keeps_its_old_host(tmp_path):
    """toy-b moves from ex0 to ex1 with weights ex1 cannot load. The plan ran ex1 first so toy-b would keep a host,
    then ex0's step dropped toy-b anyway: its only host was gone and every request for it was answered UNAVAILABLE
    until an operator stepped in. ex0's step now sees that nobody else serves toy-b and fails instead."""
    path, data = cluster_config(tmp_path)  # ex0: toy-a, toy-b; ex1: toy-a
    cfg = load_config(path)
    new = yaml.safe_load(path.read_text())
    new["models"][1]["weights"] = str(tmp_path / "typo.safetensors")
    new["executors"][0]["models"] = ["toy-a"]
    new["executors"][1]["models"] = ["toy-a", "toy-b"]
    with LocalCluster(cfg, path, log_level="WARNING"):
        status = apply_and_wait(cfg.control.bind, new, ["ex1", "ex0"])
        assert status["rollout"]["failed"] == ["ex1", "ex0"] and status["rollout"]["done"] == [], status["rollout"]
        assert status["executors"]["ex0"]["models"] == ["toy-a", "toy-b"]
        assert status["table"]["routes"]["toy-b"] == ["ex0"], status["table"]["routes"]
        assert not any(e["draining"] for e in status["executors"].values())


def test_applying_the_same_file_again_retries_the_executors_it_did_not_reach(tmp_path):
    """New weights for toy-a, whose file is not there yet: both steps fail and the executors keep the old weights.
    Once the file is in place, applying the same file again planned no step (it compared the file with the one
    before it, not with what the executors run) and reported success while the old weights kept serving."""
    from shared.models import build_model
    from shared.models.weights import save_weights

    path, data = cluster_config(tmp_path)  # ex0: toy-a, toy-b; ex1: toy-a
    cfg = load_config(path)
    weights = tmp_path / "toy-a-v2.safetensors"
    new = yaml.safe_load(path.read_text())
    new["models"][0]["weights"] = str(weights)
    with LocalCluster(cfg, path, log_level="WARNING"):
        status = apply_and_wait(cfg.control.bind, new, ["ex1", "ex0"])
        assert status["rollout"]["failed"] == ["ex1", "ex0"], status["rollout"]
        save_weights(build_model("toy", "tiny", seed=7), str(weights))
        status = apply_and_wait(cfg.control.bind, new, ["ex1", "ex0"])
        assert status["rollout"]["done"] == ["ex1", "ex0"] and status["rollout"]["failed"] == [], status["rollout"]
        # Everything runs the applied file now: a third apply of it has nothing to do.
        apply_and_wait(cfg.control.bind, new, [])
