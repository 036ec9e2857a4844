"""What `robion ctl apply` may change live (the rest is refused: it is read at start-up), and how a
rollout steps past an executor that leaves during its change."""

from services.controlplane.rollout import restart_only_changes
from shared.config import config_from_dict

BASE = {
    "models": [{"name": "a", "arch": "pi0", "robots": 4}, {"name": "b", "arch": "xr0", "robots": 2}],
    "executors": [{"name": "ex0", "models": ["a"]}, {"name": "ex1", "models": ["b"]}],
}


def cfg(**changes):
    data = {**BASE, **changes}
    return config_from_dict(data)


def test_placement_populations_and_strategy_are_live():
    old = cfg()
    new = cfg(models=[{"name": "a", "arch": "pi0", "robots": 9, "hz": 4}, {"name": "b", "arch": "xr0", "robots": 2}],
              executors=[{"name": "ex0", "models": ["a", "b"]}, {"name": "ex1", "models": ["b"]},
                         {"name": "ex2", "models": ["a"], "device": "cuda:1"}],
              control={"strategy": "eps", "solve_time_limit_s": 1.0, "headroom": 0.9})
    assert restart_only_changes(old, new) == []


def test_start_up_settings_are_named():
    old = cfg()
    new = cfg(engine={"kind": "robion", "max_batch": 4}, router={"request_timeout_s": 5.0},
              control={"heartbeat_s": 1.0, "limits": {"target": 0.95}},
              executors=[{"name": "ex0", "models": ["a"], "device": "cuda:0"}, {"name": "ex1", "models": ["b"]}])
    assert restart_only_changes(old, new) == [
        "engine.kind: 'auto' -> 'robion'", "engine.max_batch: 2 -> 4", "router.request_timeout_s: 30.0 -> 5.0",
        "control.heartbeat_s: 0.5 -> 1.0", "control.limits.target: 0.98 -> 0.95", "executors.ex0.device: 'cpu' -> 'cuda:0'"]



def _info():
    from shared.protocol import ModelInfo

    return ModelInfo.from_wire({"cameras": ["cam0"], "image_shape": [8, 8, 3], "state_dim": 4, "horizon": 2,
                                "action_dim": 2, "deadline_ms": 500.0, "arch": "pi0"})


def _state_with(names: list[str]):
    from services.controlplane.state import ClusterState

    c = cfg()
    st = ClusterState(c)
    for name in names:
        st.register(name, "cpu", {"a": _info()}, now=0.0, instance=f"{name}-1")
    return c, st


def test_an_executor_that_leaves_during_its_change_fails_the_step_without_the_full_timeout():
    from services.controlplane.rollout import Rollout, Step

    c, st = _state_with(["ex0", "ex1"])
    loads = []
    ro = Rollout([Step("ex0", [c.model("a"), c.model("b")]), Step("ex1", [c.model("b")])], timeout_s=600, gone_s=30)
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=1.0)  # ex0 drained
    st.router_version = st.table.version
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=2.0)  # the load goes out
    assert loads == ["ex0"] and ro.current.executor == "ex0"
    st.deregister("ex0")  # it dies while reloading
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=3.0)
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=20.0)
    assert ro.current.executor == "ex0"  # within the grace period: still waiting
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=34.0)
    assert ro.failed == ["ex0"] and ro.current.executor == "ex1"  # 31 s gone, not 600 s


def test_a_brief_absence_does_not_fail_the_step():
    from services.controlplane.rollout import Rollout, Step

    c, st = _state_with(["ex0"])
    ro = Rollout([Step("ex0", [c.model("a"), c.model("b")])], timeout_s=600, gone_s=30)
    ro.tick(st, lambda ex, models, load_id: None, now=1.0)
    info = st.executors["ex0"].models["a"]
    st.deregister("ex0")
    ro.tick(st, lambda ex, models, load_id: None, now=2.0)
    st.register("ex0", "cpu", {"a": info}, now=25.0)  # back before the grace period ends
    ro.tick(st, lambda ex, models, load_id: None, now=26.0)
    st.deregister("ex0")
    ro.tick(st, lambda ex, models, load_id: None, now=40.0)  # gone again: the count starts over
    ro.tick(st, lambda ex, models, load_id: None, now=60.0)
    assert ro.failed == [] and ro.current.executor == "ex0"


