"""The control plane keeps a traffic assignment through drains, odd limits and failed applies.

A real control plane runs on a loopback socket in a thread; executors are stood in for by the
register messages a real executor sends (the plane cannot tell the difference).
"""


import pytest
import yaml

import services.controlplane.state as state
from shared.cluster import control_request, control_status
from tests.helpers import TOY_INFO, cluster_config, start_control_plane

INFO = TOY_INFO


def models(a: dict, b: dict) -> list[dict]:
    return [{"name": "toy-a", "arch": "toy", "size": "tiny", "seed": 0, "slo_ms": 500, **a},
            {"name": "toy-b", "arch": "toy", "size": "tiny", "seed": 1, "slo_ms": 500, **b}]


def start_plane(tmp_path, **overrides):
    path, data = cluster_config(tmp_path, **overrides)
    cfg, stop, t = start_control_plane(path, data)
    return cfg.control.bind, data, stop, t


@pytest.fixture
def plane(tmp_path, request):
    address, data, stop, t = start_plane(tmp_path, **request.param)
    yield address, data, t
    stop.set()
    t.join(10)


def register(address: str, executor: str, names: list[str]) -> dict | None:
    return control_request(address, "register", timeout_s=5, executor=executor, device="cpu",
                           models={n: INFO for n in names})


@pytest.mark.parametrize("plane", [{"models": models({"robots": 4, "limit": 4}, {"robots": 2, "limit": 4})}],
                         indirect=True)
def test_draining_the_only_host_of_one_model_keeps_the_others_assignment(plane):
    address, _, _ = plane
    assert register(address, "ex0", ["toy-a", "toy-b"])["kind"] == "registered"
    assert register(address, "ex1", ["toy-a"])["kind"] == "registered"
    assert control_status(address, 5)["table"]["quotas"] == {"toy-a": {"ex1": 4}, "toy-b": {"ex0": 2}}
    # ex0 is toy-b's only host. toy-b's robots get UNAVAILABLE until it is back, but toy-a's
    # robots still have a solved place on ex1, not a round-robin spread.
    assert control_request(address, "drain", timeout_s=5, executor="ex0")["kind"] == "ok"
    table = control_status(address, 5)["table"]
    assert table["routes"] == {"toy-a": ["ex1"]}
    assert table["quotas"] == {"toy-a": {"ex1": 4}}
    assert table["limits"] == {"toy-a": 4, "toy-b": 4}
    assert control_request(address, "resume", timeout_s=5, executor="ex0")["kind"] == "ok"
    assert control_status(address, 5)["table"]["quotas"] == {"toy-a": {"ex1": 4}, "toy-b": {"ex0": 2}}


@pytest.mark.parametrize("plane", [{"models": models({"robots": 1, "limit": 2**31 - 1}, {"robots": 1, "limit": 2**31 - 2})},
                                   {"models": models({"robots": 2, "limit": 2**40}, {"robots": 3, "limit": 2**40})}],
                         indirect=True, ids=["lcm-too-large", "equal-large-limits"])
def test_large_robot_limits_do_not_break_registration(plane):
    """Limits the config accepts (any positive integer) must still give every robot a GPU."""
    address, data, t = plane
    population = {m["name"]: m["robots"] for m in data["models"]}
    reply = register(address, "ex0", ["toy-a", "toy-b"])
    assert reply is not None and reply["kind"] == "registered", reply
    table = control_status(address, 5)["table"]
    assert table["routes"] == {"toy-a": ["ex0"], "toy-b": ["ex0"]}
    assert table["quotas"] == {m: {"ex0": n} for m, n in population.items()}
    # A second host re-plans; losing it again re-plans too. The plane answers throughout.
    assert register(address, "ex1", ["toy-a"])["kind"] == "registered"
    assert {m: sum(q.values()) for m, q in control_status(address, 5)["table"]["quotas"].items()} == population
    control_request(address, "deregister", timeout_s=0.2, executor="ex1")
    assert control_status(address, 5)["table"]["quotas"] == {m: {"ex0": n} for m, n in population.items()}
    assert t.is_alive()


