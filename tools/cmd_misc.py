"""hil up / estop / nodes / calibrate placeholder-free helpers."""

from __future__ import annotations

import logging
import math
import signal
import subprocess
import sys
import threading
import time

import typer

from hilstack.bus.lifetime import (
    DUMP_STACKS_SIGNAL,
    catch_stop_signals,
    child_env,
    exit_with_parent,
    stop_signalled,
)
from hilstack.tools.common import (
    EndpointOpt,
    UserError,
    complete_rig,
    echo_json,
    one_line,
    provision_credentials,
    rig_bus,
    setup_logging,
    user_errors,
)


def _up_line(node, cfg) -> str:  # noqa: ANN001 - a DriverNode, a RigConfig
    return f"{node.robot} up on hil/{cfg.name}/{node.robot}/{{state,cmd}} ({node.driver.backend}, {cfg.pace})"


def _tty_line(text: str) -> str:
    """``text`` starting on a cleared line when stderr is a terminal: a live status line (its
    own ``hil up``'s, or the parent's of a per-robot process) is drawn there without a newline."""
    return "\r\x1b[K" + text if sys.stderr.isatty() else text


def _announce_when_up(node, line: str) -> threading.Event:  # noqa: ANN001 - a DriverNode
    """Print ``line`` once the node's driver is configured and active (its link is open and
    answering), or configured and held stopped by a latched e-stop; never when it fails
    before. Set the returned event when ``serve`` has ended."""
    done = threading.Event()

    def watch() -> None:
        while not done.is_set():
            if node.driver.active or node.estopped:
                typer.echo(_tty_line(line + (" (rig e-stop engaged: stopped)" if node.estopped else "")), err=True)
                return
            done.wait(0.02)

    threading.Thread(target=watch, daemon=True, name=f"announce-{node.robot}").start()
    return done


def _up_together(cfg, names: list[str], bus, steps: int | None, sets: list[str] | None = None,
                 status: bool = False) -> None:
    """Several driver nodes in this process, one thread each (sims sharing one world);
    a signal stops them all. Exit 1 when one of them failed on its link, 2 when every failure
    was a config problem (a device port that does not exist: the one code, docs/platform.md)."""
    from hilstack.configs.schema import ConfigError, rig_robot_config
    from hilstack.drivers.bridge import DriverNode
    from hilstack.drivers.registry import make_driver

    session = None
    if bus.access is not None:  # one router for the rig (bus/session.py): its driver nodes share it
        from hilstack.bus.session import open_session

        session = open_session(bus, server=True, rig=cfg.name, robots=names)
    nodes: list[DriverNode] = []
    try:
        for n in names:
            try:
                drv = make_driver(rig_robot_config(cfg, n))
            except ConfigError as e:
                raise _rig_error(cfg, n, e, sets) from None
            nodes.append(DriverNode(drv, cfg.name, n, bus, watchdog_periods=cfg.watchdog_periods, pace=cfg.pace,
                                    handle_signals=False, **({"session": session} if session is not None else {})))
    except BaseException:
        for nd in nodes:
            nd.close()
        if session is not None:
            session.close()
        raise
    errors: list[str] = []
    config_errors: list[bool] = []
    stopping = threading.Event()  # a stop was asked for: what fails after it is the shutdown

    def serve(node: DriverNode) -> None:
        announced = _announce_when_up(node, _up_line(node, cfg))
        try:
            typer.echo(_tty_line(f"{node.robot} down: {node.serve(max_steps=steps)}"), err=True)
        except Exception as e:  # its own error path already stopped its robot
            if not stopping.is_set():
                e = _rig_error(cfg, node.robot, e, sets)
                errors.append(f"{node.robot}: {one_line(e)}")
                config_errors.append(isinstance(e, ConfigError))
        finally:
            announced.set()
            stopping.set()
            for other in nodes:  # one robot of a shared world down: the world is gone for all
                other.stop_event.set()

    def stop_all(signum, frame) -> None:  # noqa: ARG001
        stopping.set()
        for node in nodes:
            node.stop_event.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, stop_all)
    if stop_signalled():  # it came while the drivers loaded
        stop_all(signal.SIGTERM, None)
    threads = [threading.Thread(target=serve, args=(nd,), name=f"driver-{nd.robot}") for nd in nodes]
    for th in threads:
        th.start()
    line = StatusLine(lambda: nodes) if status else None
    try:
        for th in threads:
            th.join()
    finally:
        if line is not None:
            line.close()
        for nd in nodes:
            nd.close()
        if session is not None:
            session.close()
    if errors:
        typer.echo("error: " + "; ".join(errors), err=True)
        raise typer.Exit(2 if all(config_errors) else 1)