def test_a_brief_absence_before_the_step_starts_does_not_fail_it():
    """ex0 missed its heartbeats for a moment just as its step came up: the step was failed at once and ex0,
    back a second later, never got the load (its process unchanged, nothing reloads it later)."""
    from services.controlplane.rollout import Rollout, Step

    c, st = _state_with(["ex0", "ex1"])
    loads = []
    ro = Rollout([Step("ex0", [c.model("a"), c.model("b")])], timeout_s=600, gone_s=30)
    info = st.executors["ex0"].models["a"]
    st.deregister("ex0")
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=1.0)
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=20.0)
    assert ro.failed == [] and ro.current.executor == "ex0" and not ro.current.started
    st.register("ex0", "cpu", {"a": info}, now=21.0, instance="ex0-1")
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=22.0)  # drained
    st.router_version = st.table.version
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=23.0)
    assert loads == ["ex0"] and ro.failed == []


def test_an_executor_that_does_not_come_back_before_its_step_is_skipped_after_the_grace():
    from services.controlplane.rollout import Rollout, Step

    c, st = _state_with(["ex0", "ex1"])
    ro = Rollout([Step("ex0", [c.model("a")]), Step("ex1", [c.model("a"), c.model("b")])], timeout_s=600, gone_s=30)
    st.deregister("ex0")
    ro.tick(st, lambda ex, models, load_id: None, now=1.0)
    ro.tick(st, lambda ex, models, load_id: None, now=32.0)
    assert ro.failed == ["ex0"] and ro.current.executor == "ex1"


def test_an_executor_that_restarts_during_its_change_is_sent_the_load_again():
    from services.controlplane.rollout import Rollout, Step

    c, st = _state_with(["ex0"])
    loads = []
    ro = Rollout([Step("ex0", [c.model("a"), c.model("b")])], timeout_s=600, gone_s=30)

    def tick(now):
        ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=now)

    tick(1.0)
    st.router_version = st.table.version
    tick(2.0)
    assert loads == ["ex0"]
    # The same process re-registering its old set after it lost the control plane (it missed its
    # heartbeats and was told to register again): keep waiting, no second load.
    st.deregister("ex0")
    tick(2.5)
    st.register("ex0", "cpu", {"a": _info()}, now=3.0, instance="ex0-1")
    ro.on_register(st, "ex0", ["a"])
    st.router_version = st.table.version
    tick(4.0)
    assert loads == ["ex0"]
    # It crashes while loading, drops off the registry, and a new process registers its old set
    # (routed again, not draining): it is drained again, then loaded again.
    st.deregister("ex0")
    tick(4.5)
    st.register("ex0", "cpu", {"a": _info()}, now=5.0, instance="ex0-2")
    st.router_version = st.table.version  # the router has picked up the table that routes to it
    ro.on_register(st, "ex0", ["a"])
    assert st.executors["ex0"].draining
    tick(6.0)
    assert loads == ["ex0"]  # not before the router routes by the drained table
    st.router_version = st.table.version
    tick(7.0)
    assert loads == ["ex0", "ex0"] and ro.failed == [] and ro.current.executor == "ex0"
    ro.on_register(st, "ex0", ["a", "b"], {"id": ro.current.load_id, "ok": True})  # reloaded: the step is done
    assert ro.finished and ro.done_steps == ["ex0"] and not st.executors["ex0"].draining