def test_solver_bounds_squares_by_robots_not_by_limits():
    from services.controlplane.solver import check_assignment, make_problem, solve

    # Two models sharing a GPU with a huge C_i but a handful of robots: a small problem.
    p = make_problem(2, [("a", 2**40, 2, None), ("b", 2**40, 3, [0])])
    res = solve(p, time_limit_s=5)
    assert res.feasible and res.optimal and res.objective == 0 and check_assignment(p, res.assignment) == []
    p = make_problem(1, [("a", 2**31, 3, None), ("b", 2**31, 1, None)])
    res = solve(p, time_limit_s=5)
    assert res.status == "optimal" and res.assignment == {"a": {0: 3}, "b": {0: 1}}, res.diagnosis
    # Squared robot counts past int64: not a TypeError from CP-SAT, but the greedy plan (exact arithmetic).
    p = make_problem(1, [("a", 2**40, 2**35, None), ("b", 2**40, 2**35, None)])
    res = solve(p, time_limit_s=5)
    assert res.feasible and res.source == "greedy" and check_assignment(p, res.assignment) == []


@pytest.mark.parametrize("plane", [{"models": models({"robots": 4, "limit": 4}, {"robots": 2, "limit": 4})}],
                         indirect=True)
def test_an_apply_that_fails_while_solving_changes_nothing(plane, monkeypatch):
    address, data, t = plane
    assert register(address, "ex0", ["toy-a", "toy-b"])["kind"] == "registered"
    before = control_status(address, 5)

    def broken(*args, **kwargs):
        raise RuntimeError("solver exploded")

    monkeypatch.setattr(state, "assign", broken)
    new = dict(data, models=models({"robots": 1, "limit": 8}, {"robots": 1, "limit": 8}))
    reply = control_request(address, "apply", timeout_s=10, config=yaml.safe_dump(new))
    assert reply is not None and reply["kind"] == "error" and "solver exploded" in reply["message"], reply
    monkeypatch.undo()
    after = control_status(address, 5)
    # The running config is still the desired state: its limits, table and (no) rollout.
    assert after["limits"] == before["limits"] == {"toy-a": 4, "toy-b": 4}
    assert after["table"] == before["table"] and after["rollout"] is None
    # A later re-plan (a new executor joins) still plans the old populations.
    assert register(address, "ex1", ["toy-a"])["kind"] == "registered"
    quotas = control_status(address, 5)["table"]["quotas"]
    assert {m: sum(q.values()) for m, q in quotas.items()} == {"toy-a": 4, "toy-b": 2}
    assert t.is_alive()


def test_a_model_without_a_robot_limit_leaves_the_others_planned():
    """One populated model with no limit (none configured, not measured yet, added by an apply) made
    ``assign`` return no quotas at all: every model's robots went round-robin per request."""
    from services.controlplane.state import ClusterState
    from services.controlplane.traffic import assign
    from shared.config import config_from_dict
    from shared.protocol import ModelInfo

    def cfg(b_limit):
        b = {"name": "B", "arch": "toy", "robots": 2, **({"limit": b_limit} if b_limit else {})}
        return config_from_dict({"models": [{"name": "A", "arch": "toy", "robots": 4, "limit": 4}, b],
                                 "executors": [{"name": "ex0", "models": ["A"]}, {"name": "ex1", "models": ["A", "B"]}]})

    placement = {"ex0": ["A"], "ex1": ["A", "B"]}
    assert assign(cfg(4), placement).robots["A"] == {"ex0": 4}
    q = assign(cfg(None), placement)
    assert set(q.robots) == {"A"} and sum(q.robots["A"].values()) == 4 and q.limits == {"A": 4}, q  # B: round-robin
    st = ClusterState(cfg(None))  # the same through the control plane's registry
    info = ModelInfo.from_wire(INFO)
    st.register("ex0", "cpu", {"A": info}, limits={}, instance="a")
    st.register("ex1", "cpu", {"A": info, "B": info}, limits={}, instance="b")
    assert set(st.table.quotas) == {"A"} and sum(st.table.quotas["A"].values()) == 4, st.table.quotas
    assert st.table.limits == {"A": 4}, st.table.limits
    st.register("ex1", "cpu", {"A": info, "B": info}, limits={"B": 3}, instance="b")  # B measured: planned too
    assert set(st.table.quotas) == {"A", "B"} and sum(st.table.quotas["B"].values()) == 2, st.table.quotas