def _rig_error(cfg, name: str, e: Exception, sets: list[str] | None) -> Exception:  # noqa: ANN001 - a RigConfig
    """A robot's ConfigError raised while its driver is built or configured (a port that does
    not exist...), blamed on the rig file when the rig (or ``--set``/``--port``) set the value,
    and naming the ``--set`` items that changed the file; other errors as they are."""
    from hilstack.configs.schema import ConfigError, blame_rig, rig_robot_config

    if not isinstance(e, ConfigError):
        return e
    e = blame_rig(rig_robot_config(cfg, name), e)
    if sets and cfg.source and e.file == str(cfg.source):
        e = ConfigError(f"{cfg.source} with --set {' '.join(sets)}", e.problems)
    return e


def _device_sets(cfg, names: list[str], field: str, value: str | None) -> list[str]:  # noqa: ANN001 - a RigConfig
    """`hil up --port/--channel VALUE` as ``--set ROBOT.params.<field>=VALUE`` for the robots of
    ``names`` whose real driver has that field (a serial port, a CAN channel). Several such
    robots get it together only when the rig file gives them one device (the WidowX and its
    mechanism on one U2D2; or none yet); robots on different devices need --robot to say which."""
    if value is None:
        return []
    import json

    from hilstack.configs.schema import rig_robot_config
    from hilstack.drivers.registry import resolve

    has = []
    for n in names:
        rc = rig_robot_config(cfg, n)
        params = resolve(rc.robot, rc.backend).params_type  # declared on the contract (None: none)
        if rc.backend == "real" and params is not None and field in params.model_fields:
            has.append((n, rc.params.get(field)))
    if not has:
        kinds = ", ".join(f"{n}: {rig_robot_config(cfg, n).backend}" for n in names)
        raise UserError(f"--{field} {value}: rig {cfg.name} has no real robot with a {field} ({kinds}); "
                        f"emulated and sim robots open their own links")
    if len({str(v) for _, v in has if v is not None}) > 1:
        raise UserError(f"--{field} {value}: rig {cfg.name}'s robots {', '.join(n for n, _ in has)} are on "
                        f"different devices: pick one with --robot, or --set ROBOT.params.{field}=...")
    return [f"{n}.params.{field}={json.dumps(value)}" for n, _ in has]


