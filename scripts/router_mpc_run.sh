#!/bin/bash
# The MPC as the commander of a rig spread over processes that reach each other only through
# `hil router` on 127.0.0.2: hil router, hil up (emulated roach), hil record, hil mpc (an untrained
# model: the plumbing, not the path cost), then the recording checked (docs/scaling.md). PY=... overrides the interpreter.
set -u
D=${1:?usage: scripts/router_mpc_run.sh OUT_DIR}; mkdir -p "$D"; D=$(cd "$D" && pwd)
cd "$(dirname "$0")/.."; export PYTHONPATH=$PWD
PY=${PY:-.venv/bin/python}
R=$($PY -c "from hilstack.bus.ports import free_port; print(free_port('127.0.0.2'))")
sed -e "s#router: tcp/127.0.0.1:7462#router: tcp/127.0.0.2:$R#" -e "s#name: roach_emulated_router#name: rt_mpc#" \
    -e "s#credentials: .*#credentials: $D/rt.credentials#" configs/rigs/roach_emulated_router.yaml > $D/rt_mpc.yaml
rm -f $D/rt.credentials $D/rt.mcap
$PY -c "
from hilstack.learning.dynamics import EnsembleDynamics
from hilstack.drivers.registry import spec_of
s = spec_of('velociroach')
EnsembleDynamics(s.state.dim, s.action.dim, hidden=(32, 32), state_names=list(s.state.names),
                 action_names=list(s.action.names), seed=0).save('$D/untrained.pt')"
t0=$(date +%s.%N)
$PY -m hilstack router $D/rt_mpc.yaml > $D/router.log 2>&1 & RP=$!
sleep 3
$PY -m hilstack up $D/rt_mpc.yaml > $D/up.log 2>&1 & UP=$!
for i in $(seq 1 120); do grep -q " up on " $D/up.log && break; sleep 1; done
echo "up after $(echo "$(date +%s.%N) - $t0" | bc) s: $(grep ' up on ' $D/up.log)"
$PY -m hilstack record --rig $D/rt_mpc.yaml --out $D/rt.mcap > $D/rec.log 2>&1 & REC=$!
sleep 3
HIL_BUS_USER=operator $PY -m hilstack mpc $D/rt_mpc.yaml --model $D/untrained.pt --steps 50 --no-reset --json > $D/mpc.json 2> $D/mpc.err
echo "mpc exit $? : $(cat $D/mpc.json | head -c 400)"
kill -INT $REC; wait $REC; echo "record exit $?"
kill -TERM $UP; wait $UP; echo "up exit $?"
kill -TERM $RP; wait $RP; echo "router exit $?"
$PY - <<PYEOF
from hilstack.bus.recording import read_messages
from hilstack.bus.schemas import Command, RobotState
msgs = [m.msg for m in read_messages("$D/rt.mcap").messages]
cmds = [m for m in msgs if isinstance(m, Command)]
states = [m for m in msgs if isinstance(m, RobotState)]
driven = [s for s in states if s.action and max(abs(a) for a in s.action) > 0.05 and s.stopped_reason == ""]
print(f"recording: {len(states)} states, {len(cmds)} commands (sources {sorted({c.source for c in cmds})}), "
      f"{len(driven)} states with a nonzero applied action and no stop reason")
PYEOF