def test_departed_replicas_leave_no_metric_series(tmp_path):
    """Every executor name ever seen kept its robion_executor_up and robion_robots_assigned series (at 0):
    docker-compose replicas register under container names that are new with every scale-out."""
    from services.controlplane.server import ControlPlane
    from shared.config import load_config
    from shared.protocol import ModelInfo

    path, data = cluster_config(tmp_path, models=models({"robots": 4, "limit": 4}, {}))
    data["control"]["metrics_port"] = 0
    path.write_text(yaml.safe_dump(data))
    plane = ControlPlane(load_config(path))
    try:
        info = ModelInfo.from_wire(INFO)
        for i in range(50):
            name = f"replica-{i:02x}"
            plane.state.register(name, "cpu", {"toy-a": info}, instance=name)
            plane._update_metrics()
            plane.state.deregister(name)
            plane._update_metrics()
        plane.state.register("ex0", "cpu", {"toy-a": info}, instance="x")
        plane._update_metrics()
        plane.state.deregister("ex0")
        plane._update_metrics()

        def samples(metric: str) -> dict:
            return {tuple(s.labels.values()): s.value for m in plane.metrics.registry.collect() if m.name == metric
                    for s in m.samples}

        # configured: still there, down (ex1 never registered)
        assert samples("robion_executor_up") == {("ex0",): 0.0, ("ex1",): 0.0}
        assert samples("robion_robots_assigned") == {("toy-a", "ex0"): 0.0, ("toy-a", "ex1"): 0.0}
        assert plane._published == {"ex0", "ex1"}
    finally:
        plane.sock.close(0)


def test_a_configured_executor_that_never_registered_reads_down(tmp_path):
    """Series were made only for executors that had registered with this control plane: one down since before
    a restart of the plane (or never started) had no robion_executor_up series, so an alert on == 0 never fired."""
    from services.controlplane.server import ControlPlane
    from shared.config import load_config
    from shared.protocol import ModelInfo

    path, data = cluster_config(tmp_path, models=models({"robots": 4, "limit": 4}, {}))
    data["control"]["metrics_port"] = 0
    path.write_text(yaml.safe_dump(data))
    plane = ControlPlane(load_config(path))
    try:
        plane.state.register("ex0", "cpu", {"toy-a": ModelInfo.from_wire(INFO)}, instance="x")
        plane._update_metrics()
        registry = plane.metrics.registry
        assert registry.get_sample_value("robion_executor_up", {"executor": "ex0"}) == 1.0
        assert registry.get_sample_value("robion_executor_up", {"executor": "ex1"}) == 0.0
        assert registry.get_sample_value("robion_robots_assigned", {"model": "toy-a", "gpu": "ex0"}) == 4.0
        assert registry.get_sample_value("robion_robots_assigned", {"model": "toy-a", "gpu": "ex1"}) == 0.0
    finally:
        plane.sock.close(0)