def test_an_executor_whose_reload_fails_is_resumed_when_it_registers_its_previous_models():
    """The executor keeps its previous models when the new ones cannot be loaded and registers them
    again: the step fails then, not after its timeout, and the executor is routed again."""
    from services.controlplane.rollout import Rollout, Step

    c, st = _state_with(["ex0", "ex1"])
    loads = []
    ro = Rollout([Step("ex0", [c.model("a"), c.model("b")]), Step("ex1", [c.model("b")])], timeout_s=600, gone_s=30)
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=1.0)
    st.router_version = st.table.version
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=2.0)
    assert loads == ["ex0"] and st.executors["ex0"].draining
    st.register("ex0", "cpu", {"a": _info()}, now=3.0, instance="ex0-1")  # registered throughout
    ro.on_register(st, "ex0", ["a"], {"id": ro.current.load_id, "ok": False, "error": "OSError: no weights"})
    assert ro.failed == ["ex0"] and ro.current.executor == "ex1"
    assert not st.executors["ex0"].draining and st.table.routes["a"] == ["ex0", "ex1"]


def test_an_executor_back_from_an_absence_during_its_change_stays_out_of_routing():
    """An executor that missed its heartbeats is off the registry; when it registers again it is a new
    entry, not draining. Its step kept waiting with the executor routed again: before the load went out,
    the load was then sent while the router still sent it requests (answered UNAVAILABLE while it
    reloads); after, it was routed for the whole reload."""
    from services.controlplane.rollout import Rollout, Step

    for loaded in (False, True):
        c, st = _state_with(["ex0", "ex1"])
        loads = []
        ro = Rollout([Step("ex0", [c.model("a"), c.model("b")])], timeout_s=600, gone_s=30)

        def tick(now):
            ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=now)

        tick(1.0)
        if loaded:
            st.router_version = st.table.version
            tick(2.0)
            assert loads == ["ex0"]
        st.expire(now=st.executors["ex1"].last_seen + st.timeout_s + 1)  # both missed their heartbeats
        tick(3.0)
        st.register("ex1", "cpu", {"a": _info()}, instance="ex1-1")
        st.register("ex0", "cpu", {"a": _info()}, instance="ex0-1")  # the same process, told to reregister
        ro.on_register(st, "ex0", ["a"])
        st.router_version = st.table.version - 1  # the router has not fetched the table of that yet
        tick(4.0)
        assert st.executors["ex0"].draining and st.table.routes["a"] == ["ex1"], loaded
        assert loads == (["ex0"] if loaded else []), loaded  # no load while the router may still route to it
        st.router_version = st.table.version
        tick(5.0)
        assert loads == ["ex0"] and not ro.failed  # sent once the router routes around it
        ro.on_register(st, "ex0", ["a", "b"], {"id": ro.current.load_id, "ok": True})
        assert ro.finished and not st.executors["ex0"].draining


def test_a_step_that_times_out_leaves_an_operator_drained_executor_drained():
    """The step's timeout puts its executor back "as it is": an operator's drain is part of that."""
    from services.controlplane.rollout import Rollout, Step

    c, st = _state_with(["ex0", "ex1"])
    assert st.set_drained("ex0", True) and st.table.routes["a"] == ["ex1"]
    ro = Rollout([Step("ex0", [c.model("a"), c.model("b")])], timeout_s=600, gone_s=30)
    loads = []
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=1.0)
    st.router_version = st.table.version
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=2.0)
    assert loads == ["ex0"]
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=700.0)
    assert ro.failed == ["ex0"] and ro.finished
    assert st.table.routes["a"] == ["ex1"] and "ex0" in st.drained


