"""Per-run table of `hil demo --rig roach_emulated` outputs (docs/velociroach.md, "Three
emulated runs with the sample count refitted"): the planner's start fit and every refit,
paths completed and cost per metre per speed for MPC and the tuned baseline, and per MPC path
its end, sample count, late plans and plan p50/p99.

    python scripts/roach_realtime/emu_table.py OUT0 OUT1 OUT2
"""
import json
import sys

for out in sys.argv[1:]:
    r = json.load(open(f"{out}/report.json"))
    pr = r.get("planner_realtime", {})
    print(out, f"wall {r['wall_s']:.0f} s", "start fit", pr.get("samples"),
          [(t["samples"], round(t["plan_ms_p50"])) for t in pr.get("trials", [])], "final", pr.get("current_samples"))
    for f in pr.get("refits", []):
        print(f"   refit {f['from']} -> {f['to']} after {f['after']}: p50 {f['plan_ms_p50']:.0f} "
              f"p95 {f['plan_ms_tail']:.0f} late {100 * f['late_share']:.0f}% ({f['reason']})")
    for sp in ("low_speed", "high_speed"):
        S = r[sp]
        late = [v["mpc"]["late_plans"] / max(1, v["mpc"]["steps"]) for v in S["paths"].values()]
        print(f"  {sp} MPC {S['mpc_completed']}/5 {S['mpc_cost_per_m']:.1f}/m DD {S['differential_drive_completed']}/5 "
              f"{S['differential_drive_cost_per_m']:.1f}/m late share {100 * min(late):.0f}-{100 * max(late):.0f}%")
        for p, v in S["paths"].items():
            m, d = v["mpc"], v["differential_drive"]
            print(f"    {p} MPC {m.get('end')} N {m.get('samples')} prog {m['progress_m']:.2f} "
                  f"tilt {m.get('max_tilt_deg', 0):.0f} late {m['late_plans']}/{m['steps']} "
                  f"p50 {m['plan_ms_p50']:.0f} p99 {m['plan_ms_p99']:.0f} | DD {d.get('end')} tilt {d.get('max_tilt_deg', 0):.0f}")
