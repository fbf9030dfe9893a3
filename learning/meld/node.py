"""MELD's policy driving a rig over the bus (issue 25 item 4): an arm and its task-reset
mechanism, each through its driver node and the driver contract (:class:`ControllerNode`).

Per episode: the mechanism is commanded to the task's pose and the pose it measures is read
back (the task is set by the mechanism, as on the real bench); the arm is driven home by a
proportional joint-velocity loop; then the policy acts at its own rate (``hold`` driver
periods per action, 6 × 50 ms = 3.3 Hz on the WidowX) on the wall clock. Every driver period
the held action goes out again, tagged with the newest state, so the driver node's command
watchdog (a few periods) never fires while the policy thinks. At each policy step the belief is
updated with the newest image and reward and the actor gives the mean action (Algorithm 8);
the time of that inference is recorded.

What is robot-specific comes in as a callable ``observe(arm_state, mech_state) -> (image,
reward, info)`` (tools/meld_tasks.py: the bench rendered at the measured joint angles, since
the emulated rig has no camera stream; a real rig's camera node publishes ``keys.image``) and
the joint channels are the spec's ``<joint>_pos`` names (the driver contract's naming).

:func:`meld_rig` is the one bring-up of such a rig in this process (used by ``hil demo meld``'s
rig run and the node's test): the rig config's robots built through the registry, their driver
nodes on one server session (the rig's router, as ``hil up`` runs a one-bus rig), the controller
ready on the bus; everything stopped and closed on exit.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from hilstack.configs.schema import BusConfig
from hilstack.control.controller_node import ControllerNode

Observe = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, float, dict[str, Any]]]


class MeldRigController:
    def __init__(self, rig: str, agent: Any, observe: Observe, bus: BusConfig | None = None, arm: str = "arm",
                 mechanism: str = "mechanism", hold: int = 6, state_timeout_s: float = 5.0):
        if hold < 1:
            raise ValueError(f"MeldRigController.hold {hold}: must be ≥ 1 driver period per action")
        self.agent, self.observe, self.hold = agent, observe, hold
        self.arm = ControllerNode(rig, arm, bus, name="meld", handle_signals=False, state_timeout_s=state_timeout_s)
        self.mech = ControllerNode(rig, mechanism, bus, name="meld-mechanism", handle_signals=False,
                                   state_timeout_s=state_timeout_s)

    def __enter__(self) -> MeldRigController:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        for n in (self.arm, self.mech):
            n.close()

    def wait_ready(self, timeout_s: float = 30.0) -> None:
        spec = self.arm.wait_ready(timeout_s)
        self.mech.wait_ready(timeout_s)
        names = list(spec.state.names)
        self.q_idx = [i for i, n in enumerate(names) if n.endswith("_pos")]
        self.period_s = spec.period_s
        self.arm.next_state(timeout_s=timeout_s)
        self.mech.next_state(timeout_s=timeout_s)

    def _stop_action(self) -> np.ndarray:
        """What the arm's stop holds (the spec's safe action: zero joint velocity)."""
        spec = self.arm.spec
        if spec.safe_action is None:
            raise ValueError(f"{self.arm.robot}: the spec has no safe action; MELD's node drives velocity-controlled arms")
        return np.asarray(spec.safe_action, dtype=np.float64)

    # ------------------------------------------------------------------ the task and the start
    def set_task(self, target: np.ndarray, tol: np.ndarray, timeout_s: float = 5.0) -> np.ndarray:
        """Command the mechanism to ``target`` (its action units) on each of its states until the
        state it measures is within ``tol`` of it; returns the measured pose. A one-line
        TimeoutError if it does not get there."""
        target, tol = np.asarray(target, dtype=np.float64), np.asarray(tol, dtype=np.float64)
        s = self.mech.next_state()
        deadline = time.monotonic() + timeout_s
        while True:
            self.mech.send_action(target, s.seq)
            s = self.mech.next_state(after_seq=s.seq)
            pose = np.asarray(s.state[: len(target)])
            if s.ok and np.all(np.abs(pose - target) <= tol):
                return pose
            if time.monotonic() > deadline:
                raise TimeoutError(f"mechanism at {pose.round(4).tolist()} not within {tol.tolist()} of "
                                   f"{target.round(4).tolist()} after {timeout_s} s")

    def home(self, q_home: np.ndarray, gain: float = 2.0, tol_rad: float = 0.05, timeout_s: float = 10.0) -> float:
        """Drive the arm's joints to ``q_home`` with a proportional joint-velocity loop (the
        spec's limits clip it); returns the largest joint error left [rad]."""
        spec = self.arm.spec
        s = self.arm.next_state()
        deadline = time.monotonic() + timeout_s
        while True:
            err = np.asarray(q_home) - np.asarray(s.state)[self.q_idx]
            if np.max(np.abs(err)) < tol_rad or time.monotonic() > deadline:
                break
            self.arm.send_action(np.clip(gain * err, spec.action.low, spec.action.high), s.seq)
            s = self.arm.next_state(after_seq=s.seq)
        self.arm.send_action(self._stop_action(), s.seq)
        return float(np.max(np.abs(err)))

    # ------------------------------------------------------------------ the episode
    def episode(self, steps: int) -> dict[str, Any]:
        """``steps`` policy actions on the wall clock. Returns rewards, infos, inference times
        [s] and the policy period achieved [s]."""
        agent, arm = self.agent, self.arm
        agent.reset()
        s = arm.next_state()
        out: dict[str, Any] = {"rewards": [], "infos": [], "inference_s": [], "step_t": [], "actions": [], "commands": 0,
                               "held": [], "state_seq": []}
        for k in range(steps + 1):
            mech = self.mech._state.last
            img, r, info = self.observe(np.asarray(s.state)[self.q_idx], np.asarray(mech.state))
            out["rewards"].append(r), out["infos"].append(info), out["step_t"].append(time.monotonic())
            out["state_seq"].append(s.seq)
            if k > 0:  # what the driver reports holding at the end of the last action's hold
                out["held"].append(np.asarray(s.action, dtype=np.float64))
            if k == steps:
                break
            t0 = time.perf_counter()
            agent.observe(img, r)
            a = agent.act(deterministic=True)
            out["inference_s"].append(time.perf_counter() - t0)
            cmd = arm.spec.action.denormalize(np.clip(a, -1.0, 1.0))
            out["actions"].append(cmd)
            for _ in range(self.hold):  # one command per driver period: the watchdog stays fed
                arm.send_action(cmd, s.seq)
                out["commands"] += 1
                s = arm.next_state(after_seq=s.seq)
        arm.send_action(self._stop_action(), s.seq)
        out["policy_period_s"] = float(np.median(np.diff(out["step_t"]))) if steps else 0.0
        out["success"] = bool(out["infos"][-1].get("success", False))
        return out