def test_a_failed_reload_is_seen_after_an_absence_before_the_load():
    """The executor missed its heartbeats while the control plane waited for the router (before the load
    went out), came back, was drained again and sent the load; then its reload failed and it registered its
    previous models. It was registered throughout since the load, so that means the reload failed: the step
    fails at once. An absence before the load used to count, and the step waited out its 600 s timeout with
    the executor drained (every `apply` BUSY meanwhile)."""
    from services.controlplane.rollout import Rollout, Step

    c, st = _state_with(["ex0", "ex1"])
    loads = []
    ro = Rollout([Step("ex0", [c.model("a"), c.model("b")])], timeout_s=600, gone_s=30)

    def tick(now):
        ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=now)

    tick(1.0)  # drained; the router has not fetched that table yet
    st.deregister("ex0")  # missed its heartbeats
    tick(2.0)
    st.register("ex0", "cpu", {"a": _info()}, instance="ex0-1")  # the same process, told to reregister
    ro.on_register(st, "ex0", ["a"])
    st.router_version = st.table.version
    tick(3.0)
    assert loads == ["ex0"] and st.executors["ex0"].draining
    st.register("ex0", "cpu", {"a": _info()}, instance="ex0-1")  # its reload failed: the previous set again
    ro.on_register(st, "ex0", ["a"], {"id": ro.current.load_id, "ok": False})
    assert ro.failed == ["ex0"] and ro.finished
    assert not st.executors["ex0"].draining and st.table.routes["a"] == ["ex0", "ex1"]


def test_a_reload_is_judged_by_its_outcome_not_by_the_model_names():
    """The step ended when the executor registered the step's model names: a failed reload of new weights (or a
    new rate or deadline) registers the same names and counted as done; and an executor that lost the control
    plane while reloading re-registered its old names, then failed its reload, and the failure was missed (the
    step waited out its 600 s timeout, the executor drained and every apply BUSY). The registration after a
    reload now carries the outcome of the load it answers."""
    from services.controlplane.rollout import Rollout, Step

    for ok in (True, False):
        c, st = _state_with(["ex0", "ex1"])
        loads: list[str] = []
        ro = Rollout([Step("ex0", [c.model("a")])], timeout_s=600, gone_s=30)  # same names, new settings
        ro.tick(st, lambda ex, models, load_id: loads.append(load_id), now=1.0)
        st.router_version = st.table.version
        ro.tick(st, lambda ex, models, load_id: loads.append(load_id), now=2.0)
        assert len(loads) == 1 and st.executors["ex0"].draining
        # It misses its heartbeats while reloading and registers again, told to: same names, no outcome yet.
        st.deregister("ex0")
        ro.tick(st, lambda ex, models, load_id: loads.append(load_id), now=3.0)
        st.register("ex0", "cpu", {"a": _info()}, instance="ex0-1")
        ro.on_register(st, "ex0", ["a"], None)
        # An outcome of an earlier load (another step's) says nothing about this one.
        ro.on_register(st, "ex0", ["a"], {"id": "earlier", "ok": True})
        assert not ro.finished and st.executors["ex0"].draining and len(loads) == 1
        st.register("ex0", "cpu", {"a": _info()}, instance="ex0-1")
        ro.on_register(st, "ex0", ["a"], {"id": loads[0], "ok": ok, **({} if ok else {"error": "bad weights"})})
        assert ro.finished and not st.executors["ex0"].draining
        assert (ro.done_steps, ro.failed) == ((["ex0"], []) if ok else ([], ["ex0"]))


def _serving(placement: dict[str, list[str]]):
    from services.controlplane.state import ClusterState

    models = sorted({m for ms in placement.values() for m in ms})
    c = config_from_dict({"models": [{"name": m, "arch": "pi0"} for m in models],
                          "executors": [{"name": n, "models": ms} for n, ms in placement.items()]})
    st = ClusterState(c)
    for name, ms in placement.items():
        st.register(name, "cpu", {m: _info() for m in ms}, now=0.0, instance=f"{name}-1")
    return c, st


def _applied(c, placement: dict[str, list[str]]):
    data = {"models": [{"name": m.name, "arch": m.arch} for m in c.models],
            "executors": [{"name": n, "models": ms} for n, ms in placement.items()]}
    return config_from_dict(data)