def test_an_apply_drops_measured_limits_of_models_whose_rate_or_deadline_changed():
    """The plane kept every limit an executor ever reported: after an apply that raised a model's rate it planned
    with the limit measured at the old rate (at 5x the rate, about 5x too many robots per GPU)."""
    import dataclasses

    from services.controlplane.state import ClusterState
    from shared.config import config_from_dict
    from shared.protocol import ModelInfo

    cfg = config_from_dict({"models": [{"name": "A", "arch": "toy", "robots": 4}, {"name": "B", "arch": "toy", "robots": 2}],
                            "executors": [{"name": "ex0", "models": ["A", "B"]}]})
    st = ClusterState(cfg)
    info = ModelInfo.from_wire(INFO)
    st.register("ex0", "cpu", {"A": info, "B": info}, limits={"A": 40, "B": 30}, instance="a")
    assert st.table.limits == {"A": 40, "B": 30}
    faster = dataclasses.replace(cfg, models=[dataclasses.replace(cfg.models[0], hz=10.0), cfg.models[1]])
    st.replace_config(faster)
    assert st.table.limits == {"B": 30}, st.table.limits  # A at 10 Hz: unmeasured until its executor says
    st.register("ex0", "cpu", {"A": info, "B": info}, limits={"A": 8, "B": 30}, instance="a")
    assert st.table.limits == {"A": 8, "B": 30}


def test_a_limit_reported_for_a_models_old_settings_is_not_taken_for_its_new_ones(caplog):
    """The apply dropped A's limit measured at 2 Hz, but an executor still on the old settings (restarted from its
    file, or registering again before its reload) reported it again, and the plane planned A at 10 Hz with it for
    good: the reload's registration, measured at 10 Hz or not yet, never took it away. A limit counts only from a
    registration whose settings of the model are the desired ones."""
    import dataclasses

    from services.controlplane.state import ClusterState
    from shared.config import config_from_dict, settings_digest
    from shared.protocol import ModelInfo

    cfg = config_from_dict({"models": [{"name": "A", "arch": "toy", "robots": 4}, {"name": "B", "arch": "toy", "robots": 2}],
                            "executors": [{"name": "ex0", "models": ["A", "B"]}]})
    info = ModelInfo.from_wire(INFO)
    st = ClusterState(cfg)
    old = {m.name: settings_digest(m) for m in cfg.models}
    st.register("ex0", "cpu", {"A": info, "B": info}, limits={"A": 40, "B": 30}, instance="a", settings=old)
    assert st.table.limits == {"A": 40, "B": 30}
    faster = dataclasses.replace(cfg, models=[dataclasses.replace(cfg.models[0], hz=10.0), cfg.models[1]])
    st.replace_config(faster)
    with caplog.at_level("WARNING", logger="robion.control"):
        st.register("ex0", "cpu", {"A": info, "B": info}, limits={"A": 40, "B": 30}, instance="b", settings=old)
    assert st.table.limits == {"B": 30}, st.table.limits
    assert "settings other than the desired ones, ignored: ['A']" in caplog.text
    new = {m.name: settings_digest(m) for m in faster.models}
    st.register("ex0", "cpu", {"A": info, "B": info}, limits={"A": 8, "B": 30}, instance="b", settings=new)
    assert st.table.limits == {"A": 8, "B": 30}


def _full_placement_config(limits: list[int], robots: list[int], executors: int, **control):
    from shared.config import config_from_dict

    names = [f"m{i}" for i in range(len(limits))]
    cfg = config_from_dict({"models": [{"name": n, "arch": "toy", "robots": r, "limit": c}
                                       for n, c, r in zip(names, limits, robots)],
                            "executors": [{"name": f"ex{j}", "models": names} for j in range(executors)],
                            **({"control": control} if control else {})})
    return cfg, {f"ex{j}": list(names) for j in range(executors)}


def test_a_solver_time_out_keeps_a_plan_within_the_gpu_limits():
    """48 executors x 32 models: the integer program timed out without a CP-SAT solution, the plane fell back
    to the even split and pushed a GPU to 105% of its limit, although the greedy plan fitted."""
    from services.controlplane.traffic import assign

    limits = [2 + i % 11 for i in range(32)]
    cfg, placement = _full_placement_config(limits, [int(c * 48 * 0.8 / 32) for c in limits], 48,
                                            solve_time_limit_s=2)
    q = assign(cfg, placement)
    assert q.result.strategy == "ip" and q.result.feasible, (q.result.strategy, q.result.diagnosis)
    assert max(q.result.gpu_load) <= 1
    assert {m: sum(per.values()) for m, per in q.robots.items()} == {m.name: m.robots for m in cfg.models}