@contextmanager
def meld_rig(rig: str, bus: BusConfig, agent: Any, observe: Observe, bus_name: str = "meld_rig",
             link_timeout_periods: int = 100, ready_timeout_s: float = 60.0, state_timeout_s: float = 30.0,
             **controller_kw: Any) -> Iterator[MeldRigController]:
    """Bring up the rig ``rig`` (a config in ``configs/rigs``: an arm and its task-reset mechanism)
    in this process and yield a :class:`MeldRigController` ready on it (specs and first states
    received). ``bus``: the rig's bus settings, its access control included and its credentials
    in place (tools/common.py: ``rig_bus`` + ``provision_credentials``).

    The robots come from the rig config through the registry (``make_driver``), with
    ``bus_name`` (the emulated device bus they share; one per live rig in a process) and
    ``link_timeout_periods`` over their params: an emulated link on 2 loaded cores can stall for
    seconds, so the default is generous (100 periods of 50 ms). Every wait is on a condition
    and bounded (``ready_timeout_s`` for the driver nodes' specs and first states,
    ``state_timeout_s`` for each state after). A driver node that fails is named in a one-line
    RuntimeError instead of the controller's timeout that follows from it. On exit the
    controller closes, the driver nodes stop (their robots stopped by their own exit path)
    and the session closes."""
    from hilstack.bus.session import open_session
    from hilstack.configs.schema import config_path, load_rig, rig_robot_config
    from hilstack.drivers.bridge import DriverNode
    from hilstack.drivers.registry import make_driver

    cfg = load_rig(config_path("rigs", rig))
    names = list(cfg.robots)
    drivers = {n: make_driver(rig_robot_config(cfg, n), bus_name=bus_name, link_timeout_periods=link_timeout_periods)
               for n in names}
    session = open_session(bus, server=True, rig=cfg.name, robots=names) if bus.access is not None else None
    extra = {"session": session} if session is not None else {}
    nodes: list[DriverNode] = []
    threads: list[threading.Thread] = []
    errors: dict[str, str] = {}

    def serve(node: DriverNode) -> None:
        try:
            node.serve()
        except Exception as e:  # noqa: BLE001 - its own error path stopped its robot; named below
            errors[node.robot] = f"{type(e).__name__}: {e}"

    try:
        for n, d in drivers.items():
            nodes.append(DriverNode(d, cfg.name, n, bus, watchdog_periods=cfg.watchdog_periods, pace=cfg.pace,
                                    handle_signals=False, **extra))
        for node in nodes:
            threads.append(threading.Thread(target=serve, args=(node,), daemon=True, name=f"driver-{node.robot}"))
            threads[-1].start()
        try:
            with MeldRigController(cfg.name, agent, observe, bus, state_timeout_s=state_timeout_s,
                                   **controller_kw) as ctl:
                deadline = time.monotonic() + ready_timeout_s
                while True:  # bounded; a driver node that died ends the wait at once (named below)
                    if errors:
                        raise TimeoutError("a driver node failed before the rig was ready")
                    try:
                        ctl.wait_ready(timeout_s=min(0.5, max(0.0, deadline - time.monotonic())))
                        break
                    except TimeoutError:
                        if time.monotonic() >= deadline:
                            raise
                yield ctl
        except Exception as e:
            if errors:
                raise RuntimeError(f"rig {cfg.name}: " + "; ".join(f"{r} failed: {m}" for r, m in errors.items())
                                   ) from e
            raise
    finally:
        for node in nodes:
            node.stop_event.set()
        for th in threads:
            th.join(30.0)
        for node in nodes:
            node.close()
        if session is not None:
            session.close()