def test_an_executor_that_is_a_models_only_host_reloads_after_another_serves_it():
    """a moves from ex0 to ex1 while ex2 changes too. By gains alone ex0 (which gains b) went first and drained
    a's only host: every request for a was answered UNAVAILABLE for the whole reload."""
    from services.controlplane.rollout import plan_steps

    c, st = _serving({"ex0": ["a"], "ex1": ["c"], "ex2": ["b", "c"]})
    new = _applied(c, {"ex0": ["b"], "ex1": ["a", "c"], "ex2": ["c"]})
    steps = plan_steps(c, new, st)
    assert [s.executor for s in steps] == ["ex1", "ex0", "ex2"]
    assert [s.unhosted for s in steps] == [[], [], []]


def test_a_swap_names_the_models_it_leaves_without_a_host():
    from services.controlplane.rollout import plan_steps

    c, st = _serving({"ex0": ["a"], "ex1": ["b"]})
    steps = plan_steps(c, _applied(c, {"ex0": ["b"], "ex1": ["a"]}), st)
    assert [(s.executor, s.unhosted) for s in steps] == [("ex0", ["a"]), ("ex1", [])]
    # With a third host of a, the swap keeps both models served.
    c, st = _serving({"ex0": ["a"], "ex1": ["b"], "ex2": ["a"]})
    steps = plan_steps(c, _applied(c, {"ex0": ["b"], "ex1": ["a"], "ex2": ["a"]}), st)
    assert [(s.executor, s.unhosted) for s in steps] == [("ex0", []), ("ex1", [])]


def test_a_replica_outside_the_config_is_reloaded_with_the_applied_settings_of_its_models():
    """A replica scaled out beside the config (docker-compose's `--scale executor=3`) kept serving a model's old
    weights or deadline after an apply changed them, beside executors on the new ones, and nothing said so. It keeps
    its model set; a model the apply removed is dropped; a change of other models leaves it alone."""
    from services.controlplane.rollout import plan_steps
    from shared.config import settings_digest

    c, st = _serving({"ex0": ["a", "b"]})
    st.register("replica-1", "cpu", {"a": _info(), "b": _info()}, now=0.0, instance="r-1",
                settings={m: settings_digest(c.model(m)) for m in ("a", "b")})
    data = {"models": [{"name": "a", "arch": "pi0", "slo_ms": 100}, {"name": "b", "arch": "pi0"}],
            "executors": [{"name": "ex0", "models": ["a", "b"]}]}
    steps = plan_steps(c, config_from_dict(data), st)
    assert sorted((s.executor, [m.name for m in s.models]) for s in steps) == [("ex0", ["a", "b"]),
                                                                               ("replica-1", ["a", "b"])]
    assert next(s for s in steps if s.executor == "replica-1").models[0].slo_ms == 100
    data = {"models": [{"name": "a", "arch": "pi0"}], "executors": [{"name": "ex0", "models": ["a"]}]}
    steps = plan_steps(c, config_from_dict(data), st)
    assert sorted((s.executor, [m.name for m in s.models]) for s in steps) == [("ex0", ["a"]), ("replica-1", ["a"])]
    data = {"models": [{"name": "a", "arch": "pi0"}, {"name": "b", "arch": "pi0"}, {"name": "c", "arch": "xr0"}],
            "executors": [{"name": "ex0", "models": ["a", "b"]}, {"name": "ex1", "models": ["c"]}]}
    assert [s.executor for s in plan_steps(c, config_from_dict(data), st)] == []


