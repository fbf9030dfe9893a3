"""The WidowX's links in Foxglove's 3D panel: the recorder's FrameTransforms, composed from the
spec's kinematic chain, put every link where MuJoCo's forward kinematics of the sim model does."""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest
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


def test_the_arm_model_sits_on_mujoco_links_in_foxglove_and_rerun(tmp_path):
    """The WidowX's 3-D model (a capsule per link from the spec's chain): in Foxglove a SceneUpdate
    whose entities, locked to the link frames, join each link's origin to the next one's where
    MuJoCo's forward kinematics puts them; in rerun a static capsule under each link's entity."""
    import rerun as rr

    from hilstack.bus.recording import LINK_RADIUS_M, TOOL_STUB_M, foxglove_model_topic
    from hilstack.tools.viz import viz_recording

    spec = widowx_spec(WidowXParams()).to_dict()
    names = spec["state"]["names"]
    model = kinematics_model()
    data = mujoco.MjData(model)
    q = dict(zip(JOINT_NAMES, (0.4, -0.6, 0.9, 0.3, -0.7, 0.5), strict=True))
    state = [q.get(n[:-4], 0.0) if n.endswith("_pos") else 0.0 for n in names]
    for j in JOINT_NAMES:
        data.qpos[model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j)]] = q[j]
    mujoco.mj_kinematics(model, data)
    base = data.xpos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "base_link")]
    origin = [np.zeros(3)] + [data.xpos[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"{j}_link")] - base
                              for j in JOINT_NAMES]
    frames = _compose(chain_transforms("widowx", spec["chain"], names, state))

    path = tmp_path / "arm.mcap"
    with McapLog(path) as log:
        log.write("hil/arm/widowx/spec", SpecMsg(robot="widowx", spec=json.loads(json.dumps(spec))), 1)
        log.write("hil/arm/widowx/state", RobotState(robot="widowx", t_s=0.0, state=state), 2)
    with open(path, "rb") as f:
        dec = DecoderFactory()
        ups = [dec.decoder_for(c.message_encoding, s)(m.data)
               for s, c, m in make_reader(f).iter_messages(topics=[foxglove_model_topic("arm", "widowx")])]
    assert len(ups) == 1 and len(ups[0].entities) == len(JOINT_NAMES) + 1
    for i, e in enumerate(ups[0].entities):
        assert e.frame_locked and e.frame_id in frames
        p, r = frames[e.frame_id]
        c = e.cylinders[0]
        half = Rotation.from_quat([c.pose.orientation.x, c.pose.orientation.y, c.pose.orientation.z,
                                   c.pose.orientation.w]).apply([0, 0, c.size.z / 2])
        centre = np.array([c.pose.position.x, c.pose.position.y, c.pose.position.z])
        a, b = p + r.apply(centre - half), p + r.apply(centre + half)  # the cylinder's ends in the world
        np.testing.assert_allclose(a, origin[i], atol=1e-6)
        if i < len(JOINT_NAMES):
            np.testing.assert_allclose(b, origin[i + 1], atol=1e-6)
        else:  # the tool stub along the wrist's roll axis
            np.testing.assert_allclose(b - a, r.apply([TOOL_STUB_M, 0, 0]), atol=1e-6)
        assert c.size.x == pytest.approx(2 * LINK_RADIUS_M) and len(e.spheres) == 2

    rrd = tmp_path / "arm.rrd"
    viz_recording(path, rrd)
    bodies = {}
    for ch in rr.chunk.RrdReader(str(rrd)).stream().to_chunks():
        if str(ch.entity_path).endswith("/body"):
            rb = ch.to_record_batch()
            bodies[str(ch.entity_path)] = {n: rb.column(n).to_pylist() for n in rb.schema.names}
    link_paths = ["/world/widowx/links"]
    for j in JOINT_NAMES:
        link_paths.append(f"{link_paths[-1]}/{j}_link")
    assert sorted(bodies) == sorted(f"{lp}/body" for lp in link_paths)
    for i, lp in enumerate(link_paths[:-1]):
        length = next(v for k, v in bodies[f"{lp}/body"].items() if k.endswith("lengths"))
        assert np.ravel(length)[0] == pytest.approx(np.linalg.norm(spec["chain"][i]["xyz"]), abs=1e-6)


def test_the_rerun_layout_has_a_tab_per_robot_by_its_kind():
    """tools/viz.py: an arm's tab plots its joint angles beside its 3-D model, the roach's its speeds
    in the world view, the tracker's its confidences, the hand (joints, no chain) its joint angles."""
    from hilstack.drivers.registry import spec_of
    from hilstack.tools.viz import blueprint, robot_kind, robot_view

    specs = {r: spec_of(r, "sim") for r in ("widowx", "velociroach", "camera", "shadow_hand")}
    assert [robot_kind(s) for s in specs.values()] == ["arm", "mobile", "tracker", "joints"]

    def views(r):
        tab = robot_view(r, specs[r])
        world, right = tab.contents
        return world, right.contents

    world, (key, *_rest) = views("widowx")
    assert world.origin == "world/widowx" and key.contents == [f"state/widowx/{j}_pos" for j in JOINT_NAMES]
    world, (key, *_rest) = views("velociroach")
    assert world.origin == "world" and key.contents == [f"state/velociroach/{n}" for n in ("vx", "vy", "wz")]
    assert views("camera")[1][0].contents == ["state/camera/ball0_conf", "state/camera/ball1_conf"]
    assert len(views("shadow_hand")[1][0].contents) == 24
    tabs = blueprint(specs=specs).root_container
    assert [t.name for t in tabs.contents] == ["widowx (arm)", "velociroach (mobile)", "camera (tracker)",
                                               "shadow_hand (joints)", "all robots"]
