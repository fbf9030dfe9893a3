"""`hil export lerobot`: recordings as a LeRobotDataset v3.0, checked by the port of lerobot 0.4.4's
loader checks (tools/export.py: check_lerobot; lerobot itself pins torch < 2.11, older than ours)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from hilstack.bus.recording import McapLog
from hilstack.bus.schemas import RobotState, SpecMsg
from hilstack.tools.cli import app
from hilstack.tools.export import check_lerobot

SPEC = {"name": "velociroach", "period_s": 0.1, "state": {"names": ["x", "y", "vbat"], "units": ["m", "m", "V"]},
        "action": {"names": ["leg_vel_l", "leg_vel_r"], "units": ["rev/s", "rev/s"]}}


@pytest.fixture
def recordings(tmp_path: Path) -> Path:
    d = tmp_path / "recs"
    d.mkdir()
    for r, lengths in enumerate([(4, 3), (5,)]):
        with McapLog(d / f"{r:03d}.mcap") as log:
            log.write("hil/r/roach/spec", SpecMsg(robot="roach", spec=SPEC), 1)
            ns = 2
            for e, n in enumerate(lengths):
                log.write("hil/r/roach/state", RobotState(robot="roach", t_s=9.0, state=[0, 0, 4], active=False,
                                                          episode=e), ns)  # not driving: no frame
                for k in range(n):
                    ns += 1
                    log.write("hil/r/roach/state", RobotState(robot="roach", t_s=10.0 * e + 0.1 * k,
                                                              state=[r, e, k], action=[0.1 * k, -0.1 * k],
                                                              active=True, episode=e), ns)
    return d


def test_export_loads_with_lerobots_checks(recordings, tmp_path):
    out = tmp_path / "ds"
    r = CliRunner().invoke(app, ["export", "lerobot", str(recordings), "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads(r.output)
    assert (res["episodes"], res["frames"], res["fps"]) == (3, 12, 10)
    chk = check_lerobot(out)
    assert chk["episodes"] == 3 and chk["timestamps_in_sync"]
    assert {"observation.state", "action", "timestamp", "episode_index", "index"} <= set(chk["features"])
    info = json.loads((out / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["features"]["observation.state"]["names"] == ["x", "y", "vbat"]
    t = pq.read_table(out / "data" / "chunk-000" / "file-000.parquet").to_pandas()
    ep1 = t[t.episode_index == 1]  # the first recording's second episode: 3 frames
    assert list(ep1.frame_index) == [0, 1, 2] and np.allclose(ep1.timestamp, [0, 0.1, 0.2])
    assert np.allclose(np.stack(ep1["observation.state"]), [[0, 1, 0], [0, 1, 1], [0, 1, 2]])
    assert np.allclose(np.stack(ep1["action"])[2], [0.2, -0.2])
    r = CliRunner().invoke(app, ["export", "lerobot", str(recordings), "--out", str(out)])
    assert r.exit_code == 2 and "--force" in r.output  # never overwritten without --force


def test_the_checks_refuse_what_lerobot_refuses(recordings, tmp_path):
    from hilstack.tools.export import export_lerobot

    out = tmp_path / "ds"
    export_lerobot(recordings, out)
    info_path = out / "meta" / "info.json"
    good = info_path.read_text()
    info = json.loads(good)
    info["codebase_version"] = "v2.1"
    info_path.write_text(json.dumps(info))
    with pytest.raises(ValueError, match="v2.1"):
        check_lerobot(out)
    info = json.loads(good)
    info["features"]["observation.state"]["shape"] = [4]
    info_path.write_text(json.dumps(info))
    with pytest.raises(ValueError, match="observation.state"):
        check_lerobot(out)
    info = json.loads(good)
    info["total_episodes"] = 4
    info_path.write_text(json.dumps(info))
    with pytest.raises(ValueError, match=r"episodes \[3\]"):
        check_lerobot(out)