class StatusLine:
    """`hil up`'s live status line: one line on stderr, redrawn every ``period_s``, a cell per
    robot from the newest state its driver node in this process published (``nodes()``: the
    nodes, once they exist): ok/STALE, active/stopped and why, the rate (states per second of
    the robot's clock over the last 2 s), the link counters and the overruns the driver node
    counts (the console's columns, tools/console.py). Sampled from the nodes, not the bus: a
    second Zenoh session in the process made 1 of 8 `hil up` runs abort at exit ("FATAL:
    exception not rethrown"). Nothing is drawn before the first state (the "up" lines first)."""

    #: how often the nodes' newest states are sampled (the rate is measured over RATE_WINDOW_S) [s]
    SAMPLE_S = 0.25
    RATE_WINDOW_S = 2.0

    def __init__(self, nodes, period_s: float = 1.0, out=None):  # noqa: ANN001 - () -> list[DriverNode]
        from collections import deque

        self.nodes = nodes
        self.out = out or sys.stderr
        self.period_s = period_s
        #: robot -> recent (monotonic, seq, t_s) samples of its newest state
        self._samples: dict[str, deque] = {}
        self._deque = deque
        self._stop = threading.Event()
        self._drawn = False
        self._thread = threading.Thread(target=self._loop, name="up-status", daemon=True)
        self._thread.start()

    def sample(self) -> None:
        now = time.monotonic()
        for node in self.nodes():
            st = node.last_state
            if st is None:
                continue
            q = self._samples.setdefault(node.robot, self._deque())
            if not q or q[-1][1] != st.seq:
                q.append((now, st.seq, st.t_s))
            while q and now - q[0][0] > self.RATE_WINDOW_S:
                q.popleft()

    def text(self) -> str:
        from hilstack.tools.console import LINK_KEYS, OVERRUN_KEYS, STALE_S, _fmt

        now = time.monotonic()
        cells = []
        for node in self.nodes():
            st = node.last_state
            q = self._samples.get(node.robot)
            if st is None or not q:
                continue
            if len(q) < 2 and now - q[0][0] < self.period_s:
                return ""  # its rate comes with the second sample: draw then (or after a period)
            flags = ["ok" if st.ok else "NOT OK"]
            if now - q[-1][0] > STALE_S:
                flags.append(f"STALE {now - q[-1][0]:.0f}s")
            flags.append("active" if st.active else "stopped")
            cell = f"{node.robot}: {' '.join(flags)}" + (f" ({st.stopped_reason})" if st.stopped_reason else "")
            if len(q) >= 2 and q[-1][2] > q[0][2]:  # states per second of the robot's clock
                cell += f" {(q[-1][1] - q[0][1]) / (q[-1][2] - q[0][2]):.1f} Hz"
            h = st.health or {}
            link = " ".join(f"{label}={_fmt(h[k])}" for k, label in LINK_KEYS.items() if k in h)
            over = " ".join(f"{k}={_fmt(h[k])}" for k in OVERRUN_KEYS if k in h and h[k])
            cells.append(cell + (f" {link}" if link else "") + (f" overruns {over}" if over else ""))
        return " | ".join(cells)

    def _loop(self) -> None:
        next_draw = 0.0
        while not self._stop.wait(self.SAMPLE_S):
            try:
                self.sample()
                if time.monotonic() < next_draw:
                    continue
                text = self.text()
                if not text:
                    continue
                self.out.write("\r" + text + "\x1b[K")
                self.out.flush()
                self._drawn = True
                next_draw = time.monotonic() + self.period_s
            except Exception:  # noqa: BLE001, S110 - a status line never stops the rig
                pass

    def close(self) -> None:
        """Stop drawing (idempotent); the line is left empty for what follows."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(2.0)
        if self._drawn:
            self.out.write("\r\x1b[K")
            self.out.flush()


def _bus_key(cfg, name: str) -> str | None:
    """The device bus a rig robot owns (its driver class's ``shared_bus_key``), or None."""
    from hilstack.configs.schema import rig_robot_config
    from hilstack.drivers.registry import resolve

    rc = rig_robot_config(cfg, name)
    return resolve(rc.robot, rc.backend).shared_bus_key(rc)


def _merge_shared_buses(groups: list[list[str]], keys: dict[str, str | None]) -> list[list[str]]:
    """Merge the process groups whose robots share a bus key."""
    out: list[list[str]] = []
    for g in groups:
        ks = {keys[n] for n in g} - {None}
        into = next((o for o in out if ks & ({keys[n] for n in o} - {None})), None)
        if into is None:
            out.append(list(g))
        else:
            into.extend(g)
    return out


log = logging.getLogger("hil")

#: how long `hil up` waits for a robot's node to stop its robot and exit after Ctrl-C/SIGTERM
#: before it dumps the node's stacks and kills it (its device's own watchdog then stops the robot)
STOP_GRACE_S = 10.0


def _run_robot_processes(procs: list, names: list[str], grace_s: float = STOP_GRACE_S) -> int:
    """Wait for `hil up`'s per-robot processes; Ctrl-C or SIGTERM is forwarded to each (every
    node stops its robot and exits). A node not gone ``grace_s`` after the signal is stuck: its
    stacks are dumped into the log (SIGUSR1, bus/lifetime.py) and it is killed, naming the
    robots; a stuck node cannot hold the rig's other robots or the operator hostage. Returns
    the rig's exit code: 0; a robot's node's own (1 link, 2 input); 1 for a killed node."""
    asked: list[float] = []  # when the first stop signal came
    forwarded: set[int] = set()  # signals a node may die of before it has its handlers

    def forward(signum, _frame):  # Ctrl-C, or a supervisor's SIGTERM: every robot's node stops its robot
        asked.append(time.monotonic())
        forwarded.add(-signum)
        for p in procs:
            if p.poll() is None:
                p.send_signal(signum)

    # installed explicitly: a `hil up` started in the background inherits SIGINT ignored
    before = {sig: signal.signal(sig, forward) for sig in (signal.SIGINT, signal.SIGTERM)}
    if stop_signalled():  # it came while the rig loaded, before the processes started
        forward(signal.SIGTERM, None)
    killed: list[str] = []
    try:
        while any(p.poll() is None for p in procs):
            time.sleep(0.1)
            if asked and time.monotonic() - asked[0] > grace_s:
                for p, n in zip(procs, names, strict=True):
                    if p.poll() is None:
                        log.error("robot %s: its node did not stop within %.0f s of the stop signal; its stacks "
                                  "follow, then it is killed (the device's own watchdog stops the robot)",
                                  n, grace_s)
                        p.send_signal(DUMP_STACKS_SIGNAL)
                        time.sleep(2.0)  # the dump is written when the node is next scheduled
                        p.kill()
                        p.wait()
                        killed.append(n)
    finally:
        for sig, h in before.items():
            signal.signal(sig, h)
    if killed:
        return 1
    # the rig failed if one robot's node did: its exit code (1 link, 2 input) is ours; a node
    # that died of the forwarded signal itself had not started its robot (no handlers yet)
    failed = [p.returncode for p in procs if p.returncode != 0 and p.returncode not in forwarded]
    codes = [c if c > 0 else 1 for c in failed]  # killed by another signal: a failure
    return (1 if 1 in codes else max(codes)) if codes else 0


def register(app: typer.Typer) -> None:
    @app.command()
    @user_errors
    def router(
        rig: str = typer.Argument(..., help="rig config name or path whose bus.router this router serves", autocompletion=complete_rig),
        tls_cert: str = typer.Option(None, "--tls-cert", help="TLS certificate (PEM) for tls/ endpoints"),
        tls_key: str = typer.Option(None, "--tls-key", help="its private key (PEM)"),
        tls_ca: str = typer.Option(None, "--tls-ca", help="CA (PEM) that signed the clients' certificates: mutual TLS"),
    ) -> None:
        """Run the rig's Zenoh router (bus.router): every node of the rig, on any host, is its client;
        with bus.access it authenticates them and applies the rig's ACL (docs/scaling.md)."""
        from pathlib import Path

        import zenoh

        from hilstack.bus.session import router_config

        setup_logging()
        _, bus, cfg = rig_bus(rig, None, need_config=True)
        if bus.router is None:
            raise UserError(f"rig {cfg.name}: bus.router is not set (the endpoint this router listens on)")
        if bool(tls_cert) != bool(tls_key):
            raise UserError("--tls-cert and --tls-key go together")
        tls = {"cert": tls_cert, "key": tls_key, "ca": tls_ca or ""} if tls_cert else None
        if tls is None and bus.router.startswith("tls/"):
            raise UserError(f"bus.router {bus.router} is a TLS endpoint: give --tls-cert and --tls-key")
        for f in (tls_cert, tls_key, tls_ca):
            if f and not Path(f).is_file():
                raise UserError(f"TLS file {f} does not exist")
        provision_credentials(cfg.name, bus, cfg)
        try:
            session = zenoh.open(router_config(bus, cfg.name, list(cfg.robots), tls))
        except Exception as e:  # zenoh.ZError: endpoint taken or unusable
            raise UserError(f"rig {cfg.name}: cannot listen on {bus.router}: {str(e).split(' at /')[0]}") from None
        stop = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
        who = f"access control for {', '.join(cfg.robots)}" if bus.access else "no access control"
        typer.echo(f"router of rig {cfg.name} on {bus.router} ({who}{', TLS' if tls else ''})", err=True)
        stop.wait()
        session.close()

    @app.command()
    @user_errors
    def up(
        rig: str = typer.Argument(..., help="rig config name or path (configs/rigs/)", autocompletion=complete_rig),
        robot: str = typer.Option(None, "--robot", help="only this robot of the rig, or several: a,b (default: all)"),
        steps: int = typer.Option(None, "--steps", help="stop after this many control periods"),
        endpoint: str = EndpointOpt,
        sets: list[str] = typer.Option(None, "--set", metavar="KEY=VALUE",
                                       help="override a value of the rig file, checked like the file: "
                                            "watchdog_periods=5, roach.params.port=/dev/ttyUSB1 (repeatable)"),
        port: str = typer.Option(None, "--port", help="the serial port of the rig's real robot that has one "
                                 "(--robot picks among several): --set ROBOT.params.port=PORT"),
        channel: str = typer.Option(None, "--channel", help="the CAN channel of the rig's real robot that has one "
                                    "(can0, or an slcan adapter's /dev/ttyACM0): --set ROBOT.params.channel=CHANNEL"),
        status: bool = typer.Option(None, "--status/--no-status", help="a live status line per robot on stderr "
                                    "(state, rate, link counters, overruns), refreshed every second "
                                    "(default: when stderr is a terminal)"),
    ) -> None:
        """Bring a rig's robots onto the bus (one driver bridge node per robot)."""
        from hilstack.configs.schema import ConfigError, rig_robot_config
        from hilstack.drivers.bridge import DriverNode
        from hilstack.drivers.registry import make_driver

        catch_stop_signals()  # first: a stop that comes while the drivers load is kept (bus/lifetime.py)
        if steps is not None and steps < 1:
            raise UserError(f"--steps {steps}: expected a number of control periods >= 1")
        setup_logging()
        exit_with_parent()
        _, bus, cfg = rig_bus(rig, endpoint, need_config=True, sets=sets)
        names = robot.split(",") if robot else list(cfg.robots)
        for n in names:
            if n not in cfg.robots:
                raise UserError(f"rig {cfg.name} has no robot {n!r}; has {list(cfg.robots)}")
        extra = [*_device_sets(cfg, names, "port", port), *_device_sets(cfg, names, "channel", channel)]
        if extra:  # the same path as --set: the rig's and the robot's schemas check the value
            sets = [*(sets or []), *extra]
            _, bus, cfg = rig_bus(rig, endpoint, need_config=True, sets=sets)
        provision_credentials(cfg.name, bus, cfg)
        groups = [[n] for n in names]
        if len(names) > 1 and bus.access is not None:
            # the rig's driver nodes are its one Zenoh router (bus/session.py): one process
            groups = [names]
        elif len(names) > 1:
            # one process per robot: a slow or failing driver cannot stall another; except a
            # sim that works in another sim's world (the hand's reset arm in the hand's
            # scene): the rig's sim robots then run together, in one process
            from hilstack.drivers.registry import resolve

            sims = [n for n in names if cfg.robots[n].backend == "sim"]
            if any(resolve(rig_robot_config(cfg, n).robot, "sim").follower is not None for n in sims):
                groups = [sims] + [[n] for n in names if n not in sims]
            # robots on one device bus (the WidowX and its mechanism on one Dynamixel adapter)
            # share one process: only that process may own the port (drivers/dynamixel/bus.py)
            groups = _merge_shared_buses(groups, {n: _bus_key(cfg, n) for n in names})
        if status is None:
            status = sys.stderr.isatty()
        if len(groups) > 1:
            procs = []
            for g in groups:
                # no status line: several processes would overwrite each other's one line
                cmd = [sys.executable, "-m", "hilstack.tools.cli", "up", rig, "--robot", ",".join(g), "--no-status"]
                if steps:
                    cmd += ["--steps", str(steps)]
                if endpoint:
                    cmd += ["--endpoint", endpoint]
                for x in sets or []:
                    cmd += ["--set", x]
                procs.append(subprocess.Popen(cmd, env=child_env()))

            raise typer.Exit(_run_robot_processes(procs, [",".join(g) for g in groups]))
        if len(names) > 1:
            _up_together(cfg, names, bus, steps, sets, status)
            return
        n = names[0]
        try:
            drv = make_driver(rig_robot_config(cfg, n))
        except ConfigError as e:
            raise _rig_error(cfg, n, e, sets) from None
        node = DriverNode(drv, cfg.name, n, bus, watchdog_periods=cfg.watchdog_periods, pace=cfg.pace)
        announced = _announce_when_up(node, _up_line(node, cfg))
        line = StatusLine(lambda: [node]) if status else None
        try:
            stats = node.serve(max_steps=steps)
        except ConfigError as e:  # found when the driver configured: a device port that does not exist...
            raise _rig_error(cfg, n, e, sets) from None
        finally:
            if line is not None:
                line.close()
            announced.set()
            node.close()
        typer.echo(_tty_line(f"{n} down: {stats}"), err=True)
        if node.cycle is not None:
            typer.echo(f"{n} timing: {node.cycle.format_summary()}", err=True)

    @app.command()
    @user_errors
    def estop(
        rig: str = typer.Argument(..., help="rig config name or file (its bus settings are used), or a rig name", autocompletion=complete_rig),
        release: bool = typer.Option(False, "--release", help="release a latched e-stop (in this user's name)"),
        reason: str = typer.Option("operator", "--reason"),
        timeout_s: float = typer.Option(
            2.0, "--timeout-s", help="how long to wait for every driver node's acknowledgement [s]"
        ),
        endpoint: str = EndpointOpt,
    ) -> None:
        """Engage (latched) or release the rig's e-stop; waits for every driver node to acknowledge.

        Exit 0: every driver node alive on the rig acknowledged (an engage: with its device's
        confirmation of the stop). Exit 1: none did, or some did not, or some device did not
        confirm its stop, within --timeout-s (the message names the rig and the nodes).
        """
        from hilstack.bus.estop import command_estop
        from hilstack.bus.node import Node

        if not (math.isfinite(timeout_s) and 0 < timeout_s <= 60):
            raise UserError(f"--timeout-s {timeout_s}: expected a number in (0, 60]")
        rig, bus, _ = rig_bus(rig, endpoint)
        if release and bus.access is not None:
            from hilstack.bus.access import user_of

            if user_of(bus.access) not in bus.access.release:
                raise UserError(f"user {user_of(bus.access)!r} may not release rig {rig}'s e-stop "
                                f"(bus.access.release: {bus.access.release})")
        node = Node("estop-cli", rig, bus, handle_signals=False)
        try:
            res = command_estop(node, engaged=not release, reason=reason, timeout_s=timeout_s)
        finally:
            node.close()
        what = "release" if release else "e-stop"
        if res.ok:
            state = "released" if release else "ENGAGED"
            by = f" (released by {node.user})" if release else ""
            typer.echo(f"{state} e-stop on rig {rig}: acknowledged by {', '.join(res.confirmed)}{by}", err=True)
            return
        if res.details:
            typer.echo(f"error: {what} on rig {rig} NOT acknowledged as asked: {'; '.join(res.details)}", err=True)
            raise typer.Exit(1)
        if res.unconfirmed:
            typer.echo(
                f"error: e-stop on rig {rig} acknowledged but the stop was NOT confirmed by the device of "
                f"{', '.join(res.unconfirmed)} within {timeout_s:g} s: check that robot, cut its power if it moves"
                + (f"; not acknowledged by {', '.join(res.missing)}" if res.missing else ""),
                err=True,
            )
        elif not res.confirmed:
            typer.echo(
                f"error: {what} on rig {rig} NOT acknowledged: no driver node answered within {timeout_s:g} s"
                + (f" (alive but silent: {', '.join(res.missing)})" if res.missing else " (no driver node alive)"),
                err=True,
            )
        else:
            typer.echo(
                f"error: {what} on rig {rig} acknowledged by {', '.join(res.confirmed)} but NOT by "
                f"{', '.join(res.missing)} within {timeout_s:g} s",
                err=True,
            )
        raise typer.Exit(1)

    @app.command()
    @user_errors
    def nodes(
        rig: str = typer.Argument(..., help="rig config name or file (its bus settings are used), or a rig name", autocompletion=complete_rig),
        json_out: bool = typer.Option(False, "--json"),
        endpoint: str = EndpointOpt,
    ) -> None:
        """List the nodes alive on a rig (liveliness tokens) and the e-stop each one holds."""
        from hilstack.bus.estop import query_latches
        from hilstack.bus.node import Node, alive_nodes

        rig, bus, _ = rig_bus(rig, endpoint)
        node = Node("nodes-cli", rig, bus, handle_signals=False)
        try:
            # a fresh session finds its peers over the first few hundred ms: keep asking
            names = [n for n in alive_nodes(node.session, rig, window_s=0.5) if n != "nodes-cli"]
            latches = query_latches(node.session, rig)
        finally:
            node.close()
        rows = []
        for n in names:
            m = latches.get(n)
            rows.append({
                "node": n,
                "estop": "none heard" if m is None else ("engaged" if m.engaged else "released"),
                "reason": "" if m is None else m.reason,
                "source": "" if m is None else m.source,
                # who sent it (a release: the user its release key names, bus/estop.py)
                "sender": "" if m is None else m.sender,
            })
        if json_out:
            echo_json(rows)
            return
        if not rows:
            typer.echo("(no nodes)")
        for r in rows:
            if r["estop"] == "engaged":
                why = f" ({r['reason'] or '-'}, from {r['source'] or '?'}" + (f" by {r['sender']})" if r["sender"] else ")")
            elif r["estop"] == "released":
                why = f" (by {r['sender'] or '?'} from {r['source'] or '?'})"
            else:
                why = ""
            typer.echo(f"{r['node']:24s} e-stop {r['estop']}{why}")

    @app.command()
    @user_errors
    def credentials(
        rig: str = typer.Argument(..., help="rig config name or file with a bus.access section", autocompletion=complete_rig),
        users: list[str] = typer.Option(None, "--user", help="add this user (repeatable; default: the rig's "
                                                             "command and release users and bus.access.user)"),
    ) -> None:
        """Create (or extend) the rig's credentials file: a random password per user, mode 600.

        Existing lines are kept. Give an operator a file with only their line (HIL_CREDENTIALS=that file)."""
        from hilstack.bus.access import credentials_path, generate

        name, bus, _ = rig_bus(rig, need_config=True)
        if bus.access is None:
            raise UserError(f"rig {name} has no bus.access section: nothing to create (docs/platform.md)")
        acc = bus.access
        want = list(users) if users else [acc.user, *acc.command, *acc.release]
        from hilstack.bus.keys import _NAME

        for u in want:
            if not _NAME.match(u):
                raise UserError(f"--user {u!r}: use letters, digits, '_' and '-'")
        path = credentials_path(acc)
        added = generate(path, want)
        typer.echo(f"{path}: added {', '.join(added) if added else 'nobody (all present)'}", err=True)