def test_a_model_the_apply_retires_does_not_hold_its_last_host_back():
    """b is retired: the new config defines only a. Its only host ex0 must still drop it. The step was skipped
    ("the only host of ['b'], which its placement change drops") when ex0 came back from a restart with its
    file's models (the reconcile's step names nothing unhosted), and whenever an operator had drained ex0, so
    the retired model came back into routing, or was never dropped, and the same apply failed every time."""
    from services.controlplane.rollout import Rollout, Step, plan_steps

    c, st = _serving({"ex0": ["a", "b"], "ex1": ["a"]})
    new = config_from_dict({"models": [{"name": "a", "arch": "pi0"}],
                            "executors": [{"name": "ex0", "models": ["a"]}, {"name": "ex1", "models": ["a"]}]})
    steps = plan_steps(c, new, st)
    assert [(s.executor, s.unhosted) for s in steps] == [("ex0", [])]  # b is retired, not left unhosted
    st.replace_config(new)
    # As _reconcile queues it for a restarted ex0: no model named unhosted.
    ro = Rollout([Step("ex0", [new.model("a")])])
    loads = []
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=1.0)
    assert ro.failed == [] and st.executors["ex0"].draining
    # An operator's drain of the only host: the plan counts it as serving nothing, and so does the step.
    c, st = _serving({"ex0": ["a", "b"], "ex1": ["a"]})
    st.set_drained("ex0", True)
    steps = plan_steps(c, new, st)
    st.replace_config(new)
    ro = Rollout(steps)
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=1.0)
    assert [s.executor for s in steps] == ["ex0"] and ro.failed == [] and ro.current.started


def test_a_model_the_apply_keeps_still_holds_its_last_host_back():
    """The check the retired model slipped through still guards a defined one: ex1 was to host b by now and
    did not, so ex0 keeps b rather than leave it with no host."""
    from services.controlplane.rollout import Rollout, Step

    c, st = _serving({"ex0": ["a", "b"], "ex1": ["a"]})
    ro = Rollout([Step("ex0", [c.model("a")])])
    ro.tick(st, lambda ex, models, load_id: None, now=1.0)
    assert ro.failed == ["ex0"] and not st.executors["ex0"].draining


def test_a_model_moved_to_a_host_that_is_not_running_keeps_its_old_host_until_the_new_one_serves():
    """b moves from ex1 to ex9, which is not started. ex1's step dropped b all the same (named only as unhosted
    "while ex1 reloads"), so b had no host until an operator started ex9, and the apply reported success."""
    from services.controlplane.rollout import Rollout, plan_steps

    c, st = _serving({"ex0": ["a"], "ex1": ["a", "b"]})
    new = _applied(c, {"ex0": ["a"], "ex1": ["a"], "ex9": ["b"]})
    steps = plan_steps(c, new, st)
    assert [(s.executor, s.unhosted, s.awaits) for s in steps] == [("ex1", [], ["b"])]
    st.replace_config(new)
    ro = Rollout(steps, host_wait_s=30.0)
    loads = []
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=1.0)
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=30.0)
    assert not ro.current.started and not st.executors["ex1"].draining and loads == []  # waiting, b still served
    ro.tick(st, lambda ex, models, load_id: loads.append(ex), now=31.5)
    assert ro.finished and ro.failed == ["ex1"] and not st.executors["ex1"].draining and loads == []
    assert "ex1" in st.table.routes["b"]

    # ex9 starts within the wait and serves b: ex1's step goes ahead.
    c, st = _serving({"ex0": ["a"], "ex1": ["a", "b"]})
    steps = plan_steps(c, new, st)
    st.replace_config(new)
    ro = Rollout(steps, host_wait_s=30.0)
    ro.tick(st, lambda ex, models, load_id: None, now=1.0)
    st.register("ex9", "cpu", {"b": _info()}, now=10.0, instance="ex9-1")
    ro.tick(st, lambda ex, models, load_id: None, now=10.0)
    assert ro.failed == [] and ro.current.started and st.executors["ex1"].draining
    assert st.table.routes["b"] == ["ex9"]


