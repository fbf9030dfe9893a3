"""The WidowX's links in Foxglove's 3D panel: the recorder's FrameTransforms, composed from the
spec's kinematic chain, put every link where MuJoCo's forward kinematics of the sim model does."""

from __future__ import annotations

import json

import mujoco
import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from hilstack.bus.recording import McapLog, chain_transforms, foxglove_tf_topic
from hilstack.bus.schemas import RobotState, SpecMsg
from hilstack.drivers.widowx.config import JOINT_NAMES, WidowXParams, widowx_spec
from hilstack.sim_backends.widowx.world import kinematics_model


def _compose(tfs) -> dict[str, tuple[np.ndarray, Rotation]]:
    frames = {"widowx": (np.zeros(3), Rotation.identity())}
    for parent, child, t, q in tfs:
        p, r = frames[parent]
        frames[child] = (p + r.apply(t), r * Rotation.from_quat(q))
    return frames


def test_link_frames_match_mujoco_forward_kinematics(tmp_path):
    spec = widowx_spec(WidowXParams()).to_dict()
    names = spec["state"]["names"]
    model = kinematics_model()
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = {j: rng.uniform(-1.0, 1.0) for j in JOINT_NAMES}
        state = [q.get(n[:-4], 0.0) if n.endswith("_pos") else 0.0 for n in names]
        for j in JOINT_NAMES:
            data.qpos[model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j)]] = q[j]
        mujoco.mj_kinematics(model, data)
        frames = _compose(chain_transforms("widowx", spec["chain"], names, state))
        base = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "base_link")
        for j in JOINT_NAMES:
            b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"{j}_link")
            p, r = frames[f"widowx/{j}_link"]
            np.testing.assert_allclose(p, data.xpos[b] - data.xpos[base], atol=1e-9)
            np.testing.assert_allclose(r.as_matrix(), data.xmat[b].reshape(3, 3), atol=1e-9)

    # and the recorder writes them on the rig's tf channel, world -> widowx -> links
    path = tmp_path / "arm.mcap"
    with McapLog(path) as log:
        log.write("hil/arm/widowx/spec", SpecMsg(robot="widowx", spec=json.loads(json.dumps(spec))), 1)
        log.write("hil/arm/widowx/state", RobotState(robot="widowx", t_s=0.0, state=state), 2)
    with open(path, "rb") as f:
        dec = DecoderFactory()
        tfs = [dec.decoder_for(c.message_encoding, s)(m.data)
               for s, c, m in make_reader(f).iter_messages(topics=[foxglove_tf_topic("arm")])]
    pairs = [(t.parent_frame_id, t.child_frame_id) for t in tfs]
    assert pairs[0] == ("world", "widowx") and pairs[-1] == ("widowx/wrist_angle_link", "widowx/wrist_rotate_link")
    assert len(pairs) == 1 + len(JOINT_NAMES)


def test_rerun_gets_the_arm_as_nested_transforms(tmp_path):
    import rerun as rr

    from hilstack.tools.viz import viz_recording

    spec = widowx_spec(WidowXParams()).to_dict()
    names = spec["state"]["names"]
    state = [0.3 if n == "shoulder_pos" else 0.0 for n in names]
    path = tmp_path / "arm.mcap"
    with McapLog(path) as log:
        log.write("hil/arm/widowx/spec", SpecMsg(robot="widowx", spec=spec), 1)
        log.write("hil/arm/widowx/state", RobotState(robot="widowx", t_s=0.0, state=state, stamp_s=1.0), 2)
    rrd = tmp_path / "arm.rrd"
    viz_recording(path, rrd)
    cols: dict[str, dict] = {}
    for c in rr.chunk.RrdReader(str(rrd)).stream().to_chunks():
        rb = c.to_record_batch()
        cols.setdefault(str(c.entity_path), {}).update({n: rb.column(n).to_pylist() for n in rb.schema.names})
    shoulder = "/world/widowx/links/waist_link/shoulder_link"
    assert f"{shoulder}/elbow_link/forearm_roll_link/wrist_angle_link/wrist_rotate_link" in cols
    t = next(v for k, v in cols[shoulder].items() if k.endswith("translation"))
    q = next(v for k, v in cols[shoulder].items() if k.endswith("quaternion"))
    np.testing.assert_allclose(t[0][0] if isinstance(t[0][0], list) else t[0], spec["chain"][1]["xyz"], atol=1e-6)
    np.testing.assert_allclose(np.ravel(q[0]), [0, np.sin(0.15), 0, np.cos(0.15)], atol=1e-6)  # 0.3 rad about y