def test_re_solving_an_unchanged_cluster_moves_no_robot(monkeypatch):
    """CP-SAT's parallel workers returned a different optimal plan on each solve: every re-plan of an
    unchanged cluster re-pinned about half the robots. Simulates an 8-core control-plane host."""
    import json
    import os

    from services.controlplane.traffic import assign

    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    cfg, placement = _full_placement_config([27, 16, 16, 9, 32, 22, 22, 12], [20, 10, 9, 5, 15, 8, 7, 3], 4)
    tables = {json.dumps(assign(cfg, placement).robots, sort_keys=True) for _ in range(4)}
    assert len(tables) == 1, tables


def test_the_control_plane_plans_what_robion_plan_prints_for_its_config():
    """Where plans tie, the GPU numbering decides. The control plane numbered GPUs in the order executors
    appeared in its routes, model by model, and `robion plan` in config order: for this config the plane
    put A's robots on ex2 and `robion plan` on ex1, though the docs say both print the same assignment."""
    from services.controlplane.planning import problem_from_cluster
    from services.controlplane.solver import solve
    from services.controlplane.state import ClusterState
    from shared.config import config_from_dict
    from shared.protocol import ModelInfo

    cfg = config_from_dict({
        "models": [{"name": "A", "arch": "toy", "robots": 2, "limit": 4}, {"name": "B", "arch": "toy"}],
        "executors": [{"name": "ex0", "models": ["B"]}, {"name": "ex1", "models": ["A"]},
                      {"name": "ex2", "models": ["A", "B"]}]})
    st = ClusterState(cfg)
    info = ModelInfo.from_wire(INFO)
    for ex in cfg.executors:
        st.register(ex.name, "cpu", {m: info for m in ex.models}, instance=ex.name)
    plan = solve(problem_from_cluster(cfg), cfg.control.strategy, time_limit_s=cfg.control.solve_time_limit_s)
    names = [e.name for e in cfg.executors]
    printed = {m: {names[j]: n for j, n in per_gpu.items() if n} for m, per_gpu in plan.assignment.items()}
    assert st.table.quotas == printed == {"A": {"ex1": 2}}, (st.table.quotas, printed)


def test_a_model_the_config_drops_leaves_no_robots_assigned_series(tmp_path):
    """An apply that removed toy-b kept robion_robots_assigned{model="toy-b"} at 0 for every configured executor."""
    from services.controlplane.server import ControlPlane
    from shared.config import config_from_dict, load_config
    from shared.protocol import ModelInfo

    path, data = cluster_config(tmp_path, models=models({"robots": 4, "limit": 4}, {"robots": 2, "limit": 4}))
    data["control"]["metrics_port"] = 0
    path.write_text(yaml.safe_dump(data))
    plane = ControlPlane(load_config(path))
    try:
        info = ModelInfo.from_wire(INFO)
        plane.state.register("ex0", "cpu", {"toy-a": info, "toy-b": info}, instance="x")
        plane._update_metrics()

        def assigned() -> set:
            return {tuple(s.labels.values()) for m in plane.metrics.registry.collect()
                    if m.name == "robion_robots_assigned" for s in m.samples}

        assert ("toy-b", "ex0") in assigned()
        data["models"] = data["models"][:1]
        for ex in data["executors"]:
            ex["models"] = ["toy-a"]
        plane.state.replace_config(config_from_dict(data))
        plane._update_metrics()
        assert {m for m, _ in assigned()} == {"toy-a"}
    finally:
        plane.sock.close(0)