def test_a_model_moved_to_a_drained_host_waits_for_its_resume():
    from services.controlplane.rollout import Rollout, plan_steps

    c, st = _serving({"ex0": ["a"], "ex1": ["a", "b"]})
    st.set_drained("ex0", True)
    new = _applied(c, {"ex0": ["a", "b"], "ex1": ["a"]})
    steps = plan_steps(c, new, st)
    # a too has no other routed host while ex1 reloads (ex0 is drained), but ex1 keeps it
    assert [(s.executor, s.unhosted, s.awaits) for s in steps] == [("ex0", [], []), ("ex1", ["a"], ["b"])]
    # Not moved there, the swap of two single-hosted models is still only unhosted while it reloads.
    c2, st2 = _serving({"ex0": ["a"], "ex1": ["b"]})
    assert [(s.unhosted, s.awaits) for s in plan_steps(c2, _applied(c2, {"ex0": ["b"], "ex1": ["a"]}), st2)] == \
        [(["a"], []), ([], [])]
    st.replace_config(new)
    ro = Rollout(steps[1:], host_wait_s=30.0)  # ex0's reload done: it serves b, still drained
    st.register("ex0", "cpu", {"a": _info(), "b": _info()}, now=1.0, instance="ex0-1")
    ro.tick(st, lambda ex, models, load_id: None, now=1.0)
    assert not ro.current.started
    st.set_drained("ex0", False)
    ro.tick(st, lambda ex, models, load_id: None, now=5.0)
    assert ro.current.started and ro.failed == []


def _returning_host(before: dict[str, list[str]], after: dict[str, list[str]]):
    """ex0 is down while ``after`` is applied: ex1's step waits for ex0 to host what ex1 drops. ex0 then comes back
    with its file's models (a) and its reload to ``after`` is queued, as the control plane's _reconcile queues it."""
    from services.controlplane.rollout import Rollout, Step, plan_steps

    c, st = _serving(before)
    st.deregister("ex0")
    new = _applied(c, after)
    steps = plan_steps(c, new, st)
    assert [(s.executor, s.awaits) for s in steps] == [("ex1", ["b"])]
    st.replace_config(new)
    ro = Rollout(steps, host_wait_s=30.0)
    ro.tick(st, lambda ex, models, load_id: None, now=1.0)
    st.register("ex0", "cpu", {"a": _info()}, now=5.0, instance="ex0-2")
    ro.pending.append(Step("ex0", [new.model(m) for m in after["ex0"]]))
    ro.tick(st, lambda ex, models, load_id: None, now=5.0)
    return st, ro


def test_a_reload_queued_for_a_returning_host_goes_before_the_step_that_waits_for_it():
    """ex0 came back (restarted, reading its old file: only a) while ex1 waited for b's new host; the reconcile that
    would load b on ex0 was queued behind ex1's step, so the wait could only run out and the apply failed."""
    st, ro = _returning_host({"ex0": ["a"], "ex1": ["a", "b"]}, {"ex0": ["a", "b"], "ex1": ["a"]})
    assert [s.executor for s in ro.pending] == ["ex0", "ex1"] and ro.pending[1].waiting_since == 1.0
    ro.tick(st, lambda ex, models, load_id: None, now=5.5)
    assert ro.current.executor == "ex0" and ro.current.started and ro.failed == []


def test_a_returning_host_moved_ahead_in_a_swap_hands_its_model_over():
    """ex0 (a) and ex1 (b) swap while ex0 is down. ex1 waits for b's new host; ex0 comes back with a and its reload to
    b is moved ahead of the wait. It failed at once ("the only host of a"), and ex1 then waited out a fresh 300 s."""
    st, ro = _returning_host({"ex0": ["a"], "ex1": ["b"]}, {"ex0": ["b"], "ex1": ["a"]})
    assert [(s.executor, s.unhosted) for s in ro.pending] == [("ex0", ["a"]), ("ex1", [])]
    assert ro.pending[1].waiting_since == 1.0  # the wait keeps its clock
    ro.tick(st, lambda ex, models, load_id: None, now=5.5)
    assert ro.current.executor == "ex0" and ro.current.started and ro.failed == []
